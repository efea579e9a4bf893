"""The electromagnets' field per ampere: actuation matrices from the coils' loop geometry.

Air-core coils add linearly, so the field at a point is B = A I with A the 3 x n actuation matrix
(T/A), each column one coil's field per ampere (`rigctl.physics.magnetics.loop_field`, or measured and
given in the rig file), or from the loops a field calibration fitted when the rig file names one
(`rigctl.physics.field_calibration`). Pulling needs the gradient too: the 8-vector U (field and the five
independent gradient terms, seed 003 eq. 6) per ampere. Planners, allocation and the emulated
world all take their coil fields from here."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, LimitError
from rigctl.physics.field_calibration import fitted_loops
from rigctl.physics.magnetics import gradient_terms, loop_field


def coil_loops(rig: RigConfig) -> list[tuple[np.ndarray, np.ndarray, float, int, float]]:
    """(centre m, unit axis, radius m, turns, gain) of each coil, in `rig.coils` order: the fitted
    loops of the rig's `field_calibration` if it names one, else the rig file's (gain 1)."""
    if rig.field_calibration is not None:
        return fitted_loops(rig.field_calibration, [c.name for c in rig.coils])
    return [(np.asarray(c.centre_mm, dtype=float) * 1e-3, np.asarray(c.axis, dtype=float),
             c.loop_radius_mm * 1e-3, c.turns, 1.0) for c in rig.coils]


def actuation_matrix(rig: RigConfig, point_mm: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The actuation matrix of the rig's coils at `point_mm`.

    Parameters
    ----------
    rig : RigConfig
        Its `coils` (loop of `turns` turns, `centre_mm`, `axis`, `loop_radius_mm`), the loops
        its `field_calibration` fitted, or its measured `actuation_matrix_T_per_A`, which takes
        precedence.
    point_mm : (3,) array
        Where the field is wanted, workspace frame, mm. A measured matrix only describes the
        workspace centre, so with one any other point is refused.

    Returns
    -------
    np.ndarray, shape (3, n_coils)
        Field per ampere in T/A; column j is coil j in `rig.coils` order.
    """
    point = np.asarray(point_mm, dtype=float).reshape(3)
    if not rig.coils:
        raise ConfigError(f"rig '{rig.rig.name}' has no [[coils]]: there is nothing to allocate to")
    if rig.actuation_matrix_T_per_A is not None:
        if np.any(point != 0.0):
            raise ConfigError(
                f"actuation_matrix_T_per_A is measured at the workspace centre; it cannot give the "
                f"field at {point.tolist()} mm (remove it to compute the matrix from the coils)"
            )
        return np.array(rig.actuation_matrix_T_per_A, dtype=float)
    point_m = point * 1e-3
    columns = [gain * loop_field(point_m, centre, axis, radius, turns, 1.0)
               for centre, axis, radius, turns, gain in coil_loops(rig)]
    matrix = np.stack(columns, axis=1)
    if not np.isfinite(matrix).all():
        bad = rig.coils[int(np.flatnonzero(~np.isfinite(matrix).all(axis=0))[0])].name
        raise ConfigError(f"point {point.tolist()} mm lies on the winding of coil {bad}")
    return matrix


GRADIENT_STEP_MM = 0.05
"""Central-difference step: truncation ~ (step / distance to the winding)^2 / 6, about 3e-8
relative for the cube's coils; round-off ~1e-10 relative."""


def coil_field_and_gradient(rig: RigConfig, point_mm: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Field (3, n) T/A and gradient (3, 3, n) T/m/A of every coil per ampere at `point_mm`
    (central differences of `loop_field`, step `GRADIENT_STEP_MM`); returns (B, G) stacked as
    a (3, 4, n) array: [..., 0, :] the field, [:, 1 + j, :] dB/dx_j."""
    if not rig.coils:
        raise ConfigError(f"rig '{rig.rig.name}' has no [[coils]]: there is nothing to allocate to")
    if rig.actuation_matrix_T_per_A is not None:
        raise ConfigError("a measured actuation_matrix_T_per_A has no gradients: remove it to "
                          "compute fields and gradients from the coils' geometry")
    point = np.asarray(point_mm, dtype=float).reshape(3) * 1e-3
    h = GRADIENT_STEP_MM * 1e-3
    offsets = np.concatenate([np.zeros((1, 3)), h * np.eye(3), -h * np.eye(3)])  # (7, 3)
    out = np.zeros((3, 4, len(rig.coils)))
    for j, (centre, axis, radius, turns, gain) in enumerate(coil_loops(rig)):
        b = gain * loop_field(point + offsets, centre, axis, radius, turns, 1.0)  # (7, 3)
        out[:, 0, j] = b[0]
        out[:, 1:, j] = ((b[1:4] - b[4:7]) / (2.0 * h)).T
    if not np.isfinite(out).all():
        raise ConfigError(f"point {point_mm} mm lies on a coil's winding")
    return out


def u_actuation_matrix(rig: RigConfig, point_mm: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The 8 x n actuation matrix of U (rows `U_COMPONENTS`) at `point_mm`, per ampere."""
    fg = coil_field_and_gradient(rig, point_mm)
    gradient = np.moveaxis(fg[:, 1:, :], -1, 0)  # (n, 3, 3)
    return np.concatenate([fg[:, 0, :], gradient_terms(gradient).T])


def max_planar_gradient(rig: RigConfig, b0_T: float, *, angles: int = 360) -> float:
    """The largest g (T/m) such that an in-plane field of `b0_T` at any angle together with any
    diagonal gradient |dBx/dx|, |dBy/dy| <= g stays within every coil's current limit (box corners
    suffice: the currents are linear in U). Raises LimitError if the field alone is too strong."""
    A8 = u_actuation_matrix(rig)
    pinv = np.linalg.pinv(A8)
    limits = np.array([c.current_limit_A for c in rig.coils])
    psi = np.linspace(0.0, 2.0 * np.pi, angles, endpoint=False)
    u_field = np.zeros((angles, 8))
    u_field[:, 0], u_field[:, 1] = b0_T * np.cos(psi), b0_T * np.sin(psi)
    i_field = np.abs(u_field @ pinv.T)  # (angles, n)
    room = limits - i_field.max(axis=0)
    if (room <= 0).any():
        j = int(np.argmin(room))
        raise LimitError(f"a {b0_T * 1e3:g} mT field needs {i_field.max(axis=0)[j]:.1f} A on coil "
                         f"{rig.coils[j].name} (limit {limits[j]:.1f} A)")
    worst = np.zeros(len(limits))
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            u = np.zeros(8)
            u[3], u[6] = sx, sy
            worst = np.maximum(worst, np.abs(pinv @ u))
    # |I_field + g I_unit| <= |I_field| + g |I_unit|: conservative, per coil
    per_coil = np.where(worst > 0, room / np.maximum(worst, 1e-300), np.inf)
    return float(per_coil.min())
