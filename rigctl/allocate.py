"""Allocate a field program to coil currents on the six-coil rig (seed 000 Sec. V-c, eq. 3-4).

Air-core coils add linearly, so the field at a point is B = A I with A the 3 x n actuation matrix
(T/A), each column the field of one coil per ampere there (from its loop geometry through
`rigctl.magnetics.loop_field`, or measured and given in the rig file). With six coils and three
field components the system is underdetermined; the currents are the minimum-norm solution, which
minimises the Joule heating sum(R I^2) for equal resistances:

    I = A^T (A A^T)^-1 B = pinv(A) B.

Seed 000 prints eq. 4 as (A^T A)^-1 A^T B, but for a 3 x 6 matrix A^T A is 6 x 6 of rank 3 and has
no inverse; the minimum-norm solution its text describes is the form above (the Moore-Penrose
pseudo-inverse, which numpy computes by SVD).

Limits are checked on the whole program before anything can be energised: the current of every
coil against its `current_limit_A`, and the voltage its supply must deliver, R I + L dI/dt (dI/dt
by a backward difference over the sample period, starting from 0 A), against its `compliance_V`.
A program that breaks a limit raises LimitError naming the move and the coil; nothing is clipped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rigctl.config import RigConfig
from rigctl.errors import ConfigError, LimitError, PlanError
from rigctl.magnetics import loop_field
from rigctl.realize import FieldProgram

logger = logging.getLogger(__name__)

FIELD_RESIDUAL = 1e-6
"""Largest |A I - B| accepted, relative to the largest |B| of the program."""


def actuation_matrix(rig: RigConfig, point_mm: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The actuation matrix of the rig's coils at `point_mm`.

    Parameters
    ----------
    rig : RigConfig
        Its `coils` (loop of `turns` turns, `centre_mm`, `axis`, `loop_radius_mm`), or its
        measured `actuation_matrix_T_per_A`, which takes precedence.
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
    columns = [
        loop_field(
            point_m,
            np.asarray(coil.centre_mm) * 1e-3,
            coil.axis,
            coil.loop_radius_mm * 1e-3,
            coil.turns,
            1.0,
        )
        for coil in rig.coils
    ]
    matrix = np.stack(columns, axis=1)
    if not np.isfinite(matrix).all():
        bad = rig.coils[int(np.flatnonzero(~np.isfinite(matrix).all(axis=0))[0])].name
        raise ConfigError(f"point {point.tolist()} mm lies on the winding of coil {bad}")
    return matrix


def currents_for_field(A: ArrayLike, B_T: ArrayLike) -> np.ndarray:
    """Minimum-norm currents producing the fields `B_T`: I = pinv(A) B (seed 000 eq. 4 corrected,
    see the module docstring).

    Parameters
    ----------
    A : (3, n) array
        Actuation matrix in T/A.
    B_T : (..., 3) array
        Wanted flux densities in tesla.

    Returns
    -------
    np.ndarray, shape (..., n)
        Currents in amperes. If B is outside the range of A this is the least-squares fit;
        `allocate` checks the residual.
    """
    A = np.asarray(A, dtype=float)
    if A.ndim != 2 or A.shape[0] != 3:
        raise ValueError(f"actuation matrix must be (3, n), got {A.shape}")
    B = np.asarray(B_T, dtype=float)
    if B.shape[-1:] != (3,):
        raise ValueError(f"fields must have shape (..., 3), got {B.shape}")
    return B @ np.linalg.pinv(A).T


@dataclass(frozen=True)
class CurrentProgram:
    """The currents that realize a field program, ready to stream.

    Attributes
    ----------
    t_s : (T,) float
        Sample times in s, uniform, from 0 (the field program's).
    currents_A : (T, n) float
        Current of each coil in A (per coil, i.e. through the series pair of supplies).
    segment : (T,) int
        Plan move index (0-based) of each sample, -1 for ramps and holds.
    coil_names : tuple of n str
        Column order of `currents_A`, as in the rig file.
    """

    t_s: np.ndarray
    currents_A: np.ndarray
    segment: np.ndarray
    coil_names: tuple[str, ...]

    def __post_init__(self) -> None:
        n = len(self.t_s)
        if self.currents_A.shape != (n, len(self.coil_names)) or self.segment.shape != (n,):
            raise ValueError(
                f"current program arrays disagree: t_s {self.t_s.shape}, currents_A "
                f"{self.currents_A.shape}, segment {self.segment.shape}, "
                f"{len(self.coil_names)} coil names"
            )


def allocate(program: FieldProgram, rig: RigConfig) -> CurrentProgram:
    """Currents for every sample of `program` on `rig`, after checking every limit.

    Raises
    ------
    LimitError
        A coil would need more than its `current_limit_A`, or its supply more than its
        `compliance_V`; or the coils cannot produce the field at all. The message names the
        move (as `FieldProgram.describe_sample` does) and the coil, and what to change.
    PlanError
        The program contains non-finite fields.
    """
    field = np.asarray(program.field_T, dtype=float)
    if not np.isfinite(field).all():
        k = int(np.flatnonzero(~np.isfinite(field).all(axis=1))[0])
        raise PlanError(f"{program.describe_sample(k)}: field sample {k} is not finite")
    A = actuation_matrix(rig)
    currents = currents_for_field(A, field)
    names = [c.name for c in rig.coils]

    scale = float(np.max(np.linalg.norm(field, axis=1), initial=0.0))
    residual = np.linalg.norm(currents @ A.T - field, axis=1)
    if residual.size and residual.max() > FIELD_RESIDUAL * scale:
        k = int(np.argmax(residual))
        raise LimitError(
            f"{program.describe_sample(k)} needs B = {np.round(field[k] * 1e3, 3).tolist()} mT, "
            f"which these coils cannot produce (actuation matrix of rank "
            f"{np.linalg.matrix_rank(A)}); check the coil axes or actuation_matrix_T_per_A"
        )

    limits = np.array([c.current_limit_A for c in rig.coils])
    over = np.abs(currents) / limits
    if over.size and over.max() > 1.0:
        k, j = np.unravel_index(np.argmax(over), over.shape)
        raise LimitError(
            f"{program.describe_sample(k)} needs {abs(currents[k, j]):.1f} A on coil {names[j]} "
            f"(limit {limits[j]:.1f} A); lower field.b0_mT or raise the coil's current_limit_A"
        )

    resistance = np.array([c.resistance_ohm for c in rig.coils])
    inductance = np.array([c.inductance_H for c in rig.coils])
    compliance = np.array([c.compliance_V for c in rig.coils])
    slope = np.diff(currents, axis=0, prepend=np.zeros((1, len(names)))) * program.rate_hz
    resistive = resistance * currents
    inductive = inductance * slope
    volts = resistive + inductive
    over_v = np.abs(volts) / compliance
    if over_v.size and over_v.max() > 1.0:
        k, j = np.unravel_index(np.argmax(over_v), over_v.shape)
        raise LimitError(
            f"{program.describe_sample(k)} needs {abs(volts[k, j]):.1f} V on coil {names[j]} "
            f"(limit {compliance[j]:.1f} V; R*I = {resistive[k, j]:.1f} V, "
            f"L*dI/dt = {inductive[k, j]:.1f} V); lower field.rolling_turns_per_s, "
            f"field.steering_deg_per_s or field.b0_mT, lengthen field.ramp_s, "
            f"or raise the coil's compliance_V"
        )

    if currents.size:
        logger.info(
            "allocated %d samples to %d coils: peak %.2f A, peak %.2f V",
            len(currents), len(names), np.abs(currents).max(), np.abs(volts).max(),
        )
    return CurrentProgram(
        t_s=np.asarray(program.t_s, dtype=float),
        currents_A=currents,
        segment=np.asarray(program.segment, dtype=int),
        coil_names=tuple(names),
    )
