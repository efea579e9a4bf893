"""The spinner as the run engine's actuator group: one channel, the magnet's rotation rate.

A cycle takes the wanted rate (turns/s, signed) and streams the jog that covers it for the time
since the last cycle (`driver.GrblController.jog`), then asks `?` and returns the rate the status
report gives (its feed, signed by the MPos change). GRBL's planner runs only as fast as it could
stop within what it holds (v^2 / 2a of angle): a queue of exactly that would slow the rotor at
every late cycle, so the jogs also keep `LEAD_S` of motion more queued (the angle sent less the
MPos reported, topped up by at most one cycle's angle per cycle). A wanted rate of zero after a nonzero one
sends a jog cancel, so the rotor stops at `$120` from where it is instead of running out the
planner's queue; no jog is sent until the controller reports `Idle` again (GRBL would flush it).
"Energised" is a no-op: GRBL holds the stepper enabled; the rotor turns only when jogged. The
e-stop is the driver's latched soft reset; the end is `stop_rotor` (jog cancel, feed hold, wait
for rest, soft reset), confirmed by a status report at rest.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from rigctl.core.channels import Channel
from rigctl.core.errors import DeviceError, LimitError, RigError
from rigctl_grbl_spinner.driver import JOG_CANCEL, GrblController, stop_rotor
from rigctl_grbl_spinner.settings import GrblSettings, SpinnerConfig

log = logging.getLogger(__name__)

DEVICE = "grbl"
MIN_JOG_DEG = 0.001  # GRBL's 3 decimals: a shorter jog is nothing
LEAD_S = 0.06  # motion kept queued beyond the planner's stopping distance: late cycles' margin


def spinner_channels(rig: SpinnerConfig) -> list[Channel]:
    g = rig.grbl
    return [Channel(g.magnet, "Hz", -g.max_rate_hz, g.max_rate_hz, DEVICE)]


class SpinnerActuators:
    """The connected controller of a rig (`connect`), one channel: the rotation rate in Hz."""

    windings = None  # a stepper's windings are the controller's business: nothing to model

    def __init__(self, controller: GrblController, settings: GrblSettings,
                 channels: list[Channel]) -> None:
        self.controller = controller
        self.settings = settings
        self.names = [controller.name]
        self.channels = channels
        self.measured = np.zeros(1)
        self._last_s: float | None = None
        self._last_position: float | None = None
        self._wanted = 0.0
        self._cancelling = False
        self._end_deg: float | None = None  # where the jogs sent so far end (MPos, degrees)

    @classmethod
    def connect(cls, rig: SpinnerConfig) -> SpinnerActuators:
        """Open, reset and check the controller (the rotor at rest): Disconnected, DeviceTimeout
        or ConfigError naming it otherwise."""
        controller = GrblController.open(rig.grbl, name=DEVICE)
        try:
            status = controller.connect()
        except BaseException:
            controller.close()
            raise
        actuators = cls(controller, rig.grbl, spinner_channels(rig))
        actuators._last_position = actuators._end_deg = status.position_deg
        return actuators

    def energise(self) -> None:
        pass

    def cycle(self, setpoints: np.ndarray) -> np.ndarray:
        wanted = float(setpoints[0])
        if abs(wanted) > self.settings.max_rate_hz + 1e-9:
            raise LimitError(f"{wanted:g} Hz is beyond the rig's max_rate_hz "
                             f"{self.settings.max_rate_hz:g}", device=DEVICE)
        now = time.monotonic()
        dt = 1.0 / self.settings.rate_hz if self._last_s is None else now - self._last_s
        dt = min(dt, 3.0 / self.settings.rate_hz)  # a late cycle adds no more than it can catch up
        self._last_s = now
        c = self.controller
        if wanted == 0.0:
            if self._wanted != 0.0:
                c.realtime(JOG_CANCEL)
                self._cancelling = True
        elif not self._cancelling:
            delta = wanted * 360.0 * dt + self._top_up(wanted, dt)
            if abs(delta) >= MIN_JOG_DEG:
                c.jog(delta, wanted)
                self._end_deg = (self._end_deg or 0.0) + delta
        self._wanted = wanted
        status = c.query_status()
        if c.alarm is not None:
            raise DeviceError(f"ALARM:{c.alarm}: the controller stopped the rotor", device=DEVICE)
        if c.banners > 1:
            raise DeviceError("the controller reset itself (its welcome banner came unasked)",
                              device=DEVICE)
        if status.state == "Idle":  # nothing queued (a jog cancel flushed what was)
            self._cancelling = False
            self._end_deg = status.position_deg
        moved = 0.0 if self._last_position is None else status.position_deg - self._last_position
        self._last_position = status.position_deg
        rate = status.feed_deg_min / 21600.0
        self.measured[0] = math.copysign(rate, moved) if moved else (rate if wanted >= 0 else -rate)
        return self.measured

    def _top_up(self, wanted_hz: float, dt: float) -> float:
        """Degrees to add to this cycle's jog so that the queue holds the planner's stopping
        distance and `LEAD_S` more at the wanted rate (never more than one cycle's angle)."""
        if self._end_deg is None or self._last_position is None:
            return 0.0
        v = abs(wanted_hz) * 360.0
        wanted_queue = v * v / (2 * self.settings.acceleration_deg_s2) + v * LEAD_S
        queued = math.copysign(1.0, wanted_hz) * (self._end_deg - self._last_position)
        return math.copysign(min(max(wanted_queue - queued, 0.0), v * dt), wanted_hz)

    def emergency_zero(self) -> list[str]:
        return [] if self.controller.emergency_stop() else [DEVICE]

    def zero_now(self) -> None:
        """After an e-stop: the latched soft reset went out; read the banner it brought."""
        try:
            self.controller.reset()
        except RigError as err:
            log.error("e-stop: %s", err)

    def stop(self, ramp_s: float) -> list[str]:
        """Rotor to rest (see the module docstring), link closed; never raises. The controller's
        name unless a status report at rest confirmed it."""
        confirmed = False
        try:
            stop_rotor(self.controller, self.settings)
            confirmed = True
        except RigError as err:
            log.error("safe stop: %s", err)
        except Exception:
            log.exception("%s: safe stop failed", DEVICE)
        self.controller.close()
        return [] if confirmed else [DEVICE]

    @staticmethod
    def make_safe_directly(rig: SpinnerConfig) -> dict[str, str | None]:
        """Open the controller anew and bring the rotor to rest (`stop_rotor`); never raises."""
        try:
            controller = GrblController.open(rig.grbl, name=DEVICE)
        except RigError as err:
            return {DEVICE: str(err)}
        except Exception as err:
            return {DEVICE: f"{type(err).__name__}: {err}"}
        try:
            controller._stopped = False
            stop_rotor(controller, rig.grbl)
            return {DEVICE: None}
        except RigError as err:
            return {DEVICE: str(err)}
        except Exception as err:
            return {DEVICE: f"{type(err).__name__}: {err}"}
        finally:
            controller.close()
