"""Driver for one coil's Kepco BOP 50-20 pair: the master programmed in SCPI, the slave in series.

The master runs in current mode; in current mode the VOLTage setting is the compliance (the
voltage the pair may apply to drive the coil). Commands are LF-terminated SCPI lines on whatever
transport the driver is handed (the BOP-GL's LAN socket, port 5025, or a serial line). See
docs/kepco-bop.md for the commands and the manual sections they come from.

The stream loop's hot path is one write and one read per supply per cycle:
`send_setpoint` writes `CURR 1.2345;:MEAS:CURR?` (a compound message: a setpoint and a measurement
query, which the BOP accepts, manual Sec. 3.6.4.6), and `read_measured` reads the answer. A
loop sends to all six supplies first and then reads all six, so the round trips overlap.

Every error names the device (`x+: ...`). After a timeout or a garbled reply the next command
first discards whatever is pending, so a late reply cannot be taken for the answer to a newer
question.

E-stop does not wait for the stream thread: `emergency_zero` may be called from any thread, even
while the stream thread waits for a reply. It writes `CURR 0.0000;:OUTP OFF` (no query, so no
reply that could be taken for a measurement) and latches: from then on every setpoint leaves as
0 A and the output cannot be switched on again, until `configure` starts afresh. A lock keeps the
two threads' messages from interleaving on the wire.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time

from rigctl.core.errors import (
    ConfigError,
    DeviceError,
    DeviceTimeout,
    Disconnected,
    LimitError,
    ProtocolError,
    RigError,
)
from rigctl.core.transport import Transport

log = logging.getLogger(__name__)

PAIR_CURRENT_RATING_A = 20.0  # BOP 50-20: +-20 A
PAIR_VOLTAGE_RATING_V = 100.0  # two 50 V units in series
MAX_REPLY_BYTES = 1024  # the BOP's longest message is 253 characters (manual App. B.2)
TERMINATOR = b"\n"
GARBLED_STREAK = 3  # unreadable measurement answers in a row that end a run (fewer are skipped)

_NUMBER = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?")
_ERROR_ENTRY = re.compile(r'([+-]?\d+)\s*,\s*"(.*)"')


def _format_amps(amps: float) -> str:
    """Four decimals (0.1 mA), never "-0.0000"."""
    return f"{round(amps, 4) + 0.0:.4f}"


def _describe(errors: list[tuple[int, str]]) -> str:
    first = f'device error {errors[0][0]} "{errors[0][1]}"'
    if len(errors) == 1:
        return first
    rest = ", ".join(f'{code} "{message}"' for code, message in errors[1:])
    return f"{first} (and {len(errors) - 1} more: {rest})"


class KepcoBop:
    """One coil's supply pair: the master BOP, programmed in current mode; the slave follows in series.

    `current_limit_A` (<= 20 A) is checked before anything is sent; `compliance_V` (<= 100 V) is
    programmed as the voltage limit; `timeout_s` is the watchdog on every reply.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        name: str,
        current_limit_A: float = 20.0,
        compliance_V: float = 100.0,
        timeout_s: float = 0.25,
    ) -> None:
        if not 0 < current_limit_A <= PAIR_CURRENT_RATING_A:
            raise ConfigError(
                f"current_limit_A must be in (0, {PAIR_CURRENT_RATING_A:g}] A, got {current_limit_A}",
                device=name,
            )
        if not 0 < compliance_V <= PAIR_VOLTAGE_RATING_V:
            raise ConfigError(
                f"compliance_V must be in (0, {PAIR_VOLTAGE_RATING_V:g}] V, got {compliance_V}",
                device=name,
            )
        if timeout_s <= 0:
            raise ConfigError(f"timeout_s must be positive, got {timeout_s}", device=name)
        self.name = name
        self.current_limit_A = float(current_limit_A)
        self.compliance_V = float(compliance_V)
        self.timeout_s = float(timeout_s)
        self._transport = transport
        self._stale = False  # a reply may still be in flight: discard input before the next command
        self._awaiting_measurement = False
        self._last_setpoint_A = 0.0
        self._wire = threading.Lock()  # one message at a time on the wire (e-stop comes from afar)
        self._estopped = False  # latched by emergency_zero: every setpoint leaves as 0 A
        self._last_measured_A = 0.0
        self._garbled_streak = 0
        self.garbled = 0  # unreadable measurement answers skipped

    @property
    def last_setpoint_A(self) -> float:
        """The last current setpoint sent (A); where `safe_stop` ramps from."""
        return self._last_setpoint_A

    # -- wire ------------------------------------------------------------------------------------

    def _write(self, command: str) -> None:
        with self._wire:
            self._write_unlocked(command)

    def _write_unlocked(self, command: str) -> None:
        if self._stale:
            self._transport.discard_input()
            self._stale = False
        try:
            self._transport.write(command.encode("ascii") + TERMINATOR)
        except Disconnected as err:
            raise Disconnected(f"link lost ({err})", device=self.name) from err
        except DeviceTimeout as err:
            self._stale = True
            raise DeviceTimeout(str(err), device=self.name) from err

    def _read_line(self) -> str:
        try:
            raw = self._transport.read_until(
                TERMINATOR, timeout_s=self.timeout_s, max_bytes=MAX_REPLY_BYTES
            )
        except DeviceTimeout as err:
            self._stale = True
            raise DeviceTimeout(
                f"no reply within {self.timeout_s:g} s (watchdog)", device=self.name
            ) from err
        except Disconnected as err:
            raise Disconnected(f"link lost ({err})", device=self.name) from err
        except ProtocolError as err:
            self._stale = True
            raise ProtocolError(str(err), device=self.name) from err
        try:
            return raw.decode("ascii").strip()
        except UnicodeDecodeError:
            self._stale = True
            raise ProtocolError(f"unreadable reply {raw!r}", device=self.name) from None

    def _query(self, command: str) -> str:
        self._write(command)
        return self._read_line()

    def _number(self, text: str, what: str) -> float:
        if not _NUMBER.fullmatch(text):
            self._stale = True
            raise ProtocolError(f"{what}: expected a number, got {text!r}", device=self.name)
        return float(text)

    def _check_setpoint(self, amps: float) -> None:
        if not math.isfinite(amps):
            raise LimitError(f"current setpoint {amps!r} is not a number; nothing was sent",
                             device=self.name)
        if abs(amps) > self.current_limit_A:
            raise LimitError(
                f"current setpoint {amps:g} A exceeds the limit +-{self.current_limit_A:g} A; "
                "nothing was sent",
                device=self.name,
            )

    # -- commands --------------------------------------------------------------------------------

    def identify(self) -> str:
        """The *IDN? answer (maker, model, serial, firmware)."""
        answer = self._query("*IDN?")
        if not answer:
            raise ProtocolError("empty *IDN? answer", device=self.name)
        return answer

    def configure(self) -> None:
        """Clear status, current mode, compliance voltage, zero current; DeviceError if the supply
        reported any error (the errors are drained and named)."""
        self._transport.discard_input()
        self._stale = False
        self._estopped = False
        self._write("*CLS")
        self._write("FUNC:MODE CURR")
        self._write(f"VOLT {self.compliance_V:.2f}")
        self._write("CURR 0.0000")
        self._last_setpoint_A = 0.0
        self.check_errors()
        log.info("%s: configured (current mode, compliance %g V)", self.name, self.compliance_V)

    def output(self, on: bool) -> None:
        """Enable or disable the output. Turning on is confirmed with OUTP?; a refusal raises
        DeviceError naming the supply's errors (e.g. over-temperature)."""
        if not on:
            self._write("OUTP OFF")
            return
        if self._estopped:
            raise DeviceError("e-stop latched: the output stays off (configure the supply again)",
                              device=self.name)
        answer = self._query("OUTP ON;:OUTP?")
        if answer == "1":
            return
        if answer != "0":
            self._stale = True
            raise ProtocolError(f"OUTP?: expected 0 or 1, got {answer!r}", device=self.name)
        errors = self.errors()
        reason = _describe(errors) if errors else "no error reported"
        raise DeviceError(f"output did not turn on: {reason}", device=self.name)

    def set_current(self, amps: float) -> None:
        """Program the current setpoint (A); LimitError before any I/O when |amps| > limit."""
        self._check_setpoint(amps)
        with self._wire:
            if self._estopped:
                amps = 0.0
            self._write_unlocked(f"CURR {_format_amps(amps)}")
            self._last_setpoint_A = float(amps)

    def measure_current(self) -> float:
        """The output current the supply measures (A)."""
        return self._number(self._query("MEAS:CURR?"), "MEAS:CURR?")

    def measure_voltage(self) -> float:
        """The output voltage the supply measures (V)."""
        return self._number(self._query("MEAS:VOLT?"), "MEAS:VOLT?")

    def errors(self, max_entries: int = 16) -> list[tuple[int, str]]:
        """Drain the error queue (SYST:ERR?) oldest first, at most `max_entries` reads."""
        drained: list[tuple[int, str]] = []
        for _ in range(max_entries):
            answer = self._query("SYST:ERR?")
            match = _ERROR_ENTRY.fullmatch(answer)
            if match is None:
                self._stale = True
                raise ProtocolError(f'SYST:ERR?: expected code,"message", got {answer!r}',
                                    device=self.name)
            code = int(match.group(1))
            if code == 0:
                return drained
            drained.append((code, match.group(2)))
        log.warning("%s: error queue not empty after %d reads", self.name, max_entries)
        return drained

    def check_errors(self) -> None:
        """Drain the error queue and raise DeviceError naming the errors, if there were any.

        The stream loop calls this at a low rate: it is how a trip (over-temperature) surfaces.
        """
        errors = self.errors()
        if errors:
            raise DeviceError(_describe(errors), device=self.name)

    # -- hot path --------------------------------------------------------------------------------

    def send_setpoint(self, amps: float) -> None:
        """Send a setpoint and ask for the measured current in one message; pair with
        `read_measured`. LimitError before any I/O when |amps| > limit."""
        self._check_setpoint(amps)
        if self._awaiting_measurement:
            raise RuntimeError(f"{self.name}: read_measured() must follow each send_setpoint()")
        with self._wire:
            if self._estopped:
                amps = 0.0
            self._write_unlocked(f"CURR {_format_amps(amps)};:MEAS:CURR?")
            self._last_setpoint_A = float(amps)
        self._awaiting_measurement = True

    def read_measured(self) -> float:
        """The measured current (A) answering the last `send_setpoint`. An unreadable answer
        (line noise on RS-232, a garbled reply) is skipped: the setpoint went out in the same
        message, so the cycle stands and the last good measurement is returned again (counted in
        `garbled`); `GARBLED_STREAK` in a row is a ProtocolError. A missing answer is the
        watchdog's (DeviceTimeout) at once."""
        if not self._awaiting_measurement:
            raise RuntimeError(f"{self.name}: read_measured() without send_setpoint()")
        try:
            self._last_measured_A = self._number(self._read_line(), "MEAS:CURR?")
        except ProtocolError as err:
            self._garbled_streak += 1
            self.garbled += 1
            if self._garbled_streak >= GARBLED_STREAK:
                raise ProtocolError(f"{err.args[0] if err.args else err} ({self._garbled_streak} "
                                    "unreadable answers in a row)", device=self.name) from None
            log.warning("%s; the measurement is skipped this cycle", err)
            return self._last_measured_A
        finally:
            self._awaiting_measurement = False
        self._garbled_streak = 0
        return self._last_measured_A

    # -- stopping --------------------------------------------------------------------------------

    def emergency_zero(self) -> bool:
        """E-stop, from any thread: 0 A and output off in one message, now, and latch (every later
        setpoint leaves as 0 A). Never raises: returns False when the message could not be sent
        (a dead link, logged; the supply's own watchdog or interlock must make it safe then)."""
        with self._wire:
            self._estopped = True
            self._last_setpoint_A = 0.0
            try:
                self._transport.write(b"CURR 0.0000;:OUTP OFF" + TERMINATOR)
            except (RigError, OSError) as err:
                log.error("%s: e-stop could not be sent (%s)", self.name, err)
                return False
        return True

    def safe_stop(self, ramp_s: float = 0.1, steps: int = 10) -> bool:
        """Ramp from the last setpoint to 0 A in `steps` over `ramp_s`, then output off, confirmed
        by `OUTP?` answering 0 (BOP par. B.14). Returns whether the supply confirmed it.

        Best effort: never raises on a dead link; what could not be done is logged.
        """
        start = self._last_setpoint_A
        try:
            self._awaiting_measurement = False
            self._transport.discard_input()
            self._stale = False
            steps = max(1, int(steps)) if start != 0.0 else 1
            t0 = time.monotonic()
            for k in range(1, steps + 1):
                amps = start * (1.0 - k / steps)
                with self._wire:
                    if self._estopped:  # an e-stop overtook the ramp: nothing but zero now
                        amps = 0.0
                    self._write_unlocked(f"CURR {_format_amps(amps)}")
                    self._last_setpoint_A = amps
                if k < steps:
                    time.sleep(max(0.0, t0 + k * ramp_s / steps - time.monotonic()))
            answer = self._query("OUTP OFF;:OUTP?")
            if answer != "0":
                log.error("%s: output off not confirmed (OUTP? answered %r)", self.name, answer)
                return False
            log.info("%s: ramped from %g A to 0 A, output off", self.name, start)
            return True
        except (RigError, OSError) as err:
            log.error("%s: safe stop incomplete (%s); the supply's state is unknown", self.name, err)
            return False

    def close(self) -> None:
        """Release the transport (does not change the supply's output)."""
        try:
            self._transport.close()
        except OSError as err:
            log.warning("%s: closing the link failed: %s", self.name, err)
