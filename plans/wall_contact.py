"""The wall-contact planner of seed 004: two particles, one shared input, non-slip walls.

Under eq. 1 of seed 004 a particle pushed into a wall does not move, so a shared input can change
the particles' relative position `delta = p2 - p1` (the Delta configuration space) only while one
of them is pinned. Alg. 1 repeats a two-move step: move 1 translates both particles until one
("the pinned one") touches the wall at a contact point c; move 2 pushes into that wall, so only the
other particle moves. The step aims at the point of the 2-move reachable set nearest to the goal's
delta; once delta is within epsilon of it, one translation delivers both particles.

How the 2-move reachable set is computed here (same set as Alg. 2 / Alg. 3, built differently).
Let Q be the convex region where particle centres can go (the workspace shrunk by the particle
radius), n the outward normal of the wall at c and d = p_other - p_pinned. After move 1 the other
particle sits at c + d; move 2 may take it to any q in Q with n.q >= n.(c + d) (pushing into the
wall, so the pinned one stays). The contact c is feasible when c + d is inside Q (the other
particle has not met a wall first). So for one wall the reachable "other minus pinned" offsets are

    { q - c : c on the wall with c + d in Q,  q in Q,  n.q >= n.c + n.d }

- polygon (Alg. 2): per edge the feasible contacts form a segment and the q form a convex slice of
  Q, so the set is their Minkowski difference, a convex polygon; the union over edges is the
  2-move reachable set. The nearest point per polygon is exact.
- disk (Alg. 3, eq. 2-5): the contact is the angle psi of c in the feasible arc of eq. 2, and the q
  form the circular segment under a chord (eq. 3-4's gamma). The nearest point of each chord region
  is found in closed form, over a psi grid refined by successively finer grids.

Among contacts that reach the same delta, the planner keeps the shortest path: for the last step
that is the reflection law of Sec. V (the contact minimising |c - p_pinned| + |g_pinned - c|).

When neither the greedy step nor the one after it reaches the goal, a look-ahead (polygons) aims
at the corner of the reachable set from which the goal is reached soonest (`_look_ahead`).
`reachable_fraction` measures how much of the Delta space M moves reach (the paper's Fig. 8-9).

Every position is kept by an exact point-particle simulation of eq. 1 in Q (`apply_move`); the plan
writer then replays the moves through THE global-input model (plans/model.py, "non-slip"), whose
disc particles can also meet each other, and re-runs Alg. 1 from the model's end state if the two
disagree (Alg. 1 is a feedback law). Lengths are in mm, points are arrays (2,) or (k, 2).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import PlanError
from rigctl.core.jit import njit
from rigctl.physics.geometry import signed_area

log = logging.getLogger(__name__)

# Points this close (relative to the region's size) to a wall count as on it.
_ON_WALL_REL = 1e-9
# Slack kept between planned positions and walls / the pinning condition (relative to size): moves
# push strictly into the wall that pins, and the moving particle ends strictly inside.
_MARGIN_REL = 1e-8
# Contacts keep this far (relative to size) from polygon corners, where the wall normal is ambiguous.
_CORNER_REL = 1e-5
# Polygon contacts keep this share of their feasible span from its ends: at an end the moving
# particle ends exactly on the margin, and a later move grazing that wall would stop it early.
_SPAN_KEEP_REL = 2.5e-6
# Contact angles per pinned particle in the disk's coarse search.
_PSI_GRID = 361
# A step whose delta is this close (relative to size) to the goal's counts as the last one: its
# path length includes the final translation.
_FINISHING_REL = 1e-6
# Corners of the 2-move reachable set tried by the look-ahead (nearest the goal's delta first).
_LOOKAHEAD_CORNERS = 12


# ---------------------------------------------------------------- regions


class CentreRegion(Protocol):
    """The convex region where particle centres may be (mm)."""

    @property
    def size(self) -> float:
        """(read only: the regions are frozen dataclasses)"""

    def contains(self, points: np.ndarray, slack: float = 0.0) -> np.ndarray:
        """(k,) True where points (k, 2) lie inside, at least `slack` mm from the boundary."""

    def exit_distance(self, point: np.ndarray, direction: np.ndarray) -> float:
        """How far (mm) from `point` (inside) along unit `direction` (2,) the boundary is."""

    def wall_normals(self, point: np.ndarray) -> np.ndarray:
        """Outward normals (k, 2) of every wall `point` (2,) touches (k = 0 inside)."""


@dataclass(frozen=True)
class PolygonRegion:
    """A convex polygon, vertices (V, 2) counter-clockwise; edge i runs from vertex i to i + 1."""

    vertices: np.ndarray
    normals: np.ndarray = field(init=False)  # (V, 2) outward unit normals
    offsets: np.ndarray = field(init=False)  # (V,) n_i . x <= offsets_i inside
    size: float = field(init=False)  # diameter (mm)
    # (V, 2) the polygon shrunk by the planner's margin (_MARGIN_REL of the size): where move 2
    # may take the moving particle. Shrinking is exact for convex polygons (every edge moves in).
    shrunk: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=float)
        if signed_area(v) < 0:
            v = v[::-1].copy()
        edge = np.roll(v, -1, axis=0) - v
        length = np.hypot(edge[:, 0], edge[:, 1])
        normals = np.stack([edge[:, 1], -edge[:, 0]], axis=1) / length[:, None]
        offsets = np.sum(normals * v, axis=1)
        if np.any(normals @ v.T > offsets[:, None] + 1e-9 * (1.0 + np.abs(v).max())):
            raise PlanError("the wall-contact planner needs a convex workspace boundary")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "normals", normals)
        object.__setattr__(self, "offsets", offsets)
        span = v[:, None, :] - v[None, :, :]
        object.__setattr__(self, "size", float(np.sqrt((span**2).sum(-1)).max()))
        object.__setattr__(self, "shrunk", _edge_lines_meet(normals, offsets - _MARGIN_REL * self.size))

    def contains(self, points: np.ndarray, slack: float = 0.0) -> np.ndarray:
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        return np.all(p @ self.normals.T <= self.offsets + 1e-12 * self.size - slack, axis=1)

    def exit_distance(self, point: np.ndarray, direction: np.ndarray) -> float:
        rate = self.normals @ direction
        room = self.offsets - self.normals @ point
        # A move this close to parallel to a wall runs along it (as in `apply_move`, which pins a
        # particle only when the move pushes into its wall by more than this): without the same
        # bound a particle on a wall would stop dead under a move meant to slide along it.
        ahead = rate > 1e-12
        if not ahead.any():
            return math.inf
        return float(max(np.min(room[ahead] / rate[ahead]), 0.0))

    def wall_normals(self, point: np.ndarray) -> np.ndarray:
        gap = self.offsets - self.normals @ point
        return self.normals[gap <= _ON_WALL_REL * self.size]

    def inset(self, distance: float) -> "PolygonRegion":
        """The polygon with every edge moved inward by `distance` mm (where centres of discs of
        that radius may go); PlanError if an edge vanishes."""
        if distance <= 0:
            return self
        vertices = _edge_lines_meet(self.normals, self.offsets - distance)
        edge = np.roll(vertices, -1, axis=0) - vertices
        if np.any(np.sum(edge * (np.roll(self.vertices, -1, axis=0) - self.vertices), axis=1) <= 0):
            raise PlanError(f"particles of radius {distance:g} mm do not fit this workspace's corners")
        return PolygonRegion(vertices)


@dataclass(frozen=True)
class DiskRegion:
    """A disk: centre (2,) and radius (mm)."""

    centre: np.ndarray
    radius: float

    @property
    def size(self) -> float:
        return 2.0 * self.radius

    def contains(self, points: np.ndarray, slack: float = 0.0) -> np.ndarray:
        p = np.asarray(points, dtype=float).reshape(-1, 2) - self.centre
        return np.hypot(p[:, 0], p[:, 1]) <= self.radius * (1 + 1e-12) - slack

    def exit_distance(self, point: np.ndarray, direction: np.ndarray) -> float:
        w = point - self.centre
        b = float(w @ direction)
        c = float(w @ w) - self.radius**2
        return max(-b + math.sqrt(max(b * b - c, 0.0)), 0.0)

    def wall_normals(self, point: np.ndarray) -> np.ndarray:
        w = point - self.centre
        dist = math.hypot(*w)
        if dist < self.radius * (1 - _ON_WALL_REL) or dist == 0:
            return np.empty((0, 2))
        return (w / dist)[None]


def _edge_lines_meet(normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(V, 2) vertex i where line i-1 meets line i ({x : normals_k . x = offsets_k})."""
    prev_n, prev_h = np.roll(normals, 1, axis=0), np.roll(offsets, 1)
    det = prev_n[:, 0] * normals[:, 1] - prev_n[:, 1] * normals[:, 0]
    x = (prev_h * normals[:, 1] - prev_n[:, 1] * offsets) / det
    y = (prev_n[:, 0] * offsets - prev_h * normals[:, 0]) / det
    return np.stack([x, y], axis=1)


