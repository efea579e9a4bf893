"""Two particles in a right prism or cylinder (seed 004 Sec. IV-G): Alg. 1 plus one z adjustment.

The workspace is a convex cross-section (polygon or disk, the 2D planner's `CentreRegion`) extruded
along z between end caps; particle centres may be anywhere with z in [lo, hi] (the caps moved in by
the particle radius). The particles are neutrally buoyant; a shared input moves them along any 3D
direction, and eq. 1 of seed 004 holds on every wall (side wall or cap): a particle on a wall does
not move while the input pushes into it.

Sec. IV-G's method, which never uses the end caps:

1. z translation (when needed): both particles move in z so that afterwards the pinned particle's
   z plus the wanted z offset is within the caps, and nobody touches a cap;
2. the particle nearer the side wall (of the two straight moves that pin one of them, the shorter)
   is moved onto the side wall; its z can no longer change;
3. a z move with a slight push into that wall: only the other particle moves, to the wanted
   relative height;
4. Alg. 1 (`plans/wall_contact.py`) in the cross-section places the particles in x, y; its moves
   have no z component, so the relative height stays;
5. a final z translation takes both to their goal heights.

When the current and the wanted z offsets are so far apart that no translation fits them both
between the caps, steps 1-3 run twice (the first time to equal heights). Points are (3,) or (k, 3)
mm; positions are point particles (the 2D planner's `apply_move` for the cross-section, exact
clamping at the caps).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import PlanError
from rigctl.plans.wall_contact import (
    CentreRegion,
    DiskRegion,
    WallContactResult,
    apply_move,
    plan_two_particles,
)

# Kept between a particle and a cap during the x, y work (relative to the z range): the method
# uses no cap contacts (Sec. IV-G), and a rig's x, y moves are never exactly level.
_CAP_MARGIN_REL = 1e-3
# The z move of step 3 leans into the pinning wall by this fraction of its length.
_PUSH_REL = 1e-3


@dataclass(frozen=True)
class PrismRegion:
    """Where particle centres may be: `section` (the 2D centre region) x [z_low, z_high] mm."""

    section: CentreRegion
    z_low: float
    z_high: float

    def __post_init__(self) -> None:
        if not self.z_high > self.z_low:
            raise PlanError(f"the prism's height leaves no room for the particles "
                            f"(z from {self.z_low:g} to {self.z_high:g} mm)")

    def contains(self, points: ArrayLike) -> np.ndarray:
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        tol = 1e-9 * (self.z_high - self.z_low)
        return (self.section.contains(p[:, :2]) & (p[:, 2] >= self.z_low - tol)
                & (p[:, 2] <= self.z_high + tol))


def prism_region(section: CentreRegion, height_mm: float, radius_mm: float) -> PrismRegion:
    """A prism of `height_mm` (caps at z = 0 and z = height) for particles of `radius_mm`, whose
    cross-section's centre region is `section`."""
    return PrismRegion(section, radius_mm, height_mm - radius_mm)


def apply_move_3d(region: PrismRegion, positions: ArrayLike, move: ArrayLike) -> np.ndarray:
    """Eq. 1 in the prism for point particles: positions (k, 3) after the shared straight move (3,)
    mm. A particle on the side wall or a cap that the move pushes into stays; any other moves
    along the input until it meets the boundary. As in the 2D planner and the global-input model,
    a move exactly along a wall is not into it."""
    p = np.array(positions, dtype=float).reshape(-1, 3)
    move = np.asarray(move, dtype=float).reshape(3)
    length = float(np.linalg.norm(move))
    if length == 0:
        return p
    u = move / length
    span = region.z_high - region.z_low
    on_cap = 1e-9 * span
    for i in range(len(p)):
        normals = region.section.wall_normals(p[i, :2])
        if len(normals) and np.any(normals @ u[:2] > 1e-12):
            continue
        if (p[i, 2] <= region.z_low + on_cap and u[2] < -1e-12) or (
                p[i, 2] >= region.z_high - on_cap and u[2] > 1e-12):
            continue
        room = length
        horizontal = math.hypot(u[0], u[1])
        if horizontal > 0:
            room = min(room, region.section.exit_distance(p[i, :2], u[:2] / horizontal) / horizontal)
        if u[2] > 0:
            room = min(room, (region.z_high - p[i, 2]) / u[2])
        elif u[2] < 0:
            room = min(room, (region.z_low - p[i, 2]) / u[2])
        p[i] = p[i] + max(room, 0.0) * u
    return p


