"""Allocate a field program to coil currents on the six-coil rig (seed 000 Sec. V-c, eq. 3-4).

Air-core coils add linearly, so the field at a point is B = A I with A the 3 x n actuation matrix
(T/A), each column the field of one coil per ampere there (from its loop geometry through
`rigctl.physics.magnetics.loop_field`, or measured and given in the rig file). With six coils and three
field components the system is underdetermined; the currents are the minimum-norm solution, which
minimises the Joule heating sum(R I^2) for equal resistances:

    I = A^T (A A^T)^-1 B = pinv(A) B.

Seed 000 prints eq. 4 as (A^T A)^-1 A^T B, but for a 3 x 6 matrix A^T A is 6 x 6 of rank 3 and has
no inverse; the minimum-norm solution its text describes is the form above (the Moore-Penrose
pseudo-inverse, which numpy computes by SVD).

Limits are checked on the whole program before anything can be energised: the current of every
coil against its `current_limit_A`, and the voltage its supply must deliver, R I + L dI/dt (dI/dt
by a backward difference over the sample period, starting from the currents the supplies carry
when the program starts: 0 A for a plan, the currents being streamed for a re-plan spliced into a
running one), against its `compliance_V`. A program that breaks a limit raises LimitError naming
the move and the coil; nothing is clipped.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import LimitError, PlanError
from rigctl.physics.coils import actuation_matrix, field_offset
from rigctl.physics.magnetics import U_COMPONENTS
from rigctl.rigs.six_coil.realize import FieldProgram

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

logger = logging.getLogger(__name__)

FIELD_RESIDUAL = 1e-6
"""Largest |A I - B| accepted, relative to the largest |B| of the program."""


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


def check_current_limits(currents: np.ndarray, rig: SixCoilRig, rate_hz: float | None,
                         describe: Callable[[int], str], *, current_advice: str,
                         voltage_advice: str = "",
                         start_A: np.ndarray | None = None) -> np.ndarray | None:
    """Check a current program (T, n) A against every coil's current limit and, with dI/dt by a
    backward difference at `rate_hz` from `start_A` (default 0 A: the supplies are off), its
    supply's compliance voltage R I + L dI/dt (not with `rate_hz` None: samples that are not a
    time series). Returns the voltages (T, n); raises LimitError naming the sample (`describe(k)`)
    and the coil."""
    names = [c.name for c in rig.coils]
    limits = np.array([c.current_limit_A for c in rig.coils])
    over = np.abs(currents) / limits
    if over.size and over.max() > 1.0:
        k, j = (int(x) for x in np.unravel_index(np.argmax(over), over.shape))
        raise LimitError(
            f"{describe(k)} needs {abs(currents[k, j]):.1f} A on coil {names[j]} "
            f"(limit {limits[j]:.1f} A); {current_advice}"
        )
    if rate_hz is None:
        return None
    resistance = np.array([c.resistance_ohm for c in rig.coils])
    inductance = np.array([c.inductance_H for c in rig.coils])
    compliance = np.array([c.compliance_V for c in rig.coils])
    start = np.zeros(len(names)) if start_A is None else np.asarray(start_A, dtype=float)
    slope = np.diff(currents, axis=0, prepend=start[None, :]) * rate_hz
    resistive = resistance * currents
    inductive = inductance * slope
    volts = resistive + inductive
    over_v = np.abs(volts) / compliance
    if over_v.size and over_v.max() > 1.0:
        k, j = (int(x) for x in np.unravel_index(np.argmax(over_v), over_v.shape))
        raise LimitError(
            f"{describe(k)} needs {abs(volts[k, j]):.1f} V on coil {names[j]} "
            f"(limit {compliance[j]:.1f} V; R*I = {resistive[k, j]:.1f} V, "
            f"L*dI/dt = {inductive[k, j]:.1f} V); {voltage_advice}"
        )
    return volts


def allocate(program: FieldProgram, rig: SixCoilRig, *,
             start_A: np.ndarray | None = None) -> CurrentProgram:
    """Currents for every sample of `program` on `rig`, after checking every limit; the voltage's
    dI/dt of the first sample from `start_A` (n,) A, the currents the supplies carry when it
    starts (default 0 A: a plan starts with them off).

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
    # an MPEM rig's Offset field is there with the supplies off: the coils make the rest
    # (as `rigctl.physics.fields.allocate` does); a loop rig's offset is 0
    coils_make = field - field_offset(rig)[0:3]
    currents = currents_for_field(A, coils_make)
    names = [c.name for c in rig.coils]

    scale = float(np.max(np.linalg.norm(field, axis=1), initial=0.0))
    residual = np.linalg.norm(currents @ A.T - coils_make, axis=1)
    if residual.size and residual.max() > FIELD_RESIDUAL * scale:
        k = int(np.argmax(residual))
        raise LimitError(
            f"{program.describe_sample(k)} needs B = {np.round(field[k] * 1e3, 3).tolist()} mT, "
            f"which these coils cannot produce (actuation matrix of rank "
            f"{np.linalg.matrix_rank(A)}); check the coil axes or actuation_matrix_T_per_A"
        )

    volts = check_current_limits(
        currents, rig, program.rate_hz, program.describe_sample,
        current_advice="lower field.b0_mT or raise the coil's current_limit_A",
        voltage_advice="lower field.rolling_turns_per_s, field.steering_deg_per_s or field.b0_mT, "
        "lengthen field.ramp_s, or raise the coil's compliance_V",
        start_A=start_A,
    )

    assert volts is not None  # checked at the program's rate
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


