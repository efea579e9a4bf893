"""The global-input model against positions worked out by hand and against a brute-force integrator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.core.errors import PlanError
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.workspace import ShapeWorkspace, Workspace

SQRT2 = math.sqrt(2.0)


def env1() -> ShapeWorkspace:
    """The paper's environment 1 in mm: border walls 50 thick and the L."""
    walls = [(0, 0, 400, 50), (0, 350, 400, 50), (0, 0, 50, 400), (350, 0, 50, 400)]
    the_l = [(175, 150, 100, 25), (150, 150, 25, 100)]
    return ShapeWorkspace(("rect", (0, 0, 400, 400)), [("rect", r) for r in walls + the_l])


def brute_force_slide(nearest, point, move, radius, step=2e-3):
    """Second method: tiny straight steps, each followed by pushing the agent straight back out
    of the wall. First order in `step`, so two step sizes are combined (Richardson) to cancel
    the first-order error. `nearest(x, y)` gives the nearest point of the wall, by hand."""

    def run(h):
        x, y = point
        count = int(math.ceil(math.hypot(*move) / h))
        dx, dy = move[0] / count, move[1] / count
        for _ in range(count):
            x, y = x + dx, y + dy
            qx, qy = nearest(x, y)
            gap = math.hypot(x - qx, y - qy)
            if gap < radius:
                x, y = qx + (x - qx) * radius / gap, qy + (y - qy) * radius / gap
        return np.array([x, y])

    return 2 * run(step / 2) - run(step)


def nearest_on_box(x0, y0, x1, y1):
    """Nearest point of the rectangle [x0, x1] x [y0, y1] to a point outside it."""
    return lambda x, y: (min(max(x, x0), x1), min(max(y, y0), y1))


def nearest_on_circle_from_inside(radius):
    """Nearest point of the circle |p| = radius to a point inside it (not the centre)."""
    return lambda x, y: (x * radius / math.hypot(x, y), y * radius / math.hypot(x, y))


def test_free_move_is_a_translation():
    model = GlobalInputModel(env1(), [8.0, 8.0])
    start = np.array([[100.0, 100.0], [300.0, 300.0]])
    np.testing.assert_array_equal(model.apply(start, [10.0, -5.0]), start + [10.0, -5.0])


def test_move_into_a_wall_at_45_degrees_slides_along_it():
    model = GlobalInputModel(env1(), [8.0])
    # The bottom wall's top face is y = 50, so the centre stops at y = 58 after 12 mm down; the
    # remaining input keeps only its tangential part: x advances by all 30 mm.
    np.testing.assert_allclose(model.apply([[100.0, 70.0]], [30.0, -30.0]), [[130.0, 58.0]], atol=1e-9)


def test_non_slip_stops_where_it_touches():
    model = GlobalInputModel(env1(), [8.0], contact="non-slip")
    # Contact after 12 mm down, i.e. 12 mm right as well; then pushed into the wall it stays.
    np.testing.assert_allclose(model.apply([[100.0, 70.0]], [30.0, -30.0]), [[112.0, 58.0]], atol=1e-9)


def test_non_slip_moves_parallel_to_a_wall():
    model = GlobalInputModel(env1(), [8.0], contact="non-slip")
    np.testing.assert_allclose(model.apply([[100.0, 58.0]], [40.0, 0.0]), [[140.0, 58.0]], atol=1e-9)


