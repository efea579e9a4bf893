"""The dual-EPM rig (seed 003): two KUKA LBR arms carrying permanent magnets and a Hall board.

`run`: the field-sequence program on the one run engine (`FieldSequenceRun`); `actuators`: the two
arms as one actuator group (`ArmPair`); `motion`: where the servo targets come from (the approach,
the plan, holds and rejoins); `sensors`: the Hall board's samples and eq. 24; `metrics`: seed 003
Table 1 and Fig. 6.
"""

from __future__ import annotations

import math

from rigctl.channels import Channel
from rigctl.config import RigConfig
from rigctl.rigs.base import Device, RigKind


def _field_sequence(plan, rig: RigConfig, *, agnostic: bool = False, time_scale: float = 1.0,
                    **run):
    from rigctl.rigs.depm.run import FieldSequenceRun

    if agnostic:
        from rigctl.plans.depm import baseline_of

        if run.get("progress_out") is not None:
            print("the magnetic-agnostic baseline: straight joint moves to the plan's end poses",
                  file=run["progress_out"], flush=True)
        plan = baseline_of(plan)
    return FieldSequenceRun(plan, rig, time_scale=time_scale, **run)


def _channels(rig: RigConfig) -> list[Channel]:
    from rigctl.rigs.depm.actuators import arm_channels

    return arm_channels(rig)


def _devices(rig: RigConfig) -> list[Device]:
    if rig.depm is None:
        return []
    arms = [Device(name, url, "arm") for name, url in zip(rig.depm.arm_names, rig.depm.arm_urls)]
    return arms + [Device("hall board", rig.depm.hall_url, "hall board")]


def _make_safe(rig: RigConfig) -> dict[str, str | None]:
    """Each arm reached anew: out of direct servo, holding where it is (a KUKA arm holds its
    pose with its brakes and drives when no motion is commanded; the Sunrise servo's own timeout
    stops it when targets stop coming)."""
    from rigctl.drivers.kuka_sunrise import KukaArm
    from rigctl.errors import RigError

    result: dict[str, str | None] = {}
    if rig.depm is None:
        return result
    for name, url in zip(rig.depm.arm_names, rig.depm.arm_urls):
        try:
            arm = KukaArm.open(url, name=name, timeout_s=rig.depm.reply_timeout_s)
            try:
                q = arm.joint_positions()
                result[name] = None if all(math.isfinite(v) for v in q) else "no joint reading"
            finally:
                arm.close()
        except RigError as err:
            result[name] = str(err)
    return result


KIND = RigKind(
    name="depm",
    description="two KUKA LBR iiwa arms carrying permanent magnets, a three-sensor Hall board",
    plans={"field-sequence": _field_sequence},
    channels=_channels, devices=_devices, make_safe=_make_safe)
