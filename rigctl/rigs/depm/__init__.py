"""The dual-EPM rig (seed 003): two KUKA LBR arms carrying permanent magnets and a Hall board.

`run`: the field-sequence program on the one run engine (`FieldSequenceRun`); `actuators`: the two
arms as one actuator group (`ArmPair`); `motion`: where the servo targets come from (the approach,
the plan, holds and rejoins); `sensors`: the Hall board's samples and eq. 24; `metrics`: seed 003
Table 1 and Fig. 6.
"""

from __future__ import annotations

import math

from rigctl.core.channels import Channel
from rigctl.core.config import RigConfig
from rigctl.rigs.base import Device, RigKind
from rigctl.rigs.depm.faults import fault_profile
from rigctl.rigs.depm.scene import arms_scene


def _field_sequence(plan, rig: RigConfig, *, agnostic: bool = False, time_scale: float = 1.0,
                    closed_loop: bool = True, **run):
    from rigctl.rigs.depm.run import FieldSequenceRun

    if agnostic:
        from rigctl.plans.depm import baseline_of

        plan = baseline_of(plan)
    return FieldSequenceRun(plan, rig, time_scale=time_scale, closed_loop=closed_loop, **run)


def _bench_rig() -> RigConfig:
    """The rig `rigctl emulate depm` serves, as a plan's checks see it before the bench starts
    (its links' addresses are the bench's to choose then): the planner's default arms, magnets
    and limits, and the loopback round trip its pre-flight counts (`rigctl.emulators.depm`)."""
    from rigctl.core.config import Emulation, PreflightSettings, RigInfo
    from rigctl.emulators.depm import LOOPBACK_ROUND_TRIP_MS, default_settings
    from rigctl.rigs.depm.settings import DepmRig

    return DepmRig(rig=RigInfo(kind="depm", name="emulated dEPM bench"), depm=default_settings(),
                     emulation=Emulation(backdoor="tcp://127.0.0.1:1"),
                     preflight=PreflightSettings(kst_round_trip_ms=LOOPBACK_ROUND_TRIP_MS))


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
    from rigctl.core.errors import RigError
    from rigctl.drivers.kuka_sunrise import KukaArm

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


def _hold(rig: RigConfig, target: dict):
    """`{"joints_rad": [[7 values], [7 values]]}`: a pose of both arms (in the rig file's order)
    that keeps every safety constraint (joint ranges, the keep-out sphere, the EPMs apart), reached
    by a straight joint-space ramp no joint of which is faster than the rig's speed fraction of
    its maximum and that keeps every constraint on its way, sampled every `check_step_s`."""
    import numpy as np

    from rigctl.core.errors import ConfigError, LimitError
    from rigctl.plans.depm import rig_from_settings
    from rigctl.plans.depm_safety import SPEED_TOLERANCE, violations
    from rigctl.rigs.depm.actuators import ArmPair
    from rigctl.rigs.depm.motion import caps
    from rigctl.run.hold import HoldRequest, target_values

    if rig.depm is None:
        raise ConfigError("a depm rig needs a [depm] table (arms, Hall board)")
    depm_rig = rig_from_settings(rig.depm)
    arms, limits = depm_rig.arms, depm_rig.limits
    q = target_values(target, "joints_rad", (len(arms), 7), KIND.name,
                      f"rad, seven joints for each arm ({', '.join(a.name for a in arms)})")

    def refuse(found: list, what: str) -> None:
        if found:
            more = f" (and {len(found) - 1} more)" if len(found) > 1 else ""
            raise LimitError(f"{what} breaks a safety constraint: {found[0]}{more}; ask for "
                             "another pose",
                             device=found[0].arm)

    refuse(violations(np.zeros(1), q[:, None, :], None, arms, limits), "the pose")
    speed, _ = caps(arms, limits)

    def check_ramp(start: np.ndarray, ramp_s: float) -> None:
        q0 = np.asarray(start, dtype=float).reshape(q.shape)
        needed_s = float(np.max(np.abs(q - q0) / speed))
        if needed_s > ramp_s * (1.0 + SPEED_TOLERANCE):
            raise LimitError(f"the ramp to this pose needs ramp_s >= {needed_s:.2f} s (the joints "
                             f"at {limits.speed_fraction:.0%} of their maximum speed), asked "
                             f"{ramp_s:g} s; ask for a longer ramp_s")
        t = np.linspace(0.0, ramp_s, max(2, int(np.ceil(ramp_s / limits.check_step_s)) + 1))
        path = q0[:, None, :] + (q - q0)[:, None, :] * (t / max(ramp_s, 1e-12))[None, :, None]
        refuse(violations(t, path, None, arms, limits), "the ramp to this pose")

    return HoldRequest({"joints_rad": q.tolist()}, q.ravel(), ArmPair.connect,
                       rig.depm.servo_rate_hz, "skip", check_ramp,
                       pose_now=lambda arms_open: arms_open.joint_positions())


def _teleop(rig: RigConfig, mode: str | None):
    from rigctl.rigs.depm.teleop import teleop_drive

    return teleop_drive(rig, mode)


def _settings() -> type[RigConfig]:
    from rigctl.rigs.depm.settings import DepmRig

    return DepmRig



def _probe_arm(rig: RigConfig, device: Device) -> str:
    from rigctl.rigs.depm.probes import arm

    return arm(rig, device)


def _probe_hall(rig: RigConfig, device: Device) -> str:
    from rigctl.rigs.depm.probes import hall

    return hall(rig, device)


def _patience_s(rig: RigConfig) -> float:
    """The arms' and the Hall board's reply timeout."""
    return rig.depm.reply_timeout_s if rig.depm is not None else 0.0


def _template() -> str:
    """The commented rig file of `rigctl init depm` (package data)."""
    from importlib.resources import files

    return (files("rigctl.rigs.depm") / "template.toml").read_text()

KIND = RigKind(
    teleop=_teleop,
    name="depm",
    description="two KUKA LBR iiwa arms carrying permanent magnets, a three-sensor Hall board",
    faults=fault_profile,
    scene="arms",
    scene_of=arms_scene,
    plans={"field-sequence": _field_sequence},
    channels=_channels, devices=_devices, make_safe=_make_safe, hold=_hold, bench_rig=_bench_rig, settings=_settings,
    template=_template, bench="rigctl.emulators.depm:DepmBench",
    probes={"arm": _probe_arm, "hall board": _probe_hall}, patience_s=_patience_s)
