"""The dual-EPM run's Hall correction: at each hold, close the loop on the U the Hall board measures.

The plan's poses come from the planner's point-dipole model (seed 003 eq. 2); the magnets are
finite cylinders, whose field is 1-13 % off the dipole's within 15 cm, so U at a hold misses the
request by a few percent. At the start of each hold the run stops the plan's clock (the arms hold,
as in a pause), averages the board's U, and iterates the inverse magnetics on the measured
residual: one Gauss-Newton step of the planner's model, linearised at the present joints,

    dq = J^T (J J^T + lambda^2 I)^-1 W (U_requested - U_measured),   J = W dU_model/dq,

W scaling the fields and the gradients by the hold's largest request of their kind (the model's
Jacobian is right to a few percent, the residual is measured: the iteration converges to the
measured U, not to the model's). Each step is a joint-space move checked against every safety
constraint before it is made; a step that would break one ends the correction of that hold.
Up to MAX_STEPS steps, until every component is within TARGET of its request (of the plan's
largest request of its kind) beyond the board's noise (NOISE_SEMS standard errors of the mean).

The correction then stays on for the rest of the hold (the plan's pose plus the correction dq)
and is blended out linearly over the next transition, which the run checks against every
constraint when it releases the clock.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from rigctl.physics.kinematics import ArmKinematics
from rigctl.physics.magnetics import field_vector
from rigctl.plans.depm_safety import SafetyLimits, Violation, violations

MAX_STEPS = 4
TARGET = 0.007  # residual, of the plan's largest request of its kind: then stop stepping (the
# board's noise averaged over SAMPLES is ~0.3 % of 100 mT/m)
DAMPING = 0.02  # lambda, in units of the scaled residual
JACOBIAN_STEP_RAD = 1e-5
SETTLE_S = 0.05  # real seconds after a move ends before the board's samples count
SAMPLES = 40  # board samples averaged per measurement (0.4 s at 100 Hz)
MAX_STEP_RAD = 0.05  # a larger step is scaled down to this (the model is linearised)
BLEND_CHECK_S = 0.1  # the blend's poses are checked this often (in the stream thread: cheap)
NOISE_SEMS = 2.0  # a residual component within this many standard errors is noise
RANGE_MARGIN_RAD = 1e-3  # a joint this near the end of its range is not pushed further


def model_U(arms: Sequence[ArmKinematics], moment_Am2: float, q: np.ndarray) -> np.ndarray:
    """U (8,) in mT and mT/m at the workspace centre of the planner's dipoles for joints (A, 7)."""
    centres, moments = [], []
    for arm, qa in zip(arms, q):
        centre, direction = arm.epm_pose(qa)
        centres.append(centre)
        moments.append(moment_Am2 * np.asarray(direction))
    return field_vector(np.zeros(3), np.array(centres), np.array(moments)) * 1e3


def kind_scales(requests) -> np.ndarray:
    """(8,): for each component, the largest |request| of its kind (field, gradient) over the
    plan's windows: a residual is judged against it (an unrequested gradient during a field hold
    is still off-activation, on the gradients' scale)."""
    requests = np.abs(np.asarray(requests, dtype=float).reshape(-1, 8))
    scale = np.ones(8)
    for part in (slice(0, 3), slice(3, 8)):
        largest = float(requests[:, part].max(initial=0.0))
        scale[part] = largest if largest > 0 else float(requests.max(initial=1.0)) or 1.0
    return scale


