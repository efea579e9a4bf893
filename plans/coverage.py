"""Configuration-space coverage of an RRT (seed 000 Sec. II-d), without allocating the grid.

The 2n-dimensional configuration space of n robots is cut into hypercubes of edge G mm; coverage
is the fraction of hypercubes that hold at least one tree node. The paper allocates the whole grid,
whose size grows as (extent / G)^(2n). Here each node is turned into its integer cell index (one
row of 2n integers) and only the distinct rows are counted (one int64 key per row when the grid has
fewer than 2^63 cells, else unique rows), so memory grows with the number of nodes, not the grid.

The denominator is the number of cells of the grid laid over the bounding box of the free region,
repeated for every robot: the box is the smallest axis-aligned box holding every free point of the
workspace (clearance > 0), found on a raster of spacing h = min(1 mm, G / 4) and widened by h on
each side (clipped to the workspace bounds). The grid's cells start at the box's lower-left corner and
there are ceil(width / G) x ceil(height / G) of them per robot, so the denominator is
(ceil(width / G) * ceil(height / G))^n. Nodes are never outside the box (robot centres are in free
space); a coordinate on the far edge falls in the last cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import PlanError


class ClearanceField(Protocol):
    bounds: tuple[float, float, float, float]

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (mm) to the nearest surface, positive in free space; points (..., 2)."""


@dataclass(frozen=True)
class Coverage:
    """occupied: distinct hypercubes holding a node; total: hypercubes in the grid (an exact int);
    fraction = occupied / total; box: (xmin, ymin, xmax, ymax) mm; cells_per_robot: (nx, ny)."""

    occupied: int
    total: int
    fraction: float
    grid_mm: float
    box: tuple[float, float, float, float]
    cells_per_robot: tuple[int, int]


def free_bounding_box(workspace: ClearanceField, resolution_mm: float = 1.0) -> tuple[float, ...]:
    """Bounding box (xmin, ymin, xmax, ymax) mm of the free region, to within `resolution_mm`.

    Evaluates the clearance on a raster of that spacing (cell centres over `workspace.bounds`),
    takes the box of the points with positive clearance and widens it by one spacing.
    """
    xmin, ymin, xmax, ymax = (float(v) for v in workspace.bounds)
    nx = max(1, math.ceil((xmax - xmin) / resolution_mm))
    ny = max(1, math.ceil((ymax - ymin) / resolution_mm))
    xs = xmin + (np.arange(nx) + 0.5) * (xmax - xmin) / nx
    ys = ymin + (np.arange(ny) + 0.5) * (ymax - ymin) / ny
    free = np.zeros((ny, nx), dtype=bool)
    for row in range(0, ny, 256):  # bounded memory for fine rasters
        grid = np.stack(np.meshgrid(xs, ys[row : row + 256]), axis=-1)
        free[row : row + 256] = workspace.clearance(grid) > 0
    cols = np.flatnonzero(free.any(axis=0))
    rows = np.flatnonzero(free.any(axis=1))
    if len(cols) == 0:
        raise PlanError("the workspace has no free space")
    step_x = (xmax - xmin) / nx
    step_y = (ymax - ymin) / ny
    return (
        max(xmin, xs[cols[0]] - step_x),
        max(ymin, ys[rows[0]] - step_y),
        min(xmax, xs[cols[-1]] + step_x),
        min(ymax, ys[rows[-1]] + step_y),
    )


def coverage(nodes: ArrayLike, box: tuple[float, float, float, float], grid_mm: float) -> Coverage:
    """Fraction of the (box)^n grid of hypercubes with edge `grid_mm` mm that hold a node.

    nodes: (N, n, 2) or (N, 2n) mm, robot i's (x, y) in columns 2i, 2i + 1.
    box: (xmin, ymin, xmax, ymax) mm, the per-robot extent of the grid (e.g. `free_bounding_box`).
    Memory and time are O(N n), whatever the grid's size.
    """
    if not grid_mm > 0:
        raise PlanError(f"grid edge must be > 0 mm, got {grid_mm}")
    xmin, ymin, xmax, ymax = (float(v) for v in box)
    if not (xmax > xmin and ymax > ymin):
        raise PlanError(f"empty box {box}")
    nodes = np.asarray(nodes, dtype=float)
    flat = nodes.reshape(len(nodes), -1)
    if flat.shape[1] % 2:
        raise PlanError(f"nodes must hold (x, y) pairs, got {flat.shape[1]} columns")
    n = flat.shape[1] // 2
    cells = np.array(
        [math.ceil((xmax - xmin) / grid_mm), math.ceil((ymax - ymin) / grid_mm)], dtype=np.int64
    )
    lower = np.tile([xmin, ymin], n)
    limit = np.tile(cells - 1, n)
    index = np.floor((flat - lower) / grid_mm).astype(np.int64)
    np.clip(index, 0, limit, out=index)
    total = int(cells[0] * cells[1]) ** n
    occupied = _count_distinct_rows(index, np.tile(cells, n), total)
    return Coverage(
        occupied=occupied,
        total=total,
        fraction=occupied / total,
        grid_mm=float(grid_mm),
        box=(xmin, ymin, xmax, ymax),
        cells_per_robot=(int(cells[0]), int(cells[1])),
    )


def _count_distinct_rows(index: np.ndarray, radix: np.ndarray, total: int) -> int:
    """Number of distinct rows of the integer array index (N, d), 0 <= index[:, j] < radix[j]."""
    if len(index) == 0:
        return 0
    if total < 2**63:
        keys = np.zeros(len(index), dtype=np.int64)
        for column, base in zip(index.T, radix):
            keys *= int(base)
            keys += column
        return int(len(np.unique(keys)))
    rows = np.ascontiguousarray(index)
    packed = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).reshape(-1)
    return int(len(np.unique(packed)))
