"""The six-coil rig's supplies as one group: connect, stream a cycle, watch health, stop safely.

A stream cycle writes every supply's setpoint first and then reads every reply, so the N round
trips overlap instead of adding up. Health is checked between cycles, one supply at a time in
turn, by draining its SCPI error queue: that is how a trip the supply reports on its own (an
over-temperature) surfaces within about a second even though the replies keep coming. Stopping
ramps all supplies down together, then switches each off; a supply whose link is dead is skipped
(its own watchdog is what makes the hardware safe then) and named in the log. An e-stop
(`emergency_zero`) is written to every supply straight from the thread that received it.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from rigctl.core.channels import Channel
from rigctl.core.config import RigConfig
from rigctl.core.errors import RigError
from rigctl.core.transport import open_transport
from rigctl.drivers.kepco_bop import KepcoBop
from rigctl.physics.thermal import Windings

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

log = logging.getLogger(__name__)


def supply_channels(rig: SixCoilRig) -> list[Channel]:
    """One current channel per supply, in A, within its limit: the coil rig's N channels."""
    return [Channel(c.name, "A", -c.current_limit_A, c.current_limit_A, "supplies") for c in rig.coils]


class CoilSupplies:
    """The connected supplies of a rig, in the rig file's coil order."""

    def __init__(self, supplies: list[KepcoBop], *, identities: list[str] | None = None,
                 health_period_s: float = 1.0, rate_hz: float = 100.0,
                 channels: list[Channel] | None = None, windings: Windings | None = None) -> None:
        self.supplies = supplies
        self.channels = channels or []  # `supply_channels`
        self.windings = windings  # the coils the run's winding model watches
        self.identities = identities or []
        self.names = [s.name for s in supplies]
        self.measured_A = np.zeros(len(supplies))
        # one supply's error queue is read every `health_every` cycles, in turn
        self._health_every = max(1, round(health_period_s * rate_hz / max(1, len(supplies))))
        self._cycles = 0

    @staticmethod
    def make_safe_directly(rig: SixCoilRig) -> dict[str, str | None]:
        """Every supply opened anew, zeroed and confirmed (`zero_supplies_directly`): a BOP holds
        its last setpoint while its link is down, so the engine tries again once it returns."""
        return zero_supplies_directly(rig)

    @classmethod
    def connect(cls, rig: RigConfig) -> CoilSupplies:
        """Open, identify and configure every supply (outputs stay off). On any failure the ones
        already opened are switched off and closed, and the error is raised."""
        from rigctl.rigs.six_coil.settings import six_coil_rig

        rig = six_coil_rig(rig)  # a run's `connect` is handed the rig as a RigConfig
        supplies: list[KepcoBop] = []
        identities: list[str] = []
        try:
            for coil in rig.coils:
                try:
                    transport = open_transport(coil.url, timeout_s=rig.stream.reply_timeout_s)
                except RigError as err:  # the transport does not know which supply it is
                    if err.device is not None:
                        raise
                    raise type(err)(str(err), device=coil.name) from None
                supply = KepcoBop(
                    transport, name=coil.name, current_limit_A=coil.current_limit_A,
                    compliance_V=coil.compliance_V, timeout_s=rig.stream.reply_timeout_s,
                )
                supplies.append(supply)
                identities.append(supply.identify())
                supply.configure()
        except RigError:
            group = cls(supplies)
            group.stop(ramp_s=0.0)
            raise
        return cls(supplies, identities=identities, rate_hz=rig.stream.rate_hz,
                   channels=supply_channels(rig), windings=Windings.of_coils(rig.coils))

    def energise(self) -> None:
        for supply in self.supplies:
            supply.output(True)

    def cycle(self, setpoints_A: np.ndarray) -> np.ndarray:
        """Send one setpoint per supply and return the measured currents (A), shape (n,)."""
        for supply, amps in zip(self.supplies, setpoints_A):
            supply.send_setpoint(float(amps))
        for j, supply in enumerate(self.supplies):
            self.measured_A[j] = supply.read_measured()
        self._cycles += 1
        if self._cycles % self._health_every == 0:
            turn = (self._cycles // self._health_every) % len(self.supplies)
            self.supplies[turn].check_errors()
        return self.measured_A

    def emergency_zero(self) -> list[str]:
        """E-stop from any thread, without waiting for the stream thread: every supply gets 0 A
        and output off in one message each, and latches at zero (see `KepcoBop.emergency_zero`).
        Never raises; returns the names of the supplies the message could not be sent to."""
        return [supply.name for supply in self.supplies if not supply.emergency_zero()]

    def zero_now(self) -> None:
        """E-stop: every setpoint to zero at once, then every output off; best effort per supply."""
        for supply in self.supplies:
            try:
                supply.set_current(0.0)
            except RigError as err:
                log.error("e-stop: %s", err)
        for supply in self.supplies:
            supply.safe_stop(ramp_s=0.0)

    def stop(self, ramp_s: float, steps: int = 10) -> list[str]:
        """Ramp every supply from its last setpoint to zero together over `ramp_s`, then switch
        each off and close it. Never raises: a dead supply is logged and skipped. Returns the
        supplies that did not confirm output off (their state is unknown)."""
        alive = list(self.supplies)
        starts = {s.name: s.last_setpoint_A for s in alive}
        t0 = time.monotonic()
        if ramp_s > 0 and any(starts.values()):
            for k in range(1, steps + 1):
                for supply in list(alive):
                    try:
                        supply.set_current(starts[supply.name] * (1.0 - k / steps))
                    except RigError as err:
                        log.error("safe stop: %s", err)
                        alive.remove(supply)
                time.sleep(max(0.0, t0 + k * ramp_s / steps - time.monotonic()))
        unconfirmed = []
        for supply in self.supplies:
            if not supply.safe_stop(ramp_s=0.0):  # zero and output off, best effort
                unconfirmed.append(supply.name)
            supply.close()
        return unconfirmed


CONFIRM_TIMEOUT_S = 0.5  # the direct make-safe waits this long for each supply's confirmation


def zero_supplies_directly(rig: SixCoilRig) -> dict[str, str | None]:
    """E-stop without the stream's connections (no run active, or its process died): open each
    supply anew and tell it 0 A and output off, every supply first; then confirm each: its answer
    to a measurement sent after the zero on the same connection (SCPI answers in order) proves the
    zero was read. A link that takes the bytes but never answers (a hung supply) is not made safe
    by a write alone: it is reported, not counted as told. Best effort, never raises; returns each
    supply's name -> None when it confirmed, else why not."""
    result: dict[str, str | None] = {}
    told: list[KepcoBop] = []
    # the zero leaves at once whatever the timeout; the confirmation may wait longer than a
    # stream cycle's reply (a loaded machine is no reason to call a supply unreachable)
    timeout_s = max(rig.stream.reply_timeout_s, CONFIRM_TIMEOUT_S)
    for coil in rig.coils:
        try:
            transport = open_transport(coil.url, timeout_s=timeout_s)
            supply = KepcoBop(transport, name=coil.name, current_limit_A=coil.current_limit_A,
                              compliance_V=coil.compliance_V, timeout_s=timeout_s)
            if supply.emergency_zero():
                told.append(supply)
                result[coil.name] = None
            else:
                supply.close()
                result[coil.name] = f"{coil.url}: the e-stop message could not be sent"
        except RigError as err:
            result[coil.name] = str(err)
    for supply in told:
        try:
            supply.measure_current()
        except RigError as err:
            result[supply.name] = f"the e-stop was sent but not confirmed: {err}"
        finally:
            supply.close()
    for name, why in result.items():
        if why is not None:
            log.error("e-stop: %s could not be reached: %s", name, why)
    return result
