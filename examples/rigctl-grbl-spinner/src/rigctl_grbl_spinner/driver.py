"""The GRBL 1.1 controller of the spinner, over the one transport layer (serial, pty or TCP).

GRBL speaks lines and single real-time bytes (gnea/grbl doc/markdown/interface.md, commands.md,
jogging.md). What this driver relies on:

- Connect: drop whatever is buffered, send a soft reset (0x18) and wait for the welcome banner
  `Grbl 1.1h ['$' for help]` within `boot_timeout_s` (an Arduino that resets itself when the port
  opens prints it after its bootloader anyway, ignoring the 0x18); ask `?`; an `Alarm` state (a
  reset while moving) is unlocked with `$X`: the position GRBL fears for is a rotor's angle,
  which nothing here depends on. Then `$$`: `$100`, `$110` and `$120` must be the rig file's, or
  the controller is refused (`ConfigError`) before anything turns.
- Lines are streamed with GRBL's character-counting flow control: the bytes of every line not yet
  answered (`ok`/`error:N`, one per line, in order) stay within the 127 its 128-byte RX buffer
  takes; a line that would overrun it waits for replies first. Every wait has a deadline
  (`reply_timeout_s`): `DeviceTimeout` naming the controller.
- The rotor turns by incremental jogs (`$J=G91X<degrees>F<degrees/min>`): each stream cycle
  sends the angle the wanted rate covers in the time since the last one, so GRBL's planner, which
  plans to stop at the end of what it holds, keeps just enough queued to run at that rate
  (`v^2 / 2a` of angle: 0.06 s at 5 turns/s and 20 turns/s^2). If this process stops, the rotor
  stops by itself once that queue has run out.
- Every cycle asks `?` and waits for the status report `<Jog|MPos:..|FS:feed,speed>` (the
  status-poll watchdog): its feed is the rate measured, its MPos change the sense.
- To stop: a jog cancel (0x85) decelerates at `$120` and flushes the queue (jogs sent while it
  runs would be flushed too: none are sent until `Idle` is reported); a feed hold (`!`) does the
  same outside a jog; a soft reset stops the steps at once (GRBL raises alarm 3 if it was
  moving). `emergency_stop` (any thread) writes the soft reset under a lock of the wire and
  latches: nothing but real-time bytes is written after it.
- `ALARM:N`, `error:N`, an unexpected banner (the board reset itself) or a line that parses as
  none of GRBL's messages are faults naming the controller.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections import deque
from dataclasses import dataclass

from rigctl.core.errors import ConfigError, DeviceError, DeviceTimeout, ProtocolError, RigError
from rigctl.core.transport import Transport, open_transport
from rigctl_grbl_spinner.settings import DEG_PER_MIN_PER_HZ, GrblSettings

log = logging.getLogger(__name__)

RX_BUFFER_BYTES = 128  # GRBL's serial RX buffer on an ATmega328p; a host keeps under it
BANNER = re.compile(r"^Grbl (\d+\.\d+[a-z]?) \['\$' for help\]$")
STATUS = re.compile(r"^<([A-Za-z]+)(?::(\d))?\|(.*)>$")
STATUS_QUERY, FEED_HOLD, CYCLE_START, SOFT_RESET, JOG_CANCEL = b"?", b"!", b"~", b"\x18", b"\x85"
ERRORS = {1: "expected a command letter", 2: "bad number format", 3: "invalid $ statement",
          8: "not idle (a $ command while moving, or a jog outside Idle/Jog)",
          9: "G-code locked out during alarm or jog", 11: "line overflow", 15: "jog beyond travel",
          16: "invalid jog command", 20: "unsupported G-code", 22: "feed rate undefined"}
ALARMS = {1: "hard limit", 2: "soft limit", 3: "reset while in motion (position lost)"}


@dataclass(frozen=True)
class Status:
    """A real-time status report: state (`Idle`, `Jog`, `Hold:0`, ...), MPos X (degrees) and the
    real-time feed (degrees/min, unsigned)."""

    state: str
    position_deg: float
    feed_deg_min: float

    @property
    def moving(self) -> bool:
        return self.feed_deg_min > 0


def parse_status(line: str) -> Status:
    """`<Jog|MPos:12.000,0.000,0.000|FS:21600,0|WCO:...>` -> Status; ProtocolError otherwise.
    Fields may come in any order and come and go (WCO, Ov, Bf, Pn): only MPos/WPos and F/FS are
    read."""
    match = STATUS.match(line)
    if match is None:
        raise ProtocolError(f"not a status report: {line!r}")
    state = match.group(1) + (f":{match.group(2)}" if match.group(2) else "")
    position = feed = None
    for field in match.group(3).split("|"):
        name, _, values = field.partition(":")
        try:
            if name in ("MPos", "WPos"):
                position = float(values.split(",")[0])
            elif name in ("FS", "F"):
                feed = float(values.split(",")[0])
        except ValueError:
            raise ProtocolError(f"bad {name} in status report {line!r}") from None
    if position is None or feed is None:
        raise ProtocolError(f"status report without position or feed: {line!r}")
    return Status(state, position, feed)


class GrblController:
    """One GRBL controller on an open transport. `connect()` before use; `close()` after."""

    def __init__(self, transport: Transport, settings: GrblSettings, *, name: str = "grbl") -> None:
        self.transport = transport
        self.settings = settings
        self.name = name
        self.timeout_s = settings.reply_timeout_s
        self._in_flight: deque[tuple[str, int]] = deque()  # lines sent, not yet answered
        self._wire = threading.Lock()  # one writer at a time: the stream thread or an e-stop
        self._stopped = False  # latched by emergency_stop
        self.status: Status | None = None  # the last report
        self.messages: list[str] = []  # push messages since the last command
        self.version: str | None = None
        self.alarm: int | None = None  # the last ALARM:N pushed
        self.banners = 0  # welcome banners seen: one more than the resets asked is a reboot

    @classmethod
    def open(cls, settings: GrblSettings, *, name: str = "grbl") -> GrblController:
        """Open the rig file's [grbl] link (Disconnected naming the controller if it cannot)."""
        url = settings.url
        if url.startswith("/"):
            url = f"serial://{url}?baud={settings.baud}"
        try:
            transport = open_transport(url, timeout_s=settings.reply_timeout_s)
        except RigError as err:
            err.device = err.device or name
            raise
        return cls(transport, settings, name=name)

    # -- the wire -------------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        try:
            with self._wire:
                self.transport.write(data)
        except RigError as err:
            raise type(err)(str(err), device=self.name) from None

    def realtime(self, byte: bytes) -> None:
        """Write one real-time byte (`?`, `!`, `~`, 0x18, 0x85): no reply is owed."""
        self._write(byte)

    def send(self, line: str) -> None:
        """Stream `line` (LF-terminated) under character counting: wait (deadline) for replies
        while the unanswered lines and this one would overrun GRBL's RX buffer."""
        if self._stopped:
            raise DeviceError("e-stopped: nothing is sent until it is reconnected", device=self.name)
        size = len(line) + 1
        if size > RX_BUFFER_BYTES - 1:
            raise ProtocolError(f"line of {size} bytes is longer than GRBL's RX buffer: {line!r}",
                                device=self.name)
        deadline = time.monotonic() + self.timeout_s
        while sum(n for _, n in self._in_flight) + size > RX_BUFFER_BYTES - 1:
            self._read(deadline, "an ok to free GRBL's RX buffer")
        self._in_flight.append((line, size))
        self._write(line.encode("ascii") + b"\n")

    def _read(self, deadline: float, waiting_for: str) -> str:
        """Read and dispatch one line from GRBL before `deadline`; returns it."""
        left = deadline - time.monotonic()
        try:
            if left <= 0:
                raise DeviceTimeout("")
            raw = self.transport.read_until(b"\n", timeout_s=left, max_bytes=512)
        except DeviceTimeout:
            raise DeviceTimeout(f"no reply within {self.timeout_s:g} s waiting for {waiting_for}",
                                device=self.name) from None
        except RigError as err:
            raise type(err)(str(err), device=self.name) from None
        line = raw.decode("ascii", errors="replace").strip()
        self._dispatch(line)
        return line

    def _dispatch(self, line: str) -> None:
        if line == "ok" or line.startswith("error:"):
            if not self._in_flight:
                raise ProtocolError(f"a reply with no line awaiting one: {line!r}", device=self.name)
            sent, _ = self._in_flight.popleft()
            if line != "ok":
                code = int(line[6:]) if line[6:].isdigit() else -1
                raise DeviceError(f"{sent!r}: error:{code} ({ERRORS.get(code, 'see GRBL error codes')})",
                                  device=self.name)
        elif line.startswith("<"):
            self.status = parse_status(line)
        elif line.startswith("ALARM:"):
            code = int(line[6:]) if line[6:].isdigit() else -1
            self.alarm = code
            self.messages.append(line)
        elif BANNER.match(line):
            self.version = BANNER.match(line).group(1)  # type: ignore[union-attr]
            self.banners += 1
            self._in_flight.clear()  # a reset empties GRBL's buffers: nothing is owed
            self.messages.append(line)
        elif line.startswith(("[", "$", ">")) or not line:
            self.messages.append(line)
        else:
            raise ProtocolError(f"unreadable line from GRBL: {line!r}", device=self.name)

    def command(self, line: str) -> list[str]:
        """Send `line` and wait (deadline) for its `ok`; the push messages before it. Only with
        nothing else in flight (commands are not streamed)."""
        self.messages = []
        self.send(line)
        deadline = time.monotonic() + self.timeout_s
        while self._in_flight:
            self._read(deadline, f"the reply to {line!r}")
        return list(self.messages)

    def query_status(self) -> Status:
        """`?` and the report it brings (every line before it is dispatched: oks of jogs in
        flight); DeviceTimeout if none comes within the reply deadline (the status watchdog)."""
        self.status = None
        self.realtime(STATUS_QUERY)
        deadline = time.monotonic() + self.timeout_s
        while self.status is None:
            self._read(deadline, "a status report")
        return self.status

    def drain(self) -> None:
        """Wait (deadline) for every line in flight to be answered."""
        deadline = time.monotonic() + self.timeout_s
        while self._in_flight:
            self._read(deadline, "the replies to the lines in flight")

    # -- the controller -------------------------------------------------------------------------
    def reset(self) -> list[str]:
        """Soft reset and the welcome banner (within `boot_timeout_s`); the messages after it
        are read by the next exchange. Returns the lines seen up to the banner."""
        self.transport.discard_input()
        self.messages = []
        self.alarm = None
        self._in_flight.clear()
        self.realtime(SOFT_RESET)
        deadline = time.monotonic() + self.settings.boot_timeout_s
        seen = []
        while True:
            try:
                line = self._read(deadline, "the welcome banner after a soft reset")
            except DeviceTimeout:
                raise DeviceTimeout(f"no welcome banner within {self.settings.boot_timeout_s:g} s "
                                    "of a soft reset: is it a GRBL controller, at this baud?",
                                    device=self.name) from None
            seen.append(line)
            if BANNER.match(line):
                return seen

    def connect(self) -> Status:
        """Reset, unlock an alarm, check the settings against the rig file; the controller idle,
        the rotor still. ConfigError if its settings are not the rig file's."""
        self.reset()
        if self.version is None or not self.version.startswith("1.1"):
            raise DeviceError(f"GRBL {self.version}: this driver speaks GRBL 1.1", device=self.name)
        status = self.query_status()
        if status.state == "Alarm":
            self.command("$X")
            status = self.query_status()
        self.check_settings(self.read_settings())
        return status

    def read_settings(self) -> dict[int, float]:
        table = {}
        for line in self.command("$$"):
            match = re.fullmatch(r"\$(\d+)=([-\d.]+)", line)
            if match:
                table[int(match.group(1))] = float(match.group(2))
        return table

    def check_settings(self, table: dict[int, float]) -> None:
        s = self.settings
        wanted = {100: (s.steps_per_degree, "steps_per_degree"),
                  110: (s.max_rate_deg_min, "max_rate_hz x 21600"),
                  120: (s.acceleration_deg_s2, "max_acceleration_hz_per_s x 360")}
        for number, (value, key) in wanted.items():
            got = table.get(number)
            if got is None or not math.isclose(got, value, rel_tol=1e-3, abs_tol=1e-3):
                raise ConfigError(f"${number}={got} on the controller, the rig file's [grbl] says "
                                  f"{value:.3f} ({key}); set ${number}={value:.3f} on it or fix "
                                  "the rig file", device=self.name)

    def jog(self, delta_deg: float, rate_hz: float) -> None:
        """Stream an incremental jog of `delta_deg` at |rate_hz| turns/s (not waited for)."""
        feed = abs(rate_hz) * DEG_PER_MIN_PER_HZ
        self.send(f"$J=G91X{delta_deg:.3f}F{feed:.1f}")

    def emergency_stop(self) -> bool:
        """Any thread, never raises: a soft reset now, latched. False if it could not be written."""
        self._stopped = True
        try:
            with self._wire:
                self.transport.write(SOFT_RESET)
            return True
        except Exception as err:  # the e-stop must report, not raise
            log.error("%s: e-stop not written: %s", self.name, err)
            return False

    def close(self) -> None:
        try:
            self.transport.close()
        except Exception:
            log.exception("%s: close failed", self.name)