def test_sliding_past_the_end_of_the_l_resumes_the_input_direction():
    model = GlobalInputModel(env1(), [8.0])
    start, move = np.array([250.0, 183.0]), np.array([40.0, -40.0])
    end = model.apply(start[None], move)[0]

    # By hand: slide right along the bar's top (y = 183) to its end x = 275, using 25 * sqrt2 of
    # the 40 * sqrt2 mm of input. Round the corner (275, 175) on the circle of radius 8: with lag
    # = angle(input) - angle(normal), sliding gives 8 d(lag)/ds = -sin(lag), so
    # tan(lag/2) = tan(lag0/2) exp(-s/8); lag0 = -45 - 90 = -135 deg, release at lag = -90 deg
    # after s = 8 ln tan(67.5 deg) = 8 ln(1 + sqrt2), at the normal 45 deg. The rest goes along u.
    u = move / np.hypot(*move)
    release = np.array([275.0, 175.0]) + 8.0 * np.array([1.0, 1.0]) / SQRT2
    rest = 40 * SQRT2 - 25 * SQRT2 - 8.0 * math.log(1.0 + SQRT2)
    np.testing.assert_allclose(end, release + rest * u, atol=1e-9)

    # Second method: brute-force integration against the bar alone.
    reference = brute_force_slide(nearest_on_box(175, 150, 275, 175), start, move, 8.0)
    np.testing.assert_allclose(end, reference, atol=1e-5)

    # Resumed direction: the last stretch is a straight line along u, tangent to the corner circle.
    offset = end - np.array([275.0, 175.0])
    assert abs(offset[0] * u[1] - offset[1] * u[0]) == pytest.approx(8.0, abs=1e-9)


def test_a_pushed_agent_stops_against_a_blocked_one():
    model = GlobalInputModel(env1(), [8.0, 6.0])
    # A is pushed into the right wall (x = 350 - 8); B rolls into A and stops touching it.
    end = model.apply([[330.0, 100.0], [300.0, 100.0]], [60.0, 0.0])
    np.testing.assert_allclose(end, [[342.0, 100.0], [328.0, 100.0]], atol=1e-9)
    assert np.hypot(*(end[0] - end[1])) == pytest.approx(8.0 + 6.0, abs=1e-9)


def test_a_pushed_agent_slides_round_a_blocked_one():
    model = GlobalInputModel(env1(), [8.0, 8.0])
    # B meets A 5 mm below its centre, slides round it and ends at the wall just under A:
    # x = 342 and |B - A| = 16 give y = 100 - 16. (Contact at x = 342 - sqrt(16^2 - 5^2) after
    # 26.8 mm, then 16 ln tan(80.9 deg) = 29.3 mm round A: within the 60 mm of input.)
    end = model.apply([[330.0, 100.0], [300.0, 95.0]], [60.0, 0.0])
    np.testing.assert_allclose(end, [[342.0, 100.0], [342.0, 84.0]], atol=1e-6)


def test_non_slip_agent_stops_where_it_first_touches_a_stuck_one():
    model = GlobalInputModel(env1(), [8.0, 8.0], contact="non-slip")
    # A sticks to the right wall; B, 5 mm lower, meets A's disc at x = 342 - sqrt(16^2 - 5^2).
    end = model.apply([[330.0, 100.0], [300.0, 95.0]], [60.0, 0.0])
    np.testing.assert_allclose(end[0], [342.0, 100.0], atol=1e-9)
    np.testing.assert_allclose(end[1], [342.0 - math.sqrt(16.0**2 - 5.0**2), 95.0], atol=1e-6)


def test_min_separation_is_kept():
    model = GlobalInputModel(env1(), [8.0, 8.0], min_separation_mm=3.0)
    end = model.apply([[330.0, 100.0], [300.0, 100.0]], [60.0, 0.0])
    np.testing.assert_allclose(end, [[342.0, 100.0], [342.0 - 19.0, 100.0]], atol=1e-9)
    assert model.is_free(end)
    assert not model.is_free(end + [[0.0, 0.0], [1.0, 0.0]])


def test_wedge_corner_holds_the_agent():
    model = GlobalInputModel(env1(), [8.0])
    np.testing.assert_allclose(model.apply([[300.0, 100.0]], [100.0, -100.0]), [[342.0, 58.0]], atol=1e-9)
    # The inside corner of the L, (175, 175), from above right.
    np.testing.assert_allclose(model.apply([[200.0, 200.0]], [-100.0, -100.0]), [[183.0, 183.0]], atol=1e-9)


