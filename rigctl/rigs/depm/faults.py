"""The dual-EPM rig's part in the fault campaign (`rigctl faults`, `rigctl.rigs.faults`): the wrist
joint A7 of both arms turned 30 degrees and back, driving while any joint turns faster than
0.01 rad/s, safe when both arms are at rest; nothing suspends its runs (no camera), and the arms
are parked upright before each run, where its plan starts."""

from __future__ import annotations

from typing import Any

import numpy as np

from rigctl.rigs.faults import FaultProfile, wait_until

DRIVING_RAD_S = 0.01


def quick_plan() -> dict:
    """Both EPMs 0.45 m from the centre, the wrist joint A7 turning 30 degrees and back, each pose
    held 1 s: the field-sequence plan's shape with the U each pose makes (seed 003 eq. 8)."""
    from rigctl.physics.kinematics import DEFAULT_BASES, default_arms
    from rigctl.physics.magnetics import field_vector
    from rigctl.plans.depm import EPM_MOMENT_AM2

    arms = default_arms()
    seed = np.array([0, 0.5, 0, -1.2, 0, 0.8, 0.0])
    q0 = np.array([arm.solve(np.array([x, 0.0, 0.0]), np.array([0, 0, 1.0]), seed,
                             keep_out=(np.zeros(3), 0.15)).q for arm, x in zip(arms, (-0.45, 0.45))])
    q1 = q0.copy()
    q1[:, 6] += np.radians(30)

    def u_mT(q: np.ndarray) -> list[float]:
        poses = [arm.epm_pose(joints) for arm, joints in zip(arms, q)]
        centres = np.array([p for p, _ in poses])
        moments = EPM_MOMENT_AM2 * np.array([d for _, d in poses])
        return [round(float(v), 9) for v in field_vector(np.zeros(3), centres, moments) * 1e3]

    move, hold = 1.5, 1.0  # 30 deg in 1.5 s: 30 deg/s peak at most (A7's limit is 40.5)
    t = [0.0, 0.5, 0.5 + move, 0.5 + move + hold, 0.5 + 2 * move + hold, 0.5 + 2 * move + 2 * hold]
    knots = [q0, q0, q1, q1, q0, q0]
    segments = [
        {"name": "turn", "U": u_mT(q1), "start_s": t[1], "reached_s": t[2], "end_s": t[3],
         "residual": [0.0] * 8},
        {"name": "back", "U": u_mT(q0), "start_s": t[3], "reached_s": t[4], "end_s": t[5],
         "residual": [0.0] * 8}]
    return {"schema": "rigctl.plan/1", "kind": "field-sequence", "rig": "depm",
            "name": "faults: wrist turn", "epm_moment_Am2": EPM_MOMENT_AM2,
            "tool_offset_mm": float(arms[0].model.tool_offset_m * 1e3),
            "sequence": [{"name": s["name"], "U": s["U"], "hold_s": hold} for s in segments],
            "t_s": t, "segments": segments,
            "arms": [{"name": arm.name, "position_mm": list(arm.base[:3, 3] * 1e3),
                      "rpy_deg": list(DEFAULT_BASES[i][2]),
                      "joints_rad": [list(k[i]) for k in knots]} for i, arm in enumerate(arms)]}


def arm_speeds(truth: dict) -> np.ndarray:
    """Every joint speed of both arms (rad/s, absolute) in the bench's truth."""
    return np.abs([arm["qd"] for arm in truth["arms"].values()])


def park_arms(backdoor: Any) -> None:
    """Both arms at rest with no client, then parked upright (all joints 0) as the plan expects
    them before its approach."""
    wait_until(lambda: all(a["mode"] == "idle" and a["connections"] == 0
                           for a in backdoor.request("truth")["arms"].values()), 30.0,
               "both arms at rest with no client")
    for arm in backdoor.request("truth")["arms"]:
        backdoor.request("place", arm=arm, q=[0.0] * 7)


def fault_profile() -> FaultProfile:
    return FaultProfile(
        plan=quick_plan,
        driving=lambda t: arm_speeds(t).max() > DRIVING_RAD_S,
        safe=lambda t: not arm_speeds(t).any(),
        safe_means="both arms at rest: every joint speed 0",
        suspend_with=None,
        reset=park_arms,
        unsafe_detail=lambda t: {"qd_max": float(arm_speeds(t).max())},
        quick=(("daemon", "left:stall_joint", "moving"),))