# -- field and gradient: the 8-vector U (seed 002 pulling, seed 003 eq. 6) ------------------------
#
# U = [Bx, By, Bz, dBx/dx, dBx/dy, dBx/dz, dBy/dy, dBy/dz] at a point: the field and the five
# independent terms of its gradient (div B = 0 and curl B = 0 give the other four). A dipole m
# there feels F = grad(m . B) = G m with G the symmetric gradient matrix. The coils' gradients come
# from `loop_field` by central differences; `tests/unit/test_pair_allocate.py` checks them against
# the closed-form on-axis gradient of a loop (to 1e-6 relative).


PULL_FLOOR_N = 1e-15
"""A pull component below this (a femtonewton) is taken as none (round-off of cos 90 deg)."""


def field_and_pull_u(psi_rad: ArrayLike, force_N: ArrayLike, moment_Am2: float,
                     b0_T: float) -> np.ndarray:
    """U (..., 8) for an in-plane field of `b0_T` at angle psi (rad from +x) that pulls a dipole of
    `moment_Am2` aligned with it by `force_N` (..., 2) in the plane.

    With m = |m| (cos psi, sin psi, 0) and the off-diagonal in-plane gradient left at zero (a
    six-coil cube cannot make it at its centre), F = |m| (cos psi dBx/dx, sin psi dBy/dy), so
    dBx/dx = Fx / (|m| cos psi), dBy/dy = Fy / (|m| sin psi). A pull along an axis the moment is
    perpendicular to cannot be made: LimitError."""
    psi = np.asarray(psi_rad, dtype=float)
    force = np.asarray(force_N, dtype=float)
    c, s = np.cos(psi), np.sin(psi)
    shape = np.broadcast_shapes(psi.shape, force.shape[:-1])
    u = np.zeros(shape + (8,))
    u[..., 0] = b0_T * c
    u[..., 1] = b0_T * s
    fx, fy = np.broadcast_to(force[..., 0], shape), np.broadcast_to(force[..., 1], shape)
    for axis, (f, proj, row) in enumerate(((fx, c, 3), (fy, s, 6))):
        want = np.abs(f) > PULL_FLOOR_N
        blind = want & (np.abs(proj) < 1e-9)
        if blind.any():
            raise LimitError(
                f"a pull along {'xy'[axis]} needs the field to have a component along {'xy'[axis]}; "
                f"at psi = {np.degrees(np.broadcast_to(psi, shape)[blind][0]):.1f} deg it has none")
        with np.errstate(divide="ignore", invalid="ignore"):
            u[..., row] = np.where(want, f / (moment_Am2 * proj), 0.0)
    return u


def currents_for_u(A8: ArrayLike, U: ArrayLike, rig: SixCoilRig | None = None) -> np.ndarray:
    """Minimum-norm currents (..., n) for 8-vectors U (..., 8) through the 8 x n matrix `A8`.

    The six coils span fewer than eight terms (at the centre of a cube: the field and two
    diagonal gradients). A U outside their span raises LimitError naming the term that cannot be
    made, with `rig` (if given) also every coil's current limit is checked, naming the coil."""
    A8 = np.asarray(A8, dtype=float)
    U = np.asarray(U, dtype=float)
    currents = U @ np.linalg.pinv(A8).T
    made = currents @ A8.T
    scale = np.maximum(np.abs(U[..., :3]).max(axis=-1, keepdims=True), 1e-12)  # field terms
    gscale = np.maximum(np.abs(U[..., 3:]).max(axis=-1, keepdims=True), 1e-6)  # T/m
    residual = np.abs(made - U) / np.concatenate(
        [np.broadcast_to(scale, U.shape[:-1] + (3,)), np.broadcast_to(gscale, U.shape[:-1] + (5,))],
        axis=-1)
    if residual.size and residual.max() > 1e-6:
        flat = residual.reshape(-1, 8)
        k, t = np.unravel_index(np.argmax(flat), flat.shape)
        raise LimitError(
            f"the coils cannot make {U_COMPONENTS[t]} = {U.reshape(-1, 8)[k, t]:.4g} together with the "
            f"rest of U (they make {made.reshape(-1, 8)[k, t]:.4g}); at the centre of a six-coil "
            "cube only the field and the diagonal gradients can be set")
    if rig is not None:
        check_current_limits(
            currents.reshape(-1, currents.shape[-1]), rig, None, lambda k: f"U sample {k}",
            current_advice="ask for a weaker pull or field, or raise the coil's current_limit_A")
    return currents


