"""Safety constraints of the dual-EPM rig, checked densely in time before any arm moves (seed 003
Sec. 3.1.1, and the rig's own limits).

- keep-out sphere: no EPM and no arm link inside the sphere of `keep_out_radius_m` about the
  workspace centre (where the patient / the magnetic agent is). Links are capsules (segment +
  radius, `ArmModel.capsule_*`); an EPM is its bounding sphere (`epm_radius_m`: half the diagonal
  of the 101.6 x 101.6 mm cylinder is 71.8 mm).
- EPM-EPM distance: the two magnets' centres stay at least `epm_min_distance_m` apart, so their
  mutual force stays well inside the arms' payload.
- joint ranges (the arm model's limits) and joint speeds (at most `speed_fraction` of each joint's
  maximum: 30 % on the seed's platform); joint accelerations (at most `accel_fraction` of each
  joint's assumed maximum, `ArmModel.max_accel_rad_s2`: the servo keeps the rest to correct
  tracking errors).

`violations(...)` lists every breach (one per constraint, arm and part, at its first time);
`check_samples(...)` raises a LimitError naming the earliest one. Pure and vectorised; the plan-level
entry point is `rigctl.plans.depm.check(plan)`, which samples a plan's trajectories and calls these.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rigctl.core.errors import LimitError
from rigctl.physics.kinematics import ArmKinematics

SPEED_TOLERANCE = 1e-6
"""Relative slack on the speed and acceleration limits so a trajectory timed exactly at a limit
passes."""


@dataclass(frozen=True)
class SafetyLimits:
    """The constraints a dual-EPM trajectory must respect (SI units)."""

    keep_out_radius_m: float = 0.15
    epm_radius_m: float = 0.072
    epm_min_distance_m: float = 0.30
    speed_fraction: float = 0.3
    accel_fraction: float = 0.5
    check_step_s: float = 0.01
    centre_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def epm_keep_out_m(self) -> float:
        """Smallest allowed distance from the centre to an EPM centre."""
        return self.keep_out_radius_m + self.epm_radius_m


@dataclass(frozen=True)
class Violation:
    """One breached constraint: when (s), where (arm, part: a link, the EPM or a joint), what."""

    time_s: float
    arm: str
    part: str
    constraint: str
    value: float
    limit: float
    unit: str

    def __str__(self) -> str:
        return (
            f"t = {self.time_s:.3f} s: arm {self.arm}, {self.part}: {self.constraint} "
            f"({self.value:.4g} {self.unit}, limit {self.limit:.4g} {self.unit})"
        )


def segment_point_distance(ends: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Distance from `point` (3,) to segments `ends` (..., 2, 3) -> (...)."""
    a, b = ends[..., 0, :], ends[..., 1, :]
    ab = b - a
    length2 = np.sum(ab * ab, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(length2 > 0, np.sum((point - a) * ab, axis=-1) / length2, 0.0)
    t = np.clip(t, 0.0, 1.0)
    nearest = a + t[..., None] * ab
    return np.linalg.norm(nearest - point, axis=-1)


def violations(
    times_s: np.ndarray,
    q: np.ndarray,
    qdot: np.ndarray | None,
    arms: Sequence[ArmKinematics],
    limits: SafetyLimits,
    qddot: np.ndarray | None = None,
) -> list[Violation]:
    """Every constraint breached by sampled trajectories, earliest time per (arm, part, constraint).

    times_s : (T,) sample times; q : (A, T, 7) joint angles (rad) of the A arms; qdot : (A, T, 7)
    joint speeds (rad/s) or None to skip the speed check; qddot likewise, accelerations (rad/s^2).
    Returned sorted by time.
    """
    times = np.asarray(times_s, dtype=float)
    q = np.asarray(q, dtype=float)
    if q.ndim != 3 or q.shape[0] != len(arms) or q.shape[1] != len(times) or q.shape[2] != 7:
        raise ValueError(f"q must have shape ({len(arms)}, {len(times)}, 7), got {q.shape}")
    found: list[Violation] = []
    epm_centres = []
    for a, arm in enumerate(arms):
        frames = arm.frames(q[a])  # (T, 9, 4, 4)
        epm_centres.append(frames[:, 8, :3, 3])
        found += _inside_keep_out(times, frames, arm, limits)
        found += _outside_ranges(times, q[a], arm)
        found += _too_fast(times, None if qdot is None else np.asarray(qdot, dtype=float)[a],
                           None if qddot is None else np.asarray(qddot, dtype=float)[a], arm, limits)
    found += _epms_too_close(times, epm_centres, arms, limits)
    return sorted(found, key=lambda v: v.time_s)


def _first(mask: np.ndarray) -> int | None:
    """The first sample where `mask` (T,) holds, or None."""
    hits = np.flatnonzero(mask)
    return int(hits[0]) if len(hits) else None


def _inside_keep_out(times: np.ndarray, frames: np.ndarray, arm: ArmKinematics,
                     limits: SafetyLimits) -> list[Violation]:
    """The arm's EPM and each of its link capsules ((T, 9, 4, 4) frames) inside the keep-out
    sphere about the workspace centre."""
    centre = np.asarray(limits.centre_m, dtype=float)
    found = []
    clearance = np.linalg.norm(frames[:, 8, :3, 3] - centre, axis=-1) - limits.epm_radius_m
    i = _first(clearance < limits.keep_out_radius_m)
    if i is not None:
        found.append(Violation(
            float(times[i]), arm.name, "EPM", "inside the keep-out sphere about the centre",
            float(clearance[i]) * 1e3, limits.keep_out_radius_m * 1e3, "mm clearance",
        ))
    origins = frames[:, :, :3, 3]
    index = np.array(arm.model.capsule_links)
    segments = origins[:, index, :]  # (T, L, 2, 3)
    distance = segment_point_distance(segments, centre) - np.array(arm.model.capsule_radii_m)
    for link, name in enumerate(arm.model.capsule_names):
        i = _first(distance[:, link] < limits.keep_out_radius_m)
        if i is not None:
            found.append(Violation(
                float(times[i]), arm.name, f"link {name}",
                "inside the keep-out sphere about the centre",
                float(distance[i, link]) * 1e3, limits.keep_out_radius_m * 1e3, "mm clearance",
            ))
    return found


def _outside_ranges(times: np.ndarray, q: np.ndarray, arm: ArmKinematics) -> list[Violation]:
    """The arm's joints (q: (T, 7) rad) outside their ranges."""
    found = []
    lower, upper = arm.model.lower_rad, arm.model.upper_rad
    for j in range(7):
        i = _first((q[:, j] < lower[j] - 1e-9) | (q[:, j] > upper[j] + 1e-9))
        if i is not None:
            bound = lower[j] if q[i, j] < lower[j] else upper[j]
            found.append(Violation(
                float(times[i]), arm.name, f"joint A{j + 1}", "outside its range",
                float(np.degrees(q[i, j])), float(np.degrees(bound)), "deg",
            ))
    return found


def _too_fast(times: np.ndarray, qdot: np.ndarray | None, qddot: np.ndarray | None,
              arm: ArmKinematics, limits: SafetyLimits) -> list[Violation]:
    """The arm's joint speeds (qdot: (T, 7) rad/s) and accelerations (qddot: (T, 7) rad/s^2)
    beyond their share of the joints' maxima; None skips that check."""
    found = []
    rates = (
        (qdot, limits.speed_fraction * arm.model.max_speed, np.degrees, "deg/s",
         f"faster than {limits.speed_fraction:.0%} of its maximum speed"),
        (qddot, limits.accel_fraction * arm.model.max_accel, np.asarray, "rad/s^2",
         f"accelerating beyond {limits.accel_fraction:.0%} of its assumed maximum"),
    )
    for values, cap, shown, unit, constraint in rates:
        if values is None:
            continue
        rate = np.abs(values)
        for j in range(7):
            i = _first(rate[:, j] > cap[j] * (1.0 + SPEED_TOLERANCE))
            if i is not None:
                found.append(Violation(
                    float(times[i]), arm.name, f"joint A{j + 1}", constraint,
                    float(shown(rate[i, j])), float(shown(cap[j])), unit,
                ))
    return found


def _epms_too_close(times: np.ndarray, epm_centres: list[np.ndarray],
                    arms: Sequence[ArmKinematics], limits: SafetyLimits) -> list[Violation]:
    """Each pair of EPMs (centres (T, 3) m per arm) closer than the minimum distance."""
    found = []
    for a in range(len(arms)):
        for b in range(a + 1, len(arms)):
            gap = np.linalg.norm(epm_centres[a] - epm_centres[b], axis=-1)
            i = _first(gap < limits.epm_min_distance_m)
            if i is not None:
                found.append(Violation(
                    float(times[i]), f"{arms[a].name}+{arms[b].name}", "EPMs",
                    "EPM-EPM distance below the minimum",
                    float(gap[i]) * 1e3, limits.epm_min_distance_m * 1e3, "mm",
                ))
    return found


def check_samples(
    times_s: np.ndarray,
    q: np.ndarray,
    qdot: np.ndarray | None,
    arms: Sequence[ArmKinematics],
    limits: SafetyLimits,
    source: str = "trajectory",
    qddot: np.ndarray | None = None,
) -> None:
    """Raise LimitError naming the earliest breached constraint (and how many there are)."""
    found = violations(times_s, q, qdot, arms, limits, qddot)
    if found:
        more = f" (and {len(found) - 1} more)" if len(found) > 1 else ""
        raise LimitError(
            f"{source}: refused, nothing moved: {found[0]}{more}; re-plan the trajectory "
            "(rigctl plan depm) or relax the rig's limits",
            device=found[0].arm,
        )
