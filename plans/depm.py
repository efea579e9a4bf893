"""The hybrid trajectory planner of seed 003 for the dual-EPM rig, and its magnetic-agnostic baseline.

A sequence of requested 8-vectors U (field and five gradient terms at the workspace centre) becomes
joint trajectories of the two arms that carry the magnets:

1. inverse magnetics: EPM positions and moment directions (moment magnitude fixed to the magnets'
   real strength) that make each requested U, by Levenberg-Marquardt with the rig's constraints as
   one-sided penalties (`inverse_magnetics`);
2. operational space (eq. 11-12): per EPM a path from the current to the new position, linear in
   the cylindrical coordinates (theta, rho, z) about the centre, plus k radial alternatives that
   bulge away from the centre (distance + Delta_k sin(pi s)), none inside the keep-out sphere;
3. magnetic space (eq. 13-14): the desired U along the path, a falling sigmoid of U_s then a rising
   sigmoid of U_e (how we read eq. 14: `magnetic_path`);
4. at every waypoint and alternative, the moments by pseudo-inverse of [L; M] (eq. 21), given the
   real |m| and refined so that constraint costs as little as possible; the alternative whose U
   is nearest the desired one in absolute terms (eq. 22) is kept;
5. joints by inverse kinematics along the path, each solve seeded with the previous knot and steps
   the arms cannot take smoothly subdivided (if the arms must change configuration anyway, other
   end poses are tried); PCHIP through the knots with shared knot times (both arms finish
   together), timed so no joint exceeds 30 % of its maximum speed.

The baseline ("magnetic-agnostic", `baseline_of`) sends the arms to the same EPM end poses by
straight joint-space moves, each arm solving its own joints as its controller would, also at 30 %
speed. `check(plan)` runs every safety constraint of `rigctl.plans.depm_safety` on a plan, densely in
time. Figures and the reading of the paper: docs/depm.md.
"""

from __future__ import annotations

import functools
import itertools
import json
import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike
from scipy.interpolate import PchipInterpolator

from rigctl.core.errors import PlanError
from rigctl.core.jit import njit
from rigctl.physics.kinematics import (
    DEFAULT_BASES,
    LBR_IIWA_14_R820,
    ArmKinematics,
    ArmModel,
    base_transform,
    cholesky_solve,
    frames_kernel,
)
from rigctl.physics.magnetics import MU0, cylinder_moment, field_vector
from rigctl.plans.depm_safety import SafetyLimits, check_samples, violations
from rigctl.plans.schema import (
    SCHEMA_ID,
    ArmPlan,
    DepmLimits,
    ExpectedField,
    FieldSequencePlan,
    Segment,
    SequenceComponent,
    rig_running,
)

log = logging.getLogger(__name__)

# The seed's magnets: axially magnetised N52 cylinders, 101.6 mm diameter and length (Sec. 3.3).
# Br = 1.48 T is the top of the N52 grade's range (1.43-1.48 T); it gives |m| = 970.1 A m^2.
EPM_DIAMETER_M = 0.1016
EPM_LENGTH_M = 0.1016
EPM_REMANENCE_T = 1.48
EPM_MOMENT_AM2 = cylinder_moment(EPM_DIAMETER_M, EPM_LENGTH_M, EPM_REMANENCE_T)

# U in plans and sequence files is mT and mT/m; inside, T and T/m.
U_TO_SI = np.array([1e-3] * 8)
# Weights that make 1 mT of field count like 10 mT/m of gradient (a 10 cm lever) in residuals.
U_SCALE_SI = np.array([1e-3] * 3 + [1e-2] * 5)

SIGMOID_SLOPE = 2.1
"""Steepness of eq. 14 per waypoint, as tuned in the seed for its 10-waypoint paths."""
SIGMOID_REFERENCE_WAYPOINTS = 10

HOME_DISTANCE_M = 0.52
START_HOLD_S = 1.0
SPEED_MARGIN = 0.97  # plan at 97 % of the allowed speed so the dense check has room
IM_MARGIN_M = 0.02  # planned EPM positions keep this far inside each positional constraint
SIDE_MARGIN_M = 0.0  # each EPM stays on its own arm's side of the plane through the centre
MAX_DISTANCE_M = 0.55  # end poses farther than this from the centre strain the arms' reach
EXPECTED_RATE_HZ = 10.0
DEFAULT_WAYPOINTS = 20
DEFAULT_K = 4
DEFAULT_BULGE_M = 0.20  # the farthest alternative bulges 20 cm out mid-path
HOP_COST_PER_M = 20.0  # selection cost of moving between alternatives: 5 cm ~ 1 mT of error
IK_KEEP_OUT_MARGIN_M = 0.03  # IK keeps link sample points this much beyond the keep-out sphere

Planner = Literal["hybrid", "agnostic"]


# ---------------------------------------------------------------- the rig a plan is made for


@dataclass
class DepmRig:
    """The two arms (with their bases), the magnets' strength and the safety limits."""

    arms: list[ArmKinematics]
    moment_Am2: float = EPM_MOMENT_AM2
    limits: SafetyLimits = field(default_factory=SafetyLimits)

    @property
    def centre(self) -> np.ndarray:
        return np.asarray(self.limits.centre_m, dtype=float)

    def side(self, index: int) -> np.ndarray:
        """Horizontal unit vector from the centre toward arm `index`'s base."""
        toward = self.arms[index].base[:3, 3] - self.centre
        toward[2] = 0.0
        return toward / np.linalg.norm(toward)

    def epm_poses(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """EPM centres and moment directions (A, ..., 3) for joints q (A, ..., 7)."""
        poses = [arm.epm_pose(q[a]) for a, arm in enumerate(self.arms)]
        return np.stack([p for p, _ in poses]), np.stack([d for _, d in poses])

    def field_at_centre(self, q: np.ndarray) -> np.ndarray:
        """U (..., 8) in T and T/m at the centre for joints q (A, ..., 7)."""
        positions, directions = self.epm_poses(q)
        centres = np.moveaxis(positions, 0, -2)  # (..., A, 3)
        moments = np.moveaxis(directions, 0, -2) * self.moment_Am2
        return field_vector(np.broadcast_to(self.centre, centres.shape[:-2] + (3,)), centres, moments)


def default_rig(limits: SafetyLimits | None = None) -> DepmRig:
    arms = [
        ArmKinematics(base=base_transform(pos, rpy), model=LBR_IIWA_14_R820, name=name)
        for name, pos, rpy in DEFAULT_BASES
    ]
    return DepmRig(arms=arms, limits=limits or SafetyLimits())


def _model_for(plan: FieldSequencePlan) -> ArmModel:
    from dataclasses import replace

    return replace(LBR_IIWA_14_R820, tool_offset_m=plan.tool_offset_mm * 1e-3)


def limits_from_plan(limits: DepmLimits) -> SafetyLimits:
    return SafetyLimits(
        keep_out_radius_m=limits.keep_out_radius_mm * 1e-3,
        epm_radius_m=limits.epm_radius_mm * 1e-3,
        epm_min_distance_m=limits.epm_min_distance_mm * 1e-3,
        speed_fraction=limits.speed_fraction,
        accel_fraction=limits.accel_fraction,
        check_step_s=limits.check_step_s,
    )


def limits_to_plan(limits: SafetyLimits) -> DepmLimits:
    return DepmLimits(
        keep_out_radius_mm=limits.keep_out_radius_m * 1e3,
        epm_radius_mm=limits.epm_radius_m * 1e3,
        epm_min_distance_mm=limits.epm_min_distance_m * 1e3,
        speed_fraction=limits.speed_fraction,
        accel_fraction=limits.accel_fraction,
        check_step_s=limits.check_step_s,
    )


def rig_from_settings(settings) -> DepmRig:
    """The rig a rig file's `[depm]` table describes (`rigctl.core.config.DepmSettings`): its arms'
    bases and EPM tool, the magnets' moment and the safety limits."""
    from dataclasses import replace

    model = replace(LBR_IIWA_14_R820, tool_offset_m=settings.tool_offset_mm * 1e-3)
    arms = [
        ArmKinematics(base=base_transform(np.asarray(position) * 1e-3, rpy), model=model, name=name)
        for name, position, rpy in zip(settings.arm_names, settings.arm_positions_mm,
                                       settings.arm_rpy_deg)
    ]
    limits = SafetyLimits(
        keep_out_radius_m=settings.keep_out_radius_mm * 1e-3,
        epm_radius_m=settings.epm_radius_mm * 1e-3,
        epm_min_distance_m=settings.epm_min_distance_mm * 1e-3,
        speed_fraction=settings.speed_fraction,
    )
    return DepmRig(arms=arms, moment_Am2=settings.epm_moment_Am2, limits=limits)


def rig_for_plan(plan: FieldSequencePlan) -> DepmRig:
    """The arms, magnet strength and limits a plan was made for (as the plan states them)."""
    model = _model_for(plan)
    arms = [
        ArmKinematics(
            base=base_transform(np.asarray(arm.position_mm) * 1e-3, arm.rpy_deg),
            model=model, name=arm.name,
        )
        for arm in plan.arms
    ]
    return DepmRig(arms=arms, moment_Am2=plan.epm_moment_Am2, limits=limits_from_plan(plan.limits))


# ---------------------------------------------------------------- sequences


def load_sequence(path: str | Path) -> list[SequenceComponent]:
    """Read a sequence file: a JSON list of {"name", "U" (8 numbers, mT and mT/m), "hold_s"}."""
    from rigctl.plans.schema import _read_json  # the one JSON reader of plan-like files

    path = Path(path)
    data = _read_json(path)
    if not isinstance(data, list) or not data:
        raise PlanError(f"--sequence: {path}: expected a non-empty JSON list of components")
    components = []
    for index, item in enumerate(data):
        try:
            components.append(SequenceComponent.model_validate(item))
        except Exception as err:  # pydantic.ValidationError: name the entry
            detail = "; ".join(
                f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in err.errors()
            ) if hasattr(err, "errors") else str(err)
            raise PlanError(f"--sequence: {path}: entry {index}: {detail}") from None
    return components


# ---------------------------------------------------------------- inverse magnetics


@dataclass(frozen=True)
class EpmPoses:
    """EPM centres (A, 3) in m, unit moment directions (A, 3), the U they make (8,) in T and T/m,
    and the residual U - requested (8,)."""

    positions: np.ndarray
    directions: np.ndarray
    U: np.ndarray
    residual: np.ndarray

    def relative_error(self, requested: np.ndarray) -> float:
        return relative_error(self.residual, requested)


def relative_error(residual: np.ndarray, requested: np.ndarray) -> float:
    """Largest |residual| relative to the largest requested entry of its kind (field, gradient)."""
    residual, requested = np.asarray(residual, float), np.asarray(requested, float)
    worst = 0.0
    for part in (slice(0, 3), slice(3, 8)):
        scale = np.max(np.abs(requested[part]))
        if scale > 0:
            worst = max(worst, float(np.max(np.abs(residual[part])) / scale))
    return worst


# Numbers that feed decisions (which solution, which alternative, subdivide or not) are rounded
# far below any physical scale: numpy's vectorised sums can differ in the last bit with memory
# alignment, and the planner must give the same plan for the same input on every run.


def _norm3(v: np.ndarray) -> np.ndarray:
    """|v| over the last axis (3), without a numpy reduction (see above)."""
    return np.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2])