def _pinning_moves(section: CentreRegion, xy: np.ndarray) -> list[tuple[float, int, np.ndarray]]:
    """Straight x, y moves that put exactly one particle on the side wall: (length, pinned, move).

    Tried: towards each particle's nearest wall point first, then (should both reach a wall
    together, e.g. equally far from one edge) along every wall normal of a polygon, or turned by
    +-30 and +-60 degrees on a disk."""
    directions = []
    for k in (0, 1):
        if isinstance(section, DiskRegion):
            w = xy[k] - section.centre
            dist = math.hypot(*w)
            angle = math.atan2(w[1], w[0]) if dist > 0 else 0.0
            directions += [np.array([math.cos(angle + t), math.sin(angle + t)])
                           for t in np.radians([0.0, 30.0, -30.0, 60.0, -60.0])]
        else:
            room = section.offsets - section.normals @ xy[k]
            directions.append(section.normals[int(np.argmin(room))])
    if not isinstance(section, DiskRegion):
        directions += list(section.normals)
    options = []
    for direction in directions:
        move = min(section.exit_distance(p, direction) for p in xy) * direction
        after = apply_move(section, xy, move)
        walls = [len(section.wall_normals(after[j])) > 0 for j in (0, 1)]
        if walls[0] != walls[1]:
            options.append((float(np.hypot(*(after - xy).T).max()), int(walls[1]), move))
    return options


def _lean_off_walls(section: CentreRegion, xy: np.ndarray, amount: float) -> np.ndarray:
    """An x, y component (2,) of `amount` mm that leads every particle touching a side wall away
    from it: a z move meant to move both must not graze a wall (eq. 1 read strictly, N . u <= 0,
    holds a particle even for a move along the wall)."""
    normals = [n for p in xy for n in section.wall_normals(p)]
    if not normals or amount == 0:
        return np.zeros(2)
    away = -np.sum(normals, axis=0)
    size = math.hypot(*away)
    return away / size * amount if size > 1e-12 else np.zeros(2)


