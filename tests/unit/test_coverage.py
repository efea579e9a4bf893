"""Coverage of the configuration-space grid, checked against hand counts."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from rigctl.core.errors import PlanError
from rigctl.plans.coverage import coverage, free_bounding_box


def test_two_robots_hand_count():
    # box [0, 10] x [0, 10], grid 5 mm: 2 x 2 cells per robot, (2 * 2)^2 = 16 hypercubes
    nodes = np.array(
        [
            [[1.0, 1.0], [6.0, 1.0]],  # cells (0,0 | 1,0)
            [[2.0, 4.0], [9.0, 4.9]],  # same hypercube as the first
            [[1.0, 1.0], [1.0, 1.0]],  # (0,0 | 0,0): new
            [[7.0, 7.0], [1.0, 6.0]],  # (1,1 | 0,1): new
            [[10.0, 10.0], [5.0, 5.0]],  # far edge -> last cell: (1,1 | 1,1): new
        ]
    )
    result = coverage(nodes, (0.0, 0.0, 10.0, 10.0), 5.0)
    assert result.total == 16
    assert result.occupied == 4
    assert result.fraction == pytest.approx(4 / 16)
    assert result.cells_per_robot == (2, 2)


def test_flat_rows_equal_pair_rows_and_ceil_of_partial_cells():
    # box 0..7 x 0..3 with grid 2: ceil(7/2)=4 by ceil(3/2)=2 -> 8 cells for one robot
    nodes = np.array([[0.5, 0.5], [1.5, 1.5], [2.5, 0.5], [6.9, 2.9], [6.1, 2.1]])
    result = coverage(nodes, (0.0, 0.0, 7.0, 3.0), 2.0)
    assert result.total == 8
    assert result.occupied == 3  # (0,0) twice, (1,0), (3,1) twice


def test_four_robots_fine_grid_does_not_allocate_it():
    # 4 robots, 300 mm box, 1 mm grid: (300 * 300)^4 = 6.6e19 hypercubes, more than fit in int64
    rng = np.random.default_rng(3)
    nodes = rng.uniform(50.0, 350.0, size=(20_000, 4, 2))
    nodes[10_000:] = nodes[:10_000]  # every node twice: 10,000 distinct cells at most
    tracemalloc.start()
    result = coverage(nodes, (50.0, 50.0, 350.0, 350.0), 1.0)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert result.total == 90_000**4
    assert result.occupied == 10_000  # random reals: distinct cells with certainty in practice
    assert peak < 50e6  # the grid at one bit per cell would be 8e18 bytes


def test_four_robots_coarse_grid_hand_count():
    # 4 robots, box 0..100, grid 50: 2 x 2 cells per robot, 4^4 = 256 hypercubes
    a = [[10.0, 10.0]] * 4
    b = [[10.0, 10.0]] * 3 + [[60.0, 10.0]]
    nodes = np.array([a, a, b, b, a])
    result = coverage(nodes, (0.0, 0.0, 100.0, 100.0), 50.0)
    assert (result.total, result.occupied) == (256, 2)


def test_bad_grid_is_refused():
    with pytest.raises(PlanError, match="grid"):
        coverage(np.zeros((1, 1, 2)), (0.0, 0.0, 1.0, 1.0), 0.0)


class _Room:
    """A square room [50, 350]^2 inside 400 x 400 bounds: clearance by hand."""

    bounds = (0.0, 0.0, 400.0, 400.0)

    def clearance(self, points):
        points = np.asarray(points)
        x, y = points[..., 0], points[..., 1]
        return np.minimum(np.minimum(x - 50.0, 350.0 - x), np.minimum(y - 50.0, 350.0 - y))


def test_free_bounding_box_of_a_room():
    box = free_bounding_box(_Room(), resolution_mm=1.0)
    assert box == pytest.approx((50.0, 50.0, 350.0, 350.0), abs=1.0)
    assert box[0] <= 50.0 and box[2] >= 350.0  # widened: never cuts free space off
