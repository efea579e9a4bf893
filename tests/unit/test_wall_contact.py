"""The wall-contact planner (seed 004): delivery checked by replaying through the model, the
2-move reachable set against sampled two-move sequences, and path lengths against closed forms."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from rigctl.apps.cli.main import main as cli_main
from rigctl.core.errors import PlanError
from rigctl.plans.checks import check_plan
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.schema import load_plan
from rigctl.plans.wall_contact import (
    DiskRegion,
    PolygonRegion,
    apply_move,
    best_two_move_step,
    centre_region,
    plan_two_particles,
    plan_wall_contact,
    plan_with_model,
    reachable_fraction,
    two_move_reachable,
)
from rigctl.plans.workspace import ShapeWorkspace

RADIUS = 0.5
EPSILON = 0.01

HEXAGON = [(25.0 * math.cos(a), 25.0 * math.sin(a)) for a in np.arange(6) * math.pi / 3]
WORKSPACES = {
    "square": {"rect": [0.0, 0.0, 50.0, 50.0]},
    "disk": {"disk": [0.0, 0.0, 25.0]},
    "acute-triangle": {"polygon": [[0.0, 0.0], [50.0, 0.0], [20.0, 40.0]]},
    "obtuse-triangle": {"polygon": [[0.0, 0.0], [60.0, 0.0], [5.0, 15.0]]},
    "hexagon": {"polygon": [list(v) for v in HEXAGON]},
}


def _shape_workspace(boundary: dict) -> ShapeWorkspace:
    (kind, value), = boundary.items()
    return ShapeWorkspace((kind, tuple(map(tuple, value)) if kind == "polygon" else tuple(value)))


def _random_pair(ws: ShapeWorkspace, rng: np.random.Generator) -> np.ndarray:
    """Two particles in free space, at least a diameter plus a hair apart, 0.05 mm off walls."""
    while True:
        points = ws.sample_free(rng, 2, RADIUS + 0.05)
        if np.hypot(*(points[1] - points[0])) > 2 * RADIUS + 0.05:
            return points


# ---------------------------------------------------------------- delivery


@pytest.mark.parametrize("name", sorted(WORKSPACES))
def test_random_pairs_are_delivered_when_replayed_through_the_model(name):
    boundary = WORKSPACES[name]
    ws = _shape_workspace(boundary)
    region = centre_region(boundary, RADIUS)
    planning_model = GlobalInputModel(ws, [RADIUS, RADIUS], "non-slip")
    replay_model = GlobalInputModel(_shape_workspace(boundary), [RADIUS, RADIUS], "non-slip")
    rng = np.random.default_rng(sorted(WORKSPACES).index(name))
    for _ in range(12):
        starts, goals = _random_pair(ws, rng), _random_pair(ws, rng)
        result, chosen, _ = plan_with_model(planning_model, region, starts, goals, EPSILON)
        assert np.array_equal(chosen, goals)
        # Independent of the planner's bookkeeping: a fresh model, from the starts.
        end = replay_model.rollout(starts, result.moves)[-1] if len(result.moves) else starts
        miss = np.hypot(*(end - goals).T)
        assert np.all(miss <= EPSILON), (starts.tolist(), goals.tolist(), miss)
        assert result.solved


def test_point_particles_reach_goals_in_every_workspace_quickly():
    rng = np.random.default_rng(7)
    for boundary in WORKSPACES.values():
        region = centre_region(boundary, RADIUS)
        ws = _shape_workspace(boundary)
        for _ in range(20):
            starts, goals = _random_pair(ws, rng), _random_pair(ws, rng)
            result = plan_two_particles(region, starts, goals, 1e-6)
            # Replay with eq. 1 move by move, then compare with the goal (not the planner's states).
            p = starts
            for move in result.moves:
                p = apply_move(region, p, move)
            assert np.all(np.hypot(*(p - goals).T) <= 1e-6)


def test_square_pairs_mostly_need_at_most_the_papers_five_moves():
    """Seed 004 Sec. IV-D: in a square every configuration is reachable in at most five moves.
    Alg. 1 is greedy; with the look-ahead nearly all random pairs meet the bound (measured: 297 of
    300), without it many do not."""
    square = PolygonRegion(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float))
    rng = np.random.default_rng(3)
    counts, greedy_counts = [], []
    for _ in range(60):
        points = rng.uniform(0.01, 0.99, size=(4, 2))
        counts.append(len(plan_two_particles(square, points[:2], points[2:], 1e-6).moves))
        greedy = plan_two_particles(square, points[:2], points[2:], 1e-6, lookahead=False)
        greedy_counts.append(len(greedy.moves))
    assert np.mean(np.array(counts) <= 5) >= 0.95
    assert np.mean(np.array(counts) <= 5) > np.mean(np.array(greedy_counts) <= 5)


# ---------------------------------------------------------------- the 2-move reachable set


def _first_contact_length(ws: ShapeWorkspace, positions, direction, radius) -> float:
    """Bisection on the input length at which the first particle touches a wall."""
    lo, hi = 0.0, 200.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        room = ws.clearance(positions + mid * direction).min() - radius
        lo, hi = (mid, hi) if room > 0 else (lo, mid)
    return lo


@pytest.mark.parametrize("name", ["square", "disk", "obtuse-triangle"])
def test_sampled_two_move_sequences_lie_in_the_reachable_set(name):
    """Move 1 to the first contact (bisection on the workspace), move 2 pushing into that wall
    (the model moves the particles): every delta so reached is one the planner can reach."""
    boundary = WORKSPACES[name]
    ws = _shape_workspace(boundary)
    region = centre_region(boundary, RADIUS)
    model = GlobalInputModel(ws, [RADIUS, RADIUS], "non-slip")
    rng = np.random.default_rng(11)
    checked = 0
    while checked < 25:
        start = _random_pair(ws, rng)
        angle = rng.uniform(0, 2 * math.pi)
        u = np.array([math.cos(angle), math.sin(angle)])
        first = _first_contact_length(ws, start, u, RADIUS) * u
        after_first = model.apply(start, first)
        pinned = int(np.argmin(ws.clearance(after_first)))
        inward = ws.normal(after_first[pinned])
        # A second move with a component into the pinning wall, of random length.
        for _ in range(20):
            v = rng.normal(size=2)
            if v @ inward < -0.05 * np.linalg.norm(v):
                break
        else:
            continue
        second = v / np.linalg.norm(v) * rng.uniform(0.5, 40.0)
        end = model.apply(after_first, second)
        delta = end[1] - end[0]
        if np.hypot(*delta) < 2 * RADIUS + 1e-3 or np.hypot(*(end[pinned] - after_first[pinned])) > 1e-9:
            continue  # the particles met each other, or the pinned one was not held
        goals = np.stack([np.zeros(2), delta])
        step = best_two_move_step(region, start, goals, 2 * RADIUS)
        assert step is not None
        assert step.distance <= 1e-3, (name, start.tolist(), delta.tolist(), step.distance)
        checked += 1


def test_square_two_move_set_matches_the_hand_computation():
    """Square [0, 10]^2, points p1 = (2, 5), p2 = (6, 5): the top and bottom walls pin both at
    once; pinned on the left wall (p1 at x = 0, p2 at x = 4) the push is leftward, so p2 ends at
    x in [0, 4]; pinned on the right wall (p2 at 10, p1 at 6) p1 ends at x in [6, 10]. Either
    way delta x is in [0, 4] and delta y in [-10, 10]: (-1, 5) is 1 away, nearest (0, 5);
    (3, -7) is reachable."""
    region = PolygonRegion(np.array([[0, 0], [10, 0], [10, 10], [0, 10]], dtype=float))
    start = np.array([[2.0, 5.0], [6.0, 5.0]])
    step = best_two_move_step(region, start, np.array([[3.0, 2.0], [2.0, 7.0]]))
    assert step.distance == pytest.approx(1.0, abs=1e-4)
    np.testing.assert_allclose(step.delta, [0.0, 5.0], atol=1e-4)
    step = best_two_move_step(region, start, np.array([[5.0, 8.0], [8.0, 1.0]]))
    assert step.distance < 1e-9
    p = start
    for move in step.moves(start):
        p = apply_move(region, p, move)
    np.testing.assert_allclose(p[1] - p[0], [3.0, -7.0], atol=1e-6)


def test_same_row_pair_reaches_only_nonnegative_dx_in_two_moves():
    """Square [0, 10]^2, p1 = (4, 5), p2 = (6, 5): by the same reasoning delta x stays in [0, 2],
    so the nearest two-move delta to (-9, 0) is (0, 0), 9 away."""
    region = PolygonRegion(np.array([[0, 0], [10, 0], [10, 10], [0, 10]], dtype=float))
    start = np.array([[4.0, 5.0], [6.0, 5.0]])
    step = best_two_move_step(region, start, np.array([[9.5, 5.0], [0.5, 5.0]]))
    assert step.distance == pytest.approx(9.0, abs=1e-4)


# ---------------------------------------------------------------- shortest paths (Sec. V)


def test_square_last_step_follows_the_reflection_law():
    """Square [0, 10]^2: p1 = (3, 5), p2 = (7, 5) to g1 = (4, 7), g2 = (6, 7). The delta shrinks
    by 2 along x with one particle pinned on a side wall; the shortest contact reflects the goal
    across that wall: |(7, 5) - (14, 7)| = sqrt(53) plus the 2 mm move."""
    region = PolygonRegion(np.array([[0, 0], [10, 0], [10, 10], [0, 10]], dtype=float))
    result = plan_two_particles(region, [[3, 5], [7, 5]], [[4, 7], [6, 7]], 1e-9)
    assert result.solved
    assert len(result.moves) == 3
    assert result.length == pytest.approx(2.0 + math.sqrt(53.0), abs=1e-6)


def test_disk_contact_on_the_common_ray_is_shortest():
    """Disk of radius 10: p1 = (-2, 0), p2 = (2, 0) to g1 = (-1, 0), g2 = (1, 0). Pinning one
    particle where the x-axis meets the circle: 8 mm there, 2 mm to close the gap, 9 mm back
    (the paper's beta = 0 case, theta* = 0): 19 mm."""
    region = DiskRegion(np.zeros(2), 10.0)
    result = plan_two_particles(region, [[-2, 0], [2, 0]], [[-1, 0], [1, 0]], 1e-6)
    assert result.solved
    assert result.length == pytest.approx(19.0, abs=1e-3)


def test_interchangeable_particles_take_the_swapped_goals_when_shorter():
    region = PolygonRegion(np.array([[0, 0], [10, 0], [10, 10], [0, 10]], dtype=float))
    starts, goals = np.array([[2.0, 5.0], [8.0, 5.0]]), np.array([[8.0, 5.0], [2.0, 5.0]])
    plain, _ = plan_wall_contact(region, starts, goals, 1e-6)
    alike, chosen = plan_wall_contact(region, starts, goals, 1e-6, interchangeable=True)
    assert plain.solved and alike.solved
    np.testing.assert_array_equal(chosen, goals[::-1])
    assert alike.length == 0.0 < plain.length


# ---------------------------------------------------------------- eq. 1 and the regions


def test_eq1_point_particles_stick_when_pushed_into_a_wall():
    region = PolygonRegion(np.array([[0, 0], [10, 0], [10, 10], [0, 10]], dtype=float))
    p = apply_move(region, [[0.0, 5.0], [5.0, 5.0]], [-3.0, 1.0])
    np.testing.assert_allclose(p, [[0.0, 5.0], [2.0, 6.0]])  # pushed in: stays; other moves
    p = apply_move(region, [[0.0, 5.0], [5.0, 5.0]], [0.0, 2.0])  # parallel: not into the wall
    np.testing.assert_allclose(p, [[0.0, 7.0], [5.0, 7.0]])
    p = apply_move(region, [[1.0, 5.0], [5.0, 5.0]], [-4.0, 0.0])  # stops at the wall
    np.testing.assert_allclose(p, [[0.0, 5.0], [1.0, 5.0]])


def test_centre_regions_shrink_by_the_radius():
    square = centre_region({"rect": [0, 0, 10, 10]}, 1.0)
    assert sorted(map(tuple, np.round(square.vertices, 9))) == [(1, 1), (1, 9), (9, 1), (9, 9)]
    disk = centre_region({"disk": [1, 2, 5]}, 0.5)
    assert disk.radius == 4.5 and disk.centre.tolist() == [1, 2]
    # Right isosceles triangle legs 10: the inset by 1 has legs 10 - 2 - sqrt(2) (incircle scaling).
    tri = centre_region({"polygon": [[0, 0], [10, 0], [0, 10]]}, 1.0)
    legs = np.ptp(tri.vertices, axis=0)
    np.testing.assert_allclose(legs, [8 - math.sqrt(2)] * 2, atol=1e-9)
    with pytest.raises(PlanError, match="convex"):
        centre_region({"polygon": [[0, 0], [10, 0], [2, 2], [0, 10]]}, 0.5)


# ---------------------------------------------------------------- reachable fractions


@pytest.mark.parametrize("region", [
    DiskRegion(np.zeros(2), 0.5),
    PolygonRegion(np.array([[0, 0], [1, 0], [0.5, 0.3]], dtype=float)),
], ids=["disk", "obtuse-triangle"])
def test_two_move_fraction_agrees_with_sampling_the_planner(region):
    """Second method: uniform samples of the Delta space (the unit disk's is |delta| <= 1; the
    polygon's is the hull of its vertex differences, built by scipy), each tested by asking the
    planner's nearest-point search whether it reaches it exactly."""
    start = np.array([0.1, 0.0]) * region.size
    grid = reachable_fraction(region, start, 2, cells=241 if isinstance(region, PolygonRegion) else 121)[0]
    rng = np.random.default_rng(5)
    positions = np.array([[0.0, 0.0], start])
    if isinstance(region, DiskRegion):
        positions = positions - start / 2  # any placement with this delta inside the disk
        samples = rng.uniform(-1, 1, size=(2000, 2))
        samples = samples[np.hypot(*samples.T) <= 1.0][:600]
    else:
        from scipy.spatial import Delaunay

        positions = positions + np.array([0.45, 0.05])
        assert region.contains(positions).all()
        v = region.vertices
        space = Delaunay((v[:, None, :] - v[None, :, :]).reshape(-1, 2))
        samples = rng.uniform(-1, 1, size=(4000, 2)) * [1.0, 0.3]
        samples = samples[space.find_simplex(samples) >= 0][:600]
    hits = 0
    for delta in samples:
        step = best_two_move_step(region, positions, np.stack([np.zeros(2), delta]))
        hits += step is not None and step.distance <= 1e-3 * region.size
    sampled = hits / len(samples)
    print(f"sampled {sampled:.4f} grid {grid:.4f}")
    assert abs(sampled - grid) < 0.03, (sampled, grid)  # 3 sigma of 600 samples


def test_disk_fractions_match_the_paper():
    """Seed 004 Sec. IV-F: d12 = 0.1 reaches 6.3 % in two moves and 30 % in four; the two-move
    maximum is 0.373 near d12 = 0.81 (their numeric method underestimates, as ours does)."""
    disk = DiskRegion(np.zeros(2), 0.5)
    two, four = reachable_fraction(disk, [0.1, 0.0], 4, cells=81, contacts=64)
    assert two == pytest.approx(0.063, abs=0.006)
    assert four == pytest.approx(0.30, abs=0.03)
    assert reachable_fraction(disk, [0.81, 0.0], 2, cells=121)[0] == pytest.approx(0.373, abs=0.01)


def test_square_is_fully_reachable_in_four_relative_moves():
    """Seed 004 Sec. IV-D: every configuration of a square in at most five moves (two two-move
    steps and the translation)."""
    square = PolygonRegion(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float))
    fractions = reachable_fraction(square, [0.1, 0.05], 4, cells=81)
    assert fractions[0] < 0.5 and fractions[1] >= 0.995