def stop_rotor(controller: GrblController, settings: GrblSettings) -> Status:
    """Bring the rotor to rest and the controller to a clean Idle: jog cancel and feed hold (a
    deceleration at $120), wait for the rate to reach zero (its deceleration time and the reply
    deadline), then a soft reset (which clears the hold and any queue; it stops the steps at once
    if the rotor still turns). Raises RigError unless a status report after the reset shows the
    rotor at rest; the caller decides what that means."""
    decel_s = settings.max_rate_hz / settings.max_acceleration_hz_per_s
    try:
        controller.realtime(JOG_CANCEL)
        controller.realtime(FEED_HOLD)
        deadline = time.monotonic() + decel_s + 2 * settings.reply_timeout_s
        status = controller.query_status()
        while status.moving and time.monotonic() < deadline:
            time.sleep(0.02)  # a bounded poll of the controller's own deceleration
            status = controller.query_status()
    except (DeviceTimeout, ProtocolError, DeviceError) as err:
        # a stalled or garbled link, a stale error: the soft reset below stops it regardless
        log.warning("%s: %s; soft reset", controller.name, err)
    controller.reset()
    status = controller.query_status()
    if status.moving:
        raise DeviceError(f"still turning after a soft reset: {status}", device=controller.name)
    return status


def probe(settings: GrblSettings, *, name: str = "grbl") -> str:
    """`rigctl doctor`'s read-only check: open the link and ask `?` until a status report comes
    (an Arduino that resets when its port opens answers after its bootloader, within
    `boot_timeout_s`); nothing that moves, resets or unlocks is written. The line says the state,
    the position and the settings are not read (`$$` would need Idle)."""
    controller = GrblController.open(settings, name=name)
    try:
        deadline = time.monotonic() + settings.boot_timeout_s
        while True:
            try:
                status = controller.query_status()
                break
            except (DeviceTimeout, ProtocolError):
                if time.monotonic() > deadline:
                    raise
                controller.transport.discard_input()
        version = f"GRBL {controller.version}, " if controller.version else ""
        return (f"{version}{status.state}, MPos X {status.position_deg:.3f} deg, "
                f"{status.feed_deg_min / DEG_PER_MIN_PER_HZ:.3f} turns/s")
    finally:
        controller.close()
