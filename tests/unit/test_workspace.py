"""Workspace geometry against distances worked out by hand, and the grid backends against the exact one."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from rigctl.errors import PlanError
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


def test_mask_backend_within_half_a_pixel_of_the_exact_walls():
    ws = ShapeWorkspace(("rect", (0, 0, 100, 80)), [("rect", (20, 20, 30, 10)), ("rect", (60, 40, 10, 30))])
    free, origin = _mask_of(ws, 0.5)
    grid = Workspace.from_mask(free, 0.5, origin)
    points = np.random.default_rng(1).uniform((0, 0), (100, 80), size=(20_000, 2))
    exact = ws.clearance(points)
    near = np.abs(exact) < 10  # where agents touch walls; medial ridges are not contact surfaces
    assert np.max(np.abs(grid.clearance(points) - exact)[near]) <= 0.5 * 0.5 + 1e-9


def test_mask_backend_on_curved_walls_stays_within_a_pixel():
    ws = ShapeWorkspace(("disk", (50, 50, 48)), [("disk", (40, 40, 10))])
    free, origin = _mask_of(ws, 0.5)
    grid = Workspace.from_mask(free, 0.5, origin)
    points = np.random.default_rng(2).uniform((2, 2), (98, 98), size=(20_000, 2))
    exact = ws.clearance(points)
    band = (exact > -3) & (exact < 5)
    error = np.abs(grid.clearance(points) - exact)[band]
    # A pixelated circle is a staircase: which pixel centres fell inside tells the wall only to
    # about half a pixel.
    assert np.max(error) < 0.5 * 0.75
    assert np.median(error) < 0.5 * 0.4


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


def test_rasterized_workspace_matches_the_exact_one_off_the_ridges():
    ws = env1()
    grid = ws.rasterize(0.5)
    assert isinstance(grid, GridWorkspace)
    points = ws.sample_free(np.random.default_rng(3), 5000, radius=0.0)
    exact, exact_normal, _ = ws.surface(points)
    coarse, coarse_normal, _ = grid.surface(points)
    near_wall = exact < 12
    assert np.max(np.abs(coarse - exact)) < 0.5 / 2
    assert np.median(np.abs(coarse - exact)[near_wall]) < 1e-9  # flat walls are sampled exactly
    agree = np.sum(coarse_normal * exact_normal, axis=1)
    assert np.percentile(agree[near_wall], 5) > math.cos(math.radians(1))


def test_grid_query_cost_does_not_grow_with_obstacle_pixels():
    few = np.ones((400, 400), dtype=bool)
    few[190:210, 190:210] = False
    many = np.random.default_rng(4).random((400, 400)) > 0.3  # speckle: ~48,000 obstacle pixels
    points = np.random.default_rng(5).uniform(0, 200, size=(50_000, 2))
    costs = []
    for mask in (few, many):
        ws = Workspace.from_mask(mask, 0.5)
        ws.surface(points)  # warm up
        start = time.perf_counter()
        for _ in range(5):
            ws.surface(points)
        costs.append(time.perf_counter() - start)
    assert costs[1] < 3 * costs[0]
