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

Besides the physics the model holds what a controller can read back over IEEE 488.2 / SCPI
(`protocol.py` parses, this holds the state, so a backdoor sees what a client set):
- the status registers: standard event status and its enable (*ESR? / *ESE), service request
  enable (*SRE), operation condition / event / enable (bit 5 waiting for trigger, 8 constant
  voltage, 10 constant current, 12 list complete, 14 list running: BOP par. 3.6.7.2; that CV / CC
  follow the selected mode, not the load, is a simplification), questionable event / enable;
  `status_byte()` summarises them as IEEE 488.2 and SCPI lay the status byte out (bit 2 error
  queue, 3 questionable, 4 message available, 5 event summary, 6 master summary, 7 operation:
  BOP par. 3.6.7.1 and B.113);
- the protection limits (VOLT:PROT / CURR:PROT, positive and negative, BOP par. B.27-B.36 and
  B.97-B.108): they bound the voltage in current mode and the current in voltage mode together
  with the VOLT / CURR setting; they may be set up to their own maximum (PROT:LIM), which starts
  at 1 % above the rating (BOP App. B.2);
- the list (BOP par. 3.6.3.4, App. B LIST commands): points of the main channel and their dwell
  times, run by CURR:MODE LIST / VOLT:MODE LIST: each point is the setpoint for its dwell (the
  coil answers with its own L/R), the list runs LIST:COUNt times (0 = until stopped), LIST:COUNt:SKIP
  points are left out after the first pass, LIST:DIRection DOWN runs it backwards; at its end the
  mode returns to FIXed and the last point stays the setpoint (guess: the manual says only that the
  unit returns to FIXed);
- the trigger levels (CURR:TRIG / VOLT:TRIG, applied by *TRG when INIT armed the trigger) and saved
  setups (*SAV / *RCL 1-99: mode, setpoints, protection; the output is left as it is, a guess).
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
SETTINGS_CONFLICT = (-221, "Settings conflict")
LISTS_NOT_SAME_LENGTH = (-226, "Lists not same length")

# Operation condition / event bits (BOP par. 3.6.7.2)
OPER_WAITING_FOR_TRIGGER = 1 << 5
OPER_CONSTANT_VOLTAGE = 1 << 8
OPER_CONSTANT_CURRENT = 1 << 10
OPER_LIST_COMPLETE = 1 << 12  # event only
OPER_LIST_RUNNING = 1 << 14