def plan_two_particles_3d(region: PrismRegion, starts: ArrayLike, goals: ArrayLike, epsilon: float,
                          max_steps: int = 40) -> WallContactResult:
    """Sec. IV-G: moves (3D) that take point particles from starts (2, 3) to goals (2, 3) mm, both
    within `epsilon` mm. PlanError when the starts share x, y (no side wall can tell them apart) or
    a start or goal is outside the region."""
    started = time.perf_counter()
    positions = np.array(starts, dtype=float).reshape(2, 3)
    goals = np.array(goals, dtype=float).reshape(2, 3)
    for name, points in (("start", positions), ("goal", goals)):
        if not region.contains(points).all():
            raise PlanError(f"a {name} is outside the prism (centres need z in "
                            f"[{region.z_low:g}, {region.z_high:g}] mm and the cross-section)")
    section = region.section
    if math.hypot(*(positions[1, :2] - positions[0, :2])) <= 1e-9 * section.size:
        raise PlanError("the particles start at the same x, y: Sec. IV-G needs them apart in the "
                        "cross-section (a side wall cannot hold one without the other)")
    span = region.z_high - region.z_low
    margin = _CAP_MARGIN_REL * span
    lo, hi = region.z_low + margin, region.z_high - margin
    moves: list[np.ndarray] = []
    states: list[np.ndarray] = []

    def do(move: np.ndarray) -> None:
        nonlocal positions
        if np.linalg.norm(move) > 0:
            positions = apply_move_3d(region, positions, move)
            moves.append(np.asarray(move, dtype=float))
            states.append(positions.copy())

    wanted_dz = goals[1, 2] - goals[0, 2]
    for _ in range(3):
        if abs(positions[1, 2] - positions[0, 2] - wanted_dz) <= 0.5 * epsilon:
            break
        options = _pinning_moves(section, positions[:, :2])
        if not options:
            raise PlanError("no straight move pins exactly one particle on the side wall")
        _, pin, _ = min(options, key=lambda o: o[0])
        free = 1 - pin
        wanted = wanted_dz if free == 1 else -wanted_dz  # free z - pinned z
        # z translation t keeping both off the caps, the pinned one's z + wanted inside too.
        z = positions[:, 2]
        low = max(lo - z[0], lo - z[1], lo - z[pin] - wanted)
        high = min(hi - z[0], hi - z[1], hi - z[pin] - wanted)
        if low <= high:
            t = float(np.clip(goals[pin, 2] - z[pin], low, high))
            target = z[pin] + t + wanted
        else:  # too far apart for one go: first to equal heights
            t = float(np.clip(0.0, max(lo - z[0], lo - z[1]), min(hi - z[0], hi - z[1])))
            target = z[pin] + t
        do(np.array([*_lean_off_walls(section, positions[:, :2], abs(t) * _PUSH_REL), t]))
        # The lean moved them a hair: the same particle's pinning move from where they are now.
        again = [o for o in _pinning_moves(section, positions[:, :2]) if o[1] == pin]
        if not again:
            continue  # the other particle pins now; the next round starts from here
        do(np.array([again[0][2][0], again[0][2][1], 0.0]))
        outward = section.wall_normals(positions[pin, :2])[0]
        dz = target - positions[free, 2]
        do(np.array([*(abs(dz) * _PUSH_REL * outward), dz]))
    # Off the caps (eq. 1 would hold a particle resting on one during the x, y moves).
    z = positions[:, 2]
    t = float(np.clip(0.0, lo - z.min(), max(hi - z.max(), lo - z.min())))
    do(np.array([*_lean_off_walls(section, positions[:, :2], abs(t) * _PUSH_REL), t]))
    # Alg. 1 in the cross-section; its moves keep every height but the last (the translation to
    # the goals), which also takes both to their goal heights.
    final_dz = 0.5 * ((goals[0, 2] - positions[0, 2]) + (goals[1, 2] - positions[1, 2]))
    flat = plan_two_particles(section, positions[:, :2], goals[:, :2], epsilon, max_steps=max_steps)
    for index, move in enumerate(flat.moves):
        do(np.array([move[0], move[1], final_dz if index == len(flat.moves) - 1 else 0.0]))
    if not len(flat.moves):
        do(np.array([*_lean_off_walls(section, positions[:, :2], abs(final_dz) * _PUSH_REL),
                     final_dz]))
    error = float(np.max(np.linalg.norm(positions - goals, axis=1)))
    return WallContactResult(np.array(moves).reshape(-1, 3), np.array(states).reshape(-1, 2, 3),
                               error <= epsilon, error, time.perf_counter() - started)


def plan_wall_contact_3d(region: PrismRegion, starts: ArrayLike, goals: ArrayLike, epsilon: float,
                         interchangeable: bool = False) -> tuple[WallContactResult, np.ndarray]:
    """`plan_two_particles_3d`, with `interchangeable` also for the swapped goals (the shorter
    solved path wins). Returns the result and the goals (2, 3) it delivers to."""
    goals = np.array(goals, dtype=float).reshape(2, 3)
    best, chosen = plan_two_particles_3d(region, starts, goals, epsilon), goals
    if interchangeable:
        other = plan_two_particles_3d(region, starts, goals[::-1].copy(), epsilon)
        if (other.solved, -other.length) > (best.solved, -best.length):
            other.seconds += best.seconds
            best, chosen = other, goals[::-1].copy()
        else:
            best.seconds += other.seconds
    return best, chosen


def plan_document_3d(workspace: dict, height_mm: float, radius_mm: float, starts: np.ndarray,
                     goals: np.ndarray, result: WallContactResult, epsilon: float) -> dict:
    """The JSON document `rigctl plan wall-contact --height` writes: the cross-section workspace,
    the height, the particles, the 3D moves and the states the point model expects. There is no 3D
    rig; the document is for analysis (its `kind` is not one `rigctl execute` runs)."""
    return {
        "schema": "rigctl.plan3d/1",
        "kind": "global-moves-3d",
        "workspace": workspace,
        "height_mm": float(height_mm),
        "agents": [{"start": s.tolist(), "goal": g.tolist(), "radius": float(radius_mm)}
                   for s, g in zip(starts, goals)],
        "moves": np.round(result.moves, 9).tolist(),
        "expected": np.round(result.states, 9).tolist(),
        "tolerance_mm": float(epsilon),
        "solved": bool(result.solved),
    }