def test_disk_boundary():
    ws = ShapeWorkspace(("disk", (0.0, 0.0, 50.0)))
    model = GlobalInputModel(ws, [5.0])
    # From the centre straight out: stops on the circle of radius 50 - 5, head on.
    move = np.array([60.0, 10.0])
    np.testing.assert_allclose(model.apply([[0.0, 0.0]], move)[0], 45.0 * move / np.hypot(*move), atol=1e-9)
    # From (0, 30) to the right: meets the circle at x = sqrt(45^2 - 30^2), then slides down it
    # towards (45, 0), the point farthest along the input, approaching it without ever passing.
    end = model.apply([[0.0, 30.0]], [1000.0, 0.0])[0]
    np.testing.assert_allclose(end, [45.0, 0.0], atol=1e-6)
    middle = model.apply([[0.0, 30.0]], [60.0, 0.0])[0]
    assert np.hypot(*middle) == pytest.approx(45.0, abs=1e-9)
    reference = brute_force_slide(nearest_on_circle_from_inside(50.0), (0.0, 30.0), (60.0, 0.0), 5.0)
    np.testing.assert_allclose(middle, reference, atol=1e-5)


@pytest.mark.parametrize("contact", ["slide", "non-slip"])
def test_moves_compose_on_straight_walls(contact):
    model = GlobalInputModel(env1(), [8.0], contact=contact)
    rng = np.random.default_rng(11)
    start = env1().sample_free(rng, 300, 8.0)[:, None, :]
    # Axis-aligned moves only meet straight walls and square corners.
    moves = rng.choice([-1.0, 1.0], size=(300, 1)) * rng.uniform(5, 200, size=(300, 1))
    moves = np.where(rng.random((300, 1)) < 0.5, np.hstack([moves, 0 * moves]), np.hstack([0 * moves, moves]))
    moves = moves + rng.uniform(-0.3, 0.3, size=(300, 2)) * (moves == 0)  # and slightly oblique
    whole = model.apply(start, moves)
    pieces = start
    for _ in range(10):
        pieces = model.apply(pieces, moves / 10)
    np.testing.assert_allclose(pieces, whole, atol=1e-6)


@pytest.mark.parametrize(
    "workspace",
    [
        env1(),
        ShapeWorkspace(
            ("polygon", [(0, 0), (300, 0), (380, 150), (300, 300), (0, 300), (60, 150)]),
            [("disk", (150, 150, 40)), ("polygon", [(220, 60), (260, 80), (240, 120)])],
        ),
    ],
    ids=["env1", "polygons-and-disk"],
)
def test_moves_compose_round_corners(workspace):
    model = GlobalInputModel(workspace, [8.0])
    rng = np.random.default_rng(5)
    start = workspace.sample_free(rng, 400, 8.0)[:, None, :]
    angle = rng.uniform(0, 2 * np.pi, 400)
    moves = rng.uniform(1, 150, (400, 1)) * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    whole = model.apply(start, moves)
    pieces = start
    fractions = rng.dirichlet(np.ones(10), size=400)  # ten uneven pieces
    for k in range(10):
        pieces = model.apply(pieces, moves * fractions[:, k : k + 1])
    np.testing.assert_allclose(pieces, whole, atol=1e-3)
    assert np.all(model.is_free(whole))


def test_batches_broadcast_and_match_single_calls():
    model = GlobalInputModel(env1(), [8.0, 8.0])
    rng = np.random.default_rng(2)
    states = env1().sample_free(rng, 40, 8.0).reshape(4, 5, 2, 2)  # batch (4, 5)
    states = np.where(model.is_free(states)[..., None, None], states, [[100.0, 100.0], [300.0, 300.0]])
    moves = rng.uniform(-60, 60, size=(5, 2))  # broadcasts over the leading 4
    batch = model.apply(states, moves)
    assert batch.shape == (4, 5, 2, 2)
    for i in range(4):
        for j in range(5):
            np.testing.assert_array_equal(batch[i, j], model.apply(states[i, j], moves[j]))


def test_rollout_lists_each_state():
    model = GlobalInputModel(env1(), [8.0])
    states = model.rollout([[100.0, 70.0]], [[30.0, -30.0], [0.0, 20.0]])
    np.testing.assert_allclose(states, [[[130.0, 58.0]], [[130.0, 78.0]]], atol=1e-9)


def test_is_free():
    model = GlobalInputModel(env1(), [8.0, 8.0])
    assert model.is_free([[100.0, 100.0], [120.0, 100.0]])
    assert not model.is_free([[100.0, 100.0], [110.0, 100.0]])  # discs overlap
    assert not model.is_free([[100.0, 55.0], [200.0, 100.0]])  # into the bottom wall
    assert model.is_free(np.zeros((3, 2, 2)) + [[100.0, 100.0], [200.0, 100.0]]).shape == (3,)