def centre_region(boundary: dict, radius: float) -> PolygonRegion | DiskRegion:
    """The region particle centres of `radius` mm can reach inside a plan boundary shape
    (`{"rect": ...}`, `{"polygon": ...}` convex, or `{"disk": ...}`); PlanError otherwise."""
    if "disk" in boundary:
        cx, cy, r = boundary["disk"]
        if r <= radius:
            raise PlanError(f"particles of radius {radius:g} mm do not fit a disk of radius {r:g} mm")
        return DiskRegion(np.array([cx, cy], dtype=float), float(r - radius))
    if "rect" in boundary:
        x, y, w, h = boundary["rect"]
        vertices = [(x, y), (x + w, y), (x + w, y + h), (x, y + h)]
    elif "polygon" in boundary:
        vertices = boundary["polygon"]
    else:
        raise PlanError(f"the wall-contact planner needs a rect, polygon or disk boundary, got {boundary}")
    return PolygonRegion(np.asarray(vertices, dtype=float)).inset(radius)


# ---------------------------------------------------------------- eq. 1 for point particles


def apply_move(region: CentreRegion, positions: ArrayLike, move: ArrayLike) -> np.ndarray:
    """Seed 004 eq. 1 for point particles in a convex region: positions (k, 2) after the shared
    straight move (2,) mm. A particle on a wall that the move pushes into stays; any other moves
    along the input until it meets the boundary, where it stops (it is then pushed into it)."""
    p = np.array(positions, dtype=float).reshape(-1, 2)
    move = np.asarray(move, dtype=float)
    length = math.hypot(*move)
    if length == 0:
        return p
    u = move / length
    for i in range(len(p)):
        normals = region.wall_normals(p[i])
        if len(normals) and np.any(normals @ u > 1e-12):
            continue
        p[i] = p[i] + min(length, region.exit_distance(p[i], u)) * u
    return p


# ---------------------------------------------------------------- one two-move step


@dataclass(frozen=True)
class TwoMoveStep:
    """One Alg. 1 iteration: `pinned` (0 or 1) touches the wall at `contact` after move 1, move 2
    takes the other particle to `other_end`. `delta` is p2 - p1 afterwards, `distance` its
    distance to the goal delta, `length` the two moves' length (mm)."""

    pinned: int
    contact: np.ndarray
    other_end: np.ndarray
    delta: np.ndarray
    distance: float
    length: float

    def moves(self, positions: np.ndarray) -> np.ndarray:
        """The two shared moves (2, 2) mm from positions (2, 2)."""
        first = self.contact - positions[self.pinned]
        second = self.other_end - (positions[1 - self.pinned] + first)
        return np.stack([first, second])


