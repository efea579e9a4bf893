"""Ground truth of the two-agent world (seed 002): magnetic spheres at a liquid surface.

Each agent is a sphere of diameter D carrying a moment of fixed size |m| that turns with the local
field at once (the field's torque is far larger than the drag's). The local field is the coils' own
field at the agent's position, computed from the supplies' *actual* currents through the loop
geometry (not the allocator's matrix), plus the other agent's dipole field. Each agent feels

- the gradient pull grad(m . B_coils) = G m, with G the coils' gradient at its position;
- the other's dipole force, the full 3-D formula (no local-frame model: that is the planner's);
- Stokes drag sigma = 3 pi eta D, and no inertia (Reynolds number ~1e-3), so v = F / sigma;
- contact: the liquid surface holds them in the plane; walls and the other agent are hard (an
  agent is pushed back out along the wall's normal, two agents apart along their line of centres).

Model mismatch (`Mismatch`): `slip` is the agents' mobility against the plan's Stokes drag (they
move `slip` times as fast under a force: a liquid 1/slip times as viscous as the plan says, as a few
degrees of temperature make water; 1 = the plan's), `noise_mm` a random walk of that many mm per
square-root second (Brownian-like jitter, surface currents), `drift_mm_per_s` a steady drift in a
direction drawn from `seed`. The camera adds its own noise when it renders the agents.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.config import CoilRig
from rigctl.emulators.world.rolling import Mismatch
from rigctl.physics.coils import coil_field_and_gradient
from rigctl.physics.magnetics import MU0
from rigctl.plans.pair import PairPhysics

ACTUATED_FIELD_T = 1e-4
"""`min_separation_mm` counts only while the coils make at least this field (the run is on)."""
MAP_REFRESH_MM = 0.05
"""Recompute the coils' per-ampere field and gradient at an agent after it moved this far."""


