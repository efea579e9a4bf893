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
  boundary from inside. The clearance is the minimum over the boundary and every obstacle.
- `GridWorkspace` (from an image, a boolean mask, or sampled from a shape workspace with
  `rasterize`): clearance, normal and curvature stored at pixel centres and interpolated bilinearly,
  so a query costs the same however many obstacle pixels there are. A rasterized workspace also
  keeps, per sample, the piece of wall nearest to it (a segment or a disk), which makes it exact
  away from the walls. Images are read with row 0 at the top, i.e. the first row of the array is
  the largest y.

Lengths are in mm throughout. Points are arrays of shape (..., 2) holding (x, y).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from rigctl.errors import PlanError

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

    A query first takes the signed distance to every shape (cheap), then the normal and curvature
    of the nearest shape only.
    """

    exact_geometry = True

    def __init__(self, boundary: tuple, obstacles: Sequence[tuple] = ()) -> None:
        # Each term: (family, sign). The boundary counts with sign -1: free space is inside it.
        (outline,) = _families([boundary])
        self._terms: list[tuple[_Family, float]] = [(outline, -1.0)]
        self._terms += [(f, 1.0) for f in _families(list(obstacles))]
        self._count = sum(family.count for family, _ in self._terms)
        low, high = outline.bounds()
        self._bounds = (float(low[0]), float(low[1]), float(high[0]), float(high[1]))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return self._bounds  # type: ignore[return-value]

    def _distances(self, flat: np.ndarray) -> np.ndarray:
        """(N, terms) clearance contributed by each shape: -distance for the boundary."""
        result = np.empty((len(flat), self._count))
        start = 0
        for family, sign in self._terms:
            np.multiply(family.distance(flat), sign, out=result[:, start : start + family.count])
            start += family.count
        return result

    def clearance(self, points: ArrayLike) -> np.ndarray:
        p = np.asarray(points, dtype=float)
        return self._distances(p.reshape(-1, 2)).min(axis=1).reshape(p.shape[:-1])

    def surface(self, points: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = np.asarray(points, dtype=float)
        lead = p.shape[:-1]
        flat = p.reshape(-1, 2)
        distances = self._distances(flat)
        nearest = np.argmin(distances, axis=1)
        phi = distances[np.arange(len(flat)), nearest]
        normal = np.empty((len(flat), 2))
        kappa = np.empty(len(flat))
        start = 0
        for family, sign in self._terms:
            stop = start + family.count
            mine = (nearest >= start) & (nearest < stop)
            if mine.any():
                n, k = family.feature(flat[mine], nearest[mine] - start)
                normal[mine] = sign * n
                kappa[mine] = sign * k
            start = stop
        return phi.reshape(lead), normal.reshape(lead + (2,)), kappa.reshape(lead)


    def primitives(self, points: ArrayLike) -> np.ndarray:
        """The piece of wall nearest each point (..., 2), as (..., 6) rows (ax, ay, bx, by, rho,
        sigma): clearance = sigma * (|p - segment ab| - rho) near it. A side of a rect or polygon
        is a segment (rho 0, sigma 1: the clearance in free space is the distance to it); a disk
        obstacle has a = b = centre, rho = radius, sigma 1; a disk boundary the same with sigma -1.
        """
        p = np.asarray(points, dtype=float)
        flat = p.reshape(-1, 2)
        nearest = np.argmin(self._distances(flat), axis=1)
        result = np.empty((len(flat), 6))
        start = 0
        for family, sign in self._terms:
            stop = start + family.count
            mine = (nearest >= start) & (nearest < stop)
            if mine.any():
                pieces = family.primitive(flat[mine], nearest[mine] - start)
                if sign < 0:  # the boundary: free space is inside a disk, outside a segment
                    pieces[:, 5] = np.where(pieces[:, 4] > 0, -1.0, 1.0)
                result[mine] = pieces
            start = stop
        return result.reshape(p.shape[:-1] + (6,))


class _Family:
    """Shapes of one kind, evaluated together: `distance` (N, K) signed distance, > 0 outside;
    `feature` the gradient (N, 2) and level-set curvature (N,) of shape `which` (N,) at each point."""

    count: int

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def distance(self, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def feature(self, p: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def primitive(self, p: np.ndarray, which: np.ndarray) -> np.ndarray:
        """The piece of shape `which` (N,) nearest each point p (N, 2), as (N, 6) rows
        (ax, ay, bx, by, rho, 1): distance |p - segment ab| - rho (a segment: rho 0; a disk: a = b)."""
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

    def distance(self, p: np.ndarray) -> np.ndarray:
        # In place where possible: the model calls this for every event round.
        qx = np.subtract(p[:, :1], self.centre[:, 0])
        np.abs(qx, out=qx)
        qx -= self.half[:, 0]
        qy = np.subtract(p[:, 1:], self.centre[:, 1])
        np.abs(qy, out=qy)
        qy -= self.half[:, 1]
        inside = np.maximum(qx, qy)
        np.minimum(inside, 0.0, out=inside)
        np.maximum(qx, 0.0, out=qx)
        np.maximum(qy, 0.0, out=qy)
        # sqrt(x^2 + y^2) rather than hypot (several times slower): no overflow at these sizes,
        # and sqrt(x^2) == |x| exactly, so distances to a side stay exact.
        np.multiply(qx, qx, out=qx)
        np.multiply(qy, qy, out=qy)
        qx += qy
        out = np.sqrt(qx, out=qx)
        out += inside
        return out

    def feature(self, p: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rel = p - self.centre[which]
        sign = np.where(rel >= 0, 1.0, -1.0)
        q = np.abs(rel) - self.half[which]
        qx, qy = q[:, 0], q[:, 1]
        x_side = qx >= qy
        normal = np.zeros_like(rel)
        normal[:, 0] = np.where(x_side, sign[:, 0], 0.0)
        normal[:, 1] = np.where(x_side, 0.0, sign[:, 1])
        kappa = np.zeros(len(p))
        corner = np.flatnonzero((qx > 0) & (qy > 0))
        if corner.size:  # outside a corner: the level set is a circle round it
            out = np.hypot(qx[corner], qy[corner])
            normal[corner] = sign[corner] * q[corner] / out[:, None]
            kappa[corner] = np.minimum(1.0 / out, _MAX_CURVATURE)
        return normal, kappa

    def primitive(self, p: np.ndarray, which: np.ndarray) -> np.ndarray:
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

    def distance(self, p: np.ndarray) -> np.ndarray:
        return (
            np.hypot(p[:, :1] - self.centre[:, 0], p[:, 1:] - self.centre[:, 1]) - self.radius
        )

    def feature(self, p: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rel = p - self.centre[which]
        dist = np.hypot(rel[:, 0], rel[:, 1])
        safe = np.maximum(dist, _TINY)
        normal = np.where(dist[:, None] > 0, rel / safe[:, None], np.array([1.0, 0.0]))
        # The level set through p is the circle of radius |p - centre|.
        return normal, np.minimum(1.0 / safe, _MAX_CURVATURE)

    def primitive(self, p: np.ndarray, which: np.ndarray) -> np.ndarray:
        c = self.centre[which]
        return np.concatenate(
            [c, c, self.radius[which, None], np.ones((len(p), 1))], axis=1
        )


class _Polygon(_Family):
    """One simple polygon, stored counter-clockwise (outward normal of edge e is (e_y, -e_x))."""

    def __init__(self, vertices) -> None:
        v = np.asarray(vertices, dtype=float)
        if _signed_area(v) < 0:
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

    def _nearest(self, p: np.ndarray):
        a = self.vertices
        w = p[:, None, :] - a[None]
        t = np.clip(np.sum(w * self.edge[None], axis=2) / self.length2[None], 0.0, 1.0)
        diff = w - t[..., None] * self.edge[None]
        d2 = np.sum(diff * diff, axis=2)
        k = np.argmin(d2, axis=1)
        rows = np.arange(len(p))
        # Crossing number: a ray towards +x crosses the boundary an odd number of times from inside.
        ay = a[None, :, 1]
        by = np.roll(a, -1, axis=0)[None, :, 1]
        py = p[:, 1:2]
        straddles = (ay > py) != (by > py)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = a[None, :, 0] + (py - ay) * self.edge[None, :, 0] / (by - ay)
        inside = (np.sum(straddles & (p[:, :1] < x_cross), axis=1) % 2) == 1
        sign = np.where(inside, -1.0, 1.0)
        return sign, np.sqrt(d2[rows, k]), k, t[rows, k], diff[rows, k]

    def distance(self, p: np.ndarray) -> np.ndarray:
        sign, d, _, _, _ = self._nearest(p)
        return (sign * d)[:, None]

    def feature(self, p: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sign, d, k, t, diff = self._nearest(p)
        at_vertex = (t <= 0.0) | (t >= 1.0)
        vertex = np.where(t >= 1.0, (k + 1) % len(self.vertices), k)
        safe = np.maximum(d, _TINY)
        # Nearest a vertex: the level set is a circle round it (inside the polygon it bends the
        # other way). On the vertex itself the normal is the bisector of its edges' normals.
        round_normal = np.where(
            d[:, None] > 0, sign[:, None] * diff / safe[:, None], self.vertex_normal[vertex]
        )
        normal = np.where(at_vertex[:, None], round_normal, self.outward[k])
        kappa = np.where(at_vertex, np.clip(sign / safe, -_MAX_CURVATURE, _MAX_CURVATURE), 0.0)
        return normal, kappa

    def primitive(self, p: np.ndarray, which: np.ndarray) -> np.ndarray:
        _, _, k, _, _ = self._nearest(p)
        a, b = self.vertices[k], self.vertices[(k + 1) % len(self.vertices)]
        return np.concatenate([a, b, np.zeros((len(p), 1)), np.ones((len(p), 1))], axis=1)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (...) from points p to segments ab, all (..., 2), broadcast; a == b is a point."""
    ab = b - a
    length2 = np.sum(ab * ab, axis=-1)
    t = np.clip(np.sum((p - a) * ab, axis=-1) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    gap = p - a - t[..., None] * ab
    return np.hypot(gap[..., 0], gap[..., 1])


def _signed_area(vertices: np.ndarray) -> float:
    x, y = vertices[:, 0], vertices[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


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

    @property
    def clearance_grid(self) -> np.ndarray:
        """The sampled clearance (H, W), mm, row 0 at the top."""
        return self._clearance.reshape(self.shape)

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
