"""The dual-EPM rig's two KUKA arms as one actuator group for the run engine.

Fourteen channels, seven joint angles (rad) per arm, named `<arm>_q1`..`<arm>_q7` after the rig
file's arm names and grouped by arm, each with the arm's joint range as its limits. A cycle sends
both arms their servo target first and then reads both replies (the measured joints), so the two
round trips overlap. "Energised" for an arm means servoing: before `energise()` the arms only
answer joint reads, and nothing can move them.

Making the arms safe is stopping them: KST's way is to end the servo motion
(`stopDirectServoJoints`), after which the robot brakes and holds where it is. An e-stop
(`emergency_zero`, any thread) sends exactly that to both arms straight from the calling thread
and latches each driver so no further target leaves; `stop` ends the servo (if it still runs),
confirms each arm at rest by reading its joints until they no longer change, and closes the
sessions. There is no ramp for arms: holding the last target is already the gentle stop, which the
program does before it ends.
"""

from __future__ import annotations

import logging

import numpy as np

from rigctl.core.channels import Channel
from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, RigError
from rigctl.drivers.kuka_sunrise import N_JOINTS, KukaArm
from rigctl.plans.depm import rig_from_settings

log = logging.getLogger(__name__)

REST_TIMEOUT_S = 5.0  # an arm that still moves this long after its servo ended is not confirmed


def arm_channels(rig: RigConfig) -> list[Channel]:
    """Seven joint angles per arm in rad, within the arm model's range: the dual-EPM channels."""
    if rig.depm is None:
        return []
    model = rig_from_settings(rig.depm).arms[0].model
    return [Channel(f"{arm}_q{j + 1}", "rad", float(model.lower_rad[j]), float(model.upper_rad[j]),
                    arm) for arm in rig.depm.arm_names for j in range(len(model.lower_rad))]


class ArmPair:
    """Both arms of a depm rig, in the rig file's order; `cycle` takes and returns (14,) rad."""

    def __init__(self, arms: list[KukaArm], channels: list[Channel]) -> None:
        self.arms = arms
        self.channels = channels  # `arm_channels`
        self.windings = None  # permanent magnets: nothing heats
        self.names = [arm.name for arm in arms]
        self.measured = np.zeros(len(arms) * N_JOINTS)
        self._latched = False

    @classmethod
    def connect(cls, rig: RigConfig) -> ArmPair:
        """Open both arms' KST sessions (each answers a joint read; nothing moves). On a failure
        the ones already open are closed and the error is raised."""
        d = rig.depm
        if d is None:
            raise ConfigError("a depm rig needs a [depm] table (arms, Hall board)")
        model = rig_from_settings(d).arms[0].model
        limits = np.stack([model.lower_rad, model.upper_rad], axis=1)
        arms: list[KukaArm] = []
        try:
            for name, url in zip(d.arm_names, d.arm_urls):
                arms.append(KukaArm.open(url, name=name, timeout_s=d.reply_timeout_s,
                                         joint_limits_rad=limits))
        except RigError:
            for arm in arms:
                arm.close()
            raise
        return cls(arms, arm_channels(rig))

    def joint_positions(self) -> np.ndarray:
        """Both arms' measured joints (A, 7) rad."""
        return np.array([arm.joint_positions() for arm in self.arms])

    def energise(self) -> None:
        """Start direct servo on both arms (each holds where it stands until it gets a target)."""
        for arm in self.arms:
            arm.start_servo()

    def cycle(self, setpoints: np.ndarray) -> np.ndarray:
        """Send each arm its seven targets, then read both: the measured joints (14,) rad. After
        an e-stop nothing is sent and the last measurement is returned."""
        if self._latched:
            return self.measured.copy()
        q = np.asarray(setpoints, dtype=float).reshape(len(self.arms), N_JOINTS)
        for arm, target in zip(self.arms, q):
            arm.send_servo(target)
        measured = np.empty_like(self.measured)
        for a, arm in enumerate(self.arms):
            measured[a * N_JOINTS:(a + 1) * N_JOINTS] = arm.read_servo()
        self.measured = measured
        return measured.copy()

    def emergency_zero(self) -> list[str]:
        """E-stop from any thread: end both arms' servo motion now (they brake and hold where they
        are) and latch. Never raises; returns the arms the stop could not be sent to."""
        self._latched = True
        unreached = []
        for arm in self.arms:
            try:
                if not arm.emergency_stop():
                    unreached.append(arm.name)
            except Exception:  # never raise on the e-stop path
                log.exception("%s: e-stop failed", arm.name)
                unreached.append(arm.name)
        return unreached

    def zero_now(self) -> None:
        """On the stream thread after an e-stop: the stop once more to each arm (belt and braces;
        KST answers it whatever the arm is doing)."""
        self.emergency_zero()

    def stop(self, ramp_s: float) -> list[str]:
        """End the servo motion (the arms hold where they are), confirm each at rest, close both.
        Never raises; returns the arms not confirmed at rest. `ramp_s` is not used: the program
        has already brought the targets to a hold."""
        unconfirmed = []
        for arm in self.arms:
            try:
                if arm.servoing:
                    arm.stop_servo()
                elif arm.estopped:
                    arm.emergency_stop()  # cheap, and sure: the latch may have beaten the start
                if not arm.wait_at_rest(REST_TIMEOUT_S):
                    unconfirmed.append(arm.name)
            except RigError as err:
                log.error("%s: stop not confirmed: %s", arm.name, err)
                unconfirmed.append(arm.name)
            finally:
                arm.close()
        return unconfirmed