# ---------------------------------------------------------------- the command


def test_cli_reachable_prints_the_fraction(capsys):
    assert cli_main(["plan", "reachable", "--disk", "--d12", "0.81", "--moves", "2", "--json"]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["fraction"] == pytest.approx(0.373, abs=0.01)
    assert cli_main(["plan", "reachable", "--disk", "--d12", "0.3", "--moves", "3"]) == 2


def _cli(tmp_path, boundary, *args):
    ws = tmp_path / "ws.json"
    ws.write_text(json.dumps({"boundary": boundary}))
    return ["plan", "wall-contact", "--workspace", str(ws), *args, "-o", str(tmp_path / "p.json")]


def test_cli_writes_a_coil_board_plan_that_checks(tmp_path, capsys):
    status = cli_main(_cli(tmp_path, WORKSPACES["disk"], "--start=-10,0", "--start", "5,5",
                           "--goal", "3,-8", "--goal=-12,10", "--json"))
    assert status == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(line) == {"solved", "moves", "length", "seconds"} and line["solved"]
    plan = load_plan(tmp_path / "p.json")
    check_plan(plan)  # the model reproduces `expected`
    assert plan.rig == "coil-board" and len(plan.moves) == line["moves"]
    end = np.array(plan.expected[-1])
    assert np.all(np.hypot(*(end - [[3, -8], [-12, 10]]).T) <= EPSILON)
    assert sum(math.hypot(*m) for m in plan.moves) == pytest.approx(line["length"], abs=1e-5)


def test_cli_rejects_obstacles_and_a_third_particle(tmp_path, capsys):
    ws = tmp_path / "ws.json"
    ws.write_text(json.dumps({"boundary": {"rect": [0, 0, 50, 50]},
                              "obstacles": [{"disk": [25, 25, 3]}]}))
    args = ["plan", "wall-contact", "--workspace", str(ws), "--start", "5,5", "--start", "10,5",
            "--goal", "40,40", "--goal", "40,45", "-o", str(tmp_path / "p.json")]
    assert cli_main(args) == 2
    assert "obstacles" in capsys.readouterr().err
    args = _cli(tmp_path, {"rect": [0, 0, 50, 50]}, "--start", "5,5", "--start", "10,5",
                "--start", "20,5", "--goal", "1,1", "--goal", "2,2", "--goal", "3,3")
    assert cli_main(args) == 2


# ---------------------------------------------------------------- speed-ups keep the answers


def test_shortest_contact_matches_a_dense_search_along_the_wall():
    """The closed-form contact (foot of the start; reflection law with the final translation)
    against the best of 200001 contacts sampled along the wall."""
    from rigctl.plans.wall_contact import _shortest_contact

    region = PolygonRegion(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]))
    a, edge = region.vertices[0], region.vertices[1] - region.vertices[0]  # the wall y = 0
    normal, offset = region.normals[0], region.offsets[0]
    ts = np.linspace(-1.0, 2.0, 200001)
    contacts = a + ts[:, None] * edge
    rng = np.random.default_rng(3)
    for _ in range(20):
        start, goal = rng.uniform(0.5, 9.5, 2), rng.uniform(0.5, 9.5, 2)
        alone = np.hypot(*(contacts - start).T)
        assert _shortest_contact(a, edge, normal, offset, start, None) == pytest.approx(
            ts[np.argmin(alone)], abs=2e-5)
        both = alone + np.hypot(*(contacts - goal).T)
        assert _shortest_contact(a, edge, normal, offset, start, goal) == pytest.approx(
            ts[np.argmin(both)], abs=2e-5)
    # Hand-computed: start (2, 1), goal (8, 3): the mirror of the goal is (8, -3), the segment
    # from (2, 1) crosses y = 0 a quarter of the way, at x = 3.5, so t = 0.35.
    t = _shortest_contact(a, edge, normal, offset, np.array([2.0, 1.0]), np.array([8.0, 3.0]))
    assert t == pytest.approx(0.35, abs=1e-12)