def best_two_move_step(
    region: CentreRegion, positions: np.ndarray, goals: np.ndarray, reach: float = 0.0,
    push: float = 0.0,
) -> TwoMoveStep | None:
    """The Alg. 1 step from positions (2, 2) toward goals (2, 2): the 2-move reachable delta
    nearest to the goal's delta, and among contacts reaching it the shortest path (Sec. V).

    reach (mm): the particles' centres never come closer than this (r1 + r2 for discs); move 2
    must not carry the moving particle through the pinned one, so offsets it could only reach
    across the disc |offset| < reach are left out (conservatively: the visible part is taken as
    the union of three half-planes bounded by the tangents from the current offset).

    push (mm): move 2 must carry the moving particle at least this far into the pinning wall's
    normal direction (0: the paper's set; a rig whose pull is not quite uniform needs a margin, so
    that the pinned particle is really pushed into its wall and not grazing along it).
    """
    reach = _clearance(region, reach)
    if isinstance(region, DiskRegion):
        return _nearest_then_shortest(_disk_steps(region, positions, goals, reach, push), region)
    return _nearest_then_shortest(_polygon_steps(region, positions, goals, reach, push=push), region)


def _clearance(region: CentreRegion, reach: float) -> float:
    """The centre distance the relative moves keep for particles `reach` mm apart (with slack)."""
    return reach * (1.0 + 1e-6) + _MARGIN_REL * region.size if reach > 0 else 0.0


def _nearest_then_shortest(candidates: list, region: CentreRegion) -> TwoMoveStep | None:
    """The candidate step nearest the goal's delta; among (near) ties, the shortest."""
    if not candidates:
        return None
    nearest = min(step.distance for step in candidates)
    tie = max(1e-9 * region.size, 1e-3 * nearest)
    return min((s for s in candidates if s.distance <= nearest + tie), key=lambda s: s.length)


def _step_length(contact, other_end, start_pin, start_other, goal_pin, finishing) -> float:
    first = contact - start_pin
    second = other_end - (start_other + first)
    length = math.hypot(*first) + math.hypot(*second)
    if finishing:
        length += math.hypot(*(goal_pin - contact))
    return length


def _visible_halfplanes(d: np.ndarray, reach: float) -> list[tuple[np.ndarray, float]]:
    """Half-planes {w : a . w >= b} (unit a) whose points the segment from offset d reaches
    without entering the disc |w| < reach: beyond the tangent lines from d, and in front of the
    disc. Empty when no disc is to be avoided."""
    dist = math.hypot(*d)
    if reach <= 0 or dist <= reach:
        return []
    u = d / dist
    beta = math.asin(reach / dist)
    planes = [(u, reach)]
    for sign in (1.0, -1.0):
        cos_b, sin_b = math.cos(beta), sign * math.sin(beta)
        toward = np.array([-u[0] * cos_b + u[1] * sin_b, -u[0] * sin_b - u[1] * cos_b])
        a = np.array([-toward[1], toward[0]])
        if a @ d < 0:
            a = -a
        planes.append((a, float(a @ d)))
    return planes


def _blocked(d: np.ndarray, w: np.ndarray, reach: float) -> np.ndarray:
    """(K,) True where the segments from offset d (2,) to offsets w (K, 2) pass through |x| < reach."""
    w = np.asarray(w, dtype=float).reshape(-1, 2)
    if reach <= 0:
        return np.zeros(len(w), dtype=bool)
    span = w - d
    t = np.clip(-(span @ d) / np.maximum(np.sum(span * span, axis=1), 1e-300), 0.0, 1.0)
    closest = d + t[:, None] * span
    return np.hypot(closest[:, 0], closest[:, 1]) < reach


@dataclass(frozen=True)
class _WallPart:
    """What one wall (polygon edge) adds to the 2-move reachable set from given positions (Alg. 2),
    independent of the goal: the pinned particle, the offset d = other - pinned, the feasible
    contacts a + t edge (t in t_range), the slice of Q move 2 may end in and the set of
    reachable offsets q - c (a convex polygon), both with their half-planes."""

    pin: int
    d: np.ndarray
    a: np.ndarray
    edge: np.ndarray
    normal: np.ndarray
    offset: float
    t_range: tuple[float, float]
    slice_: np.ndarray
    slice_planes: tuple[np.ndarray, np.ndarray]
    offsets: np.ndarray
    offsets_planes: tuple[np.ndarray, np.ndarray]


def _polygon_parts(region: PolygonRegion, positions: np.ndarray, push: float = 0.0) -> list:
    """The `_WallPart`s of every wall from positions (2, 2) (walls both particles meet together,
    or with no feasible contact, add nothing)."""
    size = region.size
    margin = _MARGIN_REL * size
    parts = []
    count = len(region.vertices)
    outward_all = positions @ region.normals.T  # (2, V)
    for e in range(count):
        n, h = region.normals[e], float(region.offsets[e])
        outward = outward_all[:, e]
        if abs(outward[0] - outward[1]) <= margin:
            continue  # both meet this wall together: the step changes nothing
        pin = int(np.argmax(outward))
        d = positions[1 - pin] - positions[pin]
        # Feasible contacts c = a + t (b - a): c + d inside the polygon, off the corners.
        a = region.vertices[e]
        edge = region.vertices[(e + 1) % count] - a
        corner = _CORNER_REL * size / math.hypot(*edge)
        t_range = _clip_interval(region, a + d, edge, corner, 1.0 - corner)
        if t_range is None:
            continue
        # Where move 2 can take the other particle: a slice of Q by a line parallel to the wall.
        # (Shrinking the slice by the margin = slicing the shrunk polygon a margin further in.)
        slice_ = _clip_polygon(region.shrunk, -n, -(h + n @ d + 2.0 * margin + push))
        if slice_ is None:
            continue
        c_lo, c_hi = a + t_range[0] * edge, a + t_range[1] * edge
        offsets = _convex_hull(np.concatenate([slice_ - c_lo, slice_ - c_hi]))
        parts.append(_WallPart(pin, d, a, edge, n, h, t_range, slice_, _halfplanes(slice_),
                               offsets, _halfplanes(offsets)))
    return parts


