"""The dual-EPM bench's magnets as they are: finite, axially magnetised N52 cylinders, not the
planner's point dipoles.

Seed 003 Sec. 4: two cylindrical N52 EPMs, 101.6 mm in diameter and in length. Each is a uniformly
polarised cylinder whose axis is its moment's direction and whose polarisation J = mu0 |m| / V
(V = pi D^2 L / 4) gives it the rig file's dipole moment exactly: far away it is the planner's
dipole (the l = 3 term of a cylinder decays as r^-5, two powers faster than the dipole's r^-3);
within 15 cm of a magnet's centre it differs by 1-13 % (the issue's figure; checked in
`tests/unit/test_epm_world.py`). The field is the closed form for an axially magnetised
cylinder (Derby and Olbert 2010: `rigctl.physics.magnetics.cylinder_axial_field`), called on
every magnet's local coordinates at once. It was magpylib's core kernel until the core install
had to shed weight (magpylib brings plotly); the test still checks it against magpylib's own
cylinder field (1e-9 relative).
Gradients (for the backdoor's exact U) are central differences.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigctl.physics.magnetics import MU0, cylinder_axial_field, gradient_terms

SEED_003_EPM_DIAMETER_M = 0.1016
SEED_003_EPM_LENGTH_M = 0.1016
GRADIENT_STEP_M = 1e-4  # central differences: the EPMs are >= 0.2 m away, truncation ~1e-7


@dataclass(frozen=True)
class CylinderEpms:
    """Axially magnetised cylinders (diameter, length in m) carrying the given moments."""

    diameter_m: float = SEED_003_EPM_DIAMETER_M
    length_m: float = SEED_003_EPM_LENGTH_M

    @property
    def volume_m3(self) -> float:
        return np.pi * self.diameter_m**2 * self.length_m / 4.0

    def field(self, points_m: np.ndarray, centres_m: np.ndarray, moments_Am2: np.ndarray) -> np.ndarray:
        """B (n, 3) T at points (n, 3) m of magnets at centres (K, 3) m with moments (K, 3) A m^2,
        superposed. A point inside a magnet is not a place a sensor can be (it gets the closed
        form's interior value; on an edge 0)."""
        points = np.asarray(points_m, dtype=float).reshape(-1, 3)
        centres = np.asarray(centres_m, dtype=float).reshape(-1, 3)
        moments = np.asarray(moments_Am2, dtype=float).reshape(-1, 3)
        strengths = np.linalg.norm(moments, axis=1)
        live = strengths > 0
        if not live.any():
            return np.zeros_like(points)
        # every (magnet, point) pair in the magnet's own frame (axis +z), one closed-form call
        frames = np.array([_z_to(m / s) for m, s in zip(moments[live], strengths[live])])  # (K, 3, 3)
        local = np.einsum("kji,knj->kni", frames, points[None] - centres[live][:, None])  # R^T r
        # the axial cylinder's closed form in cylindrical coordinates, lengths over the radius
        radius = self.diameter_m / 2.0
        rho = np.hypot(local[..., 0], local[..., 1])
        b_r, b_z = cylinder_axial_field(
            np.full(rho.size, self.length_m / self.diameter_m), rho.ravel() / radius,
            local[..., 2].ravel() / radius)
        polarization = (MU0 * strengths[live] / self.volume_m3)[:, None]  # T, (K, 1)
        b_r = b_r.reshape(rho.shape) * polarization
        b_z = b_z.reshape(rho.shape) * polarization
        with np.errstate(invalid="ignore", divide="ignore"):
            cos, sin = (np.where(rho > 0, local[..., 0] / rho, 0.0),
                        np.where(rho > 0, local[..., 1] / rho, 0.0))
        b_local = np.stack([b_r * cos, b_r * sin, b_z], axis=-1)  # (K, n, 3)
        return np.einsum("kij,knj->ni", frames, b_local)  # back to the world frame, summed

    def field_vector(self, point_m: np.ndarray, centres_m: np.ndarray, moments_Am2: np.ndarray,
                     step_m: float = GRADIENT_STEP_M) -> np.ndarray:
        """U (8,) in T and T/m at `point_m` (3,): the field and the five gradient terms (seed 003
        eq. 6), the gradient by central differences of step `step_m`."""
        h = step_m
        point = np.asarray(point_m, dtype=float).reshape(3)
        offsets = np.concatenate([np.zeros((1, 3)), h * np.eye(3), -h * np.eye(3)])
        b = self.field(point + offsets, centres_m, moments_Am2)
        gradient = ((b[1:4] - b[4:7]) / (2 * h)).T  # [i, j] = dB_i / dx_j
        gradient = 0.5 * (gradient + gradient.T)  # curl-free: symmetric up to round-off
        return np.concatenate([b[0], gradient_terms(gradient)])


def _z_to(direction: np.ndarray) -> np.ndarray:
    """The rotation matrix (3, 3) taking +z to the unit vector `direction` (Rodrigues)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, direction)
    s, c = float(np.linalg.norm(axis)), float(z @ direction)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + s * K + (1.0 - c) * K @ K