def test_look_ahead_matches_trying_every_corner_in_full():
    """The look-ahead evaluates only the walls near each corner and skips second steps that
    cannot win; a plain version (every wall, every second step) must choose the same step."""
    from rigctl.plans.wall_contact import (
        _LOOKAHEAD_CORNERS,
        _after,
        _clearance,
        _look_ahead,
        _polygon_steps,
    )

    def plain(region, positions, goals, reach, greedy):
        following = best_two_move_step(region, _after(region, positions, greedy), goals, reach)
        if following is not None and following.distance <= EPSILON:
            return greedy
        corners: list = []
        _polygon_steps(region, positions, goals, _clearance(region, reach), corners)
        corners = np.unique(np.round(np.array(corners), 9), axis=0)
        goal_delta = goals[1] - goals[0]
        corners = corners[np.argsort(np.hypot(*(corners - goal_delta).T))[:_LOOKAHEAD_CORNERS]]
        best, best_length = greedy, math.inf
        for corner in corners:
            aim = np.stack([positions[0], positions[0] + corner])
            first = best_two_move_step(region, positions, aim, reach)
            if first is None or first.distance > 1e-6 * region.size:
                continue
            second = best_two_move_step(region, _after(region, positions, first), goals, reach)
            if (second is not None and second.distance <= EPSILON
                    and first.length + second.length < best_length):
                best, best_length = first, first.length + second.length
        return best

    rng = np.random.default_rng(11)
    departures = compared = 0
    for name in ("hexagon", "acute-triangle", "square"):
        boundary = WORKSPACES[name]
        ws, region = _shape_workspace(boundary), centre_region(boundary, RADIUS)
        for _ in range(30):
            positions, goals = _random_pair(ws, rng), _random_pair(ws, rng)
            greedy = best_two_move_step(region, positions, goals, 2 * RADIUS)
            if greedy is None or greedy.distance <= EPSILON:
                continue
            fast = _look_ahead(region, positions, goals, 2 * RADIUS, greedy, EPSILON)
            slow = plain(region, positions, goals, 2 * RADIUS, greedy)
            np.testing.assert_allclose(fast.contact, slow.contact, atol=1e-9)
            np.testing.assert_allclose(fast.other_end, slow.other_end, atol=1e-9)
            assert fast.length == pytest.approx(slow.length, abs=1e-9)
            departures += fast is not greedy
            compared += 1
    # The comparison covered many look-aheads, some of which left the greedy step (52 and 10).
    assert compared >= 30 and departures >= 5