def test_rasterized_model_agrees_with_the_exact_one():
    exact_ws = env1()
    exact = GlobalInputModel(exact_ws, [8.0])
    coarse = GlobalInputModel(exact_ws.rasterize(0.5), [8.0])
    rng = np.random.default_rng(3)
    start = exact_ws.sample_free(rng, 500, 8.0)[:, None, :]
    angle = rng.uniform(0, 2 * np.pi, 500)
    moves = rng.uniform(1, 150, (500, 1)) * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    # The raster keeps each sample's nearest wall piece, so agents touch the same walls.
    np.testing.assert_allclose(coarse.apply(start, moves), exact.apply(start, moves), atol=1e-6)


def test_image_workspace_model_is_close_to_the_drawing():
    exact_ws = env1()
    x0, y0, x1, y1 = exact_ws.bounds
    xs = x0 + (np.arange(800) + 0.5) * 0.5
    ys = y0 + (np.arange(800)[::-1] + 0.5) * 0.5
    free = exact_ws.clearance(np.stack(np.meshgrid(xs, ys), axis=-1)) >= 0
    picture = GlobalInputModel(Workspace.from_mask(free, 0.5, (x0, y0)), [8.0])
    exact = GlobalInputModel(exact_ws, [8.0])
    rng = np.random.default_rng(4)
    start = exact_ws.sample_free(rng, 300, 9.0)[:, None, :]
    angle = rng.uniform(0, 2 * np.pi, 300)
    moves = rng.uniform(1, 150, (300, 1)) * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    error = np.hypot(*(exact.apply(start, moves) - picture.apply(start, moves)).reshape(-1, 2).T)
    assert np.median(error) < 1e-6
    assert np.percentile(error, 95) < 0.5  # a pixel's worth where inside corners are met


def test_bad_arguments():
    with pytest.raises(PlanError):
        GlobalInputModel(env1(), [8.0, -1.0])
    with pytest.raises(PlanError):
        GlobalInputModel(env1(), [8.0], contact="sticky")  # type: ignore[arg-type]
    model = GlobalInputModel(env1(), [8.0, 8.0])
    with pytest.raises(PlanError):
        model.apply(np.zeros((3, 2)), [1.0, 0.0])


@pytest.mark.parametrize("contact", ["slide", "non-slip"])
def test_crowds_never_overlap_or_enter_walls(contact):
    ws = env1()
    model = GlobalInputModel(ws, [5.0, 6.0, 7.0, 8.0], contact=contact, min_separation_mm=1.0)
    rng = np.random.default_rng(8)
    states = ws.sample_free(rng, 4000, 8.0).reshape(-1, 4, 2)
    states = states[model.is_free(states)][:40]
    for _ in range(3):  # long moves herd them into corners and onto each other
        angle = rng.uniform(0, 2 * np.pi, len(states))
        states = model.apply(states, 100.0 * np.stack([np.cos(angle), np.sin(angle)], axis=1))
        assert np.all(model.is_free(states))


def test_sliding_round_a_corner_onto_its_side_matches_brute_force():
    # The agent meets the circle round the L's corner (150, 250), slides round it and goes on
    # down the L's left side: it must end on that side (x = 150 - 8) where brute force puts it.
    model = GlobalInputModel(env1(), [8.0])
    start = np.array([136.0, 262.0])
    move = 30.0 * np.array([math.sin(math.radians(22.5)), -math.cos(math.radians(22.5))])
    end = model.apply(start[None], move)[0]
    reference = brute_force_slide(nearest_on_box(150, 150, 175, 250), start, move, 8.0)
    np.testing.assert_allclose(end, reference, atol=1e-5)
    assert end[0] == pytest.approx(142.0, abs=1e-9)


