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
  so a query costs the same however many obstacle pixels there are. Images are read with row 0 at
  the top, i.e. the first row of the array is the largest y.

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
# Blur (pixels) of a mask's distance field before taking normals from it.
_NORMAL_BLUR_PX = 1.0


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
            boundary=_shape_tuple(spec.boundary), obstacles=[_shape_tuple(s) for s in spec.obstacles]
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
        mask counts as obstacle. Walls along the pixel grid come out within half a pixel; curved
        walls within about 0.7 pixel (which pixel centres fell inside is all a mask tells).
        """
        free = np.asarray(free, dtype=bool)
        if free.ndim != 2 or min(free.shape) < 2:
            raise PlanError(f"workspace mask must be a 2-D array of at least 2 x 2, got {free.shape}")
        if mm_per_px <= 0:
            raise PlanError(f"mm_per_px must be > 0, got {mm_per_px}")
        if not free.any():
            raise PlanError("workspace mask has no free pixel (everything is darker than 128)")
        # One ring of obstacle around the picture: the world beyond the image is not free space.
        padded = np.pad(free, 1, constant_values=False)
        # Distance from each pixel centre to the nearest pixel of the other kind, then to the edge
        # of that pixel's square along the way: the wall is taken half way between the centres.
        inside = _distance_to_other_square(padded)
        outside = _distance_to_other_square(~padded)
        clearance = np.where(padded, inside, -outside) * mm_per_px
        # Normals from a blurred copy: the staircase of a pixelated wall is noise for directions.
        blurred = ndimage.gaussian_filter(clearance, sigma=_NORMAL_BLUR_PX, mode="nearest")
        d_row, d_col = np.gradient(blurred)
        nx, ny = d_col, -d_row  # rows grow downwards, y grows upwards
        origin = (float(origin_mm[0]) - mm_per_px, float(origin_mm[1]) - mm_per_px)
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
        return GridWorkspace(
            clearance, normal[..., 0], normal[..., 1], curvature, resolution_mm, origin
        )

    def clearance(self, points: ArrayLike) -> np.ndarray:
        """Signed distance (mm) from points (..., 2) to the nearest surface; > 0 in free space."""
        return self.surface(points)[0]

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
        low, high = outline.bounds()
        self._bounds = (float(low[0]), float(low[1]), float(high[0]), float(high[1]))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return self._bounds  # type: ignore[return-value]

    def _distances(self, flat: np.ndarray) -> np.ndarray:
        """(N, terms) clearance contributed by each shape: -distance for the boundary."""
        return np.concatenate([sign * f.distance(flat) for f, sign in self._terms], axis=1)

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
        qx = np.abs(p[:, :1] - self.centre[:, 0]) - self.half[:, 0]
        qy = np.abs(p[:, 1:] - self.centre[:, 1]) - self.half[:, 1]
        out = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
        return out + np.minimum(np.maximum(qx, qy), 0.0)

    def feature(self, p: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rel = p - self.centre[which]
        sign = np.where(rel >= 0, 1.0, -1.0)
        q = np.abs(rel) - self.half[which]
        qx, qy = q[:, 0], q[:, 1]
        corner = (qx > 0) & (qy > 0)
        out = np.where(corner, np.hypot(qx, qy), 1.0)
        x_side = qx >= qy
        gx = np.where(corner, sign[:, 0] * qx / out, np.where(x_side, sign[:, 0], 0.0))
        gy = np.where(corner, sign[:, 1] * qy / out, np.where(x_side, 0.0, sign[:, 1]))
        kappa = np.where(corner, np.minimum(1.0 / out, _MAX_CURVATURE), 0.0)
        return np.stack([gx, gy], axis=1), kappa


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


def _signed_area(vertices: np.ndarray) -> float:
    x, y = vertices[:, 0], vertices[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


class GridWorkspace(Workspace):
    """Clearance, normal and curvature sampled at pixel centres, interpolated bilinearly.

    Arrays are (H, W) with row 0 at the top of the picture (largest y); pixel (row, col) has its
    centre at x = origin_x + (col + 0.5) * mm_per_px, y = origin_y + (H - row - 0.5) * mm_per_px.
    Outside the grid the clearance keeps falling by the distance to the grid's edge.
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
    ) -> None:
        height, width = clearance.shape
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
        corners = self._fields[base[:, None] + self._corner_offsets]  # (N, 4 corners, 4 fields)
        weights = np.stack([(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty], axis=1)
        value = np.einsum("nc,ncf->nf", weights, corners)
        normal = value[:, 1:3]
        norm = np.hypot(normal[:, 0], normal[:, 1])
        normal = normal / np.maximum(norm, _TINY)[:, None]
        phi = value[:, 0]
        # Beyond the grid: keep descending with the distance to the grid, pointing back at it.
        beyond = np.hypot(off_x, off_y)
        outside = beyond > 0
        if outside.any():
            phi = phi - beyond
            back = -np.stack([off_x, off_y], axis=1) / np.maximum(beyond, _TINY)[:, None]
            normal = np.where(outside[:, None], back, normal)
        return phi.reshape(lead), normal.reshape(lead + (2,)), value[:, 3].reshape(lead)


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