PROTECTION_MARGIN = 1.01  # protection limits may reach 1 % above the rating (BOP App. B.2)
LIST_MAX_POINTS = 5900  # BOP par. 3.6.3.4: up to 5900 points with a single dwell time
LIST_MIN_DWELL_S = 93e-6  # BOP par. 3.6.3.4 (the shortest dwell)
SETUP_SLOTS = range(1, 100)  # *SAV / *RCL locations (guess: the BOP's 99 stored setups)

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
        # IEEE 488.2 / SCPI status registers (module docstring); *RST leaves them, *CLS clears events
        self.event_status_enable = 0
        self.service_request_enable = 0
        self.operation_event = 0
        self.operation_enable = 0
        self.questionable_enable = 0
        self._operation_condition = 0
        # the maxima the protection limits may be set to (PROT:LIM), positive and negative magnitudes
        self.voltage_protection_max_V = [PROTECTION_MARGIN * self.compliance_V] * 2
        self.current_protection_max_A = [PROTECTION_MARGIN * self.current_limit_A] * 2
        self._setups: dict[int, dict] = {}
        # software limits (CURR:LIM / VOLT:LIM, BOP par. B.21-B.24): positive and negative
        # magnitudes the settings may reach, at most the rating; *RST leaves them (the BOP keeps
        # them for power-up with MEM:UPD)
        self.current_soft_limit_A = [self.current_limit_A] * 2
        self.voltage_soft_limit_V = [self.compliance_V] * 2
        self.output_mode = "ACTIVE"  # OUTP:MODE: the emulated off state is always ACTIVE's
        self.clear_list()
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
        # protection limits, positive and negative magnitudes, at their maxima
        self.voltage_protection_V = list(self.voltage_protection_max_V)
        self.current_protection_A = list(self.current_protection_max_A)
        self.current_trigger_A: float | None = None  # CURR:TRIG / VOLT:TRIG (None: the setpoint)
        self.voltage_trigger_V: float | None = None
        self.trigger_armed = False
        self.trigger_continuous = False
        self.list_running = False
        self._refresh_operation()

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
            self.stop_list()
            self.mode = mode
            # The channel that was the limit becomes the main channel; start it from the rating.
            self.voltage_setpoint_V = self.compliance_V if mode == "CURR" else 0.0
            self.current_setpoint_A = 0.0 if mode == "CURR" else self.current_limit_A
            self._refresh_operation()

    def set_current(self, amps: float) -> bool:
        """CURR: the setpoint (current mode) or the current limit (voltage mode).

        Refused with -222 outside the software limits (CURR:LIM, at most the rating), or when not
        positive as a limit.
        """
        high, low = self.current_soft_limit_A
        if not math.isfinite(amps) or not -low <= amps <= high:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        if self.mode == "VOLT" and amps <= 0:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        self.current_setpoint_A = float(amps)
        return True

    def set_voltage(self, volts: float) -> bool:
        """VOLT: the compliance (current mode, must be in (0, rating]) or the output voltage; both
        within the software limits (VOLT:LIM, at most the rating)."""
        high, low = self.voltage_soft_limit_V
        if not math.isfinite(volts) or not -low <= volts <= high:
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

    # -- IEEE 488.2 / SCPI status ------------------------------------------------------------------

    def clear_status(self) -> None:
        """*CLS: empty the error queue and every event register (enables stay; BOP par. A.2)."""
        self._errors.clear()
        self.event_status = 0
        self.questionable_event = 0
        self.operation_event = 0

    def operation_condition(self) -> int:
        """STAT:OPER:COND?: the live operation bits (list complete is an event only)."""
        return self._operation_condition

    def read_operation_event(self) -> int:
        """STAT:OPER?: the operation bits latched since the last read, then cleared."""
        value, self.operation_event = self.operation_event, 0
        return value

    def preset_status(self) -> None:
        """STAT:PRES: operation and questionable enables to 0, so neither reaches the status byte.

        SCPI's meaning; the BOP manual (par. B.116) says "disables reporting of all status events"
        and then names 8193 and 255, bits that the two registers do not use: we take the first.
        """
        self.operation_enable = 0
        self.questionable_enable = 0

    def _refresh_operation(self) -> None:
        """Recompute the operation condition; a 0 -> 1 change of a bit latches it in the event."""
        condition = OPER_CONSTANT_CURRENT if self.mode == "CURR" else OPER_CONSTANT_VOLTAGE
        if self.trigger_armed:
            condition |= OPER_WAITING_FOR_TRIGGER
        if self.list_running:
            condition |= OPER_LIST_RUNNING
        self.operation_event |= condition & ~self._operation_condition
        self._operation_condition = condition

    def status_byte(self, message_available: bool = False) -> int:
        """*STB?: the IEEE 488.2 status byte, bit 6 the master summary of the enabled bits."""
        stb = 4 if self._errors else 0
        if self.questionable_event & self.questionable_enable:
            stb |= 8
        if message_available:
            stb |= 16
        if self.event_status & self.event_status_enable:
            stb |= 32
        if self.operation_event & self.operation_enable:
            stb |= 128
        if stb & self.service_request_enable & ~64:
            stb |= 64
        return stb

    def operation_complete(self) -> None:
        """*OPC: every command has finished by the time the next is read, so bit 0 is set now."""
        self.event_status |= 1

    # -- protection limits ------------------------------------------------------------------------

    def set_protection(self, channel: Literal["VOLT", "CURR"], magnitude: float,
                       side: Literal["BOTH", "POS", "NEG"] = "BOTH", *, maximum: bool = False) -> bool:
        """VOLT:PROT / CURR:PROT [:POS|:NEG], or with `maximum` their :LIM (V or A, a magnitude).

        A limit must be positive and at most its maximum (a maximum: at most 1 % above the
        rating); refused with -222 otherwise. Lowering a maximum lowers a limit above it.
        """
        rating = self.compliance_V if channel == "VOLT" else self.current_limit_A
        limits = self.voltage_protection_V if channel == "VOLT" else self.current_protection_A
        maxima = self.voltage_protection_max_V if channel == "VOLT" else self.current_protection_max_A
        sides = (0, 1) if side == "BOTH" else (0,) if side == "POS" else (1,)
        magnitude = abs(magnitude)
        ceiling = [PROTECTION_MARGIN * rating] * 2 if maximum else maxima
        if not math.isfinite(magnitude) or magnitude <= 0 or any(magnitude > ceiling[k] for k in sides):
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        for k in sides:
            if maximum:
                maxima[k] = magnitude
                limits[k] = min(limits[k], magnitude)
            else:
                limits[k] = magnitude
        return True

    def set_soft_limit(self, channel: Literal["VOLT", "CURR"], magnitude: float,
                       side: Literal["BOTH", "POS", "NEG"] = "BOTH") -> bool:
        """CURR:LIM / VOLT:LIM [:POS|:NEG]: between 0 and the rating (-222 otherwise). A setting
        beyond a lowered limit is not changed (guess: the manual does not say)."""
        rating = self.compliance_V if channel == "VOLT" else self.current_limit_A
        limits = self.voltage_soft_limit_V if channel == "VOLT" else self.current_soft_limit_A
        magnitude = abs(magnitude)
        if not math.isfinite(magnitude) or magnitude > rating:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        for k in (0, 1) if side == "BOTH" else (0,) if side == "POS" else (1,):
            limits[k] = magnitude
        return True

    # -- the list ---------------------------------------------------------------------------------

    def clear_list(self) -> None:
        """LIST:CLE: no points, no dwell times, count 1, no skip, direction up."""
        self.list_channel: Mode | None = None
        self.list_points: list[float] = []
        self.list_dwell_s: list[float] = []
        self.list_count = 1
        self.list_skip = 0
        self.list_direction: Literal["UP", "DOWN"] = "UP"
        self.list_running = False

    def add_list_points(self, channel: Mode, values: list[float]) -> bool:
        """LIST:CURR / LIST:VOLT: append points (A or V) of the list's one main channel."""
        rating = self.current_limit_A if channel == "CURR" else self.compliance_V
        if self.list_running or (self.list_channel not in (None, channel)):
            self.push_error(*SETTINGS_CONFLICT)
            return False
        if len(self.list_points) + len(values) > LIST_MAX_POINTS or any(
                not math.isfinite(v) or abs(v) > rating for v in values):
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        self.list_channel = channel
        self.list_points.extend(float(v) for v in values)
        return True

    def add_list_dwells(self, seconds: list[float]) -> bool:
        """LIST:DWEL: append dwell times (s); one dwell time serves every point."""
        if self.list_running:
            self.push_error(*SETTINGS_CONFLICT)
            return False
        if len(self.list_dwell_s) + len(seconds) > LIST_MAX_POINTS or any(
                not math.isfinite(t) or t < LIST_MIN_DWELL_S for t in seconds):
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        self.list_dwell_s.extend(float(t) for t in seconds)
        return True

    def _list_order(self) -> list[int]:
        order = list(range(len(self.list_points)))
        return order[::-1] if self.list_direction == "DOWN" else order

    def start_list(self) -> bool:
        """CURR:MODE LIST / VOLT:MODE LIST: run the list from its first point.

        The list's channel must be the present mode's (-221 otherwise, or when there is no list);
        the dwell list must hold one time or one per point (-226).
        """
        if not self.list_points or self.list_channel != self.mode:
            self.push_error(*SETTINGS_CONFLICT)
            return False
        if len(self.list_dwell_s) not in (1, len(self.list_points)):
            self.push_error(*LISTS_NOT_SAME_LENGTH)
            return False
        self._list_order_now = self._list_order()
        self._list_position = 0
        self._list_passes_left = self.list_count  # 0: until stopped
        self.list_running = True
        self._apply_list_point()
        self._refresh_operation()
        return True

    def stop_list(self) -> None:
        """CURR:MODE FIX (or a mode change): the list stops where it is."""
        if self.list_running:
            self.list_running = False
            self._refresh_operation()

    def _apply_list_point(self) -> None:
        index = self._list_order_now[self._list_position]
        if self.mode == "CURR":
            self.current_setpoint_A = self.list_points[index]
        else:
            self.voltage_setpoint_V = self.list_points[index]
        dwells = self.list_dwell_s
        self._list_left_s = dwells[0] if len(dwells) == 1 else dwells[index]

    def _advance_list(self) -> None:
        """The present point's dwell is over: the next point, the next pass, or the end."""
        self._list_position += 1
        if self._list_position == len(self._list_order_now):
            if self._list_passes_left == 1:
                self.list_running = False
                self.operation_event |= OPER_LIST_COMPLETE
                self._refresh_operation()
                return
            if self._list_passes_left > 1:
                self._list_passes_left -= 1
            # later passes leave out the first LIST:COUN:SKIP points (BIT 4886 par. B.29: up only)
            skip = self.list_skip if self.list_direction == "UP" else 0
            self._list_position = min(skip, len(self._list_order_now) - 1)
        self._apply_list_point()

    # -- trigger and saved setups -----------------------------------------------------------------

    def arm_trigger(self, continuous: bool | None = None) -> None:
        """INIT (arm once) or INIT:CONT ON|OFF."""
        if continuous is not None:
            self.trigger_continuous = continuous
        self.trigger_armed = self.trigger_continuous if continuous is not None else True
        self._refresh_operation()

    def abort_trigger(self) -> None:
        """ABOR: disarm, unless INIT:CONT ON keeps the trigger armed (BOP par. B.3)."""
        if not self.trigger_continuous:
            self.trigger_armed = False
            self._refresh_operation()

    def trigger(self) -> None:
        """*TRG / TRIG: apply the trigger levels if armed; otherwise nothing (BOP par. 3.6.3.3)."""
        if not self.trigger_armed:
            return
        if self.current_trigger_A is not None:
            self.set_current(self.current_trigger_A)
        if self.voltage_trigger_V is not None:
            self.set_voltage(self.voltage_trigger_V)
        self.abort_trigger()

    def save_setup(self, slot: int) -> bool:
        """*SAV n: keep mode, setpoints and protection limits in location n (1-99)."""
        if slot not in SETUP_SLOTS:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        self._setups[slot] = {"mode": self.mode, "current_setpoint_A": self.current_setpoint_A,
                              "voltage_setpoint_V": self.voltage_setpoint_V,
                              "voltage_protection_V": list(self.voltage_protection_V),
                              "current_protection_A": list(self.current_protection_A)}
        return True

    def recall_setup(self, slot: int) -> bool:
        """*RCL n: restore location n; -222 for a location outside 1-99 or never saved (guess)."""
        if slot not in self._setups:
            self.push_error(*DATA_OUT_OF_RANGE)
            return False
        self.stop_list()
        setup = self._setups[slot]
        self.mode = setup["mode"]
        self.current_setpoint_A = setup["current_setpoint_A"]
        self.voltage_setpoint_V = setup["voltage_setpoint_V"]
        self.voltage_protection_V = list(setup["voltage_protection_V"])
        self.current_protection_A = list(setup["current_protection_A"])
        self._refresh_operation()
        return True

    # -- dynamics -------------------------------------------------------------------------------

    def applied_voltage_V(self) -> float:
        """The terminal voltage the supply applies now (constant until the next setting change)."""
        if not self.output_on:
            return 0.0
        if self.mode == "CURR":  # the VOLT setting and the protection limits bound the voltage
            high = min(self.voltage_setpoint_V, self.voltage_protection_V[0])
            low = -min(self.voltage_setpoint_V, self.voltage_protection_V[1])
            return min(max(self.resistance_ohm * self.current_setpoint_A, low), high)
        return self.voltage_setpoint_V

    def _current_bound_A(self, sign: float) -> float:
        """Voltage mode: the largest current magnitude (A) in the direction of `sign`."""
        return min(self.current_setpoint_A, self.current_protection_A[0 if sign >= 0 else 1])

    def step(self, dt: float) -> None:
        """Advance by `dt` seconds (exact for settings held constant over the step; a running
        list's point changes split the step where they fall)."""
        if dt < 0:
            raise ValueError(f"dt must be >= 0, got {dt}")
        while self.list_running and dt >= self._list_left_s:
            dwell = self._list_left_s
            self._step_held(dwell)
            dt -= dwell
            self._advance_list()
        if self.list_running:
            self._list_left_s -= dt
        self._step_held(dt)

    def _step_held(self, dt: float) -> None:
        """Advance by `dt` seconds with the settings held."""
        if dt == 0:
            return
        v = self.applied_voltage_V()
        target = v / self.resistance_ohm
        decay = math.exp(-dt / self.time_constant_s)
        current = target + (self.current_A - target) * decay
        if self.output_on and self.mode == "VOLT" and abs(current) > self._current_bound_A(current):
            # the current protect channel takes over: the supply holds the limit current
            current = math.copysign(self._current_bound_A(current), current)
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
        # all three are set together, from a winding
        assert self._winding is not None and self.winding_C is not None and self.winding_peak_C is not None
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
