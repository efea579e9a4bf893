"""The global-input RRT: tree, nearest neighbours, Alg. 1-2 semantics, options, reuse."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.cli.main import main as plan_main
from rigctl.core.errors import PlanError
from rigctl.plans.checks import check_plan
from rigctl.plans.rrt import (
    NearestNodeIndex,
    RrtOptions,
    RrtTree,
    check_tree_meta,
    plan_rrt,
    polish,
    replay,
)
from rigctl.plans.schema import load_plan

# ---------------------------------------------------------------- nearest neighbours and the tree


def test_forest_nearest_matches_brute_force_while_growing():
    rng = np.random.default_rng(0)
    index = NearestNodeIndex(4)
    points = np.empty((0, 4))
    for block in [1, 1, 3, 7, 50, 200, 13, 500, 1000, 2]:
        new = rng.uniform(0, 100, size=(block, 4))
        index.extend(new)
        points = np.concatenate([points, new])
        samples = rng.uniform(-20, 120, size=(64, 4))
        distance, found = index.query(samples)
        brute = np.sqrt(((samples[:, None] - points[None]) ** 2).sum(-1))
        np.testing.assert_allclose(distance, brute.min(axis=1), rtol=0, atol=1e-9)
        np.testing.assert_allclose(brute[np.arange(64), found], brute.min(axis=1), atol=1e-9)
    assert len(index) == len(points)


def test_forest_stays_logarithmic():
    index = NearestNodeIndex(2)
    for _ in range(1000):
        index.extend(np.zeros((8, 2)))
    assert len(index._forest) <= 14  # 8000 points in blocks of 8: at most log2(1000) + 1 + 3


def test_tree_path_and_save_load_round_trip(tmp_path):
    tree = RrtTree([[0.0, 0.0], [10.0, 0.0]], meta={"workspace_hash": "abc"}, capacity=1)
    a = tree.add(np.array([[[1.0, 0.0], [11.0, 0.0]]]), np.array([0]), np.array([[1.0, 0.0]]))
    b = tree.add(
        np.array([[[1.0, 2.0], [11.0, 2.0]], [[0.0, -1.0], [10.0, -1.0]]]),
        np.array([a[0], 0]),
        np.array([[0.0, 2.0], [0.0, -1.0]]),
    )
    moves, path = tree.path_to(int(b[0]))
    np.testing.assert_array_equal(moves, [[1.0, 0.0], [0.0, 2.0]])
    np.testing.assert_array_equal(path, [0, 1, 2])
    tree.save(tmp_path / "t.npz")
    loaded = RrtTree.load(tmp_path / "t.npz")
    np.testing.assert_array_equal(loaded.nodes, tree.nodes)
    np.testing.assert_array_equal(loaded.parents, [-1, 0, 1, 0])
    assert loaded.meta == {"workspace_hash": "abc"}


def test_loading_something_else_is_a_plan_error(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, nodes=np.zeros((1, 1, 2)))
    with pytest.raises(PlanError, match="not an RRT tree"):
        RrtTree.load(path)
    with pytest.raises(PlanError, match="does not exist"):
        RrtTree.load(tmp_path / "missing.npz")


def test_tree_meta_mismatch_names_what_differs():
    tree = RrtTree([[0.0, 0.0]], meta={"workspace_hash": "abc", "radii": [5.0]})
    check_tree_meta(tree, {"workspace_hash": "abc", "radii": [5.0]})
    with pytest.raises(PlanError, match="workspace_hash"):
        check_tree_meta(tree, {"workspace_hash": "xyz", "radii": [5.0]})
    with pytest.raises(PlanError, match="radii"):
        check_tree_meta(tree, {"workspace_hash": "abc", "radii": [6.0]})


# ---------------------------------------------------------------- move sets


def test_tree_moves_are_k_even_directions_of_robostep():
    moves = RrtOptions(robostep_mm=5.0, k=16).tree_moves()
    assert moves.shape == (16, 2)
    np.testing.assert_allclose(np.hypot(moves[:, 0], moves[:, 1]), 5.0)
    angles = np.degrees(np.arctan2(moves[:, 1], moves[:, 0])) % 360
    np.testing.assert_allclose(angles, np.arange(16) * 22.5, atol=1e-9)
    assert moves[4, 0] == 0.0 and moves[4, 1] == 5.0  # exact along the axes


def test_axis_only_moves():
    moves = RrtOptions(robostep_mm=10.0, axis_only=True).tree_moves()
    np.testing.assert_array_equal(moves, [[10, 0], [0, 10], [-10, 0], [0, -10]])


def test_turn_length_must_divide_robostep():
    RrtOptions(robostep_mm=20.0, turn_mm=10.0)
    with pytest.raises(PlanError, match="whole number of magnet turns"):
        RrtOptions(robostep_mm=5.0, turn_mm=10.0)


def test_legal_fitted_move():
    options = RrtOptions(robostep_mm=20.0, turn_mm=10.0, axis_only=True)
    np.testing.assert_allclose(options.legal_move(np.array([3.0, -17.0])), [0.0, -20.0])
    assert options.legal_move(np.array([1.0, 4.0])) is None  # less than half a turn


def test_turn_legs_add_up_to_the_translation_in_whole_turns():
    options = RrtOptions(robostep_mm=5.0, turn_mm=5.0)
    legs = options.turn_legs(np.array([[3.0, 4.0], [0.0, 6.0], [0.0, 0.0]]))
    # 5 mm is one turn: one move; 6 mm is two turns at +-acos(6 / 10) from +y: (-4, 3) + (4, 3)
    np.testing.assert_allclose(legs, [[[3, 4], [0, 0], [0, 0]], [[0, 0], [-4, 3], [4, 3]],
                                      [[0, 0], [0, 0], [0, 0]]], atol=1e-12)
    # 23 mm: 3 turns along it (15 mm), then two one-turn moves that add up to the other 8 mm
    legs = options.turn_legs(np.array([[23.0, 0.0]]))[0]
    np.testing.assert_allclose(legs[0], [15.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.hypot(legs[1:, 0], legs[1:, 1]), [5.0, 5.0], atol=1e-12)
    np.testing.assert_allclose(legs.sum(axis=0), [23.0, 0.0], atol=1e-12)


# ---------------------------------------------------------------- environment 1 of seed 000

from rigctl.plans.model import GlobalInputModel  # noqa: E402
from rigctl.plans.workspace import ShapeWorkspace  # noqa: E402

WALLS = [("rect", (0, 0, 400, 50)), ("rect", (0, 350, 400, 50)), ("rect", (0, 0, 50, 400)),
         ("rect", (350, 0, 50, 400))]
L_SHAPE = [("rect", (175, 150, 100, 25)), ("rect", (150, 150, 25, 100))]
START = np.array([[60.0, 300.0], [60.0, 250.0]])
GOAL = np.array([[330.0, 300.0], [330.0, 200.0]])
RADIUS = 5.0


@pytest.fixture(scope="module")
def environment_1():
    return ShapeWorkspace(("rect", (0, 0, 400, 400)), WALLS + L_SHAPE)


@pytest.fixture(scope="module")
def model(environment_1):
    return GlobalInputModel(environment_1, [RADIUS, RADIUS])


def _outside_obstacles_by_hand(points: np.ndarray, radius: float) -> np.ndarray:
    """True where a disc of `radius` at points (..., 2) stays in [50, 350]^2 and off the L."""
    x, y = points[..., 0], points[..., 1]
    tol = 1e-6
    inside_room = (x >= 50 + radius - tol) & (x <= 350 - radius + tol)
    inside_room &= (y >= 50 + radius - tol) & (y <= 350 - radius + tol)
    clear = inside_room
    for x0, y0, w, h in [(175, 150, 100, 25), (150, 150, 25, 100)]:
        dx = np.maximum(np.maximum(x0 - x, x - (x0 + w)), 0.0)
        dy = np.maximum(np.maximum(y0 - y, y - (y0 + h)), 0.0)
        clear &= np.hypot(dx, dy) >= radius - tol
    return clear


def test_first_extension_moves_along_the_direction_closest_to_the_sample(model):
    # goal bias 1: every sample is the goal. The goal lies 30 degrees from the start for both
    # robots, so of the 16 directions (22.5 degree apart) 22.5 degrees ends closest (by hand:
    # 7.5 degrees off against 15 degrees for 45).
    start = np.array([[200.0, 300.0], [200.0, 80.0]])
    offset = 100.0 * np.array([np.cos(np.radians(30)), np.sin(np.radians(30))])
    goal = start + offset
    result = plan_rrt(model, start, goal, options=RrtOptions(max_nodes=2, goal_bias=1.0),
                      rng=np.random.default_rng(0))
    expected = 5.0 * np.array([np.cos(np.pi / 8), np.sin(np.pi / 8)])
    np.testing.assert_allclose(result.tree.moves[1], expected)
    np.testing.assert_allclose(result.tree.nodes[1], start + result.tree.moves[1], atol=1e-12)


def test_moves_replay_exactly_to_the_reported_state_and_respect_obstacles(model):
    options = RrtOptions(max_nodes=3000, tolerance_mm=2.0)
    result = plan_rrt(model, START, GOAL, options=options, rng=np.random.default_rng(4))
    assert len(result.moves) > 0
    states = replay(model, START, result.moves)
    np.testing.assert_array_equal(states, result.states)  # bit for bit
    assert result.distance == pytest.approx(np.linalg.norm(states[-1] - GOAL), abs=1e-12)
    assert result.nodes == len(result.tree) == 3000
    assert np.all(_outside_obstacles_by_hand(result.tree.nodes, RADIUS))
    gaps = np.linalg.norm(result.tree.nodes[:, 0] - result.tree.nodes[:, 1], axis=1)
    assert gaps.min() >= 2 * RADIUS - 1e-6
    # every node is its parent moved by its move (through the model)
    sample = np.random.default_rng(0).integers(1, len(result.tree), 200)
    parents = result.tree.parents[sample]
    again = model.apply(result.tree.nodes[parents], result.tree.moves[sample])
    np.testing.assert_array_equal(again, result.tree.nodes[sample])


def test_same_seed_same_plan_other_seed_other_tree(model):
    options = RrtOptions(max_nodes=1500)
    a = plan_rrt(model, START, GOAL, options=options, rng=np.random.default_rng(7))
    b = plan_rrt(model, START, GOAL, options=options, rng=np.random.default_rng(7))
    c = plan_rrt(model, START, GOAL, options=options, rng=np.random.default_rng(8))
    np.testing.assert_array_equal(a.tree.nodes, b.tree.nodes)
    np.testing.assert_array_equal(a.moves, b.moves)
    assert not np.array_equal(a.tree.nodes[:1500], c.tree.nodes[:1500])


def test_formation_samples_are_the_goal_translated_to_free_places(model):
    from rigctl.plans.rrt import _goal_formations

    rng = np.random.default_rng(0)
    placed = _goal_formations(model, np.array([RADIUS, RADIUS]), GOAL, rng, 500)
    assert placed.shape == (500, 2, 2)
    offsets = placed[:, 1] - placed[:, 0]
    np.testing.assert_allclose(offsets, np.broadcast_to(GOAL[1] - GOAL[0], (500, 2)), atol=1e-9)
    assert np.all(_outside_obstacles_by_hand(placed, RADIUS))
    assert np.ptp(placed[:, 0, 0]) > 100  # spread over the room, not stuck at the goal


def test_offset_error_by_hand():
    from rigctl.plans.rrt import offset_error

    # goal offset (0, 100); state offset (0, 50): residuals (0, +-25) -> sqrt(2 * 25^2)
    state = np.array([[10.0, 20.0], [10.0, -30.0]])
    goal = np.array([[0.0, 100.0], [0.0, 0.0]])
    assert offset_error(state, goal) == pytest.approx(np.sqrt(2) * 25.0)
    assert offset_error(goal + [7.0, -3.0], goal) == pytest.approx(0.0, abs=1e-12)


def test_min_separation_is_kept(environment_1):
    separated = GlobalInputModel(environment_1, [RADIUS, RADIUS], min_separation_mm=8.0)
    result = plan_rrt(separated, START, GOAL, options=RrtOptions(max_nodes=2000),
                      rng=np.random.default_rng(1))
    gaps = np.linalg.norm(result.tree.nodes[:, 0] - result.tree.nodes[:, 1], axis=1)
    assert gaps.min() >= 2 * RADIUS + 8.0 - 1e-6
    # and the constraint was active: some node has the robots at the separation distance
    assert gaps.min() <= 2 * RADIUS + 8.0 + 1e-3


def test_axis_only_and_whole_turns(model):
    options = RrtOptions(robostep_mm=20.0, axis_only=True, turn_mm=10.0, max_nodes=500,
                         greedy=True, final_approach=True, goal_bias=0.05)
    result = plan_rrt(model, START, GOAL, options=options, rng=np.random.default_rng(2))
    moves = result.tree.moves[1:]
    assert np.all((moves[:, 0] == 0) | (moves[:, 1] == 0))
    lengths = np.abs(moves).sum(axis=1) / 10.0
    np.testing.assert_allclose(lengths, np.round(lengths), atol=1e-9)
    assert lengths.min() >= 1


def test_whole_turns_reach_a_translation_that_is_no_whole_number_of_turns(model):
    # the robots stand in the goal's formation 3.2 mm from it: rounded to whole 5 mm turns the
    # translation misses by 1.8 mm per robot; as 5 mm turns at +-71.4 deg from it, it is exact
    start = GOAL - [3.0, 1.0]
    options = RrtOptions(robostep_mm=5.0, turn_mm=5.0, max_nodes=200, tolerance_mm=0.5,
                         goal_bias=0.05, greedy=True, final_approach=True)
    result = plan_rrt(model, start, GOAL, options=options, rng=np.random.default_rng(0))
    assert result.solved
    final = replay(model, start, result.moves)[-1]
    assert np.linalg.norm(final - GOAL) <= 0.5
    lengths = np.hypot(result.moves[:, 0], result.moves[:, 1]) / 5.0
    np.testing.assert_allclose(lengths, np.round(lengths), atol=1e-9)


def test_descent_to_the_goal_combines_whole_turns(model):
    # polish's descent alone (no tree): from the goal's formation 3.2 mm off, one-turn moves
    # along 16 directions and the fitted move rounded to whole turns stay >= 1.8 mm per robot
    # away; two one-turn moves at +-71.4 deg from (3, 1) end on the goal
    start = GOAL - [3.0, 1.0]
    options = RrtOptions(robostep_mm=5.0, turn_mm=5.0, tolerance_mm=0.5)
    moves, states, distance = polish(model, start, GOAL, np.zeros((0, 2)), options)
    assert distance <= 0.5
    np.testing.assert_allclose(np.linalg.norm(states[-1] - GOAL), distance, atol=1e-9)
    lengths = np.hypot(moves[:, 0], moves[:, 1]) / 5.0
    np.testing.assert_allclose(lengths, np.round(lengths), atol=1e-9)


def test_tuned_options_solve_environment_1_with_non_slip_walls(environment_1):
    sticky = GlobalInputModel(environment_1, [RADIUS, RADIUS], contact="non-slip")
    options = RrtOptions(max_nodes=20_000, tolerance_mm=2.0, goal_bias=0.05, greedy=True,
                         final_approach=True)
    result = plan_rrt(sticky, START, GOAL, options=options, rng=np.random.default_rng(0))
    assert result.solved
    final = replay(sticky, START, result.moves)[-1]
    assert np.linalg.norm(final - GOAL) <= 2.0
    assert np.all(_outside_obstacles_by_hand(final, RADIUS))


def test_reused_tree_answers_a_new_goal_from_its_nodes(model):
    grown = plan_rrt(model, START, GOAL, options=RrtOptions(max_nodes=2000),
                     rng=np.random.default_rng(5))
    new_goal = np.array([[100.0, 100.0], [300.0, 320.0]])
    answer = plan_rrt(model, START, new_goal, options=RrtOptions(max_nodes=2000),
                      rng=np.random.default_rng(6), tree=grown.tree)
    assert answer.nodes == 2000  # nothing grown: the tree was already full
    flat = grown.tree.nodes.reshape(2000, -1)
    nearest = np.argmin(np.linalg.norm(flat - new_goal.reshape(-1), axis=1))
    assert answer.best_node == nearest
    np.testing.assert_array_equal(replay(model, START, answer.moves)[-1], grown.tree.nodes[nearest])


def test_reused_tree_keeps_growing_when_not_solved(model):
    grown = plan_rrt(model, START, GOAL, options=RrtOptions(max_nodes=500),
                     rng=np.random.default_rng(5))
    more = plan_rrt(model, START, GOAL, options=RrtOptions(max_nodes=900),
                    rng=np.random.default_rng(6), tree=grown.tree)
    assert more.nodes == 900 and more.tree is grown.tree


def test_tree_from_another_start_is_refused(model):
    grown = plan_rrt(model, START, GOAL, options=RrtOptions(max_nodes=50),
                     rng=np.random.default_rng(5))
    with pytest.raises(PlanError, match="another start"):
        plan_rrt(model, START + 1.0, GOAL, options=RrtOptions(max_nodes=50),
                 rng=np.random.default_rng(5), tree=grown.tree)


def test_time_budget_stops_early(model):
    options = RrtOptions(max_nodes=10_000_000, stop_when_solved=False)
    result = plan_rrt(model, START, GOAL, options=options, rng=np.random.default_rng(0),
                      time_budget_s=0.2)
    # only the budget can have ended it (no timed assertion: the machine may be loaded)
    assert 1 < result.nodes < 10_000_000


# ---------------------------------------------------------------- the command line


EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
ROBOTS = ["--start", "60,300", "--start", "60,250", "--goal", "330,300", "--goal", "330,200"]


@pytest.fixture()
def workspace_file(tmp_path):
    document = {
        "boundary": {"rect": [0, 0, 400, 400]},
        "obstacles": [{"rect": list(r)} for _, r in WALLS + L_SHAPE],
    }
    path = tmp_path / "env1.json"
    path.write_text(json.dumps(document))
    return path


def _last_json_line(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


def test_cli_solves_on_the_coil_board_and_writes_a_checked_plan(workspace_file, tmp_path, capsys):
    out = tmp_path / "plan.json"
    status = plan_main(["plan", "rrt", "--workspace", str(workspace_file), *ROBOTS, "--rig",
                        "coil-board", "--tuned", "--tolerance", "2", "--max-nodes", "20000",
                        "-o", str(out), "--json"])
    summary = _last_json_line(capsys.readouterr().out)
    assert status == 0 and summary["solved"] is True
    assert set(summary) == {"solved", "nodes", "seconds", "distance", "moves"}
    plan = load_plan(out)
    check_plan(plan)  # the plan's own model reproduces `expected`
    final = np.array(plan.expected[-1])
    assert np.linalg.norm(final - GOAL) == pytest.approx(summary["distance"], abs=1e-9)
    assert summary["distance"] <= 2.0 and summary["moves"] == len(plan.moves)
    assert plan.rig == "coil-board" and plan.tolerance_mm == 2.0


def test_cli_unsolved_still_writes_the_best_path_and_exits_1(workspace_file, tmp_path, capsys):
    out = tmp_path / "plan.json"
    status = plan_main(["plan", "rrt", "--workspace", str(workspace_file), *ROBOTS, "--rig",
                        "coil-board", "--max-nodes", "30", "--raster", "0", "-o", str(out),
                        "--json"])
    summary = _last_json_line(capsys.readouterr().out)
    assert status == 1 and summary["solved"] is False
    plan = load_plan(out)
    assert "NOT SOLVED" in plan.name
    final = np.array(plan.expected[-1]) if plan.moves else START
    assert np.linalg.norm(final - GOAL) == pytest.approx(summary["distance"], abs=1e-9)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--goal", "1,1"], "--goal #1"),  # the goal replaced below lies inside a wall
        (["--radius", "0"], "--radius"),
        (["--robostep", "5"], "--robostep 5"),  # six-coil: not a whole magnet turn
        (["--goal-bias", "2"], "--goal-bias"),
    ],
)
def test_cli_bad_input_exits_2_naming_the_argument(
    workspace_file, tmp_path, capsys, extra, message
):
    robots = list(ROBOTS)
    if extra[0] == "--goal":
        robots[robots.index("330,300")] = extra[1]
        extra = []
    status = plan_main(["plan", "rrt", "--workspace", str(workspace_file), *robots, *extra,
                        "--max-nodes", "10", "-o", str(tmp_path / "p.json")])
    assert status == 2
    assert message in capsys.readouterr().err


def test_cli_start_overlap_and_missing_workspace(workspace_file, tmp_path, capsys):
    status = plan_main(["plan", "rrt", "--workspace", str(workspace_file), "--start", "100,100",
                        "--start", "105,100", "--goal", "200,300", "--goal", "300,300",
                        "-o", str(tmp_path / "p.json")])
    assert status == 2 and "--start #2: overlaps #1" in capsys.readouterr().err
    status = plan_main(["plan", "rrt", "--workspace", str(tmp_path / "nope.json"), *ROBOTS,
                        "-o", str(tmp_path / "p.json")])
    assert status == 2 and "workspace" in (err := capsys.readouterr().err) and "nope.json" in err


def test_cli_six_coil_moves_are_whole_turns_and_axis_only(workspace_file, tmp_path, capsys):
    out = tmp_path / "plan.json"
    plan_main(["plan", "rrt", "--workspace", str(workspace_file), *ROBOTS, "--axis-only",
               "--robostep", "20", "--max-nodes", "150", "--tuned", "-o", str(out), "--json"])
    moves = np.array(load_plan(out).moves)
    assert len(moves) > 0
    assert np.all((moves[:, 0] == 0) | (moves[:, 1] == 0))
    turns = np.abs(moves).sum(axis=1) / 10.0  # 2 pi x the default magnet radius = 10 mm
    np.testing.assert_allclose(turns, np.round(turns), atol=1e-9)


def test_cli_tree_reuse_and_coverage(workspace_file, tmp_path, capsys):
    tree = tmp_path / "tree.npz"
    common = ["plan", "rrt", "--workspace", str(workspace_file), "--rig", "coil-board",
              "--max-nodes", "400", "--raster", "0"]
    assert plan_main([*common, *ROBOTS, "--save-tree", str(tree), "-o", str(tmp_path / "a.json"),
                      "--json"]) == 1
    grown = _last_json_line(capsys.readouterr().out)
    assert grown["nodes"] == 400
    # a new goal answered from the saved tree: no growth (already 400 nodes), a valid plan
    other = ["--start", "60,300", "--start", "60,250", "--goal", "100,100", "--goal", "300,300"]
    plan_main([*common, *other, "--tree", str(tree), "-o", str(tmp_path / "b.json"), "--json"])
    answer = _last_json_line(capsys.readouterr().out)
    assert answer["nodes"] == 400
    check_plan(load_plan(tmp_path / "b.json"))
    # the tree refuses other radii and another workspace
    assert plan_main([*common, *other, "--radius", "4", "--tree", str(tree), "-o",
                      str(tmp_path / "c.json")]) == 2
    assert "radii" in capsys.readouterr().err
    moved = json.loads(workspace_file.read_text())
    moved["obstacles"][-1]["rect"][0] += 1
    elsewhere = tmp_path / "other.json"
    elsewhere.write_text(json.dumps(moved))
    assert plan_main(["plan", "coverage", "--workspace", str(elsewhere), "--tree", str(tree),
                      "--grid", "50"]) == 2
    assert "another workspace" in capsys.readouterr().err
    # coverage of the saved tree: 400 nodes cannot occupy more than 400 cells
    assert plan_main(["plan", "coverage", "--workspace", str(workspace_file), "--tree", str(tree),
                      "--grid", "50", "--json"]) == 0
    result = _last_json_line(capsys.readouterr().out)
    assert result["total"] == (6 * 6) ** 2 or result["total"] == (7 * 7) ** 2
    assert 1 <= result["occupied"] <= 400


def test_cli_plans_in_the_example_vessel_image(tmp_path, capsys):
    (tmp_path / "maze.json").write_text(json.dumps(
        {"image": str(EXAMPLES / "vessel-maze.png"), "mm_per_px": 1.0}))
    out = tmp_path / "sub" / "plan.json"
    out.parent.mkdir()
    status = plan_main(["plan", "rrt", "--workspace", str(tmp_path / "maze.json"), "--radius", "3",
                        "--start", "40,196", "--start", "80,206", "--goal", "130,230",
                        "--goal", "140,330", "--rig", "coil-board", "--max-nodes", "500",
                        "-o", str(out), "--json"])
    assert status in (0, 1)
    plan = load_plan(out)
    assert plan.workspace.image.endswith("vessel-maze.png")
    check_plan(plan)  # the image path is resolved from the plan's own folder