def _polygon_steps(
    region: PolygonRegion,
    positions: np.ndarray,
    goals: np.ndarray,
    reach: float,
    corners: list | None = None,
    push: float = 0.0,
    parts: list | None = None,
) -> list:
    """One candidate step per wall (`_WallPart`, computed here unless given for these positions):
    the offset nearest the goal's, reached by the shortest contact."""
    size = region.size
    goal_delta = goals[1] - goals[0]
    steps = []
    for part in _polygon_parts(region, positions, push) if parts is None else parts:
        pin, d, a, edge, offsets = part.pin, part.d, part.a, part.edge, part.offsets
        target = goal_delta if pin == 0 else -goal_delta  # wanted other - pinned
        if corners is not None:  # the corners of this part of the set, as deltas p2 - p1
            visible = offsets[~_blocked(d, offsets, reach)]
            corners.extend(visible if pin == 0 else -visible)
        near = _nearest_in_polygon(offsets, target, part.offsets_planes)
        if reach > 0 and _blocked(d, near, reach)[0]:
            options = []
            for a_, b_ in _visible_halfplanes(d, reach):
                cut = _clip_polygon(offsets, -a_, -b_)
                if cut is not None:
                    options.append(_nearest_in_polygon(cut, target))
            if not options:
                continue
            near = min(options, key=lambda w: math.hypot(*(w - target)))
        distance = math.hypot(*(near - target))
        finishing = distance <= _FINISHING_REL * size
        # The contacts that give `near`: t with near + c(t) in the slice; keep the shortest path.
        span = _clip_interval_poly(part.slice_planes, near + a, edge, *part.t_range,
                                   tol=1e-9 * size)
        # |move 1| + |move 2| (+ the final translation): move 2 is the same for every t, and
        # the rest is convex in t, so its minimum over the span is the free minimum clipped.
        goal_pin = goals[pin] if finishing else None
        keep = _SPAN_KEEP_REL * (span[1] - span[0])
        t = _shortest_contact(a, edge, part.normal, part.offset, positions[pin], goal_pin)
        t = min(max(t, span[0] + keep), span[1] - keep)
        c = a + t * edge
        q = near + c
        delta = q - c if pin == 0 else c - q
        length = math.hypot(*(c - positions[pin])) + math.hypot(*(near - d))
        if finishing:
            length += math.hypot(*(goals[pin] - c))
        steps.append(TwoMoveStep(pin, c, q, delta, distance, length))
    return steps


def _shortest_contact(a, edge, normal, offset, start, goal) -> float:
    """The t minimising |c - start| (+ |goal - c| when goal is given) for c = a + t edge on the
    wall line normal . c = offset, start and goal inside: the foot of start, or where the segment
    from start to the goal's mirror image crosses the wall (the reflection law of Sec. V)."""
    scale = float(edge @ edge)
    if goal is None:
        return float((start - a) @ edge) / scale
    mirror = goal + 2.0 * (offset - float(normal @ goal)) * normal
    rise = float(normal @ (mirror - start))
    s = (offset - float(normal @ start)) / rise if rise > 1e-300 else 0.0
    return float((start + s * (mirror - start) - a) @ edge) / scale


def _disk_steps(region: DiskRegion, positions: np.ndarray, goals: np.ndarray, reach: float,
                push: float = 0.0) -> list:
    R, O = region.radius, region.centre  # noqa: E741 (the paper's O, the disk's centre)
    margin = _MARGIN_REL * region.size
    goal_delta = goals[1] - goals[0]
    steps = []
    for pin in (0, 1):
        other = 1 - pin
        d = positions[other] - positions[pin]
        d12 = math.hypot(*d)
        if d12 <= margin:
            continue
        target = goal_delta if pin == 0 else -goal_delta
        # eq. 2: the pinned particle can touch first where n . d <= -|d|^2 / (2R), an arc about -d.
        centre_angle = math.atan2(-d[1], -d[0])
        half = math.acos(min(d12 / (2.0 * R), 1.0)) - _CORNER_REL
        if half <= 0:
            continue

        def evaluate(psi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            n = np.stack([np.cos(psi), np.sin(psi)], axis=-1)
            c = O + R * n
            # Move 2 keeps n.(q - O) >= R + n.d (+ margin): the chord region of eq. 3-4.
            level = R + n @ d + margin + push
            q = _nearest_in_chord_region(O, R - margin, n, level, target + c)
            blocked = _blocked(d, q - c, reach)
            if blocked.any():
                best_q = np.where(blocked[:, None], np.nan, q)
                for a_, b_ in _visible_halfplanes(d, reach):
                    alt = _nearest_in_chord_cut(O, R - margin, n, level, target + c, a_, b_ + c @ a_)
                    better = np.hypot(*(alt - c - target).T) < np.hypot(*(best_q - c - target).T)
                    better |= np.isnan(best_q[:, 0]) & ~np.isnan(alt[:, 0])
                    best_q = np.where((blocked & better)[:, None], alt, best_q)
                q = best_q
            distance = np.hypot(*(q - c - target).T)
            distance = np.where(np.isnan(distance), np.inf, distance)
            return distance, c, q

        grid = centre_angle + np.linspace(-half, half, _PSI_GRID)
        distance, c, q = evaluate(grid)
        finishing = distance <= _FINISHING_REL * region.size
        first = c - positions[pin]
        second = q - (positions[other] + first)
        lengths = np.hypot(*first.T) + np.hypot(*second.T)
        lengths += np.where(finishing, np.hypot(*(goals[pin] - c).T), 0.0)
        best = distance.min()
        tie = max(1e-9 * region.size, 1e-3 * best)
        pool = np.flatnonzero(distance <= best + tie)
        k = int(pool[np.argmin(lengths[pool])])
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]

        def score(psi: np.ndarray) -> np.ndarray:
            dist, cc, qq = evaluate(psi)
            if best > tie:  # the goal delta is out of reach: get as near as possible
                return dist
            first = cc - positions[pin]
            length = np.hypot(*first.T) + np.hypot(*(qq - (positions[other] + first)).T)
            length += np.hypot(*(goals[pin] - cc).T)  # this step finishes: count the translation
            return dist * 1e6 + length  # among exact hits, the shortest path

        psi = grid[k]
        if best <= tie:  # reachable: refine the contact for the shortest path
            refined = _minimise_on_interval(score, lo, hi)
            if score(np.array([refined]))[0] < score(np.array([psi]))[0]:
                psi = refined
        dist, cc, qq = evaluate(np.array([psi]))
        c_, q_ = cc[0], qq[0]
        delta = q_ - c_ if pin == 0 else c_ - q_
        done = dist[0] <= _FINISHING_REL * region.size
        length = _step_length(c_, q_, positions[pin], positions[other], goals[pin], done)
        steps.append(TwoMoveStep(pin, c_, q_, delta, float(dist[0]), length))
    return steps


