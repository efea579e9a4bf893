"""The coil-board firmware in Python, served on a pty: the board exactly as docs/coilboard-protocol.md says.

Usage:

    bus = SyrenBus()
    with FirmwareEmulator(sink=bus.feed, syren_startup_s=0.05) as board:
        board.url                 # the pty path a driver opens (a stable symlink, like /dev/serial/by-id)
        CoilBoard.open(board.url) ...
        board.state()             # counters, flags, outputs, ground truth (FirmwareState)
        board.unplug(); board.replug()       # the USB link goes away and comes back on the same path
        board.stall(); board.inject(b"\\x00\\xa5"); board.restore()

With `sink=None` the SyRen wire is served on a second pty instead (`board.syren_path`), as the simavr
harness does, so a caller can treat both emulators alike (`SyrenWireReader(board.syren_path, bus)`).

Two layers, as for every emulator here: `Firmware` is the board's logic with time passed in (no
I/O besides the SyRen sink; tests step it by hand), `FirmwareEmulator` serves it on a pty from the
shared emulator server's loop thread, ticking it every few milliseconds.

The SyRen wire is paced as the real software UART is (9600 baud 8N1: 1.04 ms a byte), so the
last-frame-to-zero time measured through this emulator includes the bus time as on the board.
Scheduling of SyRen packets follows firmware/coilboard/main.c (the doc leaves it open): one packet
on the wire at a time; a driver is sent its latest value (not a queue of stale ones) when it changed,
after a STOP or a watchdog trip (even if unchanged), and every driver again every 100 ms; round robin.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from rigctl.drivers import coilboard_frame as proto
from rigctl.drivers.coilboard_frame import (
    Ack,
    ErrorReply,
    Frame,
    FrameParser,
    HelloReply,
    Status,
)
from rigctl.emulators.coilboard.syren import (
    ADDRESSES,
    AUTOBAUD,
    BYTE_TIME_S,
    SERIAL_TIMEOUT,
    drive_packet,
    syren_packet,
)
from rigctl.emulators.server import EmulatorServer, PtyEndpoint

log = logging.getLogger(__name__)

FW_MAJOR = 1
FW_MINOR = 0
SYREN_STARTUP_S = 2.0
SYREN_TIMEOUT_UNITS = 3  # 300 ms: a SyRen stops its coil 300 ms after the board falls silent
SYREN_GAP_S = 0.020  # after the autobaud byte, before the first packet (as the firmware does)
REFRESH_S = 0.100
TICK_S = 0.004
_POWER_UP, _AUTOBAUD_SENT, _TIMEOUTS_QUEUED, _RUNNING = range(4)


@dataclass(frozen=True)
class FirmwareState:
    """Ground truth of the emulated board (what STATUS reports, and what it does not)."""

    flags: int
    uptime_ms: int
    outputs: tuple[int, ...]  # the applied coil commands, -127..127
    good_frames: int
    bad_frames: int
    watchdog_trips: int
    handshaken: bool
    syren_ready: bool
    last_valid_frame: float | None  # monotonic s
    last_trip: float | None  # monotonic s when the watchdog zeroed the outputs
    syren_bytes_sent: int


class Firmware:
    """The board's logic; every method takes `now` (monotonic seconds) and is called from one thread.

    `receive(data, now)` returns the reply bytes; `tick(now)` runs the clock-driven parts (the link
    watchdog, SyRen start-up and refresh, stale partial frames) and returns reply bytes too (a frame
    held behind a stray SYNC is answered once the stray is dropped). SyRen wire bytes go to `sink`
    as their last bit leaves the pin.
    """

    def __init__(
        self,
        sink: Callable[[bytes], None],
        *,
        now: float,
        watchdog_ms: int = proto.WATCHDOG_MS,
        syren_startup_s: float = SYREN_STARTUP_S,
        syren_timeout_units: int = SYREN_TIMEOUT_UNITS,
        refresh_s: float = REFRESH_S,
        fw_version: tuple[int, int] = (FW_MAJOR, FW_MINOR),
    ) -> None:
        if not 0 <= syren_timeout_units <= 127:
            raise ValueError("the SyRen serial timeout is 0..127 units of 100 ms")
        self._sink = sink
        self.watchdog_s = watchdog_ms / 1000.0
        self.watchdog_ms = watchdog_ms
        self.syren_startup_s = syren_startup_s
        self.syren_timeout_units = syren_timeout_units
        self.refresh_s = refresh_s
        self.fw_version = fw_version
        self.boot(now)

    def boot(self, now: float) -> None:
        """Power-on reset: nothing handshaken, outputs zero, the SyRen start-up from the beginning."""
        self.boot_time = now
        self.parser = FrameParser()
        self.handshaken = False
        self.outputs = [0] * proto.CHANNELS
        self.watchdog_flag = False
        self.rx_overrun = False
        self.good_frames = 0
        self.watchdog_trips = 0
        self.last_valid: float | None = None
        self.last_trip: float | None = None
        self.syren_ready = False
        self._phase = _POWER_UP
        self._phase_time = now  # when the bus entered its phase / the last full refresh
        self._queue: deque[bytes] = deque()  # start-up bytes waiting for the wire
        self._dirty: set[int] = set()  # drivers that must hear their value
        self._next_driver = 0
        self._tx = bytearray()  # the packet on the wire
        self._tx_clock = now  # when the wire finishes the byte in progress
        self.syren_bytes_sent = 0

    # -- host link ------------------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> bytes:
        replies = [self._answer(frame, now) for frame in self.parser.feed(data, now)]
        self._service_syren(now)
        return b"".join(r for r in replies if r)

    def _answer(self, frame: Frame, now: float) -> bytes:
        self.good_frames += 1
        self.last_valid = now
        expected = proto.REQUEST_PAYLOAD_BYTES.get(frame.type)
        if expected is None:
            return self._error(frame, proto.UNKNOWN_TYPE)
        if len(frame.payload) != expected:
            return self._error(frame, proto.BAD_LENGTH)
        if frame.type == proto.HELLO:
            if frame.payload[0] != proto.PROTOCOL_VERSION:
                self.handshaken = False
                return self._error(frame, proto.BAD_VERSION)
            self.handshaken = True
            hello = HelloReply(proto.PROTOCOL_VERSION, *self.fw_version, proto.CHANNELS, self.watchdog_ms)
            return proto.encode_frame(frame.seq, proto.HELLO_REPLY, hello.encode())
        if frame.type == proto.SET:
            if not self.handshaken:
                return self._error(frame, proto.NO_HELLO)
            values = [b - 256 if b > 127 else b for b in frame.payload]
            if any(v == -128 for v in values):
                return self._error(frame, proto.BAD_VALUE)
            self._set_outputs(values, force=False)
            self.watchdog_flag = False
            return self._ack(frame)
        if frame.type == proto.STOP:
            self._set_outputs([0] * proto.CHANNELS, force=True)  # a stop always goes on the bus
            return self._ack(frame)
        # STATUS
        status = Status(self.flags, self.uptime_ms(now), tuple(self.outputs), self.good_frames,
                        self.bad_frames, self.watchdog_trips)
        self.rx_overrun = False
        return proto.encode_frame(frame.seq, proto.STATUS_REPLY, status.encode())

    def _ack(self, frame: Frame) -> bytes:
        return proto.encode_frame(frame.seq, proto.ACK, Ack(self.flags, tuple(self.outputs)).encode())

    def _error(self, frame: Frame, code: int) -> bytes:
        return proto.encode_frame(frame.seq, proto.ERROR, ErrorReply(code, frame.type).encode())

    @property
    def flags(self) -> int:
        return ((proto.FLAG_HANDSHAKEN if self.handshaken else 0)
                | (proto.FLAG_WATCHDOG if self.watchdog_flag else 0)
                | (proto.FLAG_SYREN_READY if self.syren_ready else 0)
                | (proto.FLAG_RX_OVERRUN if self.rx_overrun else 0))

    @property
    def bad_frames(self) -> int:
        """Frames that failed their CRC, and partial frames dropped as stale (as the firmware counts)."""
        return self.parser.bad_frames + self.parser.stale_partials

    def uptime_ms(self, now: float) -> int:
        return int((now - self.boot_time) * 1000.0) & 0xFFFFFFFF

    # -- clock-driven ---------------------------------------------------------------------------

    def tick(self, now: float) -> bytes:
        replies = [self._answer(frame, now) for frame in self.parser.poll(now)]
        # The watchdog is armed by a valid frame and fires once per silence.
        if self.last_valid is not None and now - self.last_valid >= self.watchdog_s:
            if self.last_trip is None or self.last_trip < self.last_valid:
                self._set_outputs([0] * proto.CHANNELS, force=True)
                self.watchdog_flag = True
                self.watchdog_trips += 1
                self.last_trip = now
                log.info("coil board: no valid frame for %d ms: outputs zeroed (watchdog)",
                         self.watchdog_ms)
        self._service_syren(now)
        return b"".join(r for r in replies if r)

    def _set_outputs(self, values: list[int], *, force: bool) -> None:
        for i, value in enumerate(values):
            if force or self.outputs[i] != value:
                self._dirty.add(i)
        self.outputs = list(values)

    def _service_syren(self, now: float) -> None:
        """The bus phases of the firmware: power-up wait, autobaud byte, a 20 ms gap, the timeout
        packets, then running: changed values first, every driver again each 100 ms."""
        if self._phase == _POWER_UP and now - self.boot_time >= self.syren_startup_s:
            self._queue.append(bytes((AUTOBAUD,)))
            self._phase, self._phase_time = _AUTOBAUD_SENT, now
        if self._phase == _AUTOBAUD_SENT and now - self._phase_time >= SYREN_GAP_S:
            self._queue.extend(syren_packet(a, SERIAL_TIMEOUT, self.syren_timeout_units) for a in ADDRESSES)
            self._phase = _TIMEOUTS_QUEUED
        out = bytearray()
        while True:
            if not self._tx:
                if self._tx_clock < now:
                    self._tx_clock = now  # the wire was idle: the next byte starts now
                packet = self._next_packet(now)
                if packet is None:
                    break
                self._tx += packet
            if self._tx_clock + BYTE_TIME_S > now:
                break
            self._tx_clock += BYTE_TIME_S
            out.append(self._tx.pop(0))
        if out:
            self.syren_bytes_sent += len(out)
            self._sink(bytes(out))

    def _next_packet(self, now: float) -> bytes | None:
        """The next bytes for the wire once it is idle, or None."""
        if self._queue:
            return self._queue.popleft()
        if self._phase == _TIMEOUTS_QUEUED:
            self.syren_ready = True  # the autobaud byte and every timeout packet have left the pin
            self._phase, self._phase_time = _RUNNING, now
            self._dirty = set(range(proto.CHANNELS))  # whatever a SET asked for meanwhile
        if self._phase != _RUNNING:
            return None
        if now - self._phase_time >= self.refresh_s:
            self._phase_time = now
            self._dirty = set(range(proto.CHANNELS))
        for k in range(proto.CHANNELS):
            i = (self._next_driver + k) % proto.CHANNELS
            if i in self._dirty:
                self._dirty.discard(i)
                self._next_driver = (i + 1) % proto.CHANNELS
                return drive_packet(ADDRESSES[i], self.outputs[i])
        return None

    def state(self, now: float) -> FirmwareState:
        return FirmwareState(self.flags, self.uptime_ms(now), tuple(self.outputs), self.good_frames,
                             self.bad_frames, self.watchdog_trips, self.handshaken,
                             self.syren_ready, self.last_valid, self.last_trip, self.syren_bytes_sent)


class FirmwareEmulator:
    """The firmware served on a pty by an `EmulatorServer` (its own, or one passed in).

    `syren_startup_s` shortens the 2 s SyRen start-up for tests; `link_path` fixes the URL (default:
    a fresh symlink in a temporary directory). All methods are thread-safe: the firmware is only
    touched in the server's loop thread.
    """

    def __init__(
        self,
        sink: Callable[[bytes], None] | None = None,
        *,
        server: EmulatorServer | None = None,
        name: str = "coilboard",
        link_path: str | None = None,
        syren_startup_s: float = SYREN_STARTUP_S,
        watchdog_ms: int = proto.WATCHDOG_MS,
        syren_timeout_units: int = SYREN_TIMEOUT_UNITS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.name = name
        self._sink = sink
        self._own_server = server is None
        self._server = server or EmulatorServer()
        self._link_path = link_path
        self._clock = clock
        self._settings = dict(watchdog_ms=watchdog_ms, syren_startup_s=syren_startup_s,
                              syren_timeout_units=syren_timeout_units)
        self.firmware: Firmware | None = None
        self.endpoint: PtyEndpoint | None = None
        self.syren_endpoint: PtyEndpoint | None = None
        self._powered = False

    # -- lifetime -------------------------------------------------------------------------------

    def start(self) -> "FirmwareEmulator":
        if self._own_server:
            self._server.start()
        sink = self._sink
        if sink is None:
            self.syren_endpoint = self._server.serve_bytes_pty(lambda data: None, name=f"{self.name}-syren")
            sink = self.syren_endpoint._link.send  # called in the loop thread
        self.firmware = Firmware(sink, now=self._clock(), **self._settings)
        self._powered = True
        self.endpoint = self._server.serve_bytes_pty(self._receive, name=self.name,
                                                     link_path=self._link_path)
        self._server.every(TICK_S, self._tick)
        log.info("%s: Python firmware emulator on %s", self.name, self.endpoint.url)
        return self

    def stop(self) -> None:
        """End the emulator: its own server stops; on a shared server the board is unplugged and
        powered off (the server's `stop()` releases the rest)."""
        if self._own_server:
            self._server.stop()
        elif self.endpoint is not None:
            self.unplug(power_off=True)

    def __enter__(self) -> "FirmwareEmulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def url(self) -> str:
        """The path a driver opens (also `uart_path`, as on the simavr harness)."""
        assert self.endpoint is not None, "FirmwareEmulator not started"
        return self.endpoint.url

    uart_path = url

    @property
    def syren_path(self) -> str | None:
        """The pty carrying the SyRen wire bytes when no sink was given."""
        return self.syren_endpoint.url if self.syren_endpoint else None

    # -- loop-thread callbacks ------------------------------------------------------------------

    def _receive(self, data: bytes) -> bytes | None:
        if not self._powered or self.firmware is None:
            return None
        return self.firmware.receive(data, self._clock()) or None

    def _tick(self) -> None:
        if not self._powered or self.firmware is None:
            return
        replies = self.firmware.tick(self._clock())
        if replies and self.endpoint is not None:
            self.endpoint._link.reply(replies)  # loop thread, through the link's faults

    # -- backdoor -------------------------------------------------------------------------------

    def state(self) -> FirmwareState:
        """Ground truth now."""
        return self._server.call(lambda: self.firmware.state(self._clock()))  # type: ignore[union-attr]

    def unplug(self, *, power_off: bool = False) -> None:
        """The USB link goes away: the pty closes and its path disappears. With `power_off` the
        board stops too (no SyRen bytes: the drivers' serial timeouts stop the coils)."""
        assert self.endpoint is not None
        if power_off:
            self._server.call(setattr, self, "_powered", False)
        self.endpoint.drop_link()

    def replug(self) -> None:
        """The link comes back on the same path; a powered-off board boots afresh."""
        assert self.endpoint is not None

        def power_on() -> None:
            if not self._powered:
                self.firmware.boot(self._clock())  # type: ignore[union-attr]
                self._powered = True

        self._server.call(power_on)
        self.endpoint.restore()

    def reset(self) -> None:
        """The AVR resets (its hardware watchdog, a brown-out) while the USB link stays: the board
        forgets the handshake, its outputs go to zero and the SyRen start-up runs again."""
        self._server.call(lambda: self.firmware.boot(self._clock()))  # type: ignore[union-attr]

    def stall(self) -> None:
        """The board keeps reading but never answers (its ticks still run)."""
        assert self.endpoint is not None
        self.endpoint.stall()

    def restore(self) -> None:
        assert self.endpoint is not None
        self.endpoint.restore()

    def corrupt(self, n_replies: int = 1) -> None:
        assert self.endpoint is not None
        self.endpoint.corrupt(n_replies)

    def inject(self, data: bytes) -> None:
        """Bytes to the host, unasked (garbage on the line)."""
        assert self.endpoint is not None
        self.endpoint.inject(data)

    def set_rx_overrun(self) -> None:
        """Pretend the UART lost bytes (the RX_OVERRUN flag until the next STATUS)."""
        self._server.call(setattr, self.firmware, "rx_overrun", True)


def serve_in_child_process(connection, link_path: str | None = None, syren_startup_s: float = 0.05) -> None:
    """Target of a `multiprocessing` child: the firmware with its SyRen wire on a second pty.

    Sends `(url, syren_path)` over `connection` once serving, then serves until anything arrives on
    it. For measurements that must not share an interpreter with the driver (bench/coilboard_link.py).
    """
    emulator = FirmwareEmulator(sink=None, syren_startup_s=syren_startup_s, link_path=link_path).start()
    try:
        connection.send((emulator.url, emulator.syren_path))
        connection.recv()
    finally:
        emulator.stop()