def _unit_rows(v: np.ndarray) -> np.ndarray:
    return v / _norm3(v)[..., None]


def _matvec(matrix: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """matrix @ vector as a fixed-order sum of columns."""
    total = matrix[:, 0] * vector[0]
    for j in range(1, len(vector)):
        total = total + matrix[:, j] * vector[j]
    return total


def _pose_penalties(positions: np.ndarray, rig: DepmRig) -> np.ndarray:
    """One-sided penalties (m) of EPM positions (..., A, 3) against the inverse-magnetics
    constraints -> (..., P): keep-out, reach, own side per EPM, then the EPM-EPM distance."""
    limits = rig.limits
    rel = positions - rig.centre
    distance = _norm3(rel)  # (..., A)
    sides = np.array([rig.side(a) for a in range(len(rig.arms))])
    along = rel[..., 0] * sides[:, 0] + rel[..., 1] * sides[:, 1] + rel[..., 2] * sides[:, 2]
    terms = [
        np.maximum(0.0, limits.epm_keep_out_m + IM_MARGIN_M - distance),
        np.maximum(0.0, distance - MAX_DISTANCE_M),
        np.maximum(0.0, SIDE_MARGIN_M - along),
    ]
    count = positions.shape[-2]
    for a in range(count):
        for b in range(a + 1, count):
            gap = _norm3(positions[..., a, :] - positions[..., b, :])
            terms.append(np.maximum(0.0, limits.epm_min_distance_m + IM_MARGIN_M - gap)[..., None])
    return np.concatenate(terms, axis=-1)


def _im_seeds(rig: DepmRig) -> list[np.ndarray]:
    """Structured starting positions (A, 3): the magnets on their sides, level, raised, lowered,
    turned toward +-y."""
    seeds = []
    for elevation in (0.0, 0.6, -0.6):
        for azimuth in (0.0, 0.6, -0.6):
            rows = []
            for a in range(len(rig.arms)):
                side = rig.side(a)
                lateral = np.cross([0.0, 0.0, 1.0], side)
                direction = (np.cos(elevation) * (np.cos(azimuth) * side + np.sin(azimuth) * lateral)
                             + np.sin(elevation) * np.array([0.0, 0.0, 1.0]))
                rows.append(rig.centre + 0.30 * direction)
            seeds.append(np.array(rows))
    return seeds


def moments_for(U_target: np.ndarray, positions: np.ndarray, rig: DepmRig,
                previous: np.ndarray | None = None, refine: bool = True) -> np.ndarray:
    """Unit moment directions (A, 3) at fixed EPM positions (A, 3) for a desired U (8,) in SI.

    Eq. 21: the least-squares moments pinv([L; M]) U; each is then given the magnets' real |m|
    (its direction kept) and, with `refine`, the directions are adjusted by Levenberg-Marquardt so
    the U the real magnets make is as close as possible to the desired one (weighted by
    U_SCALE_SI), with a pull toward `previous` directions so the path does not flip; the
    refinement starts from the pseudo-inverse directions and from `previous`, the better kept.
    """
    positions = np.ascontiguousarray(positions, dtype=float)
    rel = rig.centre - positions
    r = np.sqrt(rel[:, 0] ** 2 + rel[:, 1] ** 2 + rel[:, 2] ** 2)
    A = np.empty((8, 3 * len(positions)))  # actuation_matrix's numbers, without its overhead
    _actuation_matrix(rig.centre, positions, r ** 3, r ** 4, A)  # numpy's powers (see there)
    weights = 1.0 / U_SCALE_SI
    Aw = A * weights[:, None]
    moments = np.linalg.lstsq(Aw, U_target * weights, rcond=None)[0].reshape(-1, 3)
    norms = _norm3(moments)
    fallback = previous if previous is not None else np.tile([0.0, 0.0, 1.0], (len(positions), 1))
    directions = np.where(norms[:, None] > 1e-12, moments / np.maximum(norms, 1e-300)[:, None],
                          fallback)
    directions = np.round(directions, 9)  # LAPACK's last bits must not steer what follows
    if not refine:
        return directions
    pull = 0.3 if previous is not None else 0.0  # turning a magnet right round costs like
    # 0.6 mT of error: the path does not flip (without `previous` its rows are zeros)
    target = U_target * weights
    toward = np.zeros_like(directions) if previous is None else np.asarray(previous, dtype=float)
    args = (np.ascontiguousarray(Aw), target, float(rig.moment_Am2), toward.reshape(-1), pull)
    start = directions
    if previous is not None:
        # Refine from whichever is better already: the pseudo-inverse directions or the previous
        # waypoint's (the latter keeps the path from flipping when the two are close in cost).
        if _direction_cost(*args, toward.reshape(-1)) <= _direction_cost(*args,
                                                                        directions.reshape(-1)):
            start = previous
    x = _direction_fit(*args, np.array(start, dtype=float).reshape(-1), 60, 1e-8)
    return np.round(_unit_rows(x.reshape(-1, 3)), 12)  # run-to-run identical (see above)


# The refinement of `moments_for`, compiled (the planner solves it at every waypoint of every
# alternative path). Unknowns x (3A,): each magnet's direction, unnormalised; residuals: the
# weighted U error Aw (|m| x / |x|) - target (8), |x_a| - 1 per magnet, and pull (x_a / |x_a| -
# previous_a) per magnet (zeros when pull is 0).


@njit(error_model="numpy")
def _direction_residuals(Aw, target, moment, previous, pull, x, r, jac):  # pragma: no cover
    """Residuals into r (8 + 4A,) and, with `jac` of 8 + 4A rows, their Jacobian (8 + 4A, 3A)."""
    n = x.shape[0]
    count = n // 3
    unit = np.empty(n)
    d_unit = np.empty((3, 3))
    for a in range(count):
        o = 3 * a
        norm = np.sqrt(x[o] * x[o] + x[o + 1] * x[o + 1] + x[o + 2] * x[o + 2])
        for i in range(3):
            unit[o + i] = x[o + i] / norm
        r[8 + a] = norm - 1.0
        for i in range(3):
            r[8 + count + o + i] = pull * (unit[o + i] - previous[o + i])
        if jac.shape[0] == 0:
            continue
        for i in range(3):  # d unit_i / d x_j = (delta_ij - u_i u_j) / |x|
            for j in range(3):
                d_unit[i, j] = ((1.0 if i == j else 0.0) - unit[o + i] * unit[o + j]) / norm
        for j in range(3):
            jac[8 + a, o + j] = unit[o + j]
            for i in range(3):
                jac[8 + count + o + i, o + j] = pull * d_unit[i, j]
            for k in range(8):
                total = 0.0
                for i in range(3):
                    total += Aw[k, o + i] * d_unit[i, j]
                jac[k, o + j] = moment * total
    for k in range(8):
        total = 0.0
        for j in range(n):
            total += Aw[k, j] * (unit[j] * moment)
        r[k] = total - target[k]


@njit(error_model="numpy")
def _direction_cost(Aw, target, moment, previous, pull, x):  # pragma: no cover - compiled
    """|residuals|^2 of directions x (3A,)."""
    r = np.empty(8 + 4 * (x.shape[0] // 3))
    _direction_residuals(Aw, target, moment, previous, pull, x, r, np.empty((0, 0)))
    return np.sum(r * r)


@njit(error_model="numpy")
def _normal_equations(jac, r, normal, gradient):  # pragma: no cover - compiled
    """J^T J into normal (n, n) and J^T r into gradient (n,) for J (m, n), r (m,)."""
    rows, n = jac.shape
    for i in range(n):
        total = 0.0
        for k in range(rows):
            total += jac[k, i] * r[k]
        gradient[i] = total
        for j in range(i + 1):
            total = 0.0
            for k in range(rows):
                total += jac[k, i] * jac[k, j]
            normal[i, j] = normal[j, i] = total


@njit(error_model="numpy")
def _damped_step(normal, gradient, damping):  # pragma: no cover - compiled
    """The Levenberg-Marquardt step with Marquardt's scaling: (N + damping (diag N + 1e-12)) s =
    -g."""
    system = normal.copy()
    for i in range(gradient.shape[0]):
        system[i, i] += damping * (normal[i, i] + 1e-12)
    return cholesky_solve(system, -gradient)


@njit(error_model="numpy")
def _direction_fit(Aw, target, moment, previous, pull, x0, max_iterations,
                   tolerance):  # pragma: no cover - compiled
    """Levenberg-Marquardt (Marquardt's diagonal scaling) from x0 (3A,): the fitted x (3A,).

    Our own rather than scipy's MINPACK: its results can differ in the last bits with the memory
    layout of the Jacobian, and from a far start that picks a different solution from run to run.
    Stops when a step improves the cost by less than `tolerance` relative or moves x by < 1e-13.
    """
    n = x0.shape[0]
    rows = 8 + 4 * (n // 3)
    empty = np.empty((0, 0))
    x = x0.copy()
    r, r_trial = np.empty(rows), np.empty(rows)
    jac = np.zeros((rows, n))
    normal, gradient = np.empty((n, n)), np.empty(n)
    _direction_residuals(Aw, target, moment, previous, pull, x, r, empty)
    cost = np.sum(r * r)
    damping = 1e-3
    for _ in range(max_iterations):
        _direction_residuals(Aw, target, moment, previous, pull, x, r, jac)
        _normal_equations(jac, r, normal, gradient)
        while True:
            step = _damped_step(normal, gradient, damping)
            trial = x + step
            _direction_residuals(Aw, target, moment, previous, pull, trial, r_trial, empty)
            cost_trial = np.sum(r_trial * r_trial)
            if cost_trial < cost:
                break
            damping *= 4.0
            if damping > 1e12:
                return x
        improvement = cost - cost_trial
        x, cost = trial, cost_trial
        damping = max(damping / 3.0, 1e-12)
        if improvement <= tolerance * cost or np.max(np.abs(step)) < 1e-13 or cost < 1e-30:
            break
    return x


# Inverse magnetics, compiled: unknowns x (6A,) = the EPM centres (A, 3) then their moment
# directions, unnormalised (A, 3); residuals (8 + 4A + A(A-1)/2,): the weighted U error, the
# one-sided penalties of `_pose_penalties` (in its order) times PENALTY_WEIGHT, |direction| - 1.

PENALTY_WEIGHT = 1e3  # 1 mm of constraint violation weighs like 1 mT of field error
FD_STEP = 1e-7  # forward-difference step of the Jacobian (m; unitless for directions)


@njit(error_model="numpy")
def _dipoles_U(centre, positions, moments, U):  # pragma: no cover - compiled
    """U (8,) in T and T/m at `centre` (3,) of dipoles (A, 3) with moments (A, 3): the sums of
    `rigctl.physics.magnetics._dipole_kernel`, term by term, magnets added in order."""
    c = MU0 / (4.0 * np.pi)
    U[:] = 0.0
    for a in range(positions.shape[0]):
        x, y, z = centre[0] - positions[a, 0], centre[1] - positions[a, 1], centre[2] - positions[a, 2]
        mx, my, mz = moments[a, 0], moments[a, 1], moments[a, 2]
        r2 = x * x + y * y + z * z
        inv_r2 = 1.0 / r2 if r2 > 0 else np.nan
        inv_r = np.sqrt(inv_r2)
        inv_r3 = inv_r * inv_r2
        inv_r5 = inv_r3 * inv_r2
        m_dot = mx * x + my * y + mz * z
        rel, mom = (x, y, z), (mx, my, mz)
        for i in range(3):
            U[i] += c * (3.0 * m_dot * rel[i] * inv_r5 - mom[i] * inv_r3)
        g = 3.0 * c * inv_r5
        for k in range(5):  # the terms of GRADIENT_TERMS: (0, 0), (0, 1), (0, 2), (1, 1), (1, 2)
            i, j = (0, 0, 0, 1, 1)[k], (0, 1, 2, 1, 2)[k]
            value = rel[i] * mom[j] + mom[i] * rel[j] - 5.0 * m_dot * rel[i] * rel[j] * inv_r2
            if i == j:
                value = value + m_dot
            U[3 + k] += g * value


@njit(error_model="numpy")
def _actuation_matrix(point, centres, r3, r4, A):  # pragma: no cover - compiled
    """[L; M] (8, 3A) at `point` (3,) for magnets at `centres` (A, 3) into A:
    `rigctl.physics.magnetics.actuation_matrix`, operation for operation, to the last bit. The
    distances' cubes and fourth powers r3, r4 (A,) come from numpy: its `**` is its own SIMD
    power, which neither libm's pow nor products match in the last bit."""
    c_field = MU0 / (4.0 * np.pi)
    for k in range(centres.shape[0]):
        x, y, z = point[0] - centres[k, 0], point[1] - centres[k, 1], point[2] - centres[k, 2]
        r = np.sqrt(x ** 2 + y ** 2 + z ** 2)
        r_hat = (x / r, y / r, z / r)
        c = 3.0 * MU0 / (4.0 * np.pi) / r4[k]
        for i in range(3):
            for j in range(3):
                A[i, 3 * k + j] = c_field * (3.0 * (r_hat[i] * r_hat[j]) - (1.0 if i == j else 0.0)) / r3[k]
        for row in range(5):  # the terms of GRADIENT_TERMS: (0, 0), (0, 1), (0, 2), (1, 1), (1, 2)
            i, j = (0, 0, 0, 1, 1)[row], (0, 1, 2, 1, 2)[row]
            factor = (1.0 if i == j else 0.0) - 5.0 * r_hat[i] * r_hat[j]
            for m in range(3):
                term = factor * r_hat[m] + (1.0 if m == i else 0.0) * r_hat[j]
                term = term + r_hat[i] * (1.0 if m == j else 0.0)
                A[3 + row, 3 * k + m] = c * term


@njit(error_model="numpy")
def _pose_residuals(centre, target, weights, moment, sides, keep_out_m, reach_m, side_margin_m,
                    min_gap_m, x, r):  # pragma: no cover - compiled
    """The residuals of inverse magnetics at x (6A,) into r."""
    count = sides.shape[0]
    positions = x[: 3 * count].reshape((count, 3))
    dirs = x[3 * count:].reshape((count, 3))
    moments = np.empty((count, 3))
    penalties = 8
    norms_at = 8 + 3 * count + count * (count - 1) // 2
    for a in range(count):
        norm = np.sqrt(dirs[a, 0] * dirs[a, 0] + dirs[a, 1] * dirs[a, 1] + dirs[a, 2] * dirs[a, 2])
        for k in range(3):
            moments[a, k] = dirs[a, k] / norm * moment
        r[norms_at + a] = norm - 1.0
        rx, ry, rz = (positions[a, 0] - centre[0], positions[a, 1] - centre[1],
                      positions[a, 2] - centre[2])
        distance = np.sqrt(rx * rx + ry * ry + rz * rz)
        along = rx * sides[a, 0] + ry * sides[a, 1] + rz * sides[a, 2]
        r[penalties + a] = PENALTY_WEIGHT * max(0.0, keep_out_m - distance)
        r[penalties + count + a] = PENALTY_WEIGHT * max(0.0, distance - reach_m)
        r[penalties + 2 * count + a] = PENALTY_WEIGHT * max(0.0, side_margin_m - along)
    pair = penalties + 3 * count
    for a in range(count):
        for b in range(a + 1, count):
            dx, dy, dz = (positions[a, 0] - positions[b, 0], positions[a, 1] - positions[b, 1],
                          positions[a, 2] - positions[b, 2])
            gap = np.sqrt(dx * dx + dy * dy + dz * dz)
            r[pair] = PENALTY_WEIGHT * max(0.0, min_gap_m - gap)
            pair += 1
    U = np.empty(8)
    _dipoles_U(centre, positions, moments, U)
    for k in range(8):
        r[k] = (U[k] - target[k]) * weights[k]


@njit(error_model="numpy")
def _pose_fit(centre, target, weights, moment, sides, keep_out_m, reach_m, side_margin_m,
              min_gap_m, x0, max_iterations, tolerance):  # pragma: no cover - compiled
    """Levenberg-Marquardt (Marquardt's diagonal scaling) of inverse magnetics from x0 (6A,), on
    a forward-difference Jacobian: the fitted x. Stops when a step improves the cost by less than
    `tolerance` relative or moves x by < 1e-13 (the loop of `_direction_fit`)."""
    n = x0.shape[0]
    count = sides.shape[0]
    rows = 8 + 4 * count + count * (count - 1) // 2
    x = x0.copy()
    r, r_trial, r_step = np.empty(rows), np.empty(rows), np.empty(rows)
    jac = np.empty((rows, n))
    normal, gradient = np.empty((n, n)), np.empty(n)
    problem = (centre, target, weights, moment, sides, keep_out_m, reach_m, side_margin_m,
               min_gap_m)
    _pose_residuals(*problem, x, r)
    cost = np.sum(r * r)
    damping = 1e-3
    for _ in range(max_iterations):
        for j in range(n):
            shifted = x.copy()
            shifted[j] = x[j] + FD_STEP
            _pose_residuals(*problem, shifted, r_step)
            for i in range(rows):
                jac[i, j] = (r_step[i] - r[i]) / FD_STEP
        _normal_equations(jac, r, normal, gradient)
        while True:
            step = _damped_step(normal, gradient, damping)
            trial = x + step
            _pose_residuals(*problem, trial, r_trial)
            cost_trial = np.sum(r_trial * r_trial)
            if cost_trial < cost:
                break
            damping *= 4.0
            if damping > 1e12:
                return x
        improvement = cost - cost_trial
        x, cost = trial, cost_trial
        r, r_trial = r_trial, r
        damping = max(damping / 3.0, 1e-12)
        if improvement <= tolerance * cost or np.max(np.abs(step)) < 1e-13 or cost < 1e-30:
            break
    return x


def inverse_magnetics(U_target: ArrayLike, rig: DepmRig, **options) -> list[EpmPoses]:
    """EPM poses that make U_target (8,) in T and T/m at the centre: every distinct solution found
    from the starting poses (see `inverse_magnetics_solutions`), in the order found (the current
    poses' neighbourhood first)."""
    return list(inverse_magnetics_solutions(U_target, rig, **options))


def inverse_magnetics_solutions(
    U_target: ArrayLike,
    rig: DepmRig,
    *,
    start_positions: np.ndarray | None = None,
    start_directions: np.ndarray | None = None,
    tolerance: float = 1e-4,
    max_starts: int = 10,
) -> Iterator[EpmPoses]:
    """EPM poses that make U_target (8,) in T and T/m at the centre, yielded as found.

    Unknowns: each EPM's centre and moment direction (|m| fixed to `rig.moment_Am2`); residuals:
    the weighted U error plus one-sided penalties that keep every EPM outside the keep-out sphere
    (with its radius and a margin), within reach (<= MAX_DISTANCE_M), on its own arm's side, and
    the EPMs apart. Solved by Levenberg-Marquardt (`_pose_fit`) from the current poses and
    from structured starting poses, directions from eq. 21. Yields every distinct solution that
    meets all constraints and makes U within `tolerance` (relative to the largest requested entry
    of its kind), the current poses' neighbourhood first; the caller takes the first the arms
    reach, so later starts are only tried when needed.
    """
    target = np.asarray(U_target, dtype=float)
    count = len(rig.arms)
    limits = rig.limits
    problem = (np.asarray(rig.centre, dtype=float), target, 1.0 / U_SCALE_SI, float(rig.moment_Am2),
               np.array([rig.side(a) for a in range(count)]), limits.epm_keep_out_m + IM_MARGIN_M,
               MAX_DISTANCE_M, SIDE_MARGIN_M, limits.epm_min_distance_m + IM_MARGIN_M)

    def starts():  # lazily: most sequences need only the first one or two
        if start_positions is not None:
            dirs = start_directions if start_directions is not None else moments_for(
                target, start_positions, rig)
            yield np.asarray(start_positions, float), np.asarray(dirs, float)
        for seed in _im_seeds(rig):
            yield seed, moments_for(target, seed, rig)

    found: list[EpmPoses] = []
    for positions, dirs in itertools.islice(starts(), max_starts):
        x0 = np.round(np.concatenate([positions.reshape(-1), dirs.reshape(-1)]), 10)
        x = _pose_fit(*problem, x0, 150, 1e-12)
        positions = np.round(x[: 3 * count].reshape(count, 3), 10)
        unit = np.round(_unit_rows(x[3 * count:].reshape(count, 3)), 12)
        if np.any(_pose_penalties(positions, rig) > 1e-9):
            continue
        U = field_vector(rig.centre, positions, unit * rig.moment_Am2)
        pose = EpmPoses(positions, unit, U, U - target)
        if pose.relative_error(target) > tolerance:
            continue
        if any(np.allclose(pose.positions, s.positions, atol=1e-4) for s in found):
            continue
        found.append(pose)
        yield pose


# ---------------------------------------------------------------- operational and magnetic paths


def operational_paths(
    start_m: np.ndarray,
    end_m: np.ndarray,
    rig: DepmRig,
    arm: int,
    waypoints: int,
    k: int,
    bulge_m: float = DEFAULT_BULGE_M,
) -> np.ndarray:
    """k candidate EPM paths (k, N + 1, 3) from `start_m` to `end_m` for arm `arm` (eq. 11-12).

    The base path is linear in cylindrical coordinates (theta, rho, z) about the vertical axis
    through the centre, theta measured from the arm's own side so the path never crosses to the
    other arm's half. Alternative j moves every waypoint away from the centre by
    Delta_j sin(pi s), Delta_j = j bulge_m / (k - 1): the end points stay, the middle moves out,
    where the field is weaker. Any point closer to the centre than the EPM keep-out distance
    (+ margin) is pushed out radially to it.
    """
    centre = rig.centre
    side = rig.side(arm)
    lateral = np.cross([0.0, 0.0, 1.0], side)
    s = np.linspace(0.0, 1.0, waypoints + 1)

    def cylindrical(point):
        rel = point - centre
        u, v = rel @ side, rel @ lateral
        return np.arctan2(v, u), np.hypot(u, v), rel[2]

    theta0, rho0, z0 = cylindrical(np.asarray(start_m, float))
    theta1, rho1, z1 = cylindrical(np.asarray(end_m, float))
    theta = theta0 + (theta1 - theta0) * s
    rho = rho0 + (rho1 - rho0) * s
    z = z0 + (z1 - z0) * s
    base = (rho * np.cos(theta))[:, None] * side + (rho * np.sin(theta))[:, None] * lateral
    base = base + z[:, None] * np.array([0.0, 0.0, 1.0])
    distance = np.linalg.norm(base, axis=1)
    direction = base / np.maximum(distance, 1e-12)[:, None]
    floor = rig.limits.epm_keep_out_m + IM_MARGIN_M
    deltas = np.linspace(0.0, bulge_m, k) if k > 1 else np.zeros(1)
    paths = []
    for delta in deltas:
        radius = np.maximum(distance + delta * np.sin(np.pi * s), floor)
        paths.append(centre + radius[:, None] * direction)
    paths = np.array(paths)
    paths[:, 0], paths[:, -1] = start_m, end_m
    return paths


def magnetic_path(U_start: np.ndarray, U_end: np.ndarray, waypoints: int) -> np.ndarray:
    """The desired U at each waypoint (N + 1, 8): eq. 13-14 as read here.

    Eq. 14 prints U_s / (1 + e^{2.1 (s - n/2)}) for n <= N/2 and U_e / (1 + e^{-2.1 (s - n/2)})
    for n > N/2, with U_s at n = 0 and U_e at n = N. Taken literally (s = n) the centre n/2 would
    move with the point itself, and with centre N/2 for both halves the path would jump from
    0.5 U_s to 0.89 U_e at the middle. The text says what is meant: |U| "reduces, then increases,
    both sigmoidally", so U_s fades out over the first half and U_e fades in over the second.
    We therefore centre each sigmoid on its own half (N/4 and 3N/4), keep the seed's steepness of
    2.1 per waypoint for its 10-waypoint paths (scaled by 10/N so the shape along the path does
    not depend on N), and keep the exact end values. Only the start and end components ever
    appear in the path, so by construction it asks for no cross-activation at all.
    """
    n = np.arange(waypoints + 1, dtype=float)
    slope = SIGMOID_SLOPE * SIGMOID_REFERENCE_WAYPOINTS / waypoints
    fall = 1.0 / (1.0 + np.exp(slope * (n - waypoints / 4.0)))
    rise = 1.0 / (1.0 + np.exp(-slope * (n - 3.0 * waypoints / 4.0)))
    first = n <= waypoints / 2.0
    path = np.where(first[:, None], fall[:, None] * U_start, rise[:, None] * U_end)
    path[0], path[-1] = U_start, U_end
    return path


# ---------------------------------------------------------------- the planner


@dataclass
class PlanStats:
    """Timing of one planning run (s): per transition, and the inverse-magnetics part of it."""

    transition_s: list[float] = field(default_factory=list)
    inverse_magnetics_s: list[float] = field(default_factory=list)
    transition_cpu_s: list[float] = field(default_factory=list)
    """Process CPU time per transition: what a machine busy with other work inflates least."""
    refused_s: list[float] = field(default_factory=list)
    refused_cpu_s: list[float] = field(default_factory=list)
    """Wall and CPU time (s) spent on a transition that ended in a PlanError (at most one per
    run: the planner stops there): how long a user waits to hear that a request cannot be made."""


def _keep_out(rig: DepmRig) -> tuple[np.ndarray, float]:
    return rig.centre, rig.limits.keep_out_radius_m + IK_KEEP_OUT_MARGIN_M


def home_joints(rig: DepmRig) -> np.ndarray:
    """A parked start (A, 7): each EPM HOME_DISTANCE_M out on its own side, the moments turned
    so U at the centre is as small as those positions allow (eq. 21 with U = 0 at |m|)."""
    positions = np.array([rig.centre + HOME_DISTANCE_M * rig.side(a) for a in range(len(rig.arms))])
    directions = moments_for(np.zeros(8), positions, rig,
                             previous=np.tile([0.0, 0.0, 1.0], (len(rig.arms), 1)))
    seed = np.array([0.0, 0.8, 0.0, -1.5, 0.0, 0.8, 0.0])
    return np.array([
        arm.solve_or_raise(positions[a], directions[a], seed, keep_out=_keep_out(rig))
        for a, arm in enumerate(rig.arms)
    ])


def warm_up() -> float:
    """Compile (or load from numba's cache) the planner's kernels (inverse kinematics, the moment
    refinement, inverse magnetics, the transitions' breach check) if this process has not yet;
    returns the seconds it took. The first plan of a process would otherwise pay it in its first
    transition (compiling: ~15 s of CPU, once per installation; loading: well under a second)."""
    started = time.perf_counter()
    _load_kernels()
    return time.perf_counter() - started


@functools.cache
def _load_kernels() -> None:
    rig = default_rig()
    home = home_joints(rig)  # inverse kinematics and the moment refinement
    _first_breach(rig, np.stack([home, home], axis=1), np.array([1.0]))
    next(inverse_magnetics_solutions(np.array([1e-3] + [0.0] * 7), rig, max_starts=1), None)


def _reachable_ends(
    target: np.ndarray, rig: DepmRig, q_now: np.ndarray, positions: np.ndarray,
    directions: np.ndarray, name: str,
) -> Iterator[tuple[EpmPoses, np.ndarray]]:
    """Inverse-magnetics solutions both arms reach from q_now (with their joints), as found."""
    tried = reached = 0
    for pose in inverse_magnetics_solutions(
        target, rig, start_positions=positions, start_directions=directions
    ):
        tried += 1
        joints = []
        for a, arm in enumerate(rig.arms):
            result = arm.solve(pose.positions[a], pose.directions[a], q_now[a], keep_out=_keep_out(rig))
            if not result.ok:
                break
            joints.append(result.q)
        else:
            reached += 1
            yield pose, np.array(joints)
    if reached:
        return
    if not tried:
        raise PlanError(
            f"sequence component {name!r}: no EPM poses make the requested U within the rig's "
            "constraints (keep-out sphere, EPM-EPM distance, reach); lower the request"
        )
    raise PlanError(
        f"sequence component {name!r}: the {tried} EPM pose(s) that make it are out of "
        "the arms' reach; move the arms' bases or lower the request"
    )


MAX_JOINT_STEP_RAD = np.radians(20.0)
"""Largest joint change allowed between consecutive knots; bigger steps are subdivided."""
MAX_SUBDIVISIONS = 4


def _blend(poses_a, poses_b, fraction):
    """EPM poses (positions, directions) part-way from a to b (directions renormalised)."""
    positions = (1 - fraction) * poses_a[0] + fraction * poses_b[0]
    directions = _unit_rows((1 - fraction) * poses_a[1] + fraction * poses_b[1] + 1e-12)
    return positions, directions


def _reach(rig: DepmRig, previous, target, q_previous: np.ndarray, depth: int = 0):
    """Joint knots that carry both EPMs from `previous` to `target` poses ((A, 3), (A, 3)):
    [(positions, directions, q (A, 7)), ...] ending at `target`, or None.

    Each solve starts from the previous knot's joints. If an arm cannot follow (no solution, or
    a joint would have to turn more than MAX_JOINT_STEP_RAD), the step is split at the blended
    pose, up to MAX_SUBDIVISIONS times: the arm then follows the path between waypoints too,
    instead of taking a different elbow or wrist branch.
    """
    solved = []
    for a, arm in enumerate(rig.arms):
        result = arm.solve(target[0][a], target[1][a], q_previous[a], keep_out=_keep_out(rig))
        if not result.ok or np.max(np.abs(result.q - q_previous[a])) > MAX_JOINT_STEP_RAD:
            break
        solved.append(result.q)
    else:
        return [(target[0], target[1], np.array(solved))]
    if depth >= MAX_SUBDIVISIONS:
        return None
    middle = _blend(previous, target, 0.5)
    first = _reach(rig, previous, middle, q_previous, depth + 1)
    if first is None:
        return None
    second = _reach(rig, middle, target, first[-1][2], depth + 1)
    return None if second is None else first + second


def _enough(jumps: int, max_jumps: int | None) -> None:
    if max_jumps is not None and jumps >= max_jumps:
        raise PlanError(f"{jumps} configuration change(s): no better than an end pose tried before")


def _hybrid_transition(
    rig: DepmRig, q_now: np.ndarray, U_start: np.ndarray, end: EpmPoses, q_end: np.ndarray,
    waypoints: int, k: int, bulge_m: float, max_jumps: int | None = None,
) -> tuple[list, int]:
    """The knots of one planned transition (Sec. 3.1-3.2), [(EPM positions (A, 3), moment
    directions (A, 3), joints (A, 7)), ...], at least N + 1 of them (steps that the arms cannot
    take in one go are subdivided, see `_reach`), and how many times the arms had to change
    configuration on the way (0 when they follow the path throughout). PlanError as soon as that
    reaches `max_jumps` (another end pose already did as well)."""
    count = len(rig.arms)
    start_positions, start_directions = rig.epm_poses(q_now)
    paths = np.array([
        operational_paths(start_positions[a], end.positions[a], rig, a, waypoints, k, bulge_m)
        for a in range(count)
    ])  # (A, k, N + 1, 3)
    desired = magnetic_path(U_start, end.U, waypoints)
    weights = 1.0 / U_SCALE_SI
    knots = [(start_positions, start_directions, q_now)]
    jumps = 0
    min_gap = rig.limits.epm_min_distance_m + IM_MARGIN_M
    for n in range(1, waypoints):
        previous_positions, previous_dirs, q_previous = knots[-1]
        candidates = []
        for j in range(paths.shape[1]):
            positions = paths[:, j, n]
            gaps = [np.linalg.norm(positions[a] - positions[b])
                    for a in range(count) for b in range(a + 1, count)]
            if min(gaps) < min_gap:
                continue
            dirs = moments_for(desired[n], positions, rig, previous=previous_dirs)
            U = np.empty(8)  # field_vector's numbers to the last bit, without its overhead
            _dipoles_U(rig.centre, positions, dirs * rig.moment_Am2, U)
            # Eq. 22, plus (ours) a small cost for hopping between alternatives, so consecutive
            # waypoints do not jump radially for a negligible magnetic gain.
            hop = float(np.sum(np.linalg.norm(positions - previous_positions, axis=1)))
            cost = float(np.sum(np.abs((desired[n] - U) * weights))) + HOP_COST_PER_M * hop
            candidates.append((cost, j, positions, dirs))
        if not candidates:
            raise PlanError(
                f"waypoint {n}: every alternative path brings the EPMs closer than "
                f"{rig.limits.epm_min_distance_m * 1e3:.0f} mm; raise --k or the bulge"
            )
        candidates.sort(key=lambda c: c[0])  # eq. 22: the alternative nearest the magnetic path
        for _, j, positions, dirs in candidates:
            added = _reach(rig, knots[-1][:2], (positions, dirs), q_previous)
            if added is not None:
                knots.extend(added)
                break
        else:
            # No alternative can be followed continuously: the arms must change branch (elbow,
            # wrist). Take the best alternative any arm configuration reaches. Either way this
            # counts as one change: give up first if that is already too many.
            _enough(jumps + 1, max_jumps)
            fraction = n / waypoints
            for _, j, positions, dirs in candidates:
                solved = []
                for a, arm in enumerate(rig.arms):
                    seeds = (q_previous[a], (1 - fraction) * q_now[a] + fraction * q_end[a], q_end[a])
                    for seed in seeds:
                        result = arm.solve(positions[a], dirs[a], seed, keep_out=_keep_out(rig))
                        if result.ok:
                            solved.append(result.q)
                            break
                    else:
                        break
                if len(solved) == count:
                    log.debug("waypoint %d: the arms change configuration", n)
                    jumps += 1
                    _enough(jumps, max_jumps)
                    knots.append((positions, dirs, np.array(solved)))
                    break
            else:
                # Nothing here is reachable (the path passes beyond the arms' reach): leave the
                # waypoint out; the next reachable one is approached from the last knot.
                log.debug("waypoint %d: no alternative is reachable by both arms; skipped", n)
                jumps += 1
                _enough(jumps, max_jumps)
    added = _reach(rig, knots[-1][:2], (end.positions, end.directions), knots[-1][2])
    if added is None:
        # The end pose is reachable (checked by `_reachable_ends`), only not smoothly from here:
        # go there directly; the dense safety check of the whole plan has the last word.
        added = [(end.positions, end.directions, q_end)]
        jumps += 1
    knots.extend(added)
    return knots, jumps


def _padded_curves(q: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, list[PchipInterpolator]]:
    """A transition's knot times (M,) from 0 and its PCHIP per arm, as the whole plan has them:
    the arms rest before and after every transition (a hold, `MIN_REST_S` at least, or the
    start), so padding with a rest segment on each side gives exactly the plan's curves there."""
    times = np.concatenate([[0.0], np.cumsum(h)])
    knots = np.concatenate([[-1.0], times, [times[-1] + 1.0]])
    values = np.concatenate([q[:, :1], q, q[:, -1:]], axis=1)
    return times, [PchipInterpolator(knots, values[a], axis=0) for a in range(len(q))]


def _peaks(curve: PchipInterpolator) -> tuple[np.ndarray, np.ndarray]:
    """Exact peak |speed| and |acceleration| (pieces, 7) of every piece of a PCHIP: on a piece
    c0 s^3 + c1 s^2 + c2 s + c3 the speed is quadratic (peak at an end or at s = -c1 / 3 c0) and
    the acceleration linear (peak at an end)."""
    c = curve.c  # (4, pieces, 7)
    h = np.diff(curve.x)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        s_star = np.where(c[0] != 0, -c[1] / (3.0 * c[0]), 0.0)
    s_star = np.clip(s_star, 0.0, h)

    def speed(s):
        return np.abs(3.0 * c[0] * s * s + 2.0 * c[1] * s + c[2])

    speeds = np.maximum(np.maximum(speed(0.0), speed(h)), speed(s_star))
    accels = np.maximum(np.abs(2.0 * c[1]), np.abs(6.0 * c[0] * h + 2.0 * c[1]))
    return speeds, accels


def _segment_times(q: np.ndarray, rig: DepmRig) -> np.ndarray:
    """Durations (N,) of the segments of a transition q (A, N + 1, 7), at rest at both ends, so
    that the PCHIP through them stays within SPEED_MARGIN x the allowed joint speeds and
    accelerations (stretching a piece's time by c divides its speeds by c and its accelerations
    by c^2): first each piece is stretched by what it alone needs (TIMING_PASSES times, as the
    pieces' neighbours change the slopes at the knots), then the whole transition by what is
    still missing, so the result respects both limits exactly."""
    speed_caps = np.array([rig.limits.speed_fraction * arm.model.max_speed for arm in rig.arms])
    accel_caps = np.array([rig.limits.accel_fraction * arm.model.max_accel for arm in rig.arms])
    steps = np.abs(np.diff(q, axis=1))  # (A, N, 7)
    h = np.max(steps / speed_caps[:, None, :], axis=(0, 2))
    h = np.maximum(h, 1e-3)

    def need(h: np.ndarray) -> np.ndarray:
        """Per piece (N,): the stretch that brings it within both limits (<= 1: within)."""
        _, curves = _padded_curves(q, h)
        worst = np.zeros(len(h))
        for a, curve in enumerate(curves):
            speeds, accels = _peaks(curve)
            speeds, accels = speeds[1:-1], accels[1:-1]  # the rest pieces do not move
            worst = np.maximum(worst, np.maximum(
                np.max(speeds / speed_caps[a], axis=1) / SPEED_MARGIN,
                np.sqrt(np.max(accels / accel_caps[a], axis=1) / SPEED_MARGIN)))
        return worst

    for _ in range(TIMING_PASSES):
        stretch = need(h)
        if np.all(stretch <= 1.0):
            break
        h = h * np.maximum(stretch, 1.0)
    scale = float(np.max(need(h)))
    return h * scale if scale > 0 else h


TIMING_PASSES = 6


MIN_REST_S = 0.2
"""The arms rest this long at an end pose whose hold is 0, so every transition starts and ends at
rest: it is then timed and checked on its own, exactly as the whole plan will run it."""
CHECK_MARGIN_M = 0.002
"""The planner checks its transitions against the keep-out sphere and the EPM-EPM distance
enlarged by this, sampled four times as densely as `check`, so `check` never refuses its plans."""
MAX_REPAIRS = 16


def _first_breach(rig: DepmRig, q: np.ndarray, h: np.ndarray) -> float | None:
    """The first time (s from the transition's start) its curves come closer than CHECK_MARGIN_M
    to a positional constraint or leave a joint range, or None: `violations`' tests of those
    (its earliest breach), compiled (`_first_breach_index`), as repairing a transition runs it
    again and again; `plan_violations` still checks the whole plan at the end."""
    limits = rig.limits
    times, curves = _padded_curves(q, h)
    t = np.union1d(np.arange(0.0, times[-1], limits.check_step_s / 4.0), times)
    arms = rig.arms
    index = _first_breach_index(
        np.ascontiguousarray([curve(t) for curve in curves]), np.array([arm.base for arm in arms]),
        np.array([arm._dh_table for arm in arms]), np.array([arm.model.tool_offset_m for arm in arms]),
        np.array([arm.model.lower_rad for arm in arms]), np.array([arm.model.upper_rad for arm in arms]),
        np.array([arm._capsule_links for arm in arms]), np.array([arm._capsule_radii for arm in arms]),
        np.asarray(limits.centre_m, dtype=float), limits.keep_out_radius_m + CHECK_MARGIN_M,
        limits.epm_radius_m, limits.epm_min_distance_m + CHECK_MARGIN_M)
    return None if index < 0 else float(t[index])


@njit(error_model="numpy")
def _first_breach_index(q, bases, dh, tool_offsets, lower, upper, links, radii, centre, keep_out_m,
                        epm_radius_m, min_gap_m):  # pragma: no cover - compiled
    """The first sample of q (A, T, 7) where an EPM's bounding sphere or a link capsule is
    inside the keep-out sphere, a joint is out of its range (1e-9 rad slack) or two EPMs are
    closer than min_gap_m (the tests of `rigctl.plans.depm_safety.violations`), or -1."""
    count, samples = q.shape[0], q.shape[1]
    frames = np.empty((9, 4, 4))
    epms = np.empty((count, 3))
    for s in range(samples):
        for a in range(count):
            for j in range(7):
                if q[a, s, j] < lower[a, j] - 1e-9 or q[a, s, j] > upper[a, j] + 1e-9:
                    return s
            frames_kernel(bases[a], dh[a], tool_offsets[a], q[a, s], frames)
            for k in range(3):
                epms[a, k] = frames[8, k, 3]
            dx, dy, dz = epms[a, 0] - centre[0], epms[a, 1] - centre[1], epms[a, 2] - centre[2]
            if np.sqrt(dx * dx + dy * dy + dz * dz) - epm_radius_m < keep_out_m:
                return s
            for link in range(links.shape[1]):
                if _segment_clearance(frames, links[a, link, 0], links[a, link, 1],
                                      centre) - radii[a, link] < keep_out_m:
                    return s
        for a in range(count):
            for b in range(a + 1, count):
                dx, dy, dz = epms[a, 0] - epms[b, 0], epms[a, 1] - epms[b, 1], epms[a, 2] - epms[b, 2]
                if np.sqrt(dx * dx + dy * dy + dz * dz) < min_gap_m:
                    return s
    return -1


@njit(error_model="numpy")
def _segment_clearance(frames, first, second, centre):  # pragma: no cover - compiled
    """Distance from `centre` to the segment between two frame origins (as
    `depm_safety.segment_point_distance`)."""
    ab, ac = np.empty(3), np.empty(3)
    for k in range(3):
        ab[k] = frames[second, k, 3] - frames[first, k, 3]
        ac[k] = centre[k] - frames[first, k, 3]
    length2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2]
    t = (ac[0] * ab[0] + ac[1] * ab[1] + ac[2] * ab[2]) / length2 if length2 > 0 else 0.0
    t = min(max(t, 0.0), 1.0)
    total = 0.0
    for k in range(3):
        gap = frames[first, k, 3] + t * ab[k] - centre[k]
        total += gap * gap
    return np.sqrt(total)


LIFTS_M = (0.0, 0.05, 0.10, 0.15)


def _solve_both(rig: DepmRig, positions: np.ndarray, directions: np.ndarray,
                seed: np.ndarray) -> np.ndarray | None:
    solved = [arm.solve(positions[a], directions[a], seed[a], keep_out=_keep_out(rig))
              for a, arm in enumerate(rig.arms)]
    return np.array([r.q for r in solved]) if all(r.ok for r in solved) else None


def _middle_knot(rig: DepmRig, first: tuple, second: tuple) -> tuple | None:
    """A knot between two knots (positions, directions, joints): along a small joint step, the
    blended EPM pose solved from the first knot's joints (or from the joints' midpoint); across a
    configuration change (a step over MAX_JOINT_STEP_RAD, which blending would only push ahead),
    the joints' midpoint with its EPMs lifted away from the centre by LIFTS_M, the first lift whose
    two halves clear the constraints, else the first that solves. None if nothing solves."""
    q_a, q_b = first[2], second[2]
    q_mid = 0.5 * (q_a + q_b)
    if np.max(np.abs(q_b - q_a)) <= MAX_JOINT_STEP_RAD:
        positions, directions = _blend(first[:2], second[:2], 0.5)
        for seed in (q_a, q_mid):
            q = _solve_both(rig, positions, directions, seed)
            if q is not None:
                return positions, directions, q
        return None
    positions, directions = rig.epm_poses(q_mid[:, None, :])
    positions, directions = positions[:, 0], directions[:, 0]
    outward = _unit_rows(positions - rig.centre)
    fallback = None
    for lift in LIFTS_M:
        lifted = positions + lift * outward
        q = _solve_both(rig, lifted, directions, q_mid)
        if q is None:
            continue
        knot = (lifted, directions, q)
        local = np.stack([q_a, q, q_b], axis=1)
        if _first_breach(rig, local, _segment_times(local, rig)) is None:
            return knot
        fallback = fallback or knot
    return fallback


def _made_safe(rig: DepmRig, knots: list) -> tuple[np.ndarray, np.ndarray]:
    """Joints (A, M, 7) and segment durations (M - 1,) of a transition whose curves keep every
    positional constraint with a margin: PCHIP between two safe knots can still swing a link or
    an EPM inward (the more, the larger the joint step), so where the curves come too close a
    knot is added halfway, at the blended EPM pose solved by inverse kinematics with the keep-out
    penalty, until none do. PlanError if a knot itself is too close or MAX_REPAIRS do not do."""
    knots = list(knots)
    for _ in range(MAX_REPAIRS + 1):
        q = np.stack([k[2] for k in knots], axis=1)
        h = _segment_times(q, rig)
        breach = _first_breach(rig, q, h)
        if breach is None:
            return q, h
        times = np.concatenate([[0.0], np.cumsum(h)])
        i = int(np.clip(np.searchsorted(times, breach, side="right") - 1, 0, len(h) - 1))
        if np.min(np.abs(times - breach)) < 1e-9:
            raise PlanError(f"a knot of the transition is too close to a constraint at "
                            f"t = {breach:.3f} s of the transition")
        middle = _middle_knot(rig, knots[i], knots[i + 1])
        if middle is None:
            raise PlanError(f"the transition comes too close to a constraint at t = {breach:.3f} s "
                            "and no knot can be added there")
        knots.insert(i + 1, middle)
    raise PlanError(f"the transition still comes too close to a constraint after {MAX_REPAIRS} "
                    "added knots")


def _check_options(planner: str, waypoints: int, k: int) -> None:
    if planner not in ("hybrid", "agnostic"):
        raise PlanError(f"planner must be 'hybrid' or 'agnostic', got {planner!r}")
    if waypoints < 2:
        raise PlanError(f"--waypoints: need at least 2, got {waypoints}")
    if k < 1:
        raise PlanError(f"--k: need at least 1, got {k}")


def _controller_end(rig: DepmRig, end_poses: Sequence[tuple[np.ndarray, np.ndarray]],
                    end_joints: Sequence[np.ndarray] | None, i: int, q_now: np.ndarray) -> np.ndarray:
    """(A, 7) joints for component `i`'s commanded EPM poses as the arm's own controller finds
    them from where it stands, knowing nothing of the keep-out sphere or the magnets."""
    positions, directions = end_poses[i]
    taught = None if end_joints is None else end_joints[i]
    return np.array([
        _controller_joints(arm, positions[a], directions[a], q_now[a],
                           None if taught is None else taught[a])
        for a, arm in enumerate(rig.arms)
    ])


END_POSE_CANDIDATES = 5
"""End poses whose transitions are planned and scored (`Table1Tally`) before one is kept."""
SCORE_RATE_HZ = 50.0  # U samples per second of plan when a transition is scored (bench/depm.py's)
SCORE_FIELD_BAND_mT, SCORE_GRADIENT_BAND_mT_per_m = 0.5, 5.0  # "close to 0" after a fall (Table 1)
SCORE_FALL_DWELL_S = 0.5
SCORE_SETTLE_FRACTION = 0.25
OVERSHOOT_WEIGHT_PER_PCT = 1.0  # 1 % of over- or undershoot weighs like 1 mT of off-activation


@dataclass
class Table1Tally:
    """What Table 1 (seed 003 Sec. 4.2; docs/depm.md, "The metrics") holds against a plan so far,
    per U component (8,), from the model's U along its transitions and holds: the peak |u| and
    the sum and count of u^2 while the component is off (not requested, and not falling any
    more), and the largest overshoot (+) or undershoot (-), in % of the request, while it rises
    and while it falls. Fields in mT, gradients in mT/m. `score` sums the averages as Table 1
    gives them."""

    off_peak: np.ndarray = field(default_factory=lambda: np.zeros(8))
    off_sum_sq: np.ndarray = field(default_factory=lambda: np.zeros(8))
    off_count: np.ndarray = field(default_factory=lambda: np.zeros(8))
    rise_pct: np.ndarray = field(default_factory=lambda: np.zeros(8))
    fall_pct: np.ndarray = field(default_factory=lambda: np.zeros(8))

    def added(self, t_s: np.ndarray, U: np.ndarray, previous: np.ndarray, requested: np.ndarray,
              reached_s: float) -> "Table1Tally":
        """The tally with one more transition and its hold: U (T, 8) in mT and mT/m at times t_s
        (T,) from the transition's start; `previous` and `requested` (8,): the old and the new
        request (zero: not requested); the arms arrive at `reached_s`."""
        new = Table1Tally(*(x.copy() for x in (self.off_peak, self.off_sum_sq, self.off_count,
                                                self.rise_pct, self.fall_pct)))
        rising = t_s < reached_s + SCORE_SETTLE_FRACTION * (t_s[-1] - reached_s)
        for c in range(8):
            u, R, R_old = U[:, c], requested[c], previous[c]
            if abs(R) > 1e-9:  # rising (or staying on): past the request, or to the other sign
                new.rise_pct[c] = _worse(new.rise_pct[c], _overshoot_pct(u[rising], R))
                continue
            off = np.ones(len(t_s), dtype=bool)
            if abs(R_old) > 1e-9:  # falling, until |u| stays in the band of "close to 0"
                band = SCORE_FIELD_BAND_mT if c < 3 else SCORE_GRADIENT_BAND_mT_per_m
                end = _fall_end_index(t_s, u, band)
                new.fall_pct[c] = _worse(new.fall_pct[c], _overshoot_pct(u[:end], R_old))
                off[:end] = False
            if off.any():
                new.off_peak[c] = max(new.off_peak[c], float(np.max(np.abs(u[off]))))
                new.off_sum_sq[c] += float(np.sum(u[off] ** 2))
                new.off_count[c] += int(off.sum())
        return new

    def score(self) -> float:
        """Table 1's averages summed, lower is better: peak off-activation and sigma while off
        (fields in mT, gradients per 10 mT/m: eq. 22's 1 mT ~ 10 mT/m), and the overshoots
        rising and falling (OVERSHOOT_WEIGHT_PER_PCT per %)."""
        sigma = np.sqrt(self.off_sum_sq / np.maximum(self.off_count, 1))
        off = (np.mean(self.off_peak[:3]) + np.mean(sigma[:3])
               + (np.mean(self.off_peak[3:]) + np.mean(sigma[3:])) / 10.0)
        overshoot = np.mean(np.abs(self.rise_pct)) + np.mean(np.abs(self.fall_pct))
        return float(off + OVERSHOOT_WEIGHT_PER_PCT * overshoot)


def _overshoot_pct(values: np.ndarray, requested: float) -> float:
    """Seed 003 Sec. 4.2 (as `rigctl.rigs.depm.metrics`): how far the values pass the request
    (+ %) or go to the opposite sign (- %), the larger of the two, in % of the request."""
    if values.size == 0:
        return 0.0
    v = values * np.sign(requested) / abs(requested)
    over, under = max(float(v.max()) - 1.0, 0.0), min(float(v.min()), 0.0)
    return 100.0 * (under if -under > over else over)


def _worse(a: float, b: float) -> float:
    return a if abs(a) >= abs(b) else b


def _fall_end_index(t_s: np.ndarray, u: np.ndarray, band: float) -> int:
    """The first sample from which |u| stays within `band` for SCORE_FALL_DWELL_S (or to the
    end); len(u) if there is none."""
    outside = np.flatnonzero(np.abs(u) > band)
    if not outside.size:
        return 0
    for i in range(len(u)):
        if abs(u[i]) > band:
            continue
        later = outside[outside > i]
        if not later.size or t_s[later[0]] - t_s[i] >= SCORE_FALL_DWELL_S:
            return i
    return len(u)


def _transition_U(rig: DepmRig, q: np.ndarray, h: np.ndarray, hold_s: float
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """The model's U (T, 8) in mT and mT/m along a transition's curves (knots q (A, M, 7),
    durations h (M - 1,)) and its hold, sampled at SCORE_RATE_HZ from the transition's start, as
    the whole plan will have them (`_padded_curves`); with the sample times and the arrival time."""
    times, curves = _padded_curves(q, h)
    reached = float(times[-1])
    t = np.arange(0.0, reached + max(hold_s, MIN_REST_S) + 1e-9, 1.0 / SCORE_RATE_HZ)
    joints = np.stack([curve(np.minimum(t, reached)) for curve in curves])  # (A, T, 7)
    return t, rig.field_at_centre(joints) / U_TO_SI, reached


def _transitions(rig: DepmRig, q_now: np.ndarray, U_now: np.ndarray,
                 ends: Iterator[tuple[EpmPoses, np.ndarray]], waypoints: int, k: int, bulge_m: float,
                 component: SequenceComponent) -> list[tuple]:
    """The hybrid transitions from `q_now` (A, 7) to the first END_POSE_CANDIDATES end poses of
    `ends` (as `_reachable_ends` gives them) that the arms can follow, with the fewest
    configuration changes any of them needs (a change swings the magnets off the planned path; an
    end pose is dropped as soon as it needs more than the best so far): [(changes, knots
    (A, n, 7) rad, the n - 1 durations between them s, the model's U along the transition and
    its hold as `_transition_U` gives it), ...] in the order found."""
    found: list[tuple] = []
    for trial, (end, q_end) in enumerate(itertools.islice(ends, END_POSE_CANDIDATES)):
        fewest = min((f[0] for f in found), default=None)
        try:
            path, jumps = _hybrid_transition(rig, q_now, U_now, end, q_end, waypoints, k,
                                             bulge_m, None if fewest is None else fewest + 1)
            q, h = _made_safe(rig, path)
        except PlanError as err:
            log.debug("%s: end pose %d: %s", component.name, trial, err)
            continue
        log.debug("%s: end pose %d: %d configuration change(s)", component.name, trial, jumps)
        found.append((jumps, q, h, _transition_U(rig, q, h, component.hold_s)))
    if not found:
        raise PlanError(
            f"sequence component {component.name!r}: no path to any of its end poses "
            "keeps the EPMs apart and clear of the keep-out sphere; raise --k or change "
            "the sequence"
        )
    fewest = min(f[0] for f in found)
    return [f for f in found if f[0] == fewest]


BEAM_WIDTH = 3
"""Partial plans kept after each component: the best by their Table 1 so far (`Table1Tally`)."""


@dataclass
class _Branch:
    """One partial plan of the beam: its knots and times so far, where the arms stand, and the
    configuration changes of its transitions and their `Table1Tally`."""

    jumps: int
    tally: Table1Tally
    q_now: np.ndarray
    U_now: np.ndarray
    previous: np.ndarray
    times: list
    knots: list
    segments: list

    def extended(self, component: SequenceComponent, jumps: int, q: np.ndarray, h: np.ndarray,
                 model_U: tuple | None, rig: DepmRig) -> "_Branch":
        """This partial plan with one more transition (knots q (A, n, 7), durations h) and its
        hold; `model_U`: (t, U, reached) from `_transition_U`, None: not scored."""
        times, knots = list(self.times), list(self.knots)
        start_s = times[-1]
        for n in range(1, q.shape[1]):
            times.append(times[-1] + float(h[n - 1]))
            knots.append(q[:, n])
        reached_s = times[-1]
        q_end = q[:, -1]
        times.append(reached_s + (component.hold_s if component.hold_s > 0 else MIN_REST_S))
        knots.append(q_end)
        U_reached = rig.field_at_centre(q_end[:, None, :])[0]
        target = np.asarray(component.U, dtype=float) * U_TO_SI
        segment = Segment(
            name=component.name, U=component.U, start_s=start_s, reached_s=reached_s,
            end_s=times[-1], residual=tuple(float(v) for v in (U_reached - target) / U_TO_SI),
        )
        requested = np.asarray(component.U, dtype=float)
        tally = self.tally if model_U is None else self.tally.added(
            model_U[0], model_U[1], self.previous, requested, model_U[2])
        return _Branch(self.jumps + jumps, tally, q_end, U_reached,
                       np.asarray(component.U, dtype=float), times, knots,
                       self.segments + [segment])


def plan_sequence(
    sequence: Sequence[SequenceComponent],
    rig: DepmRig | None = None,
    *,
    waypoints: int = DEFAULT_WAYPOINTS,
    k: int = DEFAULT_K,
    planner: Planner = "hybrid",
    q_start: np.ndarray | None = None,
    bulge_m: float = DEFAULT_BULGE_M,
    name: str | None = None,
    stats: PlanStats | None = None,
    end_poses: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
    end_joints: Sequence[np.ndarray] | None = None,
) -> FieldSequencePlan:
    """Plan a whole sequence and return the `field-sequence` plan (with `expected` filled).

    The arms start from `q_start` (A, 7) rad, or parked (`home_joints`). The end poses of every
    component come from inverse magnetics. "hybrid" joins them with the planned transitions,
    choosing among up to END_POSE_CANDIDATES end poses per component by a beam search: after each
    component the BEAM_WIDTH partial plans with the fewest configuration changes and then the
    best Table 1 so far (`Table1Tally`: off-activation peak and sigma, overshoots, from the
    model's U along them) are kept, each extended by the next component's candidates; the best
    whole plan is returned (deterministic: ties keep the order found);
    "agnostic" plans the hybrid first and then moves to the very same EPM end poses by straight
    joint-space moves (the baseline, `baseline_of`). `end_poses` (per component: EPM positions
    (A, 3) and moment directions (A, 3)) replaces inverse magnetics for the agnostic planner;
    `end_joints` (per component (A, 7)), joints known to make those poses, are where an arm goes
    when its own solve from where it stands finds none (`_controller_joints`).
    Timing goes into `stats` if given.
    """
    _check_options(planner, waypoints, k)
    if planner == "agnostic" and end_poses is None:
        hybrid = plan_sequence(sequence, rig, waypoints=waypoints, k=k, q_start=q_start,
                               bulge_m=bulge_m, name=name, stats=stats)
        return baseline_of(hybrid, name=name)
    rig = rig or default_rig()
    stats = stats if stats is not None else PlanStats()
    q_now = home_joints(rig) if q_start is None else np.asarray(q_start, dtype=float)
    U_start = rig.field_at_centre(q_now[:, None, :])[0]
    beam = [_Branch(0, Table1Tally(), q_now, U_start, np.zeros(8), [0.0, START_HOLD_S], [q_now, q_now], [])]
    for index, component in enumerate(sequence):
        started, started_cpu = time.perf_counter(), time.process_time()
        target = np.asarray(component.U, dtype=float) * U_TO_SI
        children, refusal, im_s = [], None, 0.0
        for branch in beam:
            im_started = time.perf_counter()
            try:
                if end_poses is not None:
                    q_end = _controller_end(rig, end_poses, end_joints, index, branch.q_now)
                else:
                    positions, directions = rig.epm_poses(branch.q_now)
                    ends = _reachable_ends(target, rig, branch.q_now, positions, directions,
                                           component.name)
                    first_end = next(ends)
                im_s += time.perf_counter() - im_started
                if planner == "hybrid":
                    found = _transitions(rig, branch.q_now, branch.U_now,
                                         itertools.chain([first_end], ends), waypoints, k,
                                         bulge_m, component)
                else:
                    q = np.stack([branch.q_now, q_end], axis=1)  # (A, 2, 7)
                    found = [(0, q, _segment_times(q, rig), None)]
            except PlanError as err:
                refusal = refusal or err
                continue
            children += [branch.extended(component, *f, rig) for f in found]
        if not children:
            stats.refused_s.append(time.perf_counter() - started)
            stats.refused_cpu_s.append(time.process_time() - started_cpu)
            raise refusal
        # the best partial plans: fewest configuration changes, then the best summed score (a
        # stable sort: ties keep the order found, so the same input gives the same plan)
        children.sort(key=lambda c: (c.jumps, c.tally.score()))
        beam = children[:BEAM_WIDTH]
        stats.inverse_magnetics_s.append(im_s)
        stats.transition_s.append(time.perf_counter() - started)
        stats.transition_cpu_s.append(time.process_time() - started_cpu)
    best = beam[0]
    times, segments = best.times, best.segments
    knots = best.knots
    knots = np.array(knots)  # (K, A, 7)
    arms = [
        ArmPlan(
            name=arm.name,
            position_mm=tuple(round(float(v) * 1e3, 9) + 0.0 for v in arm.base[:3, 3]),
            rpy_deg=_rpy_deg(arm.base[:3, :3]),
            joints_rad=[tuple(float(v) for v in row) for row in knots[:, a]],
        )
        for a, arm in enumerate(rig.arms)
    ]
    plan = FieldSequencePlan(
        schema=SCHEMA_ID, kind="field-sequence", rig=rig_running("field-sequence"), name=name, planner=planner,
        epm_moment_Am2=rig.moment_Am2, tool_offset_mm=rig.arms[0].model.tool_offset_m * 1e3,
        waypoints=waypoints, k=k, limits=limits_to_plan(rig.limits), sequence=list(sequence),
        t_s=[float(t) for t in times], arms=arms, segments=segments,
    )
    plan = simulate(plan)
    if planner == "hybrid":
        found = plan_violations(plan)
        if found:  # cannot happen if `_made_safe` did its job: never hand out a refused plan
            raise PlanError(f"the planned trajectories break {len(found)} safety constraint(s), "
                            f"first {found[0]}; report this planner fault with the sequence")
    return plan


def baseline_of(plan: FieldSequencePlan, name: str | None = None) -> FieldSequencePlan:
    """The magnetic-agnostic baseline of a plan (seed 003 Sec. 4.2): from the same start joints
    to the same EPM end pose of every component (so the same U), each arm solving its own joints
    for the commanded pose from where it stands (or, where that solve finds none, taking the
    plan's own joints for it: `_controller_joints`), by a straight joint-space move at the same
    speed limit, as an arm's point-to-point controller does; the holds are kept."""
    rig = rig_for_plan(plan)
    knots = np.asarray(plan.t_s)
    joints = np.array([arm.joints_rad for arm in plan.arms], dtype=float)  # (A, K, 7)
    reached = [joints[:, int(np.argmin(np.abs(knots - s.reached_s)))] for s in plan.segments]
    return plan_sequence(
        plan.sequence, rig, waypoints=plan.waypoints, k=plan.k,
        planner="agnostic", q_start=joints[:, 0], end_poses=[rig.epm_poses(q) for q in reached],
        end_joints=reached,
        name=name or (f"{plan.name} (agnostic baseline)" if plan.name else None),
    )


def _controller_joints(arm: ArmKinematics, position: np.ndarray, direction: np.ndarray,
                       q_from: np.ndarray, taught: np.ndarray | None) -> np.ndarray:
    """The joints an arm's own controller takes for a commanded EPM pose: its inverse kinematics
    from where it stands. A local solve can end in a minimum that misses a pose the arm does
    reach (a far move, a wrist flip); a controller is then given the pose as a frame taught with
    its redundancy (KUKA: status, turn and elbow angle), which names the joints: `taught`, the
    joints the plan itself reached the pose with. LimitError if there are none."""
    result = arm.solve(position, direction, q_from)
    if result.ok:
        return result.q
    if taught is not None:
        return np.asarray(taught, dtype=float)
    return arm.solve_or_raise(position, direction, q_from)


def _rpy_deg(rotation: np.ndarray) -> tuple[float, float, float]:
    """Fixed-axis roll, pitch, yaw (deg) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    pitch = np.arcsin(-np.clip(rotation[2, 0], -1.0, 1.0))
    roll = np.arctan2(rotation[2, 1], rotation[2, 2])
    yaw = np.arctan2(rotation[1, 0], rotation[0, 0])
    return tuple(float(np.round(np.degrees(v), 9)) + 0.0 for v in (roll, pitch, yaw))


# ---------------------------------------------------------------- evaluating and checking plans


def joint_trajectory(plan: FieldSequencePlan) -> list[PchipInterpolator]:
    """One PCHIP interpolant per arm through the plan's knots: call with times (s) -> (..., 7) rad;
    `.derivative()` gives rad/s. Outside [t_s[0], t_s[-1]] the arms rest at the end knots."""
    times = np.asarray(plan.t_s, dtype=float)
    return [
        PchipInterpolator(times, np.asarray(arm.joints_rad, dtype=float), axis=0, extrapolate=True)
        for arm in plan.arms
    ]


def _clamped(times: np.ndarray, plan: FieldSequencePlan) -> np.ndarray:
    return np.clip(np.asarray(times, dtype=float), plan.t_s[0], plan.t_s[-1])


def joints_at(plan: FieldSequencePlan, times_s: ArrayLike) -> np.ndarray:
    """Joint angles (A, T, 7) rad of both arms at times (T,) s (held at the ends)."""
    t = _clamped(np.atleast_1d(times_s), plan)
    return np.array([curve(t) for curve in joint_trajectory(plan)])


def sample_joints(plan: FieldSequencePlan, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Both arms sampled at `rate_hz` from the first to the last knot: t (T,), q (A, T, 7)."""
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    t = np.arange(plan.t_s[0], plan.t_s[-1], 1.0 / rate_hz)
    t = np.append(t, plan.t_s[-1]) if t[-1] < plan.t_s[-1] else t
    return t, joints_at(plan, t)


def expected_U(plan: FieldSequencePlan, times_s: ArrayLike) -> np.ndarray:
    """U (T, 8) in mT and mT/m at the centre from the planned joints (dipole model)."""
    rig = rig_for_plan(plan)
    return rig.field_at_centre(joints_at(plan, times_s)) / U_TO_SI


def simulate(plan: FieldSequencePlan) -> FieldSequencePlan:
    """A copy of the plan with `expected` (U at the centre at EXPECTED_RATE_HZ) filled in."""
    t = np.arange(plan.t_s[0], plan.t_s[-1] + 1e-9, 1.0 / EXPECTED_RATE_HZ)
    U = expected_U(plan, t)
    expected = ExpectedField(
        rate_hz=EXPECTED_RATE_HZ, t_s=[round(float(v), 6) for v in t],
        U=[tuple(round(float(v), 6) for v in row) for row in U],
    )
    copy = plan.model_copy(update={"expected": expected})
    copy._source, copy._base_dir = plan._source, plan._base_dir
    return copy


def _dense(plan: FieldSequencePlan, step: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Times (T,), joints, speeds and accelerations (A, T, 7) every `step` and at every knot."""
    t = np.union1d(np.arange(plan.t_s[0], plan.t_s[-1], step), np.asarray(plan.t_s))
    curves = joint_trajectory(plan)
    q = np.array([curve(t) for curve in curves])
    qdot = np.array([curve.derivative()(t) for curve in curves])
    qddot = np.array([curve.derivative(2)(t) for curve in curves])
    return t, q, qdot, qddot


def plan_violations(plan: FieldSequencePlan, arms: Sequence[ArmKinematics] | None = None,
                    limits: SafetyLimits | None = None) -> list:
    """Every safety constraint the plan's trajectories break (rigctl.plans.depm_safety.Violation),
    sampled every `check_step_s` and at every knot; against the plan's own arms and limits, or
    the given ones (a rig file's)."""
    rig = rig_for_plan(plan)
    arms = rig.arms if arms is None else list(arms)
    limits = rig.limits if limits is None else limits
    t, q, qdot, qddot = _dense(plan, limits.check_step_s)
    return violations(t, q, qdot, arms, limits, qddot)


STEADY_STATE_TOLERANCE = 0.02


def check(plan: FieldSequencePlan) -> None:
    """Every safety constraint, densely in time (LimitError naming the time, arm, part and
    constraint), then the end poses against the requested U (PlanError if a component is off by
    more than 2 % of its largest requested field / gradient entry)."""
    rig = rig_for_plan(plan)
    t, q, qdot, qddot = _dense(plan, rig.limits.check_step_s)
    check_samples(t, q, qdot, rig.arms, rig.limits, source=plan.source, qddot=qddot)
    for index, segment in enumerate(plan.segments):
        requested = np.asarray(segment.U, dtype=float)
        got = expected_U(plan, [segment.reached_s])[0]
        for part, unit in ((slice(0, 3), "mT"), (slice(3, 8), "mT/m")):
            scale = np.max(np.abs(requested[part]))
            error = np.max(np.abs(got[part] - requested[part]))
            if error > STEADY_STATE_TOLERANCE * max(scale, 1.0 if unit == "mT" else 10.0):
                raise PlanError(
                    f"{plan.source}: segments.{index} ({segment.name}): the end poses make U off "
                    f"by {error:.3g} {unit} from the request; re-plan"
                )


# ---------------------------------------------------------------- figures for bench/depm.py


def eight_components(field_mT: float = 10.0, gradient_mT_per_m: float = 100.0,
                     hold_s: float = 5.0) -> list[SequenceComponent]:
    """The sequence of seed 003 Sec. 4: each U component alone, in the order of eq. 23."""
    from rigctl.physics.magnetics import U_COMPONENTS

    components = []
    for index, label in enumerate(U_COMPONENTS):
        U = [0.0] * 8
        U[index] = field_mT if index < 3 else gradient_mT_per_m
        components.append(SequenceComponent(name=label, U=tuple(U), hold_s=hold_s))
    return components


def plan_timing(waypoints: int = DEFAULT_WAYPOINTS, k: int = DEFAULT_K,
                sequence: Sequence[SequenceComponent] | None = None) -> dict:
    """Planner time per transition and inverse-magnetics time for a sequence (default: the
    eight-component one), wall clock (s) and process CPU time (s; what a busy machine inflates
    least): {"transition_s": {"mean", "max"}, "inverse_magnetics_s": {"mean", "max"}, ...}."""
    stats = PlanStats()
    started, cpu = time.perf_counter(), time.process_time()
    plan_sequence(sequence or eight_components(), waypoints=waypoints, k=k, stats=stats)
    total, cpu = time.perf_counter() - started, time.process_time() - cpu
    return {
        "waypoints": waypoints, "k": k, "transitions": len(stats.transition_s),
        "transition_s": {"mean": float(np.mean(stats.transition_s)),
                         "max": float(np.max(stats.transition_s))},
        "transition_cpu_s": {"mean": float(np.mean(stats.transition_cpu_s)),
                             "max": float(np.max(stats.transition_cpu_s))},
        "inverse_magnetics_s": {"mean": float(np.mean(stats.inverse_magnetics_s)),
                                "max": float(np.max(stats.inverse_magnetics_s))},
        "whole_plan_s": total,
        "whole_plan_cpu_s": cpu,
    }


# ---------------------------------------------------------------- `rigctl plan depm`


def cli(args) -> int:
    """`rigctl plan depm`: plan a sequence file, write the plan, check it. Exit 0 planned and
    safe, 1 written but refused by the safety check, 2 bad input (raised as PlanError)."""
    import sys

    from rigctl.plans.schema import dump_plan

    sequence = load_sequence(args.sequence)
    output = Path(args.output)
    if not output.resolve().parent.is_dir():
        raise PlanError(f"-o: folder {output.resolve().parent} does not exist")
    planner: Planner = "agnostic" if args.agnostic else "hybrid"
    rig = None
    if getattr(args, "rig", None):
        from rigctl.core.config import load_rig
        from rigctl.core.errors import ConfigError

        config = load_rig(args.rig)
        kind = rig_running("field-sequence")
        if config.rig.kind != kind:
            raise ConfigError(f"--rig: {args.rig} is a {config.rig.kind} rig; this planner plans for "
                              f"{kind} rigs (their arms and magnets)")
        rig = rig_from_settings(config.depm)
    stats = PlanStats()
    started = time.perf_counter()
    plan = plan_sequence(sequence, rig, waypoints=args.waypoints, k=args.k, planner=planner,
                         name=f"{planner} plan of {Path(args.sequence).name}", stats=stats)
    seconds = time.perf_counter() - started
    output.write_text(dump_plan(plan))
    found = plan_violations(plan)
    worst = max(relative_error(s.residual, s.U) for s in plan.segments)
    print(f"depm ({planner}): {len(sequence)} components, {plan.t_s[-1]:.1f} s of motion, "
          f"{len(plan.t_s)} knots, planned in {seconds:.2f} s "
          f"(max {max(stats.transition_s):.2f} s per transition), worst end-pose error "
          f"{worst:.2e} relative, {len(found)} safety violation(s) -> {output}", file=sys.stderr)
    for violation in found:
        print(f"  refused: {violation}", file=sys.stderr)
    if args.json:
        print(json.dumps({
            "planner": planner, "components": len(sequence), "duration_s": round(plan.t_s[-1], 3),
            "seconds": round(seconds, 4),
            "transition_s_max": round(max(stats.transition_s), 4),
            "transition_cpu_s_max": round(max(stats.transition_cpu_s), 4),
            "inverse_magnetics_s_max": round(max(stats.inverse_magnetics_s), 4),
            "violations": len(found),
        }))
    return 1 if found else 0
