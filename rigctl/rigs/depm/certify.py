"""The dual-EPM rig's pre-flight checks of a field-sequence plan (`rigctl.run.certificate`), on the
plan's joint trajectories sampled every `check_step_s` and at every knot: each arm's joint range,
speed and acceleration (as shares of the joints' maxima), the keep-out sphere (EPM and links),
the EPM-EPM distance, the field and gradient at the workspace centre, the static field at the
rig file's exposure points, each arm's link per stream cycle, and the plan's size and duration."""

from __future__ import annotations

import numpy as np

from rigctl.core.config import RigConfig
from rigctl.physics.magnetics import field_vector
from rigctl.plans.depm import DepmRig, joint_trajectory
from rigctl.plans.depm_safety import segment_point_distance
from rigctl.plans.schema import MAX_DURATION_S
from rigctl.run.certificate import (
    Check,
    ceiling,
    exposure_checks,
    floor,
    link_checks,
    size_checks,
)

MAX_KNOTS = 100_000


def dense_samples(plan, step_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Times (T,) s and joints, speeds, accelerations (A, T, 7) every `step_s` and at each knot."""
    t = np.union1d(np.arange(plan.t_s[0], plan.t_s[-1], step_s), np.asarray(plan.t_s))
    curves = joint_trajectory(plan)
    return (t, np.array([c(t) for c in curves]), np.array([c.derivative()(t) for c in curves]),
            np.array([c.derivative(2)(t) for c in curves]))


def arm_link_checks(rig: RigConfig, rate_hz: float) -> list[Check]:
    """Each arm's KST link per stream cycle: a servo target and its answer, one round trip
    (`[preflight] kst_round_trip_ms`; the two arms' exchanges overlap, `ArmPair.cycle`, and some
    300 bytes take 25 us of a 100 Mbit/s link), against 80 % of the period at `rate_hz`."""
    d = rig.depm
    assert d is not None
    seconds = rig.preflight.kst_round_trip_ms * 1e-3
    return link_checks({f"arm {name} (KST servo target and answer)": seconds
                        for name in d.arm_names}, rate_hz)


def field_sequence_checks(plan, rig: RigConfig, depm_rig: DepmRig, rate_hz: float) -> list[Check]:
    """Every check of a field-sequence plan streamed at `rate_hz` (real cycles per second)."""
    d = rig.depm
    assert d is not None
    limits = depm_rig.limits
    t, q, qdot, qddot = dense_samples(plan, limits.check_step_s)
    centre = np.asarray(limits.centre_m, dtype=float)
    checks: list[Check] = []
    epms, directions = [], []  # each arm's EPM centre and moment direction (T, 3), from one FK
    for a, arm in enumerate(depm_rig.arms):
        m = arm.model
        # the safety check's own slack (1e-9 rad): a knot exactly at a limit is in range
        room = np.minimum(q[a] - m.lower_rad, m.upper_rad - q[a]) + 1e-9  # (T, 7)
        k, j = np.unravel_index(np.argmin(room), room.shape)
        checks.append(floor("joint range", f"arm {arm.name}", np.degrees(room[k, j]), 0.0, "deg",
                            f"closest: A{j + 1} at t = {t[k]:.2f} s"))
        for values, cap, share, what in ((qdot, m.max_speed, limits.speed_fraction, "joint speed"),
                                         (qddot, m.max_accel, limits.accel_fraction,
                                          "joint acceleration")):
            ratio = np.abs(values[a]) / cap
            k, j = np.unravel_index(np.argmax(ratio), ratio.shape)
            checks.append(ceiling(what, f"arm {arm.name}", 100 * ratio[k, j], 100 * share,
                                  "% of max", f"A{j + 1} at t = {t[k]:.2f} s", tolerance=1e-6))
        frames = arm.frames(q[a])
        epm = frames[:, 8, :3, 3]
        epms.append(epm)
        directions.append(frames[:, 8, :3, 0])  # the flange x axis (`ArmKinematics.epm_pose`)
        clearance = np.linalg.norm(epm - centre, axis=-1) - limits.epm_radius_m
        segments = frames[:, :, :3, 3][:, np.array(m.capsule_links), :]
        links = segment_point_distance(segments, centre) - np.array(m.capsule_radii_m)
        k = int(np.argmin(clearance))
        checks.append(floor("keep-out clearance", f"arm {arm.name} EPM", 1e3 * clearance[k],
                            1e3 * limits.keep_out_radius_m, "mm", f"t = {t[k]:.2f} s"))
        k, link = np.unravel_index(np.argmin(links), links.shape)
        checks.append(floor("keep-out clearance", f"arm {arm.name} links", 1e3 * links[k, link],
                            1e3 * limits.keep_out_radius_m, "mm",
                            f"link {m.capsule_names[link]} at t = {t[k]:.2f} s"))
    gap = np.linalg.norm(epms[0] - epms[1], axis=-1)
    k = int(np.argmin(gap))
    checks.append(floor("EPM-EPM distance", "both arms", 1e3 * gap[k],
                        1e3 * limits.epm_min_distance_m, "mm", f"t = {t[k]:.2f} s"))
    centres = np.stack(epms, axis=1)  # (T, A, 3)
    moments = np.stack(directions, axis=1) * depm_rig.moment_Am2
    U = field_vector(np.broadcast_to(centre, (len(t), 3)), centres, moments)  # (T, 8) T, T/m
    checks.append(ceiling("field |B| at the centre", "workspace",
                          1e3 * np.linalg.norm(U[:, :3], axis=1).max(), rig.preflight.max_field_mT,
                          "mT"))
    checks.append(ceiling("gradient at the centre", "workspace", 1e3 * np.abs(U[:, 3:]).max(),
                          rig.preflight.max_gradient_mT_per_m, "mT/m"))
    checks += exposure_checks(d.exposure_points, t, centres, moments, d.exposure_limit_mT)
    checks += arm_link_checks(rig, rate_hz)
    checks += size_checks(len(plan.t_s), MAX_KNOTS, float(plan.t_s[-1] - plan.t_s[0]),
                          MAX_DURATION_S, unit="knots")
    return checks