def _nearest_in_chord_cut(centre, radius, n, level, x, a, b) -> np.ndarray:
    """Nearest points (K, 2) to x (K, 2) in the chord region of `_nearest_in_chord_region` cut by
    {y : a . y >= b} (a (2,) unit, b (K,)); nan rows where that is empty. If the uncut nearest
    point is outside the cut, the answer lies on the cutting line."""
    y = _nearest_in_chord_region(centre, radius, n, level, x)
    keep = y @ a >= b - 1e-12
    v = np.array([-a[1], a[0]])
    foot = b[:, None] * a  # a point of the line a . y = b
    rel = foot - centre
    # On the line: inside the circle ...
    half_b = rel @ v
    disc = half_b**2 - (np.sum(rel * rel, axis=1) - radius**2)
    root = np.sqrt(np.maximum(disc, 0.0))
    lo, hi = -half_b - root, -half_b + root
    # ... and on the kept side of the chord: n . (foot + s v - centre) >= level.
    rate = n @ v
    room = level - np.sum(n * rel, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = room / rate
    lo = np.where(rate > 1e-15, np.maximum(lo, bound), lo)
    hi = np.where(rate < -1e-15, np.minimum(hi, bound), hi)
    empty = (disc < 0) | (lo > hi) | ((np.abs(rate) <= 1e-15) & (room > 0))
    s = np.clip((x - foot) @ v, lo, hi)
    on_line = foot + s[:, None] * v
    result = np.where(keep[:, None], y, on_line)
    return np.where((~keep & empty)[:, None], np.nan, result)


def _nearest_in_chord_region(
    centre: np.ndarray, radius: float, n: np.ndarray, level: np.ndarray, x: np.ndarray
) -> np.ndarray:
    """Nearest points (K, 2) to x (K, 2) in {q : |q - centre| <= radius, n.(q - centre) >= level},
    n (K, 2) unit, level (K,) in (-radius, radius): a disk cut by a chord."""
    rel = x - centre
    along = np.sum(rel * n, axis=1)
    dist = np.hypot(rel[:, 0], rel[:, 1])
    inside = (dist <= radius) & (along >= level)
    # Candidate on the arc: the radial projection, if it lies on the kept side of the chord.
    safe = np.maximum(dist, 1e-300)[:, None]
    on_arc = centre + radius * rel / safe
    arc_ok = (dist > radius) & (np.sum((on_arc - centre) * n, axis=1) >= level)
    # Candidate on the chord: the projection onto the chord segment.
    tangent = np.stack([-n[:, 1], n[:, 0]], axis=1)
    half = np.sqrt(np.maximum(radius**2 - level**2, 0.0))
    s = np.clip(np.sum(rel * tangent, axis=1), -half, half)
    on_chord = centre + level[:, None] * n + s[:, None] * tangent
    result = np.where(arc_ok[:, None], on_arc, on_chord)
    return np.where(inside[:, None], x, result)


# ---------------------------------------------------------------- small convex geometry


def _clip_polygon(vertices: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray | None:
    """The part of a convex polygon (V, 2) with normal . x <= offset, or None if empty."""
    side = (vertices @ normal - offset).tolist()  # plain floats: this loop runs very often
    points = vertices.tolist()
    out = []
    count = len(points)
    for i in range(count):
        j = (i + 1) % count
        if side[i] <= 0:
            out.append(points[i])
        if (side[i] < 0 < side[j]) or (side[j] < 0 < side[i]):
            t = side[i] / (side[i] - side[j])
            (xi, yi), (xj, yj) = points[i], points[j]
            out.append([xi + t * (xj - xi), yi + t * (yj - yi)])
    return np.array(out) if len(out) >= 3 else None


def _edges(vertices: np.ndarray) -> np.ndarray:
    """(V, 2) edge vectors of a polygon (V, 2): vertex i to vertex i + 1."""
    return np.concatenate((vertices[1:], vertices[:1])) - vertices


def _halfplanes(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward normals (V, 2) and offsets (V,) of a counter-clockwise convex polygon."""
    edge = _edges(vertices)
    length = np.maximum(np.hypot(edge[:, 0], edge[:, 1]), 1e-300)
    normals = np.stack([edge[:, 1], -edge[:, 0]], axis=1) / length[:, None]
    return normals, (normals * vertices).sum(axis=1)


def _clip_interval(region: PolygonRegion, base, direction, lo: float, hi: float):
    """The t in [lo, hi] with base + t * direction inside the region, or None."""
    return _interval(region.normals, region.offsets, base, direction, lo, hi, 0.0)


def _clip_interval_poly(planes, base, direction, lo, hi, tol):
    """As `_clip_interval` for a convex polygon given by its half-planes (normals (V, 2),
    offsets (V,)), `tol` mm lenient; if nothing fits (rounding on a boundary), the t that
    violates least."""
    normals, offsets = planes
    found = _interval(normals, offsets, base, direction, lo, hi, tol)
    if found is not None:
        return found
    ts = np.linspace(lo, hi, 65)
    worst = np.max((base + ts[:, None] * direction) @ normals.T - offsets, axis=1)
    t = float(ts[np.argmin(worst)])
    return t, t


def _interval(normals, offsets, base, direction, lo, hi, tol):
    rate = (normals @ direction).tolist()
    room = (offsets - normals @ base + tol).tolist()
    for r, m in zip(rate, room):
        if abs(r) < 1e-15:
            if m < 0:
                return None
        elif r > 0:
            hi = min(hi, m / r)
        else:
            lo = max(lo, m / r)
    return (lo, hi) if lo <= hi else None


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull (H, 2) of points (K, 2) (monotone chain)."""
    pts = sorted(map(tuple, np.round(points, 12)))
    if len(pts) <= 2:
        return np.array(pts)

    def cross(o, a, b) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


def _nearest_in_polygon(vertices: np.ndarray, x: np.ndarray, planes=None) -> np.ndarray:
    """Nearest point (2,) to x (2,) in a counter-clockwise convex polygon (V, 2) (its
    `_halfplanes`, if known, in planes)."""
    normals, offsets = _halfplanes(vertices) if planes is None else planes
    if np.all(normals @ x <= offsets):
        return x.copy()
    a = vertices
    edge = _edges(a)
    t = ((x - a) * edge).sum(axis=1) / np.maximum((edge * edge).sum(axis=1), 1e-300)
    foot = a + t.clip(0.0, 1.0)[:, None] * edge
    gap = foot - x
    return foot[int((gap * gap).sum(axis=1).argmin())]


def _minimise_on_interval(f, lo: float, hi: float, points: int = 21, rounds: int = 5) -> float:
    """Minimum of a vectorised unimodal f(t (K,)) -> (K,) on [lo, hi]: a grid, then finer grids
    round the best point (each round narrows the bracket ten-fold)."""
    for _ in range(rounds):
        if hi - lo <= 1e-15:
            break
        ts = np.linspace(lo, hi, points)
        k = int(np.argmin(f(ts)))
        lo, hi = ts[max(k - 1, 0)], ts[min(k + 1, points - 1)]
    return 0.5 * (lo + hi)


# ---------------------------------------------------------------- Alg. 1


def _after(region: CentreRegion, positions: np.ndarray, step: TwoMoveStep) -> np.ndarray:
    for move in step.moves(positions):
        positions = apply_move(region, positions, move)
    return positions


def _look_ahead(
    region: CentreRegion,
    positions: np.ndarray,
    goals: np.ndarray,
    reach: float,
    greedy: TwoMoveStep,
    epsilon: float,
    push: float = 0.0,
    memo: dict | None = None,
) -> TwoMoveStep:
    """A departure from Alg. 1's greedy choice, for polygons: when the greedy step cannot reach
    the goal's delta and neither can the step after it, aim instead at the corner of the 2-move
    reachable set from which the next step reaches the goal with the shortest two steps (if any
    does). Greedy steps toward a delta near the edge of the Delta space can otherwise crawl.
    memo: greedy steps already computed (see `_memo_step`)."""
    if not isinstance(region, PolygonRegion):
        return greedy
    memo = {} if memo is None else memo
    following = _memo_step(memo, region, _after(region, positions, greedy), goals, reach, push)
    if following is not None and following.distance <= epsilon:
        return greedy
    # The reachable set from these positions does not depend on the goal: build it once for the
    # greedy step's corners and for every step aimed at one of them.
    clear = _clearance(region, reach)
    parts = _memo_parts(memo, region, positions, push)
    corners: list = []
    _polygon_steps(region, positions, goals, clear, corners, push, parts)
    if not corners:
        return greedy
    corners_arr = np.unique(np.round(np.array(corners), 9), axis=0)
    # The corners nearest the goal's delta are the likeliest to see it; try those first.
    goal_delta = goals[1] - goals[0]
    order = np.argsort(np.hypot(*(corners_arr - goal_delta).T))
    corners_arr = corners_arr[order[:_LOOKAHEAD_CORNERS]]
    # A step aimed at a corner is kept only if it reaches it (within 1e-6 of the size), and it is
    # chosen among the parts nearest the corner, so parts farther than that need no evaluation
    # (their half-planes with that slack, doubled, hold every part near enough to count).
    slack = 2e-6 * region.size
    holds = np.array([
        np.all((corners_arr if part.pin == 0 else -corners_arr) @ part.offsets_planes[0].T
               <= part.offsets_planes[1] + slack, axis=1)
        for part in parts
    ]).reshape(len(parts), len(corners_arr))
    firsts = []
    for k, corner in enumerate(corners_arr):
        near_parts = [part for part, held in zip(parts, holds[:, k]) if held]
        if not near_parts:
            continue
        aim = np.stack([positions[0], positions[0] + corner])
        candidates = _polygon_steps(region, positions, aim, clear, push=push, parts=near_parts)
        first = _nearest_then_shortest(candidates, region)
        if first is not None and first.distance <= 1e-6 * region.size:
            firsts.append(first)
    # Shortest first steps first: once a first step alone is as long as the best pair found,
    # no later one can do better, so their second steps need not be planned.
    best, best_length = greedy, math.inf
    for first in sorted(firsts, key=lambda step: step.length):
        if first.length >= best_length:
            break
        second = _memo_step(memo, region, _after(region, positions, first), goals, reach, push)
        if second is not None and second.distance <= epsilon:
            length = first.length + second.length
            if length < best_length:
                best, best_length = first, length
    return best


def _memo_step(memo: dict, region, positions, goals, reach, push) -> TwoMoveStep | None:
    """`best_two_move_step`, remembered by positions: the look-ahead plans the step after its
    choice, which Alg. 1's next iteration would plan again from the very same positions."""
    key = ("step", positions.tobytes())
    if key not in memo:
        if isinstance(region, PolygonRegion):
            parts = _memo_parts(memo, region, positions, push)
            steps = _polygon_steps(region, positions, goals, _clearance(region, reach),
                                   push=push, parts=parts)
            memo[key] = _nearest_then_shortest(steps, region)
        else:
            memo[key] = best_two_move_step(region, positions, goals, reach, push)
    return memo[key]


def _memo_parts(memo: dict, region: PolygonRegion, positions: np.ndarray, push: float) -> list:
    """`_polygon_parts`, remembered by positions (the look-ahead needs them at Alg. 1's)."""
    key = ("parts", positions.tobytes())
    if key not in memo:
        memo[key] = _polygon_parts(region, positions, push)
    return memo[key]


@dataclass
class WallContactResult:
    """A planned move sequence: moves (m, 2) mm, states (m, 2, 2) after each move (point
    kinematics), whether the goal was reached within epsilon, the path length (mm, sum of |move|)
    and planning time (s). The 3D planner (`wall_contact_3d`) uses it with (m, 3) and (m, 2, 3)."""

    moves: np.ndarray
    states: np.ndarray
    solved: bool
    error: float
    seconds: float

    @property
    def length(self) -> float:
        return float(np.sum(np.linalg.norm(self.moves, axis=1))) if len(self.moves) else 0.0


def plan_two_particles(
    region: CentreRegion,
    starts: ArrayLike,
    goals: ArrayLike,
    epsilon: float,
    reach: float = 0.0,
    max_steps: int = 40,
    lookahead: bool = True,
    push: float = 0.0,
) -> WallContactResult:
    """Alg. 1 (2-PARTICLEPATHPLAN): moves that bring particles from starts (2, 2) to goals (2, 2)
    mm, both within `epsilon` mm, in the centre region, centres kept `reach` mm apart during
    the relative moves (see `best_two_move_step`, also for `push`). Iterates two-move steps toward the
    nearest 2-move reachable delta (at most `max_steps`), then translates to the goal."""
    started = time.perf_counter()
    # Coincident particles can never be told apart again (seed 004 asks for distinct starts), so
    # the relative moves keep them apart even as points (by epsilon, and by 1e-4 of the size so
    # that the tangents `best_two_move_step` draws round the other particle stay well-conditioned).
    reach = max(reach, epsilon, 1e-4 * region.size)
    positions = np.array(starts, dtype=float).reshape(2, 2)
    goals = np.array(goals, dtype=float).reshape(2, 2)
    goal_delta = goals[1] - goals[0]
    moves: list[np.ndarray] = []
    states: list[np.ndarray] = []
    memo: dict = {}  # greedy steps by positions (goals, reach and push are fixed here)

    def do(move: np.ndarray) -> None:
        nonlocal positions
        positions = apply_move(region, positions, move)
        moves.append(np.asarray(move, dtype=float))
        states.append(positions.copy())

    for _ in range(max_steps):
        if math.hypot(*(positions[1] - positions[0] - goal_delta)) <= epsilon:
            break
        step = _memo_step(memo, region, positions, goals, reach, push)
        if lookahead and step is not None and step.distance > epsilon:
            step = _look_ahead(region, positions, goals, reach, step, epsilon, push, memo)
        before = math.hypot(*(positions[1] - positions[0] - goal_delta))
        if step is None or step.distance >= before - 1e-12 * region.size:
            log.debug("wall contact: no step improves the relative position (%.3g mm)", before)
            break
        for move in step.moves(positions):
            if math.hypot(*move) > 0:
                do(move)
    # Final translation: split the relative error so both particles end as close as possible.
    final = 0.5 * ((goals[0] - positions[0]) + (goals[1] - positions[1]))
    if math.hypot(*final) > 0:
        do(final)
    error = float(np.max(np.hypot(*(positions - goals).T)))
    return WallContactResult(
        np.array(moves).reshape(-1, 2), np.array(states).reshape(-1, 2, 2),
        error <= epsilon, error, time.perf_counter() - started,
    )


def plan_wall_contact(
    region: CentreRegion,
    starts: ArrayLike,
    goals: ArrayLike,
    epsilon: float,
    interchangeable: bool = False,
    reach: float = 0.0,
) -> tuple[WallContactResult, np.ndarray]:
    """Alg. 1, with `interchangeable` also for the swapped goal assignment (keeps the shorter
    solved path, Sec. VI). Returns the result and the goals (2, 2) it delivers to."""
    goals = np.array(goals, dtype=float).reshape(2, 2)
    best = plan_two_particles(region, starts, goals, epsilon, reach)
    chosen = goals
    if interchangeable:
        swapped = goals[::-1].copy()
        other = plan_two_particles(region, starts, swapped, epsilon, reach)
        if (other.solved, -other.length) > (best.solved, -best.length):
            other.seconds += best.seconds
            best, chosen = other, swapped
        else:
            best.seconds += other.seconds
    return best, chosen


def plan_with_model(
    model,
    region: CentreRegion,
    starts: ArrayLike,
    goals: ArrayLike,
    epsilon: float,
    interchangeable: bool = False,
    rounds: int = 4,
) -> tuple[WallContactResult, np.ndarray, np.ndarray]:
    """Plan, then replay through the global-input `model` (non-slip); while the model's end state
    misses the goal by more than epsilon (the disc particles met, which point kinematics ignores),
    plan again from it. Returns (result with model states, goals used, planner seconds)."""
    starts = np.array(starts, dtype=float).reshape(2, 2)
    reach = float(model.radii.sum()) + model.min_separation_mm
    result, goals = plan_wall_contact(region, starts, goals, epsilon, interchangeable, reach)
    planner_seconds = result.seconds
    moves = result.moves
    states = model.rollout(starts, moves) if len(moves) else np.empty((0, 2, 2))
    for _ in range(rounds):
        end = states[-1] if len(states) else starts
        error = float(np.max(np.hypot(*(end - goals).T)))
        if error <= epsilon:
            break
        log.info("wall contact: the model ends %.3g mm from the goal; planning again from there", error)
        more = plan_two_particles(region, end, goals, epsilon, reach)
        planner_seconds += more.seconds
        if not len(more.moves):
            break
        moves = np.concatenate([moves, more.moves])
        states = np.concatenate([states, model.rollout(end, more.moves)])
    end = states[-1] if len(states) else starts
    error = float(np.max(np.hypot(*(end - goals).T)))
    final = WallContactResult(moves, states, error <= epsilon, error, planner_seconds)
    return final, goals, np.array(planner_seconds)


# ---------------------------------------------------------------- reachable fractions (Fig. 8-9)


def delta_space_contains(region: CentreRegion, points: np.ndarray) -> np.ndarray:
    """(N,) True where relative positions points (N, 2) are possible at all: Q - Q, a disk of
    twice the radius, or the convex hull of vertex differences (Sec. IV-A)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if isinstance(region, DiskRegion):
        return np.hypot(points[:, 0], points[:, 1]) <= 2.0 * region.radius * (1 + 1e-12)
    v = region.vertices
    hull = _convex_hull((v[:, None, :] - v[None, :, :]).reshape(-1, 2))
    normals, offsets = _halfplanes(hull)
    return np.all(points @ normals.T <= offsets + 1e-9 * region.size, axis=1)


@njit(error_model="numpy")
def _disk_chords(w, n, wall, R, inside):  # pragma: no cover - compiled
    """inside[i] |= some contact k fits point w[i] (M, 2): |w + R n_k| <= R, i.e. |w|^2 + 2 R n_k.w
    <= 0, pushing into the wall, n_k.w >= n_k.d = wall[k] (the chord regions of a disk). A loop
    that stops at the first contact that fits: the (M, K) arrays of the same test cost more in
    page faults than in arithmetic (`rigctl plan reachable` 4.5x slower on a 121 x 121 grid)."""
    fit_tol, wall_tol = 1e-12 * R * R, 1e-12 * R
    for i in range(w.shape[0]):
        if inside[i]:
            continue
        x, y = w[i, 0], w[i, 1]
        norm2 = x * x + y * y
        for k in range(n.shape[0]):
            along = x * n[k, 0] + y * n[k, 1]
            if norm2 + 2 * R * along <= fit_tol and along >= wall[k] - wall_tol:
                inside[i] = True
                break


def two_move_reachable(
    region: CentreRegion, delta: np.ndarray, points: np.ndarray, contacts: int = 96
) -> np.ndarray:
    """(N,) True where deltas points (N, 2) are in the 2-move reachable set from delta (2,),
    point particles. Polygons: exact (the per-edge convex polygons of Alg. 2). Disks: the union
    of the chord regions of `contacts` contact angles spread over eq. 2's arc (an underestimate
    that converges as `contacts` grows, like the paper's numeric method)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    inside = np.zeros(len(points), dtype=bool)
    for pin, sign in ((0, 1.0), (1, -1.0)):
        d = sign * np.asarray(delta, dtype=float)  # other - pinned
        w = sign * points
        if isinstance(region, DiskRegion):
            R = region.radius
            d12 = math.hypot(*d)
            if d12 == 0 or d12 > 2 * R:
                continue
            half = math.acos(d12 / (2.0 * R))
            psi = math.atan2(-d[1], -d[0]) + np.linspace(-half, half, contacts)
            n = np.stack([np.cos(psi), np.sin(psi)], axis=1)  # (K, 2)
            _disk_chords(w, n, n @ d, R, inside)
            continue
        for e in range(len(region.vertices)):
            normal, h = region.normals[e], region.offsets[e]
            if normal @ d >= 0:
                continue  # the other particle is as near this wall: this particle cannot pin on it
            a = region.vertices[e]
            edge = region.vertices[(e + 1) % len(region.vertices)] - a
            t_range = _clip_interval(region, a + d, edge, 0.0, 1.0)
            slice_ = _clip_polygon(region.vertices, -normal, -(h + normal @ d))
            if t_range is None or slice_ is None:
                continue
            c_lo, c_hi = a + t_range[0] * edge, a + t_range[1] * edge
            offsets = _convex_hull(np.concatenate([slice_ - c_lo, slice_ - c_hi]))
            if len(offsets) < 3:
                continue
            normals, limits = _halfplanes(offsets)
            inside |= np.all(w @ normals.T <= limits + 1e-9 * region.size, axis=1)
    return inside


def warm_up() -> None:
    """Compile (or load from numba's cache) this module's kernel, so that no planner call pays
    for it: a study's workers run this before their first case."""
    two_move_reachable(DiskRegion(np.zeros(2), 1.0), np.array([0.5, 0.0]), np.zeros((1, 2)), 2)


def reachable_fraction(
    region: CentreRegion, start_delta: ArrayLike, moves: int, cells: int = 121, contacts: int = 96
) -> list[float]:
    """Fractions of the Delta configuration space reachable within 2, 4, ... `moves` moves (even)
    from start_delta (2,) mm, point particles (the quantity of seed 004 Fig. 8-9).

    The space is cut into `cells` x `cells` grid points; the (k + 2)-move set is the k-move set
    joined with the 2-move sets of the k-move set's boundary points (Sec. IV-B). The fraction is
    the share of grid points of the space that are reached, so it carries the grid's resolution
    (about one cell along the set's boundary) besides the disk's contact sampling.
    """
    if moves < 2 or moves % 2:
        raise PlanError(f"--moves: a reachable set grows by two moves at a time; give an even "
                        f"number >= 2, got {moves}")
    start = np.asarray(start_delta, dtype=float)
    extent = 2.0 * region.size if isinstance(region, PolygonRegion) else 4.0 * region.radius
    axis = np.linspace(-extent / 2, extent / 2, cells)
    gx, gy = np.meshgrid(axis, axis, indexing="ij")
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    space = delta_space_contains(region, grid)
    total = int(space.sum())
    reached = two_move_reachable(region, start, grid, contacts) & space
    fractions = [reached.sum() / total]
    for _ in range(moves // 2 - 1):
        shaped = reached.reshape(cells, cells)
        interior = shaped.copy()
        interior[1:-1, 1:-1] &= (shaped[:-2, 1:-1] & shaped[2:, 1:-1]
                                 & shaped[1:-1, :-2] & shaped[1:-1, 2:])
        border = np.flatnonzero(reached & ~interior.ravel())
        grown = reached.copy()
        for index in border:
            todo = space & ~grown
            if not todo.any():
                break
            grown[todo] |= two_move_reachable(region, grid[index], grid[todo], contacts)
        reached = grown
        fractions.append(reached.sum() / total)
    return [float(f) for f in fractions]
