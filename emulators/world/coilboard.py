"""The coil board's world (seed 004 Sec. VII): particles in syrup pulled by four iron-core coils.

Four coils sit outside the workspace on the +x, -x, +y and -y axes (coils 0..3, the order of the
board protocol), their pole faces `pole_distance_mm` from the workspace centre. The SyRen outputs
(-1..1, what the firmware put on the wire, read from a `SyrenBus`) set each coil's drive.

Force law (`CoilBoardPhysics`). An iron-core coil seen from a few core diameters away is a magnetic
dipole at its pole face, so its field falls as 1/d^3; the particle (a 1 mm NdFeB sphere) turns to
align with the field and is pulled up the field magnitude's gradient, so the pull falls as
1/d^(3+1) = 1/d^4 and points at the pole (the non-uniformity the paper reports: the particle
nearer the coil moves faster, and forces are not parallel but point to the coil's centre):

    F_i(p) = |a_i| F0 (D / |c_i - p|)^n (c_i - p) / |c_i - p|,   n = `exponent` (4), D = pole distance

a_i the coil's output; its sign does not matter (a reversed field turns the magnet round and pulls
it all the same). Forces of coils driven together add. The magnet sees the coils only, not the
other magnet (their mutual attraction is left out).

Motion (low Reynolds number, seed 004 Sec. III): velocity = mobility x force, with Stokes' mobility
1 / (6 pi eta r) of a sphere of radius r in a fluid of viscosity eta (corn syrup, 12 Pa s in the
paper). Contact with walls follows eq. 1 of seed 004: a particle on a wall whose force points into
the wall does not move. `friction` generalises this to a Coulomb cone: the particle stays while
the force's tangential part is at most friction x its normal part, and otherwise slides with the
excess; the paper's walls are the limit friction = inf (the default). A moving particle stops on
the wall it meets. Particle against particle: one held (by a wall, or behind one) holds the
particle pushed into it, by the same rule; two free particles pushed together move with the mean
of their velocities along the line of centres (the faster pushes the slower).

Workspaces: any `rigctl.plans.workspace.Workspace` (disk, convex polygon from a plan), and the
intestine phantom of Sec. VII-B: `intestine_ring_spec()`, a 46 mm disk with sixty 2 mm protrusions
on its inner wall.

The model is pure: `step(dt, outputs)` advances it; no threads, no I/O (the bench drives it).
Lengths in mm, times in s, forces in N.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import PlanError
from rigctl.plans.workspace import Workspace

# Coil i pulls towards centre + D * COIL_DIRECTIONS[i] (the board protocol's order +x, -x, +y, -y).
COIL_DIRECTIONS = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
_CONTACT_TOL_MM = 1e-4  # this close to a wall or another particle counts as touching
_MAX_STEP_MM = 0.02  # the longest displacement of one sub-step
_BISECTIONS = 30


@dataclass(frozen=True)
class CoilBoardPhysics:
    """Parameters of the coil board's world.

    pole_distance_mm: D, from the workspace centre to each coil's pole face; exponent: n of the pull
    law (4: a dipole's field gradient); force_at_centre_N: F0, one coil's pull at full drive at the
    workspace centre; viscosity_Pa_s: eta of the fluid; friction: Coulomb coefficient of the walls
    (inf: seed 004 eq. 1, a particle pushed into a wall never slides); mobility_spread,
    mobility_seed: each particle's mobility is off Stokes' by a factor drawn uniformly from
    1 +- mobility_spread (seeded; 0: every particle as Stokes says), a particle a little smaller
    or rougher than the plan's, or a clump, which a planner that knows only the radii cannot see.

    The defaults give a 1 mm sphere 6 mm/s at the centre (F0 / (6 pi eta r)), 9.8 mm/s 23 mm
    from the centre towards the pulling coil (the 46 mm disk's edge) and 3.9 mm/s 23 mm away from
    it; 23 mm off the coil's axis the pull leans 6.6 degrees towards the axis.
    """

    pole_distance_mm: float = 200.0
    exponent: float = 4.0
    force_at_centre_N: float = 6.0e-3 * 6.0 * math.pi * 12.0 * 0.5e-3
    viscosity_Pa_s: float = 12.0
    friction: float = math.inf
    mobility_spread: float = 0.0
    mobility_seed: float = 0.0

    def __post_init__(self) -> None:
        if not (self.pole_distance_mm > 0 and self.exponent >= 0 and self.force_at_centre_N >= 0
                and self.viscosity_Pa_s > 0 and self.friction >= 0
                and 0 <= self.mobility_spread < 1):
            raise PlanError(f"coil-board physics: D > 0, n >= 0, F0 >= 0, eta > 0, friction >= 0, "
                            f"0 <= mobility_spread < 1 needed, got {self}")

    def mobility_factors(self, n: int) -> np.ndarray:
        """(n,) each particle's mobility over Stokes' (`mobility_spread`, `mobility_seed`)."""
        if self.mobility_spread == 0:
            return np.ones(n)
        rng = np.random.default_rng(int(self.mobility_seed))
        return 1.0 + self.mobility_spread * rng.uniform(-1.0, 1.0, n)

    def mobility_mm_per_s_per_N(self, radius_mm: ArrayLike) -> np.ndarray:
        """Stokes mobility 1 / (6 pi eta r) of spheres of radius (n,) mm, in (mm/s)/N."""
        r_m = np.asarray(radius_mm, dtype=float) * 1e-3
        return 1e3 / (6.0 * math.pi * self.viscosity_Pa_s * r_m)


def coil_forces(physics: CoilBoardPhysics, centre_mm: ArrayLike, positions_mm: ArrayLike,
                outputs: ArrayLike) -> np.ndarray:
    """Pull (n, 2) N on particles at positions (n, 2) mm from coils driven at outputs (4,) -1..1,
    the workspace centre at centre_mm (2,). A particle on a pole face (d = 0) feels nothing."""
    p = np.asarray(positions_mm, dtype=float).reshape(-1, 2)
    a = np.abs(np.asarray(outputs, dtype=float).reshape(4))
    poles = np.asarray(centre_mm, dtype=float) + physics.pole_distance_mm * COIL_DIRECTIONS
    total = np.zeros_like(p)
    for pole, drive in zip(poles, a):
        if drive == 0.0:
            continue
        to_pole = pole - p
        d = np.hypot(to_pole[:, 0], to_pole[:, 1])
        safe = np.where(d > 0, d, 1.0)
        scale = drive * physics.force_at_centre_N * (physics.pole_distance_mm / safe) ** physics.exponent
        total += np.where(d[:, None] > 0, (scale / safe)[:, None] * to_pole, 0.0)
    return total


def intestine_ring_spec(centre_mm: tuple[float, float] = (0.0, 0.0), inner_diameter_mm: float = 46.0,
                        protrusions: int = 60, protrusion_mm: float = 2.0,
                        base_fraction: float = 0.5, arc_points: int = 2) -> dict:
    """The intestine phantom of seed 004 Sec. VII-B as a plan workspace spec (a polygon boundary):
    a disk of `inner_diameter_mm` whose wall carries `protrusions` triangular villi `protrusion_mm`
    long, each as wide at its base as `base_fraction` of the spacing, with `arc_points` points of
    the disk's wall between neighbours."""
    if protrusions < 3 or not 0 < protrusion_mm < inner_diameter_mm / 2 or not 0 < base_fraction < 1:
        raise PlanError("intestine ring: need >= 3 protrusions shorter than the radius, "
                        "0 < base_fraction < 1")
    cx, cy = centre_mm
    radius = inner_diameter_mm / 2.0
    pitch = 2.0 * math.pi / protrusions
    half_base = 0.5 * base_fraction * pitch
    vertices: list[list[float]] = []
    for k in range(protrusions):
        theta = k * pitch
        ring = [(theta - half_base, radius), (theta, radius - protrusion_mm), (theta + half_base, radius)]
        gap = [(theta + half_base + (pitch - 2 * half_base) * (j + 1) / (arc_points + 1), radius)
               for j in range(arc_points)]
        for angle, r in ring + gap:
            vertices.append([cx + r * math.cos(angle), cy + r * math.sin(angle)])
    return {"boundary": {"polygon": vertices}, "obstacles": []}


class CoilBoardWorld:
    """Ground truth: particles (n, 2) mm of radii (n,) mm in `workspace`, the coils' centre at
    `centre_mm` (default: the middle of the workspace's bounds)."""

    def __init__(self, workspace: Workspace, positions_mm: ArrayLike, radii_mm: ArrayLike,
                 physics: CoilBoardPhysics = CoilBoardPhysics(),
                 centre_mm: ArrayLike | None = None) -> None:
        self.workspace = workspace
        self.positions_mm = np.array(positions_mm, dtype=float).reshape(-1, 2)
        self.radii_mm = np.broadcast_to(np.asarray(radii_mm, dtype=float),
                                        (len(self.positions_mm),)).copy()
        self.physics = physics
        if centre_mm is None:
            xmin, ymin, xmax, ymax = workspace.bounds
            centre_mm = ((xmin + xmax) / 2.0, (ymin + ymax) / 2.0)
        self.centre_mm = np.asarray(centre_mm, dtype=float).reshape(2)
        self.mobility_factors = physics.mobility_factors(len(self.radii_mm))
        self._mobility = physics.mobility_mm_per_s_per_N(self.radii_mm) * self.mobility_factors
        self.time_s = 0.0
        if np.any(workspace.clearance(self.positions_mm) < self.radii_mm - 1e-6):
            raise PlanError("coil-board world: a particle does not fit where it was placed")
        n = len(self.positions_mm)
        for i in range(n):
            for j in range(i + 1, n):
                gap = np.hypot(*(self.positions_mm[j] - self.positions_mm[i]))
                if gap < self.radii_mm[i] + self.radii_mm[j] - 1e-6:
                    raise PlanError(f"coil-board world: particles {i} and {j} overlap")

    # -- velocities ---------------------------------------------------------------------------
    def free_velocities(self, outputs: ArrayLike) -> np.ndarray:
        """(n, 2) mm/s each particle would move at with no wall or other particle about."""
        forces = coil_forces(self.physics, self.centre_mm, self.positions_mm, outputs)
        return forces * self._mobility[:, None]

    def velocities(self, outputs: ArrayLike) -> np.ndarray:
        """(n, 2) mm/s after the wall rule (eq. 1 / the friction cone) and particle contacts."""
        v = self.free_velocities(outputs)
        clearance, normal, _ = self.workspace.surface(self.positions_mm)
        on_wall = clearance <= self.radii_mm + _CONTACT_TOL_MM
        held = np.zeros(len(v), dtype=bool)
        for i in np.flatnonzero(on_wall).tolist():
            v[i], held[i] = self._contact(v[i], normal[i])
        # Particle pairs: a held particle is a wall for the other; free ones push each other.
        for _ in range(2):
            for i in range(len(v)):
                for j in range(i + 1, len(v)):
                    gap = self.positions_mm[j] - self.positions_mm[i]
                    dist = math.hypot(*gap)
                    if dist > self.radii_mm[i] + self.radii_mm[j] + _CONTACT_TOL_MM or dist == 0:
                        continue
                    n_ij = gap / dist  # from i to j
                    if (v[j] - v[i]) @ n_ij >= 0:
                        continue  # not closing
                    if held[i] and not held[j]:
                        v[j], held[j] = self._contact(v[j], n_ij)
                    elif held[j] and not held[i]:
                        v[i], held[i] = self._contact(v[i], -n_ij)
                    elif not held[i] and not held[j]:
                        mean = 0.5 * (v[i] + v[j]) @ n_ij
                        v[i] += (mean - v[i] @ n_ij) * n_ij
                        v[j] += (mean - v[j] @ n_ij) * n_ij
        return v

    def _contact(self, v: np.ndarray, inward: np.ndarray) -> tuple[np.ndarray, bool]:
        """A velocity against a surface with unit normal `inward` (pointing away from it): eq. 1
        (or the friction cone). Returns the velocity and whether the particle is held."""
        push = float(v @ inward)
        if push >= 0:
            return v, False
        tangential = v - push * inward
        speed_t = math.hypot(*tangential)
        excess = speed_t - self.physics.friction * (-push)
        if not excess > 0:  # inside the cone (always, for friction = inf)
            return np.zeros(2), True
        return tangential * (excess / speed_t), False

    # -- time ---------------------------------------------------------------------------------
    def step(self, dt: float, outputs: ArrayLike) -> None:
        """Advance dt s with the coils at outputs (4,), in sub-steps of at most `_MAX_STEP_MM`."""
        remaining = float(dt)
        while remaining > 0:
            v = self.velocities(outputs)
            speed = float(np.max(np.hypot(v[:, 0], v[:, 1]))) if len(v) else 0.0
            h = remaining if speed == 0 else min(remaining, _MAX_STEP_MM / speed)
            if speed > 0:
                # Midpoint rule (second order) while the contacts stay as they are.
                here = self.positions_mm
                self.positions_mm = here + 0.5 * h * v
                middle = self.velocities(outputs)
                self.positions_mm = here
                if np.array_equal(middle == 0, v == 0):
                    v = middle
            self._advance(v * h)
            remaining -= h
            self.time_s += h
            if speed == 0:
                break

    def _advance(self, displacement: np.ndarray) -> None:
        before = self.positions_mm.copy()
        for i, d in enumerate(displacement):
            if not d.any():
                continue
            target = before[i] + d
            if self.workspace.clearance(target) >= self.radii_mm[i]:
                self.positions_mm[i] = target
                continue
            # Stop on the wall: the largest fraction of the step that still fits (bisection).
            lo, hi = 0.0, 1.0
            for _ in range(_BISECTIONS):
                mid = 0.5 * (lo + hi)
                if self.workspace.clearance(before[i] + mid * d) >= self.radii_mm[i]:
                    lo = mid
                else:
                    hi = mid
            self.positions_mm[i] = before[i] + lo * d
        # Two particles that would overlap: the one that moved further into the other gives way,
        # back along its own step to contact.
        n = len(self.positions_mm)
        for i in range(n):
            for j in range(i + 1, n):
                reach = self.radii_mm[i] + self.radii_mm[j]
                gap = self.positions_mm[j] - self.positions_mm[i]
                if math.hypot(*gap) >= reach:
                    continue
                mover = i if np.hypot(*(self.positions_mm[i] - before[i])) >= np.hypot(
                    *(self.positions_mm[j] - before[j])) else j
                other = j if mover == i else i
                start, end = before[mover], self.positions_mm[mover]
                lo, hi = 0.0, 1.0
                for _ in range(_BISECTIONS):
                    mid = 0.5 * (lo + hi)
                    if math.hypot(*(start + mid * (end - start) - self.positions_mm[other])) >= reach:
                        lo = mid
                    else:
                        hi = mid
                self.positions_mm[mover] = start + lo * (end - start)