def test_a_move_along_the_wall_a_particle_is_on_slides_along_it():
    """A move parallel to a wall up to rounding (into it by 1e-14 of its length) neither pins
    the particle on that wall (eq. 1 needs a push) nor stops it dead: it slides the full length."""
    region = PolygonRegion(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]))
    end = apply_move(region, [[0.0, 5.0]], [-3e-14, 3.0])
    np.testing.assert_allclose(end, [[0.0, 8.0]], atol=1e-12)


def test_planner_margin_polygon_lies_the_margin_inside_every_edge():
    from rigctl.plans.wall_contact import _MARGIN_REL

    region = PolygonRegion(np.array([[0.0, 0.0], [60.0, 0.0], [5.0, 15.0]]))
    margin = _MARGIN_REL * region.size
    gaps = region.offsets[None, :] - region.shrunk @ region.normals.T  # (vertex, edge)
    # Vertex i of the shrunk polygon is where edges i-1 and i, moved in by the margin, meet.
    for i in range(3):
        assert gaps[i, i] == pytest.approx(margin, abs=1e-12)
        assert gaps[i, i - 1] == pytest.approx(margin, abs=1e-12)
        assert gaps[i, (i + 1) % 3] > margin


def test_the_disk_two_move_test_is_the_union_of_its_contacts_chord_regions():
    """The compiled loop against the definition written as arrays: a point w (other minus pinned
    after the two moves) is reached when some contact n_k on eq. 2's arc has |w + R n_k| <= R (the
    pinned particle stays in the disk) and n_k . w >= n_k . d (it pushes into the wall)."""
    R, contacts = 1.0, 48
    rng = np.random.default_rng(7)
    points = rng.uniform(-2 * R, 2 * R, (3000, 2))
    for delta in ([0.3, 0.1], [1.9, 0.0], [0.0, -0.5], [-1.2, 0.7]):
        d = np.array(delta)
        expected = np.zeros(len(points), dtype=bool)
        for sign in (1.0, -1.0):
            dd, w = sign * d, sign * points
            half = np.arccos(np.hypot(*dd) / (2 * R))
            psi = np.arctan2(-dd[1], -dd[0]) + np.linspace(-half, half, contacts)
            n = np.stack([np.cos(psi), np.sin(psi)], axis=1)
            inside_disk = np.linalg.norm(w[:, None, :] + R * n[None], axis=2) <= R + 1e-9
            into_wall = w @ n.T >= (n @ dd)[None, :] - 1e-9
            expected |= (inside_disk & into_wall).any(axis=1)
        got = two_move_reachable(DiskRegion(np.zeros(2), R), d, points, contacts)
        assert 0 < got.sum() < len(points)
        np.testing.assert_array_equal(got, expected)
