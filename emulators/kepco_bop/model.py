"""Pure model of one coil fed by a Kepco BOP 50-20 master/slave pair: state advances only in `step(dt)`.

The coil is an R-L load. Whatever the supply is asked to do, it applies a terminal voltage `v`
that is constant over a step, so the coil current follows the exact solution of L di/dt = v - R i:

    i(t + dt) = v/R + (i(t) - v/R) * exp(-dt R / L)

- Current mode, output on: the supply applies v = R * I_set, clamped to +-compliance. Unclamped,
  the current approaches the setpoint with the time constant L/R and the terminal voltage
  R i + L di/dt equals R * I_set <= compliance throughout; clamped, di/dt is limited so that the
  voltage stays at the compliance and the current settles at +-compliance/R (the BOP's voltage
  protect channel limits the output; BOP-GL 1KW manual Sec. 3.3.6).
  A real BOP's current loop forces faster than L/R up to its compliance; this model is the slower,
  conservative case, which is what the rig's settle time (hold_s >= 5 L/R) assumes.
- Voltage mode, output on: v = V_set, and |i| is held at the current setting (protect channel).
- Output off (or over-temperature): the supply holds its terminals at 0 V, so the stored energy
  decays through the coil's own resistance with the same time constant (an "active" load type
  in the manual's terms, Sec. 3.3.7); the terminal voltage reads 0.

The winding heats (`rigctl.physics.thermal`, given a `winding`): its temperature follows the Joule power
of the coil's current over every step, and when it reaches `trip_C` the supply trips on
over-temperature exactly as `inject_overtemperature` makes it (output off, device error 20101
queued, questionable bit 3): the coil's thermal cut-out wired to the BOP's interlock, which is how
a lab protects a winding (that the BOP reports it as its own over-temperature is a guess). The trip
clears by itself once the winding has cooled `TRIP_HYSTERESIS_K` below it; the output stays off
until switched on again.

Refused settings (|I| above the rating, a compliance outside (0, rating]) post SCPI error -222
"Data out of range" and leave the setting unchanged (BOP 1KW manual App. B, CURRent command).
The error queue is FIFO and bounded: 15 errors are kept, the 16th becomes -350 "Too many errors"
and later ones are dropped until the queue is read (Kepco MST 488 manual, SYST:ERR? par. B.46;
that the BOP-GL queue has the same depth is a guess).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal

from rigctl.physics.thermal import Windings, step_current_one

Mode = Literal["CURR", "VOLT"]

NO_ERROR = (0, "No error")
QUEUE_OVERFLOW = (-350, "Too many errors")
DATA_OUT_OF_RANGE = (-222, "Data out of range")
# BOP 1KW manual Table B-5 lists device errors 2yy01 "OVER TEMPERATURE", yy being the unit's place
# on the master/slave bus; yy = 01 for the master is our reading, i.e. a guess.
OVER_TEMPERATURE = (20101, "OVER TEMPERATURE")

# Questionable condition register: over-temperature is bit 3 (value 8) in Kepco's BIT 232 manual
# (Fig. B-20); that the BOP-GL uses the same bit is a guess.
QUES_OVERTEMPERATURE = 8

ERROR_QUEUE_DEPTH = 16

TRIP_HYSTERESIS_K = 10.0  # a thermal cut-out closes again this far below its trip point
THERMAL_STEP_S = 0.01  # the winding is stepped with the mean square current of this much time


@dataclass(frozen=True)
class BopStatus:
    """A snapshot of the model for backdoors and tests (A, V, s)."""

    output_on: bool
    mode: Mode
    current_setpoint_A: float
    voltage_setpoint_V: float
    current_A: float
    voltage_V: float
    overtemperature: bool
    time_s: float
    winding_C: float | None = None


class BopCoilModel:
    """One coil (R, L) on a BOP pair; a current or voltage source with a compliance, stepped by hand.

    Units: A, V, ohm, H, s. `current_limit_A` and `compliance_V` are the pair's ratings (20 A,
    100 V for two BOP 50-20 in series); the compliance *setting* starts at the rating.
    """

    def __init__(
        self,
        resistance_ohm: float,
        inductance_H: float,
        current_limit_A: float = 20.0,
        compliance_V: float = 100.0,
        winding: Windings | None = None,
        trip_C: float | None = None,
    ) -> None:
        if resistance_ohm <= 0 or inductance_H <= 0:
            raise ValueError("resistance_ohm and inductance_H must be positive")
        if current_limit_A <= 0 or compliance_V <= 0:
            raise ValueError("current_limit_A and compliance_V must be positive")
        self.resistance_ohm = float(resistance_ohm)
        self.inductance_H = float(inductance_H)
        self.current_limit_A = float(current_limit_A)
        self.compliance_V = float(compliance_V)
        self.time_s = 0.0
        self.current_A = 0.0
        self.voltage_V = 0.0
        self.overtemperature = False
        self._errors: deque[tuple[int, str]] = deque()
        self.event_status = 0  # IEEE 488.2 standard event status register, cleared by *ESR? / *CLS
        self.questionable_event = 0  # latched questionable bits, cleared by STAT:QUES? / *CLS
        # the winding (one, `rigctl.physics.thermal.Windings`): its temperature, peak, and trip point
        self.winding = winding
        self._winding = None if winding is None else winding.one()
        self.winding_C = None if winding is None else float(winding.ambient_C[0])
        self.winding_peak_C = self.winding_C
        self.trip_C = trip_C
        self._tripped_by_heat = False
        self._heat_i2t = 0.0  # integral of i^2 dt (A^2 s) and time not yet given to the winding
        self._heat_t = 0.0
        self.reset()

    # -- settings -------------------------------------------------------------------------------

    def reset(self) -> None:
        """*RST: output off, current mode, zero setpoints, compliance at the rating.

        The coil's current is physical state and is not reset; it decays once the output is off.
        """
        self.output_on = False
        self.mode: Mode = "CURR"
        self.current_setpoint_A = 0.0
        self.voltage_setpoint_V = self.compliance_V  # in current mode VOLT is the compliance

    @property
    def compliance_setting_V(self) -> float:
        """The voltage limit in force in current mode (the VOLT setting), V."""
        return self.voltage_setpoint_V if self.mode == "CURR" else self.compliance_V

    @property
    def time_constant_s(self) -> float:
        """L/R in s."""
        return self.inductance_H / self.resistance_ohm

    def set_mode(self, mode: Mode) -> None:
        if mode not in ("CURR", "VOLT"):
            raise ValueError(f"mode must be CURR or VOLT, got {mode!r}")
        if mode != self.mode:
            self.mode = mode
            # The channel that was the limit becomes the main channel; start it from the rating.
            self.voltage_setpoint_V = self.compliance_V if mode == "CURR" else 0.0
            self.current_setpoint_A = 0.0 if mode == "CURR" else self.current_limit_A

    def set_current(self, amps: float) -> bool:
        """CURR: the setpoint (current mode) or the current limit (voltage mode).

        Refused with -222 when |amps| exceeds the rating, or is not positive as a limit.
        """
        if not math.isfinite(amps) or abs(amps) > self.current_limit_A:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        if self.mode == "VOLT" and amps <= 0:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        self.current_setpoint_A = float(amps)
        return True

    def set_voltage(self, volts: float) -> bool:
        """VOLT: the compliance (current mode, must be in (0, rating]) or the output voltage."""
        if not math.isfinite(volts) or abs(volts) > self.compliance_V:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        if self.mode == "CURR" and volts <= 0:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        self.voltage_setpoint_V = float(volts)
        return True

    def set_output(self, on: bool) -> bool:
        """OUTP ON/OFF. Turning on while over-temperature is refused and re-posts the fault."""
        if on and self.overtemperature:
            self.push_error(*OVER_TEMPERATURE)
            return False
        self.output_on = bool(on)
        return True

    # -- faults and the error queue ---------------------------------------------------------------

    def push_error(self, code: int, message: str) -> None:
        """Queue an error (FIFO); when one short of full, the overflow marker takes the last place."""
        if code <= -100 and code > -200:
            self.event_status |= 32  # command error
        elif code <= -200 and code > -300:
            self.event_status |= 16  # execution error
        elif code <= -400 and code > -500:
            self.event_status |= 4  # query error
        else:
            self.event_status |= 8  # device-dependent error (Table B-5: "Device Error bit 3")
        if len(self._errors) >= ERROR_QUEUE_DEPTH:
            return
        if len(self._errors) == ERROR_QUEUE_DEPTH - 1:
            self._errors.append(QUEUE_OVERFLOW)
            return
        self._errors.append((int(code), str(message)))

    def pop_error(self) -> tuple[int, str]:
        """SYST:ERR?: the oldest error, or (0, "No error")."""
        return self._errors.popleft() if self._errors else NO_ERROR

    @property
    def error_count(self) -> int:
        return len(self._errors)

    def clear_status(self) -> None:
        """*CLS: empty the error queue and the event status."""
        self._errors.clear()
        self.event_status = 0
        self.questionable_event = 0

    def read_event_status(self) -> int:
        """*ESR?: read and clear the standard event status register."""
        value, self.event_status = self.event_status, 0
        return value

    def questionable_condition(self) -> int:
        """STAT:QUES:COND?: the live questionable condition bits."""
        return QUES_OVERTEMPERATURE if self.overtemperature else 0

    def read_questionable_event(self) -> int:
        """STAT:QUES?: the questionable bits latched since the last read, then cleared."""
        value, self.questionable_event = self.questionable_event, 0
        return value

    def inject_overtemperature(self) -> None:
        """Backdoor: the supply trips on over-temperature: output off, device error queued."""
        self.overtemperature = True
        self.questionable_event |= QUES_OVERTEMPERATURE
        self.output_on = False
        self.push_error(*OVER_TEMPERATURE)

    def clear_overtemperature(self) -> None:
        """Backdoor: the supply has cooled down; the output stays off until turned on again."""
        self.overtemperature = False

    # -- dynamics -------------------------------------------------------------------------------

    def applied_voltage_V(self) -> float:
        """The terminal voltage the supply applies now (constant until the next setting change)."""
        if not self.output_on:
            return 0.0
        if self.mode == "CURR":
            limit = self.voltage_setpoint_V
            return min(max(self.resistance_ohm * self.current_setpoint_A, -limit), limit)
        return self.voltage_setpoint_V

    def step(self, dt: float) -> None:
        """Advance by `dt` seconds (exact for settings held constant over the step)."""
        if dt < 0:
            raise ValueError(f"dt must be >= 0, got {dt}")
        if dt == 0:
            return
        v = self.applied_voltage_V()
        target = v / self.resistance_ohm
        decay = math.exp(-dt / self.time_constant_s)
        current = target + (self.current_A - target) * decay
        if self.output_on and self.mode == "VOLT" and abs(current) > self.current_setpoint_A:
            # the current protect channel takes over: the supply holds the limit current
            current = math.copysign(self.current_setpoint_A, current)
            v = self.resistance_ohm * current
        if self._winding is not None:  # exact for i^2 linear over the step; fine at dt << L/R
            self._heat_i2t += 0.5 * (self.current_A ** 2 + current ** 2) * dt
            self._heat_t += dt
            if self._heat_t >= THERMAL_STEP_S:
                self._heat(self._heat_t, self._heat_i2t / self._heat_t)
                self._heat_i2t = self._heat_t = 0.0
        self.current_A = current
        self.voltage_V = v
        self.time_s += dt

    def _heat(self, dt: float, mean_square_A2: float) -> None:
        """The winding over `dt` with the step's mean square current; trip or recover."""
        assert self._winding is not None and self.winding_C is not None
        self.winding_C = step_current_one(self.winding_C, math.sqrt(mean_square_A2), dt,
                                          self._winding)
        self.winding_peak_C = max(self.winding_peak_C, self.winding_C)
        if self.trip_C is None:
            return
        if self.winding_C >= self.trip_C and not self.overtemperature:
            self._tripped_by_heat = True
            self.inject_overtemperature()
        elif self._tripped_by_heat and self.winding_C < self.trip_C - TRIP_HYSTERESIS_K:
            self._tripped_by_heat = False
            self.clear_overtemperature()

    def status(self) -> BopStatus:
        return BopStatus(
            output_on=self.output_on,
            mode=self.mode,
            current_setpoint_A=self.current_setpoint_A,
            voltage_setpoint_V=self.voltage_setpoint_V,
            current_A=self.current_A,
            voltage_V=self.voltage_V,
            overtemperature=self.overtemperature,
            time_s=self.time_s,
            winding_C=self.winding_C,
        )