def correction_step(arms: Sequence[ArmKinematics], moment_Am2: float, q: np.ndarray,
                    requested: np.ndarray, measured: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """dq (A, 7) rad: one damped Gauss-Newton step of the model towards `requested` from the
    measured residual (see the module docstring), residuals over `scales` (`kind_scales`). A joint
    at the end of its range that the step would push further is frozen (its column dropped) and
    the step solved again; at most MAX_STEP_RAD per joint, never past a range."""
    q = np.asarray(q, dtype=float)
    w = 1.0 / np.asarray(scales, dtype=float)
    base = model_U(arms, moment_Am2, q)
    flat = q.ravel()
    J = np.zeros((8, q.size))
    for j in range(q.size):
        probe = flat.copy()
        probe[j] += JACOBIAN_STEP_RAD
        J[:, j] = (model_U(arms, moment_Am2, probe.reshape(q.shape)) - base) / JACOBIAN_STEP_RAD
    lower = np.concatenate([a.model.lower_rad for a in arms])
    upper = np.concatenate([a.model.upper_rad for a in arms])
    r = w * (np.asarray(requested, dtype=float) - np.asarray(measured, dtype=float))
    free = np.ones(q.size, dtype=bool)
    dq = np.zeros(q.size)
    for _ in range(q.size):
        Jw = w[:, None] * J * free[None, :]
        dq = Jw.T @ np.linalg.solve(Jw @ Jw.T + DAMPING**2 * np.eye(8), r)
        stuck = free & (((flat + dq < lower + RANGE_MARGIN_RAD) & (dq < 0))
                        | ((flat + dq > upper - RANGE_MARGIN_RAD) & (dq > 0)))
        if not stuck.any():
            break
        free &= ~stuck
    largest = float(np.max(np.abs(dq)))
    if largest > MAX_STEP_RAD:
        dq *= MAX_STEP_RAD / largest
    dq = np.clip(flat + dq, lower, upper) - flat
    return dq.reshape(q.shape)


def mean_and_sem(samples: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The mean (8,) of the board's U samples and its standard error (8,)."""
    u = np.asarray(samples, dtype=float)
    return u.mean(axis=0), u.std(axis=0, ddof=1) / np.sqrt(len(u))


def significant_residual(requested: np.ndarray, measured: np.ndarray, sem: np.ndarray) -> np.ndarray:
    """requested - measured with NOISE_SEMS standard errors taken off each component's magnitude
    (a residual within the board's noise is none): the correction does not chase noise (the
    gradients' is ~1.4 % of a 24 mT/m request over 40 samples at a 2 mm pitch)."""
    r = np.asarray(requested, dtype=float) - np.asarray(measured, dtype=float)
    return np.sign(r) * np.maximum(np.abs(r) - NOISE_SEMS * np.asarray(sem), 0.0)


def _smooth(x: float) -> float:
    """1 -> 0 on [0, 1] with zero slope at both ends (a cosine), so the blend adds no jerk step."""
    return 0.5 * (1.0 + np.cos(np.pi * min(max(x, 0.0), 1.0)))


@dataclass
class HoldOffsets:
    """The corrections dq (A, 7) found at each window's hold: on from the hold's start (the
    window's `reached_s`) to its end, then blended to zero (a cosine) by the next window's
    `reached_s`; the last window's stays on to the plan's end. The corrected pose is clipped to
    the joints' ranges (`lower`, `upper` (A, 7) rad)."""

    reached_s: np.ndarray  # (W,)
    end_s: np.ndarray  # (W,)
    lower: np.ndarray
    upper: np.ndarray
    offsets: dict[int, np.ndarray] = field(default_factory=dict)

    def at(self, t: float) -> np.ndarray | None:
        for i, dq in self.offsets.items():
            last = i + 1 >= len(self.reached_s)
            if self.reached_s[i] <= t <= self.end_s[i] or (last and t >= self.reached_s[i]):
                return dq
            if not last and self.end_s[i] < t < self.reached_s[i + 1]:
                return dq * _smooth((t - self.end_s[i]) / (self.reached_s[i + 1] - self.end_s[i]))
        return None

    def apply(self, t: float, pose: np.ndarray) -> np.ndarray:
        """The pose (A, 7) to send at plan time t for the plan's `pose` there."""
        dq = self.at(t)
        return pose if dq is None else np.clip(pose + dq, self.lower, self.upper)

    def blend_violations(self, i: int, curves, arms: Sequence[ArmKinematics],
                         limits: SafetyLimits) -> list[Violation]:
        """The constraints the plan with window i's correction breaks (positions: ranges,
        keep-out, EPM distance), from its hold to where the blend ends, every BLEND_CHECK_S. The
        plan's speeds were checked with the plan; the blend adds at most |dq| pi / (2 T) to them
        over a transition of T s (|dq| <= a few MAX_STEP_RAD: under 0.05 rad/s for T >= 3 s)."""
        last = i + 1 >= len(self.reached_s)
        until = self.end_s[i] if last else self.reached_s[i + 1]
        t = np.append(np.arange(self.reached_s[i], until, BLEND_CHECK_S), until)
        q = np.array([self.apply(ti, np.array([curve(ti) for curve in curves])) for ti in t])
        return violations(t, np.moveaxis(q, 0, 1), None, arms, limits)