class PairWorld:
    """Two agents on the floor of the six-coil bench.

    workspace: the plan's `Workspace` (mm); positions_mm: (2, 2) start centres; physics: the agents;
    rig: the bench's coils (geometry); floor_centre_mm: the workspace point under the coils' centre.
    """

    def __init__(self, workspace, positions_mm: ArrayLike, physics: PairPhysics, rig: CoilRig,
                 floor_centre_mm: ArrayLike, mismatch: Mismatch | None = None) -> None:
        self.workspace = workspace
        self.physics = physics
        self.rig = rig
        self.floor_centre_mm = np.asarray(floor_centre_mm, dtype=float)
        self._p = np.array(positions_mm, dtype=float).reshape(2, 2)
        self.radius_mm = 0.5 * physics.body_diameter_mm
        self.radii = np.full(2, self.radius_mm)
        self.mismatch = mismatch or Mismatch()
        rng = np.random.default_rng(self.mismatch.seed)
        heading = rng.uniform(0.0, 2.0 * math.pi)
        self._drift = self.mismatch.drift_mm_per_s * np.array([math.cos(heading), math.sin(heading)])
        self._rng = rng
        self._maps: np.ndarray | None = None  # (2, 3, 4, n): per agent, field and gradient per A
        self._map_at = np.full((2, 2), np.inf)
        self.moments = np.zeros((2, 3))  # A m^2; zero until a field is felt
        self.contacts = 0  # steps in which some contact was resolved
        self._room = np.zeros(2)  # mm each agent may travel before the walls must be asked again
        self._travel = np.zeros(2)  # mm travelled since they were last asked
        self.min_separation_mm = float(np.hypot(*(self._p[1] - self._p[0])))

    @property
    def positions_mm(self) -> np.ndarray:
        return self._p.copy()

    def _coil_maps(self) -> np.ndarray:
        if np.max(np.hypot(*(self._p - self._map_at).T)) > MAP_REFRESH_MM:
            points = np.zeros((2, 3))
            points[:, :2] = self._p - self.floor_centre_mm
            self._maps = np.stack([coil_field_and_gradient(self.rig, p) for p in points])
            self._map_at = self._p.copy()
        assert self._maps is not None
        return self._maps

    def step(self, dt_s: float, currents_A: ArrayLike) -> None:
        """Advance by dt_s (keep it <= 1 ms) under the supplies' actual currents (n,) A.

        Called every millisecond of simulated time, so the two-body arithmetic is done on plain
        floats (numpy's per-call cost on 3-vectors is ten times the arithmetic)."""
        maps = (self._coil_maps() @ np.asarray(currents_A, dtype=float)).tolist()  # (2, 3, 4)
        (x1, y1), (x2, y2) = self._p.tolist()
        sx, sy = (x2 - x1) * 1e-3, (y2 - y1) * 1e-3
        r = math.hypot(sx, sy)
        nx, ny = sx / r, sy / r
        (m1x, m1y, m1z), (m2x, m2y, m2z) = self.moments.tolist()
        interacting = (m1x or m1y or m1z) and (m2x or m2y or m2z)
        # local field: the coils' plus the other agent's dipole field (from last step's moment)
        k_field = MU0 / (4.0 * math.pi * r**3)
        local = []
        for i, (mx, my, mz, sign) in enumerate(((m2x, m2y, m2z, -1.0), (m1x, m1y, m1z, 1.0))):
            bx, by, bz = maps[i][0][0], maps[i][1][0], maps[i][2][0]
            if interacting:
                ux, uy = sign * nx, sign * ny  # from the other agent to this one
                mn = mx * ux + my * uy
                bx += k_field * (3.0 * mn * ux - mx)
                by += k_field * (3.0 * mn * uy - my)
                bz += k_field * (-mz)
            local.append((bx, by, bz))
        m_abs = self.physics.moment_Am2
        moments = []
        for i, (bx, by, bz) in enumerate(local):
            norm = math.sqrt(bx * bx + by * by + bz * bz)
            if norm > 1e-9:
                moments.append((m_abs * bx / norm, m_abs * by / norm, m_abs * bz / norm))
            else:  # no field: the magnets keep their moment
                moments.append(tuple(self.moments[i].tolist()))
        self.moments = np.array(moments)
        forces = []
        for i, (mx, my, mz) in enumerate(moments):  # G m, G[a][b] = dB_a / dx_b = maps[i][a][1 + b]
            g = maps[i]
            forces.append([g[0][1] * mx + g[0][2] * my + g[0][3] * mz,
                           g[1][1] * mx + g[1][2] * my + g[1][3] * mz])
        (a1, a2, a3), (b1, b2, b3) = moments
        if a1 or a2 or a3:
            m1n, m2n = a1 * nx + a2 * ny, b1 * nx + b2 * ny
            m12 = a1 * b1 + a2 * b2 + a3 * b3
            c = 3.0 * MU0 / (4.0 * math.pi * r**4)
            fx = c * (m1n * b1 + m2n * a1 + m12 * nx - 5.0 * m1n * m2n * nx)  # on agent 2
            fy = c * (m1n * b2 + m2n * a2 + m12 * ny - 5.0 * m1n * m2n * ny)
            forces[1][0] += fx
            forces[1][1] += fy
            forces[0][0] -= fx
            forces[0][1] -= fy
        to_mm = dt_s * 1e3 * self.mismatch.slip / self.physics.drag_N_s_per_m
        step = np.array(forces) * to_mm + self._drift * dt_s
        if self.mismatch.noise_mm > 0:
            step += self._rng.normal(0.0, self.mismatch.noise_mm * math.sqrt(dt_s), (2, 2))
        self._p = self._p + step
        self._travel += np.hypot(step[:, 0], step[:, 1])
        self._resolve_contacts()
        b0 = maps[0][0][0] ** 2 + maps[0][1][0] ** 2 + maps[0][2][0] ** 2
        if b0 > ACTUATED_FIELD_T**2:  # with the coils off the magnets attract: not a run's doing
            self.min_separation_mm = min(self.min_separation_mm,
                                         float(math.hypot(*(self._p[1] - self._p[0]))))

    def _resolve_contacts(self) -> None:
        touched = False
        gap = self._p[1] - self._p[0]
        dist = float(math.hypot(gap[0], gap[1]))
        reach = 2.0 * self.radius_mm
        if dist < reach:
            n = gap / dist if dist > 0 else np.array([1.0, 0.0])
            push = 0.5 * (reach - dist) * n
            self._p[0] -= push
            self._p[1] += push
            self._travel += 0.5 * (reach - dist)
            touched = True
        # the walls are asked only when an agent may have used up its last known room
        if (self._travel >= self._room).any():
            clearance, normal, _ = self.workspace.surface(self._p)
            inside = clearance < self.radius_mm
            if inside.any():
                self._p[inside] += (self.radius_mm - clearance[inside])[:, None] * normal[inside]
                clearance[inside] = self.radius_mm
                touched = True
            self._room = np.maximum(clearance - self.radius_mm, 0.0)
            self._travel[:] = 0.0
        self.contacts += int(touched)
