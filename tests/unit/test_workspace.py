"""Workspace geometry against distances worked out by hand, and the grid backends against the exact one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.core.errors import PlanError
from rigctl.plans.workspace import GridWorkspace, ShapeWorkspace, Workspace

# A 100 x 100 box with one 20 x 10 block in it (x 40..60, y 40..50).
BOX = ShapeWorkspace(("rect", (0, 0, 100, 100)), [("rect", (40, 40, 20, 10))])
# Right triangle (0,0), (40,0), (0,30); its hypotenuse is the line 3x + 4y = 120.
TRIANGLE = [(0, 0), (40, 0), (0, 30)]


def env1() -> ShapeWorkspace:
    walls = [(0, 0, 400, 50), (0, 350, 400, 50), (0, 0, 50, 400), (350, 0, 50, 400)]
    the_l = [(175, 150, 100, 25), (150, 150, 25, 100)]
    return ShapeWorkspace(("rect", (0, 0, 400, 400)), [("rect", r) for r in walls + the_l])


def test_rect_clearance_inside_near_a_corner_and_outside_round_it():
    clearance, normal, curvature = BOX.surface(np.array([[58.0, 49.0], [63.0, 54.0], [50.0, 37.0]]))
    # (58, 49): 2 from the right side, 1 from the top -> -1, leaving upwards.
    assert clearance[0] == pytest.approx(-1.0)
    np.testing.assert_allclose(normal[0], [0.0, 1.0])
    # (63, 54): 3 right and 4 above the corner (60, 50): a 3-4-5 triangle, on a circle round it.
    assert clearance[1] == pytest.approx(5.0)
    np.testing.assert_allclose(normal[1], [0.6, 0.8])
    assert curvature[1] == pytest.approx(1 / 5)
    # (50, 37): 3 below the bottom face, flat.
    assert clearance[2] == pytest.approx(3.0)
    np.testing.assert_allclose(normal[2], [0.0, -1.0])
    assert curvature[2] == 0.0


def test_boundary_counts_from_inside():
    clearance, normal, _ = BOX.surface(np.array([[3.0, 80.0], [100.0, 80.0], [104.0, 103.0]]))
    np.testing.assert_allclose(clearance, [3.0, 0.0, -5.0])
    np.testing.assert_allclose(normal[0], [1.0, 0.0])
    np.testing.assert_allclose(normal[2], [-0.8, -0.6])  # back towards the corner (100, 100)


@pytest.mark.parametrize("vertices", [TRIANGLE, TRIANGLE[::-1]], ids=["ccw", "cw"])
def test_polygon_either_orientation(vertices):
    ws = ShapeWorkspace(("rect", (-50, -50, 150, 150)), [("polygon", vertices)])
    points = np.array([[30.0, 20.0], [10.0, 5.0], [-3.0, -4.0]])
    clearance, normal, curvature = ws.surface(points)
    # (30, 20): (3*30 + 4*20 - 120) / 5 = 10 from the hypotenuse.
    assert clearance[0] == pytest.approx(10.0)
    np.testing.assert_allclose(normal[0], [0.6, 0.8])
    # (10, 5) is inside: 5 above the bottom edge, 10 from the left, 14 from the hypotenuse.
    assert clearance[1] == pytest.approx(-5.0)
    np.testing.assert_allclose(normal[1], [0.0, -1.0])
    # (-3, -4): 5 from the vertex (0, 0).
    assert clearance[2] == pytest.approx(5.0)
    np.testing.assert_allclose(normal[2], [-0.6, -0.8])
    assert curvature[2] == pytest.approx(0.2)


def test_disk_obstacle_and_disk_boundary():
    ws = ShapeWorkspace(("disk", (0, 0, 50)), [("disk", (10, 0, 5))])
    clearance, normal, curvature = ws.surface(np.array([[30.0, 40.0], [0.0, 30.0], [10.0, 8.0]]))
    assert clearance[0] == pytest.approx(0.0, abs=1e-12)  # |(30, 40)| = 50: on the boundary
    # (0, 30): 20 from the boundary circle (the small disk is sqrt(1000) - 5 = 26.6 away); the
    # clearance grows towards the centre.
    assert clearance[1] == pytest.approx(20.0)
    np.testing.assert_allclose(normal[1], [0.0, -1.0])
    assert curvature[1] == pytest.approx(-1 / 30)  # level set: the circle of radius 30, bending round us
    # (10, 8): 8 from the small disk's centre, 3 from its rim.
    assert clearance[2] == pytest.approx(3.0)
    np.testing.assert_allclose(normal[2], [0.0, 1.0])
    assert curvature[2] == pytest.approx(1 / 8)


def test_batch_shapes_and_contains():
    points = np.zeros((3, 4, 2)) + [20.0, 20.0]
    assert BOX.clearance(points).shape == (3, 4)
    assert BOX.normal(points).shape == (3, 4, 2)
    assert BOX.contains(np.array([[20.0, 20.0], [58.0, 49.0]]), 5.0).tolist() == [True, False]
    assert BOX.bounds == (0.0, 0.0, 100.0, 100.0)


def test_sample_free_respects_radius_and_seed():
    ws = env1()
    first = ws.sample_free(np.random.default_rng(7), 500, radius=8.0)
    again = ws.sample_free(np.random.default_rng(7), 500, radius=8.0)
    assert first.shape == (500, 2)
    np.testing.assert_array_equal(first, again)
    assert np.all(ws.clearance(first) >= 8.0)
    with pytest.raises(PlanError):
        ws.sample_free(np.random.default_rng(0), 1, radius=300.0)


def _mask_of(ws: Workspace, mm_per_px: float) -> tuple[np.ndarray, tuple[float, float]]:
    """Pixels whose centres are free; row 0 at the top."""
    x0, y0, x1, y1 = ws.bounds
    width, height = round((x1 - x0) / mm_per_px), round((y1 - y0) / mm_per_px)
    xs = x0 + (np.arange(width) + 0.5) * mm_per_px
    ys = y0 + (np.arange(height)[::-1] + 0.5) * mm_per_px
    return ws.clearance(np.stack(np.meshgrid(xs, ys), axis=-1)) >= 0, (x0, y0)


def test_mask_backend_within_about_half_a_pixel_of_the_drawn_walls():
    ws = ShapeWorkspace(("rect", (0, 0, 100, 80)), [("rect", (20, 20, 30, 10)), ("rect", (60, 40, 10, 30))])
    free, origin = _mask_of(ws, 0.5)
    grid = Workspace.from_mask(free, 0.5, origin)
    points = np.random.default_rng(1).uniform((0, 0), (100, 80), size=(20_000, 2))
    exact = ws.clearance(points)
    error = np.abs(grid.clearance(points) - exact)
    near = (exact > 0) & (exact < 5)  # where agents touch walls
    assert np.max(error[near]) <= 0.5 * 0.75  # corners are rounded by the blur
    # Along straight walls, away from corners and from the creases between walls, it is exact.
    corners = np.array([(x, y) for x in (0, 20, 50, 60, 70, 100) for y in (0, 20, 30, 40, 70, 80)])
    offsets = points[:, None, :] - corners[None]
    plain = (exact > 0) & (exact < 3) & (np.min(np.hypot(offsets[..., 0], offsets[..., 1]), axis=1) > 8)
    np.testing.assert_allclose(grid.clearance(points)[plain], exact[plain], atol=1e-9)


def test_image_rows_run_downwards_and_origin_places_it(tmp_path):
    cv2 = pytest.importorskip("cv2")
    picture = np.full((40, 60), 255, dtype=np.uint8)
    picture[:10, :] = 0  # the top 10 rows are wall
    path = tmp_path / "top-wall.png"
    cv2.imwrite(str(path), picture)
    ws = Workspace.from_image(path, mm_per_px=0.5, origin_mm=(100.0, 200.0))
    # Image is 30 x 20 mm placed at (100, 200); the wall covers y in [215, 220].
    assert ws.clearance(np.array([115.0, 212.0])) == pytest.approx(3.0, abs=0.25)
    assert ws.clearance(np.array([115.0, 218.0])) < 0
    np.testing.assert_allclose(ws.normal(np.array([115.0, 210.0])), [0.0, -1.0], atol=1e-6)
    # Beyond the picture is not free space either.
    assert ws.clearance(np.array([99.0, 205.0])) < 0
    with pytest.raises(PlanError, match="does not exist"):
        Workspace.from_image(tmp_path / "missing.png", 0.5)


def test_rasterized_workspace_is_exact_away_from_the_walls():
    ws = env1()
    grid = ws.rasterize(0.5)
    assert isinstance(grid, GridWorkspace) and grid.exact_geometry
    points = ws.sample_free(np.random.default_rng(3), 5000, radius=0.0)
    exact, exact_normal, exact_curvature = ws.surface(points)
    coarse, coarse_normal, coarse_curvature = grid.surface(points)
    # Cells whose corners are all in free space use the corners' wall pieces: exact, including
    # the crease along the diagonal of an inside corner, which interpolation would cut.
    away = exact > 1.0
    np.testing.assert_allclose(coarse[away], exact[away], atol=1e-9)
    np.testing.assert_allclose(coarse_normal[away], exact_normal[away], atol=1e-9)
    np.testing.assert_allclose(coarse_curvature[away], exact_curvature[away], atol=1e-9)
    assert grid.clearance(np.array([183.0, 183.0])) == pytest.approx(8.0, abs=1e-12)  # the L's crease
    # Cells at a wall are interpolated.
    assert np.max(np.abs(coarse - exact)[~away]) < 0.5 / 2
    assert np.all(grid.clearance_lower_bound(points) <= coarse + 1e-9)


def test_wall_pieces_nearest_a_point():
    ws = ShapeWorkspace(("disk", (0, 0, 100)), [("rect", (10, 10, 20, 10)), ("disk", (-40, 0, 5))])
    pieces = ws.primitives(np.array([[20.0, 25.0], [-40.0, 9.0], [0.0, -90.0]]))
    ends = sorted([tuple(pieces[0, :2]), tuple(pieces[0, 2:4])])
    assert ends == [(10.0, 20.0), (30.0, 20.0)]  # the rect's top side, either way round
    np.testing.assert_allclose(pieces[0, 4:], [0, 1])
    np.testing.assert_allclose(pieces[1], [-40, 0, -40, 0, 5, 1])  # the small disk
    np.testing.assert_allclose(pieces[2], [0, 0, 0, 0, 100, -1])  # inside the boundary disk


def test_rect_clearance_in_free_space_matches_dense_boundary_samples():
    # Second method: the distance to the nearest of points laid 0.01 mm apart along every side
    # of every rect (the boundary included); it overestimates by at most 0.005 mm.
    ws = env1()
    rects = [(0, 0, 400, 400), (0, 0, 400, 50), (0, 350, 400, 50), (0, 0, 50, 400),
             (350, 0, 50, 400), (175, 150, 100, 25), (150, 150, 25, 100)]
    samples = []
    for x, y, w, h in rects:
        for (ax, ay), (bx, by) in [((x, y), (x + w, y)), ((x + w, y), (x + w, y + h)),
                                   ((x + w, y + h), (x, y + h)), ((x, y + h), (x, y))]:
            t = np.linspace(0.0, 1.0, int(math.hypot(bx - ax, by - ay) / 0.01) + 1)
            samples.append(np.stack([ax + t * (bx - ax), ay + t * (by - ay)], axis=1))
    samples = np.concatenate(samples)
    rng = np.random.default_rng(3)
    points = rng.uniform(50, 350, (300, 2))
    points = points[ws.clearance(points) > 0][:60]
    nearest = np.array([np.min(np.hypot(*(samples - p).T)) for p in points])
    clearance = ws.clearance(points)
    assert np.all(clearance <= nearest + 1e-12)
    assert np.all(clearance >= nearest - 0.005)


# Swept discs: `sweep_clear` and `slide_clear`, the exact shortcuts the model takes on shapes.


def test_sweep_clear_against_hand_distances():
    # BOX: block x 40..60, y 40..50 inside walls at 0 and 100; radius 5.
    starts = np.array([
        [30.0, 56.0],  # passes 6 above the block's top (y 50): clear
        [30.0, 54.0],  # passes 4 above: touches it
        [55.0, 55.0],  # touching the top, moving straight up and away: clear
        [66.0, 56.0],  # ends at (63, 53), sqrt(3^2 + 3^2) = 4.24 from the corner (60, 50)
        [50.0, 90.0],  # toward the top wall y = 100, ending 3 short of it: touches it
        [50.0, 90.0],  # the same start moving down: clear
    ])
    moves = np.array([[40.0, 0.0], [40.0, 0.0], [0.0, 20.0], [-3.0, -3.0], [0.0, 7.0],
                      [0.0, -20.0]])
    clear = BOX.sweep_clear(starts, moves, 5.0)
    np.testing.assert_array_equal(clear, [True, False, True, False, False, True])


def test_sweep_clear_a_diagonal_past_a_corner():
    # From (65, 70) along (-1, -1): at x > 60 the nearest block point is the corner (60, 50),
    # farther than 10; at x <= 60 it is the top face, y - 50 >= 10. Stopping at (55, 60) the
    # closest approach is 10, at the end; going on to (45, 50) ends on the top face.
    start = np.array([[65.0, 70.0], [65.0, 70.0]])
    to_55_60 = np.array([[-10.0, -10.0], [-10.0, -10.0]])
    np.testing.assert_array_equal(BOX.sweep_clear(start, to_55_60, np.array([9.9, 10.1])),
                                  [True, False])
    assert not BOX.sweep_clear(start[:1], np.array([[-20.0, -20.0]]), 1.0)[0]


def test_sweep_clear_disk_and_polygon():
    ws = ShapeWorkspace(("disk", (0, 0, 100)), [("disk", (0, 0, 10)), ("polygon", TRIANGLE_AWAY)])
    # Horizontal segments at height h past the central disk (radius 10): gap h - 10.
    starts = np.array([[-50.0, 17.0], [-50.0, 14.0], [-50.0, -17.0]])
    moves = np.array([[60.0, 0.0], [60.0, 0.0], [60.0, 0.0]])
    np.testing.assert_array_equal(ws.sweep_clear(starts, moves, 5.0), [True, False, True])
    # Toward the boundary circle: from (0, -80) down by 10 ends 10 from it, by 16 ends 4 from it.
    starts = np.array([[0.0, -80.0], [0.0, -80.0]])
    np.testing.assert_array_equal(
        ws.sweep_clear(starts, np.array([[0.0, -10.0], [0.0, -16.0]]), 5.0), [True, False]
    )
    # Straight through the triangle: never clear.
    assert not ws.sweep_clear(np.array([[30.0, 45.0]]), np.array([[40.0, 0.0]]), 1.0)[0]


TRIANGLE_AWAY = [(40, 40), (60, 40), (50, 70)]


@pytest.mark.parametrize("workspace", [
    env1(),
    ShapeWorkspace(("polygon", ((0, 0), (200, 0), (200, 100), (100, 150), (0, 100))),
                   [("disk", (50, 50, 10)), ("polygon", ((120, 20), (150, 20), (135, 60)))]),
])
def test_sweep_clear_matches_dense_samples_of_the_clearance(workspace):
    # Second method: the clearance at 2001 points along each segment; a clear segment never
    # comes within the radius, and one that stays 0.02 mm beyond it (more than a sample
    # spacing can hide) is found clear.
    rng = np.random.default_rng(4)
    radius = 5.0
    starts = workspace.sample_free(rng, 3000, radius)
    angle = rng.uniform(0, 2 * np.pi, len(starts))
    moves = rng.uniform(0, 20, (len(starts), 1)) * np.stack([np.cos(angle), np.sin(angle)], 1)
    clear = workspace.sweep_clear(starts, moves, radius)
    along = np.linspace(0.0, 1.0, 2001)
    lowest = workspace.clearance(starts[:, None] + along[None, :, None] * moves[:, None]).min(1)
    assert not np.any(clear & (lowest < radius - 1e-9))
    assert not np.any(~clear & (lowest > radius + 0.02))
    assert 0.2 < clear.mean() < 0.99  # both answers occur


def test_grid_sweep_clear_is_conservative():
    grid = BOX.rasterize(0.5)
    starts = np.array([[30.0, 56.0], [20.0, 20.0]])
    moves = np.array([[40.0, 0.0], [5.0, 5.0]])
    # the grid knows only a lower bound at the start: the long pass is not known to be clear
    np.testing.assert_array_equal(grid.sweep_clear(starts, moves, 5.0), [False, True])


def test_slide_clear_needs_the_same_wall_all_the_way_and_nothing_else():
    # A disc of radius 5 on the block's top face (y 50), so its centre is at y 55; normal (0, 1).
    up = np.array([0.0, 1.0])
    starts = np.array([[42.0, 55.0], [42.0, 55.0], [42.0, 55.0], [42.0, 56.0]])
    moves = np.array([[15.0, 0.0], [20.0, 0.0], [-5.0, 0.0], [10.0, 0.0]])
    # 42 -> 57 stays over the face (x 40..60); 42 -> 62 runs past its end; 42 -> 37 too; the
    # last one is not touching the face at all.
    np.testing.assert_array_equal(
        BOX.slide_clear(starts, moves, 5.0, np.tile(up, (4, 1)), 1e-7), [True, False, False, False]
    )
    # Along the floor of the box (y 0, free-space normal (0, 1)) toward the left wall x = 0:
    # from x 30 by -20 ends 10 from it (clear), by -27 ends 3 from it (the wall is in the way).
    floor = np.array([[30.0, 5.0], [30.0, 5.0]])
    np.testing.assert_array_equal(
        BOX.slide_clear(floor, np.array([[-20.0, 0.0], [-27.0, 0.0]]), 5.0, np.tile(up, (2, 1)),
                        1e-7),
        [True, False],
    )
    # the wrong normal names no wall there
    assert not BOX.slide_clear(floor[:1], np.array([[-20.0, 0.0]]), 5.0, np.array([[0.0, -1.0]]),
                               1e-7)[0]
    # a grid knows no walls: never
    assert not BOX.rasterize(0.5).slide_clear(floor[:1], np.array([[-20.0, 0.0]]), 5.0,
                                              up[None], 1e-7)[0]


def test_polygon_edges_slide_clear():
    # Triangle obstacle TRIANGLE_AWAY: the bottom edge y = 40 from x 40 to 60 faces (0, -1).
    ws = ShapeWorkspace(("rect", (0, 0, 100, 100)), [("polygon", TRIANGLE_AWAY)])
    down = np.array([[0.0, -1.0]])
    start = np.array([[45.0, 35.0]])
    assert ws.slide_clear(start, np.array([[10.0, 0.0]]), 5.0, down, 1e-7)[0]
    assert not ws.slide_clear(start, np.array([[20.0, 0.0]]), 5.0, down, 1e-7)[0]


def test_kernels_are_compiled_once_whatever_the_arrays_look_like():
    # A read-only or strided view would otherwise make numba compile a second version in the
    # middle of a run (seconds); every query is handed the one array type the kernels are
    # made for when the first ShapeWorkspace is built.
    from rigctl.plans import workspace as module

    ws = env1()
    view = np.broadcast_to(np.array([100.0, 100.0]), (5, 2))  # read-only, stride 0
    strided = np.ones((3, 4, 2))[:, ::2] * 100.0
    np.testing.assert_allclose(ws.clearance(view), 50.0)
    ws.surface(strided)
    assert ws.sweep_clear(view, view[::-1] * 0.01, 5.0).all()
    ws.slide_clear(view, view, np.full(5, 5.0), view, 1e-7)
    for kernel in (module._shape_query, module._shape_sweep_clear, module._shape_slide_clear):
        assert len(kernel.signatures) == 1, kernel
