"""Workspace geometry: how far a point is from the nearest wall, and which way is away from it.

Every planner, the plan checks and the emulated world ask a workspace one thing: the *clearance* of a
point, the signed distance (mm) to the nearest surface of the free region. It is positive in free
space, zero on a wall, negative inside an obstacle or outside the boundary. An agent (a disc of
radius r) fits at a point when the clearance there is at least r. Alongside the clearance the
workspace gives the unit normal (the direction in which the clearance grows) and the curvature of the
level set through the point, so the global-input model can slide agents around rounded contact
surfaces in closed form:

- curvature 0: the level set is a straight line (the nearest feature is an edge);
- curvature k > 0: a circle of radius 1/k bending around an obstacle (nearest feature a corner or a
  disk obstacle); its centre is at ``p - normal / k``;
- curvature k < 0: a circle bending around the free space (inside a disk boundary); its centre is
  again ``p - normal / k``.

Two backends share that interface:

- `ShapeWorkspace` (from the plan's shapes): exact distances to rects, polygons and disks, and to the
  boundary from inside. The clearance is the minimum over the boundary and every obstacle. Its
  queries are compiled (numba): the model asks for every event of every agent. It also answers
  exactly whether a disc's straight path is clear (`sweep_clear`) and whether a slide along a
  straight side stays on it (`slide_clear`); the grid answers those conservatively.
- `GridWorkspace` (from an image, a boolean mask, or sampled from a shape workspace with
  `rasterize`): clearance, normal and curvature stored at pixel centres and interpolated bilinearly,
  so a query costs the same however many obstacle pixels there are. A rasterized workspace also
  keeps, per sample, the piece of wall nearest to it (a segment or a disk), which makes it exact
  away from the walls. Images are read with row 0 at the top, i.e. the first row of the array is
  the largest y.

Lengths are in mm throughout. Points are arrays of shape (..., 2) holding (x, y).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from rigctl.core.errors import PlanError
from rigctl.core.jit import njit
from rigctl.physics.geometry import signed_area

if TYPE_CHECKING:
    from rigctl.plans.schema import ImageWorkspaceSpec, ShapeWorkspaceSpec

log = logging.getLogger(__name__)

# Curvatures larger than this (1/mm) are clipped: a level set tighter than 1 um is a singular point.
_MAX_CURVATURE = 1e3
_TINY = 1e-300
# Grid cells with wall pieces (see GridWorkspace): how a query inside them is answered.
_CELL_AT_WALL, _CELL_ONE_PIECE, _CELL_PIECES = 0, 1, 2
# Blur (pixels) of a mask's distance field (see `Workspace.from_mask`).
_MASK_BLUR_PX = 0.7


class Workspace:
    """The free region of the plane: clearance, normal and curvature at any point.

    Subclasses implement `surface`; everything else is built on it.
    """

    #: True when `surface` returns exact curvature (lines and circles), so the model may treat every
    #: change of contact surface as an event; False for grids, whose level sets are approximate.
    exact_geometry: bool = False

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) in mm of a box that contains all free space."""
        raise NotImplementedError

    def surface(self, points: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Clearance (...,) mm, unit normal (..., 2) and level-set curvature (...,) 1/mm at points (..., 2)."""
        raise NotImplementedError

    # The rest is shared by both backends.

    @classmethod
    def from_spec(
        cls, spec: "ShapeWorkspaceSpec | ImageWorkspaceSpec", base_dir: str | Path | None = None
    ) -> "Workspace":
        """Build the workspace a plan names. `base_dir` resolves a relative image path (the plan's folder)."""
        if hasattr(spec, "image"):
            path = Path(spec.image)
            if not path.is_absolute() and base_dir is not None:
                path = Path(base_dir) / path
            return cls.from_image(path, spec.mm_per_px, tuple(spec.origin))
        return ShapeWorkspace(
            boundary=_shape_tuple(spec.boundary),
            obstacles=[_shape_tuple(s) for s in spec.obstacles],
        )

    @classmethod
    def from_image(
        cls, path: str | Path, mm_per_px: float, origin_mm: Sequence[float] = (0.0, 0.0)
    ) -> "GridWorkspace":
        """A workspace from a picture: pixels darker than 128 grey are obstacles.

        `origin_mm` is the workspace position of the image's lower-left corner; row 0 of the image
        is its top edge (largest y).
        """
        import cv2  # OpenCV is only needed for image workspaces

        path = Path(path)
        _check_image_size(path)
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise PlanError(f"workspace image {path} does not exist or is not a readable image")
        return cls.from_mask(image >= 128, mm_per_px, origin_mm)

    @classmethod
    def from_mask(
        cls, free: np.ndarray, mm_per_px: float, origin_mm: Sequence[float] = (0.0, 0.0)
    ) -> "GridWorkspace":
        """A workspace from a boolean mask (H, W), True = free, row 0 at the top (largest y).

        The signed distance comes from `scipy.ndimage.distance_transform_edt`; everything outside the
        mask counts as obstacle. Straight walls along the pixel grid come out exact; corners and
        slanted or curved walls within about 0.75 pixel (which pixel centres fell inside is all
        a mask tells, and the blur that smooths the staircase also rounds corners).
        """
        free = np.asarray(free, dtype=bool)
        if free.ndim != 2 or min(free.shape) < 2:
            raise PlanError(f"workspace mask must be 2-D, at least 2 x 2, got {free.shape}")
        if mm_per_px <= 0:
            raise PlanError(f"mm_per_px must be > 0, got {mm_per_px}")
        if not free.any():
            raise PlanError("workspace mask has no free pixel (everything is darker than 128)")
        # A ring of obstacle around the picture: the world beyond the image is not free space.
        # It is as wide as the blur below reaches, so the blur sees a wall there, not an edge.
        ring = 1 + int(math.ceil(4.0 * _MASK_BLUR_PX))
        padded = np.pad(free, ring, constant_values=False)
        # Distance from each pixel centre to the nearest pixel of the other kind, then to the edge
        # of that pixel's square along the way: the wall is taken half way between the centres.
        inside = _distance_to_other_square(padded)
        outside = _distance_to_other_square(~padded)
        staircase = np.where(padded, inside, -outside) * mm_per_px
        # A slanted or curved wall drawn in pixels is a staircase, and its distance field ripples
        # by a tenth of a pixel along it: enough to catch a particle gliding past. A light blur
        # smooths the ripple and leaves straight walls (a linear field) as they were.
        clearance = ndimage.gaussian_filter(staircase, sigma=_MASK_BLUR_PX, mode="nearest")
        d_row, d_col = np.gradient(clearance)
        nx, ny = d_col, -d_row  # rows grow downwards, y grows upwards
        origin = (float(origin_mm[0]) - ring * mm_per_px, float(origin_mm[1]) - ring * mm_per_px)
        curvature = np.zeros_like(clearance)  # a staircase has no usable curvature
        return GridWorkspace(clearance, nx, ny, curvature, mm_per_px, origin)

    def rasterize(self, resolution_mm: float) -> "GridWorkspace":
        """The grid backend sampled from this workspace at pixel centres `resolution_mm` apart."""
        if resolution_mm <= 0:
            raise PlanError(f"resolution_mm must be > 0, got {resolution_mm}")
        xmin, ymin, xmax, ymax = self.bounds
        width = int(math.ceil((xmax - xmin) / resolution_mm)) + 2
        height = int(math.ceil((ymax - ymin) / resolution_mm)) + 2
        origin = (xmin - resolution_mm, ymin - resolution_mm)
        xs = origin[0] + (np.arange(width) + 0.5) * resolution_mm
        ys = origin[1] + (np.arange(height)[::-1] + 0.5) * resolution_mm  # row 0 = largest y
        grid = np.stack(np.meshgrid(xs, ys), axis=-1)
        clearance, normal, curvature = self.surface(grid)
        pieces = self.primitives(grid) if isinstance(self, ShapeWorkspace) else None
        log.debug("rasterized workspace to %d x %d cells of %g mm", height, width, resolution_mm)
        return GridWorkspace(
            clearance, normal[..., 0], normal[..., 1], curvature, resolution_mm, origin, pieces
        )

    def clearance(self, points: ArrayLike) -> np.ndarray:
        """Signed distance (mm) from points (..., 2) to the nearest surface; > 0 in free space."""
        return self.surface(points)[0]

    def clearance_lower_bound(self, points: ArrayLike) -> np.ndarray:
        """A cheap lower bound (mm) of `clearance` at points (..., 2), for quick "far from walls"
        tests; the clearance itself unless a backend has something cheaper."""
        return self.clearance(points)

    def sweep_clear(self, starts: ArrayLike, moves: ArrayLike, radius: ArrayLike) -> np.ndarray:
        """(M,) True where a disc of `radius` (M,) mm, free at starts (M, 2) mm, certainly moves
        by moves (M, 2) mm touching nothing (the clearance stays >= radius all the way).

        False means "not known to be clear". Here: the clearance lower bound at the start
        exceeds the move's length plus the radius; backends with exact shapes answer exactly.
        """
        starts = np.asarray(starts, dtype=float).reshape(-1, 2)
        moves = np.asarray(moves, dtype=float).reshape(-1, 2)
        length = np.hypot(moves[:, 0], moves[:, 1])
        return self.clearance_lower_bound(starts) >= length + np.asarray(radius, dtype=float)

    def slide_clear(
        self, starts: ArrayLike, moves: ArrayLike, radius: ArrayLike, normal: ArrayLike,
        tolerance: float,
    ) -> np.ndarray:
        """(M,) True where a disc of `radius` (M,) mm touching a straight wall of normal (M, 2)
        at starts (M, 2) mm certainly slides by moves (M, 2) mm (parallel to that wall) with the
        wall under it all the way and nothing else within `radius - tolerance`.

        False means "not known"; a grid knows no walls, only samples, so here it is always False.
        """
        return np.zeros(len(np.asarray(starts).reshape(-1, 2)), dtype=bool)

    def normal(self, points: ArrayLike) -> np.ndarray:
        """Unit vector (..., 2) in which the clearance increases at points (..., 2)."""
        return self.surface(points)[1]

    def contains(self, points: ArrayLike, radius: ArrayLike = 0.0) -> np.ndarray:
        """True where a disc of `radius` (mm, broadcast against points[..., 0]) fits at points (..., 2)."""
        return self.clearance(points) >= np.asarray(radius, dtype=float)

    def sample_free(self, rng: np.random.Generator, n: int, radius: float = 0.0) -> np.ndarray:
        """n points (n, 2) drawn uniformly from where a disc of `radius` fits (rejection sampling)."""
        xmin, ymin, xmax, ymax = self.bounds
        found: list[np.ndarray] = []
        count = 0
        draws = 0
        batch = max(64, 2 * n)
        while count < n:
            candidates = rng.uniform((xmin, ymin), (xmax, ymax), size=(batch, 2))
            good = candidates[self.contains(candidates, radius)]
            found.append(good)
            count += len(good)
            draws += batch
            if count == 0 and draws >= 200_000:
                raise PlanError(f"no free space for a disc of radius {radius} mm in this workspace")
        return np.concatenate(found)[:n]


class ShapeWorkspace(Workspace):
    """Exact geometry of a boundary shape with shape obstacles.

    Shapes are tuples: ("rect", (x, y, w, h)) with (x, y) the lower-left corner, ("polygon",
    ((x, y), ...)) in either orientation, ("disk", (cx, cy, r)).

    All shapes go into one table (the boundary first, then rects, disks, polygons), which a
    compiled kernel (`_shape_query`) walks point by point: the signed distance to every shape,
    then the normal and curvature of the nearest one only. The model asks this for every event
    of every agent, so it is compiled (numba) rather than a chain of numpy passes over
    (points x shapes) arrays: environment 1, 330 ns per point before, 20-40 ns now.
    """

    exact_geometry = True

    def __init__(self, boundary: tuple, obstacles: Sequence[tuple] = ()) -> None:
        # Each term: (family, sign). The boundary counts with sign -1: free space is inside it.
        (outline,) = _families([boundary])
        self._terms: list[tuple[_Family, float]] = [(outline, -1.0)]
        self._terms += [(f, 1.0) for f in _families(list(obstacles))]
        low, high = outline.bounds()
        self._bounds = (float(low[0]), float(low[1]), float(high[0]), float(high[1]))
        self._table = _ShapeTable([(family, sign) for family, sign in self._terms])
        _load_kernels()

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return self._bounds  # type: ignore[return-value]

    def _query(self, points: ArrayLike, features: bool):
        p = np.asarray(points, dtype=float)
        flat = _kernel_array(p, (2,))
        count = len(flat)
        phi = np.empty(count)
        normal = np.empty((count, 2))
        kappa = np.empty(count)
        term = np.empty(count, dtype=np.int64)
        piece = np.empty(count, dtype=np.int64)
        _shape_query(flat, *self._table.arrays, features, phi, normal, kappa, term, piece)
        return p.shape[:-1], flat, phi, normal, kappa, term, piece

    def clearance(self, points: ArrayLike) -> np.ndarray:
        lead, _, phi, _, _, _, _ = self._query(points, False)
        return phi.reshape(lead)

    def surface(self, points: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lead, _, phi, normal, kappa, _, _ = self._query(points, True)
        return phi.reshape(lead), normal.reshape(lead + (2,)), kappa.reshape(lead)

    def sweep_clear(self, starts: ArrayLike, moves: ArrayLike, radius: ArrayLike) -> np.ndarray:
        starts, moves = _kernel_array(starts, (2,)), _kernel_array(moves, (2,))
        rho = _kernel_array(np.broadcast_to(np.asarray(radius, dtype=float), len(starts)), ())
        clear = np.empty(len(starts), dtype=bool)
        _shape_sweep_clear(starts, moves, rho, *self._table.arrays, clear)
        return clear

    def slide_clear(
        self, starts: ArrayLike, moves: ArrayLike, radius: ArrayLike, normal: ArrayLike,
        tolerance: float,
    ) -> np.ndarray:
        starts, moves = _kernel_array(starts, (2,)), _kernel_array(moves, (2,))
        normal = _kernel_array(normal, (2,))
        rho = _kernel_array(np.broadcast_to(np.asarray(radius, dtype=float), len(starts)), ())
        clear = np.empty(len(starts), dtype=bool)
        kind, sign, param, vertex, edge, length2, outward, _ = self._table.arrays
        _shape_slide_clear(starts, moves, rho, normal, float(tolerance), kind, sign, param,
                           vertex, edge, length2, outward, clear)
        return clear

    def primitives(self, points: ArrayLike) -> np.ndarray:
        """The piece of wall nearest each point (..., 2), as (..., 6) rows (ax, ay, bx, by, rho,
        sigma): clearance = sigma * (|p - segment ab| - rho) near it. A side of a rect or polygon
        is a segment (rho 0, sigma 1: the clearance in free space is the distance to it); a disk
        obstacle has a = b = centre, rho = radius, sigma 1; a disk boundary the same with sigma -1.
        """
        lead, flat, _, _, _, nearest, piece = self._query(points, False)
        result = np.empty((len(flat), 6))
        start = 0
        for family, sign in self._terms:
            stop = start + family.count
            mine = (nearest >= start) & (nearest < stop)
            if mine.any():
                pieces = family.primitive(flat[mine], nearest[mine] - start, piece[mine])
                if sign < 0:  # the boundary: free space is inside a disk, outside a segment
                    pieces[:, 5] = np.where(pieces[:, 4] > 0, -1.0, 1.0)
                result[mine] = pieces
            start = stop
        return result.reshape(lead + (6,))


class _Family:
    """Shapes of one kind: their bounds, their rows of the kernel's shape table, and the piece of
    wall nearest a point (for rasterizing)."""

    count: int

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def primitive(self, p: np.ndarray, which: np.ndarray, piece: np.ndarray) -> np.ndarray:
        """The piece of shape `which` (N,) nearest each point p (N, 2) (`piece`: the kernel's
        nearest edge of a polygon), as (N, 6) rows (ax, ay, bx, by, rho, 1): distance
        |p - segment ab| - rho (a segment: rho 0; a disk: a = b)."""
        raise NotImplementedError


def _families(shapes: list[tuple]) -> list[_Family]:
    rects = [value for kind, value in shapes if kind == "rect"]
    disks = [value for kind, value in shapes if kind == "disk"]
    families: list[_Family] = []
    if rects:
        families.append(_Rects(rects))
    if disks:
        families.append(_Disks(disks))
    families += [_Polygon(value) for kind, value in shapes if kind == "polygon"]
    unknown = {kind for kind, _ in shapes} - {"rect", "disk", "polygon"}
    if unknown:
        raise PlanError(f"unknown shape kind(s) {sorted(unknown)}")
    return families


class _Rects(_Family):
    """Axis-aligned boxes, stored as centre (K, 2) and half size (K, 2)."""

    def __init__(self, rects: list) -> None:
        r = np.asarray(rects, dtype=float).reshape(-1, 4)
        self.half = r[:, 2:] / 2.0
        self.centre = r[:, :2] + self.half
        self.count = len(r)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return (self.centre - self.half).min(axis=0), (self.centre + self.half).max(axis=0)

    def primitive(self, p: np.ndarray, which: np.ndarray, piece: np.ndarray) -> np.ndarray:
        centre, half = self.centre[which], self.half[which]
        rel = p - centre
        q = np.abs(rel) - half
        # The nearest side: across the larger of the two excesses (a corner region is as near
        # to both sides that meet there; take the horizontal one).
        corner = (q[:, 0] > 0) & (q[:, 1] > 0)
        vertical = (q[:, 0] >= q[:, 1]) & ~corner
        side_x = centre[:, 0] + np.where(rel[:, 0] >= 0, half[:, 0], -half[:, 0])
        side_y = centre[:, 1] + np.where(rel[:, 1] >= 0, half[:, 1], -half[:, 1])
        x0, x1 = centre[:, 0] - half[:, 0], centre[:, 0] + half[:, 0]
        y0, y1 = centre[:, 1] - half[:, 1], centre[:, 1] + half[:, 1]
        segment = np.where(
            vertical[:, None],
            np.stack([side_x, y0, side_x, y1], axis=1),
            np.stack([x0, side_y, x1, side_y], axis=1),
        )
        return np.concatenate([segment, np.zeros((len(p), 1)), np.ones((len(p), 1))], axis=1)


class _Disks(_Family):
    """Disks (K, 3) = (cx, cy, r)."""

    def __init__(self, disks: list) -> None:
        d = np.asarray(disks, dtype=float).reshape(-1, 3)
        self.centre, self.radius = d[:, :2], d[:, 2]
        self.count = len(d)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        r = self.radius[:, None]
        return (self.centre - r).min(axis=0), (self.centre + r).max(axis=0)

    def primitive(self, p: np.ndarray, which: np.ndarray, piece: np.ndarray) -> np.ndarray:
        c = self.centre[which]
        return np.concatenate(
            [c, c, self.radius[which, None], np.ones((len(p), 1))], axis=1
        )


class _Polygon(_Family):
    """One simple polygon, stored counter-clockwise (outward normal of edge e is (e_y, -e_x))."""

    def __init__(self, vertices) -> None:
        v = np.asarray(vertices, dtype=float)
        if signed_area(v) < 0:
            v = v[::-1]
        self.vertices = v
        self.edge = np.roll(v, -1, axis=0) - v
        self.length2 = np.sum(self.edge * self.edge, axis=1)
        self.outward = np.stack([self.edge[:, 1], -self.edge[:, 0]], axis=1) / np.sqrt(
            self.length2
        )[:, None]
        bisector = self.outward + np.roll(self.outward, 1, axis=0)
        self.vertex_normal = bisector / np.linalg.norm(bisector, axis=1, keepdims=True)
        self.count = 1

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def primitive(self, p: np.ndarray, which: np.ndarray, piece: np.ndarray) -> np.ndarray:
        a, b = self.vertices[piece], self.vertices[(piece + 1) % len(self.vertices)]
        return np.concatenate([a, b, np.zeros((len(p), 1)), np.ones((len(p), 1))], axis=1)


_RECT, _DISK, _POLYGON = 0, 1, 2


def _check_image_size(path: Path) -> None:
    """A workspace image is a PNG of at most MAX_IMAGE_PIXELS: read from its header, before the
    picture is decoded (a small file can hold a huge blank picture)."""
    from rigctl.plans.schema import MAX_IMAGE_PIXELS

    try:
        with open(path, "rb") as file:
            head = file.read(24)
    except OSError:
        return  # imread says it does not exist or is not readable
    if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise PlanError(f"workspace image {path} is not a PNG")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if width * height > MAX_IMAGE_PIXELS:
        raise PlanError(f"workspace image {path} is {width} x {height} pixels; at most "
                        f"{MAX_IMAGE_PIXELS} pixels")


def _kernel_array(values: ArrayLike, tail: tuple[int, ...]) -> np.ndarray:
    """values as a writable C-ordered float64 array (-1, *tail): the one array type the kernels
    are compiled for (a read-only or strided view would make numba compile them again)."""
    flat = np.asarray(values, dtype=float).reshape((-1,) + tail)
    if flat.flags.c_contiguous and flat.flags.writeable:
        return flat
    return flat.copy()


class _ShapeTable:
    """The shapes of a ShapeWorkspace as flat arrays for `_shape_query`, in term order.

    kind (T,), sign (T,) (+1 obstacle, -1 boundary), param (T, 4): a rect's centre and half
    size, a disk's centre and radius, a polygon's first and last + 1 vertex in `vertex` (V, 2),
    with edge vectors (V, 2), squared edge lengths (V,), outward edge normals (V, 2) and vertex
    bisector normals (V, 2) alongside.
    """

    def __init__(self, terms: list[tuple[_Family, float]]) -> None:
        kind, sign, param = [], [], []
        vertex, edge, length2, outward, bisector = [], [], [], [], []
        used = 0
        for family, term_sign in terms:
            if isinstance(family, _Rects):
                for centre, half in zip(family.centre, family.half):
                    kind.append(_RECT)
                    param.append((centre[0], centre[1], half[0], half[1]))
            elif isinstance(family, _Disks):
                for centre, radius in zip(family.centre, family.radius):
                    kind.append(_DISK)
                    param.append((centre[0], centre[1], radius, 0.0))
            else:
                count = len(family.vertices)
                kind.append(_POLYGON)
                param.append((used, used + count, 0.0, 0.0))
                vertex.append(family.vertices)
                edge.append(family.edge)
                length2.append(family.length2)
                outward.append(family.outward)
                bisector.append(family.vertex_normal)
                used += count
            sign += [term_sign] * family.count

        def stacked(parts: list, tail: tuple[int, ...]) -> np.ndarray:
            return np.ascontiguousarray(np.concatenate(parts) if parts else np.zeros((0,) + tail))

        self.arrays = (
            np.asarray(kind, dtype=np.int64),
            np.asarray(sign, dtype=float),
            np.ascontiguousarray(np.asarray(param, dtype=float).reshape(-1, 4)),
            stacked(vertex, (2,)),
            stacked(edge, (2,)),
            stacked(length2, ()),
            stacked(outward, (2,)),
            stacked(bisector, (2,)),
        )


@njit(error_model="numpy")
def _shape_query(
    points, kind, sign, param, vertex, edge, length2, outward, bisector, features,
    phi, normal, kappa, term, piece,
):  # pragma: no cover - compiled
    """For each point (N, 2): the clearance phi (N,) (min over the shapes of the signed distance,
    the boundary's negated), the index of the nearest shape `term` (N,) (the first of equals)
    and, for a polygon, its nearest edge `piece` (N,); with `features` also the unit normal
    (N, 2) and level-set curvature (N,) of the nearest shape, both with its sign.

    Rect: q = |p - c| - h; distance sqrt(max(q, 0)^2) + min(max(qx, qy), 0); outside a corner
    the level set is a circle round it. Disk: |p - c| - r, the level set a circle about c.
    Polygon: the nearest edge point (clamped projection), negative inside (crossing number);
    nearest a vertex the level set is a circle round it, on the vertex the bisector normal.
    """
    for i in range(points.shape[0]):
        x = points[i, 0]
        y = points[i, 1]
        best = np.inf
        best_term = 0
        best_edge = 0
        for j in range(kind.shape[0]):
            edge_j = 0
            if kind[j] == _RECT:
                d = _box_distance(x, y, param[j, 0], param[j, 1], param[j, 2], param[j, 3])
            elif kind[j] == _DISK:
                d = math.hypot(x - param[j, 0], y - param[j, 1]) - param[j, 2]
            else:
                d, edge_j, _ = _polygon_distance(x, y, int(param[j, 0]), int(param[j, 1]),
                                                 vertex, edge, length2)
            d *= sign[j]
            if d < best:
                best = d
                best_term = j
                best_edge = edge_j
        phi[i] = best
        term[i] = best_term
        piece[i] = best_edge - int(param[best_term, 0]) if kind[best_term] == _POLYGON else 0
        if not features:
            continue
        j = best_term
        if kind[j] == _RECT:
            rx = x - param[j, 0]
            ry = y - param[j, 1]
            sx = 1.0 if rx >= 0 else -1.0
            sy = 1.0 if ry >= 0 else -1.0
            qx = abs(rx) - param[j, 2]
            qy = abs(ry) - param[j, 3]
            if qx > 0 and qy > 0:  # outside a corner: the level set is a circle round it
                out = math.hypot(qx, qy)
                nx, ny, k = sx * qx / out, sy * qy / out, min(1.0 / out, _MAX_CURVATURE)
            elif qx >= qy:
                nx, ny, k = sx, 0.0, 0.0
            else:
                nx, ny, k = 0.0, sy, 0.0
        elif kind[j] == _DISK:
            rx = x - param[j, 0]
            ry = y - param[j, 1]
            dist = math.hypot(rx, ry)
            safe = max(dist, _TINY)
            if dist > 0:
                nx, ny = rx / safe, ry / safe
            else:
                nx, ny = 1.0, 0.0
            k = min(1.0 / safe, _MAX_CURVATURE)
        else:
            first, stop = int(param[j, 0]), int(param[j, 1])
            e = best_edge
            wx = x - vertex[e, 0]
            wy = y - vertex[e, 1]
            t = min(max((wx * edge[e, 0] + wy * edge[e, 1]) / length2[e], 0.0), 1.0)
            dx = wx - t * edge[e, 0]
            dy = wy - t * edge[e, 1]
            dist = math.sqrt(dx * dx + dy * dy)
            inner = _polygon_distance(x, y, first, stop, vertex, edge, length2)[2]  # -1 inside
            if t <= 0.0 or t >= 1.0:  # nearest a vertex: a circle round it
                safe = max(dist, _TINY)
                if dist > 0:
                    nx, ny = inner * dx / safe, inner * dy / safe
                else:
                    v = e + 1 if t >= 1.0 else e
                    if v == stop:
                        v = first
                    nx, ny = bisector[v, 0], bisector[v, 1]
                k = min(max(inner / safe, -_MAX_CURVATURE), _MAX_CURVATURE)
            else:
                nx, ny, k = outward[e, 0], outward[e, 1], 0.0
        normal[i, 0] = sign[j] * nx
        normal[i, 1] = sign[j] * ny
        kappa[i] = sign[j] * k


@njit(error_model="numpy")
def _polygon_distance(x, y, first, stop, vertex, edge, length2):  # pragma: no cover - compiled
    """Signed distance from (x, y) to the polygon of vertices first..stop-1 (negative inside),
    the index of its nearest edge (the first of equals) and the sign (-1 inside, else 1)."""
    best2 = np.inf
    nearest = first
    crossings = 0
    for e in range(first, stop):
        ax = vertex[e, 0]
        ay = vertex[e, 1]
        wx = x - ax
        wy = y - ay
        t = min(max((wx * edge[e, 0] + wy * edge[e, 1]) / length2[e], 0.0), 1.0)
        dx = wx - t * edge[e, 0]
        dy = wy - t * edge[e, 1]
        d2 = dx * dx + dy * dy
        if d2 < best2:
            best2 = d2
            nearest = e
        # Crossing number: a ray towards +x crosses the boundary an odd number of times from inside.
        by = vertex[e + 1 if e + 1 < stop else first, 1]
        if (ay > y) != (by > y):
            if x < ax + (y - ay) * edge[e, 0] / (by - ay):
                crossings += 1
    sign = -1.0 if crossings % 2 == 1 else 1.0
    return sign * math.sqrt(best2), nearest, sign


@njit(error_model="numpy")
def _point_segment_distance(px, py, ax, ay, dx, dy):  # pragma: no cover - compiled
    """Distance from (px, py) to the segment from (ax, ay) along (dx, dy)."""
    wx = px - ax
    wy = py - ay
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 <= 0.0 else min(max((wx * dx + wy * dy) / length2, 0.0), 1.0)
    gx = wx - t * dx
    gy = wy - t * dy
    return math.sqrt(gx * gx + gy * gy)


@njit(error_model="numpy")
def _segment_enters_box(ax, ay, dx, dy, cx, cy, hx, hy):  # pragma: no cover - compiled
    """Whether the segment from (ax, ay) along (dx, dy) meets the box centre (cx, cy), half
    size (hx, hy) (slab test: the parameter ranges inside the x and the y slab overlap)."""
    low, high = _slab(ax, dx, cx, hx, 0.0, 1.0)
    low, high = _slab(ay, dy, cy, hy, low, high)
    return low <= high


@njit(error_model="numpy")
def _slab(a, d, c, h, low, high):  # pragma: no cover - compiled
    """[low, high] narrowed to the t where a + t d lies in [c - h, c + h] (empty: low > high)."""
    if d == 0.0:
        return (low, high) if abs(a - c) <= h else (1.0, 0.0)
    t1 = (c - h - a) / d
    t2 = (c + h - a) / d
    return max(low, min(t1, t2)), min(high, max(t1, t2))


@njit(error_model="numpy")
def _box_distance(x, y, cx, cy, hx, hy):  # pragma: no cover - compiled
    """Signed distance from (x, y) to the box centre (cx, cy), half size (hx, hy): with
    q = |p - c| - h, sqrt(max(q, 0)^2) + min(max(qx, qy), 0); sqrt(x^2 + y^2) rather than hypot,
    since sqrt(x^2) == |x| exactly keeps distances to a side exact."""
    qx = abs(x - cx) - hx
    qy = abs(y - cy) - hy
    ox = max(qx, 0.0)
    oy = max(qy, 0.0)
    return math.sqrt(ox * ox + oy * oy) + min(max(qx, qy), 0.0)


@njit(error_model="numpy")
def _segments_distance(ax, ay, dx, dy, bx, by, ex, ey):  # pragma: no cover - compiled
    """Distance between segments a + s d and b + t e (s, t in [0, 1]); 0 where they cross."""
    # Proper crossing: each segment's ends lie strictly on both sides of the other's line.
    c1 = dx * (by - ay) - dy * (bx - ax)
    c2 = dx * (by + ey - ay) - dy * (bx + ex - ax)
    c3 = ex * (ay - by) - ey * (ax - bx)
    c4 = ex * (ay + dy - by) - ey * (ax + dx - bx)
    if ((c1 > 0) != (c2 > 0)) and ((c3 > 0) != (c4 > 0)) and c1 != 0 and c2 != 0:
        return 0.0
    return min(
        min(_point_segment_distance(ax, ay, bx, by, ex, ey),
            _point_segment_distance(ax + dx, ay + dy, bx, by, ex, ey)),
        min(_point_segment_distance(bx, by, ax, ay, dx, dy),
            _point_segment_distance(bx + ex, by + ey, ax, ay, dx, dy)),
    )


@njit(error_model="numpy")
def _shape_sweep_clear(
    points, moves, rho, kind, sign, param, vertex, edge, length2, outward, bisector, clear,
):  # pragma: no cover - compiled
    """clear[i]: the segment from points[i] along moves[i] stays at least rho[i] > 0 from every
    shape's outline (`_segment_clear`)."""
    for i in range(points.shape[0]):
        clear[i] = _segment_clear(points[i, 0], points[i, 1], moves[i, 0], moves[i, 1], rho[i],
                                  kind, sign, param, vertex, edge, length2)


@njit(error_model="numpy")
def _segment_clear(
    ax, ay, dx, dy, rho, kind, sign, param, vertex, edge, length2,
):  # pragma: no cover - compiled
    """True where the segment from (ax, ay) along (dx, dy) stays at least rho > 0 from every
    shape's outline, so a disc of radius rho that starts free moves along it touching nothing.

    Shapes farther from the start than the move is long plus rho are skipped (the distance
    changes by at most the distance moved). An obstacle rect: 0 if the segment enters the box
    (slab test), else the nearer of its ends to the box and the box's corners to it (two disjoint
    convex sets are closest at a vertex of one). A convex boundary (rect, disk) is farthest from
    the inside along a segment at one of its ends. A disk obstacle: centre to segment minus its
    radius. A polygon: its edges to the segment.
    """
    bx = ax + dx
    by = ay + dy
    reach = math.sqrt(dx * dx + dy * dy) + rho
    for j in range(kind.shape[0]):
        if kind[j] == _RECT:
            cx, cy, hx, hy = param[j, 0], param[j, 1], param[j, 2], param[j, 3]
            qx = abs(ax - cx) - hx
            qy = abs(ay - cy) - hy
            if sign[j] < 0:  # inside the boundary box: nearest it at an end
                gap = -max(max(qx, qy), max(abs(bx - cx) - hx, abs(by - cy) - hy))
            elif max(qx, qy) >= reach:  # the box is at least that far
                continue
            elif _segment_enters_box(ax, ay, dx, dy, cx, cy, hx, hy):
                return False
            else:
                gap = min(_box_distance(ax, ay, cx, cy, hx, hy),
                          _box_distance(bx, by, cx, cy, hx, hy))
                for corner in range(4):  # only corners within reach of the start can matter
                    px = cx - hx if corner & 1 == 0 else cx + hx
                    py = cy - hy if corner & 2 == 0 else cy + hy
                    if (px - ax) * (px - ax) + (py - ay) * (py - ay) < reach * reach:
                        gap = min(gap, _point_segment_distance(px, py, ax, ay, dx, dy))
        elif kind[j] == _DISK:
            cx, cy, radius = param[j, 0], param[j, 1], param[j, 2]
            if sign[j] < 0:
                far = max(math.hypot(ax - cx, ay - cy), math.hypot(bx - cx, by - cy))
                gap = radius - far
            else:
                gap = _point_segment_distance(cx, cy, ax, ay, dx, dy) - radius
        else:
            first, stop = int(param[j, 0]), int(param[j, 1])
            start = abs(_polygon_distance(ax, ay, first, stop, vertex, edge, length2)[0])
            if start >= reach:
                continue
            gap = start
            for e in range(first, stop):
                gap = min(gap, _segments_distance(ax, ay, dx, dy, vertex[e, 0],
                                                  vertex[e, 1], edge[e, 0], edge[e, 1]))
        if gap < rho:
            return False
    return True


@njit(error_model="numpy")
def _shape_slide_clear(
    points, moves, rho, normal, tol, kind, sign, param, vertex, edge, length2, outward,
    clear,
):  # pragma: no cover - compiled
    """clear[i]: a disc of radius rho[i] touching a straight wall of free-space normal
    normal[i] at points[i] slides by moves[i] (parallel to it) along that wall all the way and
    touches nothing else: some straight side or edge with that normal lies at rho[i] (within
    `tol`) from both ends of the move and reaches under both, and every outline stays at least
    rho[i] - tol from the path (`_segment_clear`). A side is one straight piece, so the wall
    lies under the whole path when it lies under both ends.
    """
    for i in range(points.shape[0]):
        ax, ay = points[i, 0], points[i, 1]
        bx, by = ax + moves[i, 0], ay + moves[i, 1]
        nx, ny = normal[i, 0], normal[i, 1]
        r = rho[i]
        found = False
        for j in range(kind.shape[0]):
            if found:
                break
            if kind[j] == _RECT:
                cx, cy, hx, hy = param[j, 0], param[j, 1], param[j, 2], param[j, 3]
                for side in range(4):
                    # free-space normal of the side: outward for an obstacle, inward for a boundary
                    sx = (1.0 if side == 0 else -1.0) if side < 2 else 0.0
                    sy = 0.0 if side < 2 else (1.0 if side == 2 else -1.0)
                    if abs(nx - sign[j] * sx) > 1e-12 or abs(ny - sign[j] * sy) > 1e-12:
                        continue
                    if side < 2:  # a vertical side at x = line, spanning y
                        line = cx + sx * hx
                        gap_a, gap_b = (ax - line) * nx, (bx - line) * nx
                        inside = (abs(ay - cy) <= hy) and (abs(by - cy) <= hy)
                    else:
                        line = cy + sy * hy
                        gap_a, gap_b = (ay - line) * ny, (by - line) * ny
                        inside = (abs(ax - cx) <= hx) and (abs(bx - cx) <= hx)
                    if inside and abs(gap_a - r) <= tol and abs(gap_b - r) <= tol:
                        found = True
                        break
            elif kind[j] == _POLYGON:
                for e in range(int(param[j, 0]), int(param[j, 1])):
                    fx, fy = sign[j] * outward[e, 0], sign[j] * outward[e, 1]
                    if abs(nx - fx) > 1e-12 or abs(ny - fy) > 1e-12:
                        continue
                    vx, vy = vertex[e, 0], vertex[e, 1]
                    gap_a = (ax - vx) * fx + (ay - vy) * fy
                    gap_b = (bx - vx) * fx + (by - vy) * fy
                    t_a = ((ax - vx) * edge[e, 0] + (ay - vy) * edge[e, 1]) / length2[e]
                    t_b = ((bx - vx) * edge[e, 0] + (by - vy) * edge[e, 1]) / length2[e]
                    if (0.0 <= t_a <= 1.0 and 0.0 <= t_b <= 1.0 and abs(gap_a - r) <= tol
                            and abs(gap_b - r) <= tol):
                        found = True
                        break
        clear[i] = found and _segment_clear(ax, ay, moves[i, 0], moves[i, 1], r - tol, kind,
                                            sign, param, vertex, edge, length2)

def warm_up() -> float:
    """Compile (or load from numba's cache) the geometry kernels if this process has not yet;
    returns the seconds it took. Every ShapeWorkspace does this when it is made, so no kernel
    is compiled or loaded in the middle of a run (a stepping emulator, a re-planning loop)."""
    started = time.perf_counter()
    _load_kernels()
    return time.perf_counter() - started


@functools.cache
def _load_kernels() -> None:
    """Run each kernel once on a rect, a disk and a triangle: numba compiles (or loads) it, and
    for the one argument type `_kernel_array` and `_ShapeTable` give it."""
    triangle = _Polygon(((2.0, 2.0), (3.0, 2.0), (3.0, 3.0)))
    terms = [(_Rects([(0.0, 0.0, 4.0, 4.0)]), -1.0), (_Disks([(1.0, 1.0, 0.5)]), 1.0),
             (triangle, 1.0)]
    table = _ShapeTable(terms).arrays
    one = _kernel_array(np.ones((1, 2)), (2,))
    rho = _kernel_array(np.full(1, 0.1), ())
    outputs = (np.empty(1), np.empty((1, 2)), np.empty(1), np.empty(1, np.int64),
               np.empty(1, np.int64))
    _shape_query(one, *table, True, *outputs)
    _shape_sweep_clear(one, one, rho, *table, np.empty(1, dtype=bool))
    _shape_slide_clear(one, one, rho, one, 1e-7, *table[:7], np.empty(1, dtype=bool))


class GridWorkspace(Workspace):
    """Clearance, normal and curvature sampled at pixel centres, interpolated bilinearly.

    Arrays are (H, W) with row 0 at the top of the picture (largest y); pixel (row, col) has its
    centre at x = origin_x + (col + 0.5) * mm_per_px, y = origin_y + (H - row - 0.5) * mm_per_px.
    Outside the grid the clearance keeps falling by the distance to the grid's edge.

    `pieces` (grids from `rasterize`, (H, W, 6), see `ShapeWorkspace.primitives`): the piece of
    wall nearest each sample. In a cell whose four corners are in free space the clearance is
    then the distance to the nearest of the corners' pieces, exact wherever the point's nearest
    wall is one of them (everywhere but where three walls meet within a cell): straight walls,
    rounded corners and the creases of inside corners alike, which bilinear interpolation would
    blunt. Cells that touch a wall fall back to bilinear interpolation.
    """

    exact_geometry = False

    def __init__(
        self,
        clearance: np.ndarray,
        normal_x: np.ndarray,
        normal_y: np.ndarray,
        curvature: np.ndarray,
        mm_per_px: float,
        origin_mm: Sequence[float],
        pieces: np.ndarray | None = None,
    ) -> None:
        height, width = clearance.shape
        self._pieces = None
        self._cell_kind = None
        # With wall pieces every free cell is answered exactly (contacts of agents wider than
        # about 1.5 pixels happen in free cells), so the model may treat it as exact geometry.
        self.exact_geometry = pieces is not None
        if pieces is not None:
            pieces = np.asarray(pieces, dtype=float)
            self._pieces = np.ascontiguousarray(pieces.reshape(-1, 6))
            self._cell_kind = _cell_kinds(clearance, pieces)
        self.shape = (height, width)
        self.mm_per_px = float(mm_per_px)
        self.origin = (float(origin_mm[0]), float(origin_mm[1]))
        # One (H * W, 4) table so a query gathers each corner's four fields in one indexing step.
        self._fields = np.ascontiguousarray(
            np.stack([clearance, normal_x, normal_y, curvature], axis=-1).reshape(-1, 4)
        )
        self._clearance = np.ascontiguousarray(clearance, dtype=float).reshape(-1)
        self._corner_offsets = np.array([0, 1, width, width + 1], dtype=np.intp)
        self._inv = 1.0 / self.mm_per_px
        self._col0 = self.origin[0] / self.mm_per_px + 0.5
        self._row0 = (height - 0.5) + self.origin[1] / self.mm_per_px

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        height, width = self.shape
        x0, y0 = self.origin
        return (x0, y0, x0 + width * self.mm_per_px, y0 + height * self.mm_per_px)

    def _cells(self, points: ArrayLike):
        """Grid cell, bilinear weights and distance beyond the grid for points (..., 2)."""
        p = np.asarray(points, dtype=float)
        flat = p.reshape(-1, 2)
        height, width = self.shape
        col = flat[:, 0] * self._inv - self._col0
        row = self._row0 - flat[:, 1] * self._inv
        col_in = np.clip(col, 0.0, width - 1.0)
        row_in = np.clip(row, 0.0, height - 1.0)
        j0 = np.minimum(col_in.astype(np.intp), width - 2)
        i0 = np.minimum(row_in.astype(np.intp), height - 2)
        tx = col_in - j0
        ty = row_in - i0
        base = i0 * width + j0
        off_x = (col - col_in) * self.mm_per_px
        off_y = (row_in - row) * self.mm_per_px
        return p.shape[:-1], base, tx, ty, off_x, off_y

    def clearance(self, points: ArrayLike) -> np.ndarray:
        if self._pieces is not None:
            return self.surface(points)[0]
        return self._bilinear_clearance(points)

    def clearance_lower_bound(self, points: ArrayLike) -> np.ndarray:
        if self._pieces is None:
            return self._bilinear_clearance(points)
        # Bilinear interpolation overshoots round corners by at most (pixel^2 / 8) * curvature;
        # a quarter pixel covers curvatures up to 2 / pixel.
        return self._bilinear_clearance(points) - 0.25 * self.mm_per_px

    def _bilinear_clearance(self, points: ArrayLike) -> np.ndarray:
        lead, base, tx, ty, off_x, off_y = self._cells(points)
        f = self._clearance
        width = self.shape[1]
        top = f[base] + (f[base + 1] - f[base]) * tx
        bottom = f[base + width] + (f[base + width + 1] - f[base + width]) * tx
        phi = top + (bottom - top) * ty
        phi -= np.hypot(off_x, off_y)
        return phi.reshape(lead)

    def surface(self, points: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lead, base, tx, ty, off_x, off_y = self._cells(points)
        if self._cell_kind is None:
            phi, normal, curvature = self._bilinear(base, tx, ty)
        else:
            p = np.asarray(points, dtype=float).reshape(-1, 2)
            phi, normal, curvature = np.empty(len(p)), np.empty((len(p), 2)), np.empty(len(p))
            kind = self._cell_kind[base - base // self.shape[1]]  # cell i0 * (W - 1) + j0
            for code in (_CELL_AT_WALL, _CELL_ONE_PIECE, _CELL_PIECES):
                rows = np.flatnonzero(kind == code)
                if rows.size == 0:
                    continue
                if code == _CELL_AT_WALL:
                    found = self._bilinear(base[rows], tx[rows], ty[rows])
                else:
                    corners = self._corner_offsets[: 4 if code == _CELL_PIECES else 1]
                    found = self._from_pieces(p[rows], base[rows, None] + corners)
                phi[rows], normal[rows], curvature[rows] = found
        # Beyond the grid: keep descending with the distance to the grid, pointing back at it.
        beyond = np.hypot(off_x, off_y)
        outside = beyond > 0
        if outside.any():
            phi = phi - beyond
            back = -np.stack([off_x, off_y], axis=1) / np.maximum(beyond, _TINY)[:, None]
            normal = np.where(outside[:, None], back, normal)
        return phi.reshape(lead), normal.reshape(lead + (2,)), curvature.reshape(lead)

    def _bilinear(self, base: np.ndarray, tx: np.ndarray, ty: np.ndarray):
        """Clearance (K,), unit normal (K, 2), curvature (K,) interpolated in cells `base` (K,)."""
        corners = self._fields[base[:, None] + self._corner_offsets]  # (K, 4 corners, 4 fields)
        weights = np.stack([(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty], axis=1)
        value = np.einsum("nc,ncf->nf", weights, corners)
        normal = value[:, 1:3]
        normal = normal / np.maximum(np.hypot(normal[:, 0], normal[:, 1]), _TINY)[:, None]
        return value[:, 0], normal, value[:, 3]

    def _from_pieces(self, p: np.ndarray, samples: np.ndarray):
        """Clearance (K,), normal (K, 2), curvature (K,) at points p (K, 2) from the nearest of
        the wall pieces of grid samples `samples` (K, m)."""
        pieces = self._pieces[samples]  # (K, m, 6)
        a, b, rho, sigma = pieces[..., 0:2], pieces[..., 2:4], pieces[..., 4], pieces[..., 5]
        ab = b - a
        length2 = np.sum(ab * ab, axis=-1)
        t = np.sum((p[:, None, :] - a) * ab, axis=-1) / np.where(length2 > 0, length2, 1.0)
        t = np.clip(t, 0.0, 1.0)
        gap = p[:, None, :] - a - t[..., None] * ab
        dist = np.hypot(gap[..., 0], gap[..., 1])
        value = sigma * (dist - rho)
        rows = np.arange(len(p))
        pick = np.argmin(value, axis=1) if samples.shape[1] > 1 else np.zeros(len(p), dtype=np.intp)
        dist, sigma, gap = dist[rows, pick], sigma[rows, pick], gap[rows, pick]
        safe = np.maximum(dist, _TINY)
        # On the wall piece itself the direction is lost; free cells keep points off it.
        normal = sigma[:, None] * gap / safe[:, None]
        # Round where the nearest point is an end of the segment (or the centre of a disk).
        t_pick = t[rows, pick]
        round_ = (t_pick <= 0.0) | (t_pick >= 1.0) | (length2[rows, pick] == 0)
        curvature = np.where(round_, np.clip(sigma / safe, -_MAX_CURVATURE, _MAX_CURVATURE), 0.0)
        return value[rows, pick], normal, curvature


def _cell_kinds(clearance: np.ndarray, pieces: np.ndarray) -> np.ndarray:
    """Per grid cell, row-major ((H - 1) * (W - 1),): at a wall (a corner not in free space), in
    free space with one wall piece nearest all four corners, or with several."""
    free = clearance > 0
    all_free = free[:-1, :-1] & free[:-1, 1:] & free[1:, :-1] & free[1:, 1:]
    first = pieces[:-1, :-1]
    same = np.ones(all_free.shape, dtype=bool)
    for other in (pieces[:-1, 1:], pieces[1:, :-1], pieces[1:, 1:]):
        same &= np.all(other == first, axis=-1)
    kind = np.where(all_free, np.where(same, _CELL_ONE_PIECE, _CELL_PIECES), _CELL_AT_WALL)
    return kind.astype(np.int8).reshape(-1)


def _distance_to_other_square(mask: np.ndarray) -> np.ndarray:
    """For True pixels of `mask` (H, W): distance (px) from the centre to the nearest False square.

    The Euclidean distance transform gives the nearest False pixel centre at offset v; the square
    around it starts 0.5 * (|v_x| + |v_y|) / |v| before its centre along v.
    """
    distance, (rows, cols) = ndimage.distance_transform_edt(mask, return_indices=True)
    dr = np.abs(rows - np.arange(mask.shape[0])[:, None])
    dc = np.abs(cols - np.arange(mask.shape[1])[None, :])
    half_width = 0.5 * (dr + dc) / np.maximum(distance, 1.0)
    return np.where(mask, distance - half_width, 0.0)


def _shape_tuple(shape) -> tuple:
    """A schema shape (one of rect / polygon / disk set) as the ("kind", value) tuple used here."""
    for kind in ("rect", "polygon", "disk"):
        value = getattr(shape, kind, None)
        if value is not None:
            return (kind, value)
    raise PlanError(f"shape has none of rect, polygon, disk: {shape!r}")