def test_agents_a_hair_inside_contact_compose_round_corners():
    # Agents left up to 5e-8 mm inside their contact level (as event solving leaves them) that
    # slide round the L's corners onto the straight sides: the closed-form meeting of an arc
    # with the side must give the same end as the same move applied in 20 pieces.
    model = GlobalInputModel(env1(), [5.0])
    rng = np.random.default_rng(11)
    corners = np.array([[150.0, 150.0], [150.0, 250.0], [175.0, 250.0], [275.0, 175.0], [275.0, 150.0]])
    count = 600
    which = rng.integers(0, len(corners), count)
    theta = rng.uniform(0, 2 * np.pi, count)
    radius = 5.0 - rng.uniform(0.0, 5e-8, count)
    start = corners[which] + radius[:, None] * np.stack([np.cos(theta), np.sin(theta)], axis=1)
    start = start[env1().clearance(start) > 5.0 - 1e-7][:, None, :]
    angle = rng.integers(0, 16, len(start)) * (2 * np.pi / 16)
    moves = 5.0 * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    whole = model.apply(start, moves)
    pieces = start
    for _ in range(20):
        pieces = model.apply(pieces, moves / 20)
    np.testing.assert_allclose(pieces, whole, atol=1e-6)
    assert np.all(env1().clearance(whole) >= 5.0 - 1e-7)


def test_k_moves_from_each_node_match_single_calls():
    # The planner's call shape, (b, 1, n, 2) against (1, k, 2), looks the walls up once per node
    # and sends only the agents a wall can reach through the events; the second method applies
    # each (configuration, move) on its own.
    model = GlobalInputModel(env1(), [5.0, 5.0])
    rng = np.random.default_rng(7)
    first = env1().sample_free(rng, 400, 5.0)
    near = first[env1().clearance(first) < 12.0][:40]  # mostly within reach of a wall
    second = near + rng.choice([-1.0, 1.0], (len(near), 2)) * rng.uniform(10.5, 20.0, (len(near), 2))
    nodes = np.stack([near, second], axis=1)
    nodes = nodes[model.is_free(nodes)]
    angle = np.arange(16) * (2 * np.pi / 16)
    moves = 5.0 * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    together = model.apply(nodes[:, None], moves[None, :])
    assert together.shape == (len(nodes), 16, 2, 2)
    for i, node in enumerate(nodes):
        for j, move in enumerate(moves):
            np.testing.assert_allclose(together[i, j], model.apply(node, move), atol=1e-12)


def test_exact_shortcuts_agree_with_the_event_by_event_path():
    # On shapes the model translates agents whose swept path is clear and slides an agent along
    # a wall in one step where the wall runs under all of it; a rasterized workspace knows no
    # such shortcuts and goes event by event (it keeps each sample's wall piece, so it is exact
    # for discs this wide): the two must agree. The agents start touching walls (pushed into
    # them first) and far enough apart that they do not meet within the move.
    exact_ws = env1()
    exact = GlobalInputModel(exact_ws, [5.0, 5.0])
    events = GlobalInputModel(exact_ws.rasterize(0.5), [5.0, 5.0])
    rng = np.random.default_rng(11)
    first = exact_ws.sample_free(rng, 300, 5.0)
    second = exact_ws.sample_free(rng, 300, 5.0)
    nodes = np.stack([first, second], axis=1)
    nodes = nodes[np.hypot(*(first - second).T) > 40.0][:60]
    axes = np.array([[300.0, 0.0], [-300.0, 0.0], [0.0, 300.0], [0.0, -300.0]])
    nodes = exact.apply(nodes, axes[rng.integers(0, 4, len(nodes))])
    nodes = nodes[np.hypot(*(nodes[:, 0] - nodes[:, 1]).T) > 20.0]
    assert len(nodes) > 20
    assert np.mean(exact_ws.clearance(nodes) < 5.0 + 1e-6) > 0.5  # mostly touching a wall
    angle = np.arange(16) * (2 * np.pi / 16)
    moves = 5.0 * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    np.testing.assert_allclose(exact.apply(nodes[:, None], moves[None]),
                               events.apply(nodes[:, None], moves[None]), atol=1e-6)
    long = 12.0 * moves
    far_apart = np.hypot(*(nodes[:, 0] - nodes[:, 1]).T) > 2 * 12.0 + 10.0
    np.testing.assert_allclose(exact.apply(nodes[far_apart, None], long[None]),
                               events.apply(nodes[far_apart, None], long[None]), atol=1e-6)
