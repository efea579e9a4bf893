"""`rigctl doctor`'s probes of a dual-EPM rig (`RigKind.probes`): each arm's joint positions, and
one Hall board sample (a board at rest reads the earth's field, tens of microtesla)."""

from __future__ import annotations

import numpy as np

from rigctl.core.config import RigConfig
from rigctl.rigs.base import Device


def arm(rig: RigConfig, device: Device) -> str:
    from rigctl.drivers.kuka_sunrise import KukaArm

    arm = KukaArm.open(device.url, name=device.name, timeout_s=rig.depm.reply_timeout_s)
    try:
        q = arm.joint_positions()
    finally:
        arm.close()
    return "joints " + " ".join(f"{v:+.3f}" for v in np.asarray(q)) + " rad"


def hall(rig: RigConfig, device: Device) -> str:
    from rigctl.drivers.hall import HallBoard

    board = HallBoard.open(device.url, name=device.name, timeout_s=rig.depm.reply_timeout_s)
    try:
        sample = board.read()
    finally:
        board.close()
    magnitude_uT = np.linalg.norm(sample.field_T, axis=1) * 1e6
    saturated = " SATURATED" if np.any(sample.saturated) else ""
    return (f"{len(magnitude_uT)} sensors, |B| " + ", ".join(f"{b:.0f}" for b in magnitude_uT)
            + f" uT{saturated}")
