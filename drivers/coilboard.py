"""Driver for the coil board (seed 004's Arduino + four SyRen drivers), docs/coilboard-protocol.md.

Usage:

    board = CoilBoard.open("serial:///dev/ttyACM0?baud=115200")   # or a pty path, or tcp://host:port
    board.set((60, 0, -30, 0))       # coils +x, -x, +y, -y; -127..127; returns the board's ACK
    board.status()                   # flags, uptime, outputs, counters
    board.stop(); board.close()      # close() stops the coils first
    board.emergency_stop()           # any thread, at once; latched: only zeros leave afterwards

    CoilBoard.from_settings(rig.board)   # the [board] table of a rig file (CoilBoardSettings)

The driver owns no loop: a caller streams with `rigctl.core.stream.StreamLoop` (a run through
`rigctl.rigs.coil_board.actuators.BoardActuators`).

The link: every request carries a fresh SEQ; a reply counts only with a good CRC, the same SEQ and
the expected type and length, so a late reply to an earlier attempt is never taken for the answer.
A lost reply (the board got a bad CRC, or the reply was garbled) is retried `retries` times with a
new SEQ; SET, STATUS and STOP are idempotent. Garbage is skipped by the shared `FrameParser`.
While open, a heartbeat thread sends STATUS whenever nothing was sent for 100 ms, so the board's
200 ms watchdog only fires when the host is really gone. When the link drops (an unplug), the driver
re-opens the same URL and handshakes again for up to `reconnect_s`; after that every call raises
`Disconnected` naming the board, and the board's own watchdog has already zeroed the coils.

E-stop does not wait for whoever holds the link (a SET waiting for its reply, a reconnect):
`emergency_stop` writes a STOP frame straight away under a lock of its own that only guards the
wire (the SEQ counter and the bytes of one frame), and latches, so every later SET leaves as all
zeros, until `connect` starts afresh. Its ACK carries a SEQ nobody waits for and is dropped as
stale; a SET written just before it is overridden by it, one written after it is zeros.
"""

from __future__ import annotations

import logging
import math
import os
import struct
import threading
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from rigctl.core.errors import (
    ConfigError,
    DeviceError,
    DeviceTimeout,
    Disconnected,
    LimitError,
    ProtocolError,
    RigError,
)
from rigctl.core.transport import DEFAULT_BAUD, Transport, open_transport, parse_url
from rigctl.drivers import coilboard_frame as proto
from rigctl.drivers.coilboard_frame import (
    Ack,
    ErrorReply,
    Frame,
    FrameParser,
    HelloReply,
    Status,
)

if TYPE_CHECKING:
    from rigctl.core.config import CoilBoardSettings

log = logging.getLogger(__name__)

REPLY_TIMEOUT_S = 0.1
RETRIES = 2
RECONNECT_S = 3.0
CONNECT_S = 3.0  # an Arduino Uno resets when its port opens; its bootloader takes up to ~2 s
_BACKOFF_S = (0.01, 0.02, 0.05, 0.1, 0.2)

_ZERO_COMMANDS = proto.encode_commands((0,) * proto.CHANNELS)

_EXPECTED_REPLY = {
    proto.HELLO: proto.HELLO_REPLY,
    proto.SET: proto.ACK,
    proto.STATUS: proto.STATUS_REPLY,
    proto.STOP: proto.ACK,
}


class BoardRefused(DeviceError):
    """The board answered with an ERROR frame; `code` is the protocol's error code."""

    def __init__(self, error: ErrorReply, *, device: str) -> None:
        super().__init__(error.describe(), device=device)
        self.code = error.code
        self.request_type = error.request_type


def transport_url(url: str, baud: int = DEFAULT_BAUD) -> str:
    """A bare device path at a baud rate other than the default becomes serial://path?baud=N."""
    if url.startswith("/") and baud != DEFAULT_BAUD:
        return f"serial://{url}?baud={baud}"
    return url


class CoilBoard:
    """One coil board on one link. Thread-safe: requests are serialised by a lock.

    `reply_timeout_s` bounds each attempt, `retries` the re-sends after a lost reply, `reconnect_s`
    the time spent re-opening the URL after the link dropped, `connect_s` the handshake at open.
    `max_command` (<= 127) is checked before anything is sent; `directions` (+1/-1 per coil)
    flips a coil wired reversed, so callers always speak of the coil's pull.
    """

    def __init__(
        self,
        url: str,
        *,
        name: str = "coil board",
        reply_timeout_s: float = REPLY_TIMEOUT_S,
        retries: int = RETRIES,
        reconnect_s: float = RECONNECT_S,
        connect_s: float = CONNECT_S,
        heartbeat_s: float | None = proto.HEARTBEAT_S,
        max_command: int = proto.MAX_COMMAND,
        directions: Sequence[int] = (1, 1, 1, 1),
        coil_names: Sequence[str] = ("+x", "-x", "+y", "-y"),
        opener: Callable[..., Transport] = open_transport,
    ) -> None:
        if not 1 <= max_command <= proto.MAX_COMMAND:
            raise ConfigError(f"max_command must be 1..{proto.MAX_COMMAND}, got {max_command}", device=name)
        if len(directions) != proto.CHANNELS or any(d not in (1, -1) for d in directions):
            raise ConfigError(f"directions must be four of +1/-1, got {list(directions)}", device=name)
        if reply_timeout_s <= 0 or retries < 0 or reconnect_s < 0:
            raise ConfigError("reply_timeout_s > 0, retries >= 0 and reconnect_s >= 0 required", device=name)
        self.url = url
        self.name = name
        self.reply_timeout_s = reply_timeout_s
        self.retries = retries
        self.reconnect_s = reconnect_s
        self.connect_s = connect_s
        self.heartbeat_s = heartbeat_s
        self.max_command = max_command
        self.directions = tuple(directions)
        self.coil_names = tuple(coil_names)
        self._opener = opener
        self._transport: Transport | None = None
        # Stale partials are only dropped at a read's deadline: bytes are stamped when this side
        # reads them, and a busy host must not throw away a reply it was merely slow to read.
        self._parser = FrameParser(stale_s=math.inf)
        self._seq = 0
        self._lock = threading.RLock()  # one request (with its retries, reconnects) at a time
        self._wire = threading.Lock()  # one frame's SEQ and bytes at a time (e-stop takes only this)
        self._estopped = False  # latched by emergency_stop: every SET leaves as all zeros
        self._sent_commands = _ZERO_COMMANDS  # the SET payload last written (under _lock)
        self._last_sent = 0.0
        self.hello: HelloReply | None = None
        self.last_status: Status | None = None
        self.last_ack: Ack | None = None
        self.fault: RigError | None = None
        # Link statistics: what the driver had to recover from.
        self.lost_replies = 0
        self.stale_replies = 0
        self.reconnects = 0
        self.board_restarts = 0  # the board answered NO_HELLO mid-run: it had reset
        self.max_gap_s = 0.0  # longest silence between two frames sent while the link was up
        self.requests = 0
        self.link_up = False  # False while (re)connecting and after a fault
        self._closed = False
        self._stop_heartbeat = threading.Event()
        self._heartbeat: threading.Thread | None = None

    # -- opening --------------------------------------------------------------------------------

    @classmethod
    def open(cls, url: str, **options: Any) -> "CoilBoard":
        """Open the link, handshake, and start the heartbeat; Disconnected/DeviceError on failure."""
        board = cls(url, **options)
        board.connect()
        return board

    @classmethod
    def from_settings(cls, settings: "CoilBoardSettings", *, name: str = "coil board", **options: Any
                      ) -> "CoilBoard":
        """Open the board a rig file's [board] table names."""
        options = {
            "reply_timeout_s": settings.reply_timeout_s,
            "retries": settings.retries,
            "reconnect_s": settings.reconnect_s,
            "max_command": settings.max_command,
            "directions": settings.coil_directions,
            "coil_names": settings.coil_names,
            **options,
        }
        return cls.open(transport_url(settings.url, settings.baud), name=name, **options)

    def connect(self) -> HelloReply:
        """Open the URL and handshake within `connect_s` (clearing a previous fault); then
        heartbeats run (if enabled)."""
        with self._lock:
            self._closed = False
            self.fault = None
            self._estopped = False
            hello = self._reopen(self.connect_s, why="open")
        if self.heartbeat_s and (self._heartbeat is None or not self._heartbeat.is_alive()):
            self._stop_heartbeat.clear()
            self._heartbeat = threading.Thread(target=self._heartbeat_loop, name=f"{self.name} heartbeat",
                                               daemon=True)
            self._heartbeat.start()
        return hello

    def _open_transport(self) -> Transport:
        return self._opener(self.url, timeout_s=self.reply_timeout_s)

    def _drop_transport(self) -> None:
        if self._transport is not None:
            try:
                self._transport.close()
            except Exception:  # a dead link may fail to close; it is gone either way
                pass
            self._transport = None
        self._parser.reset()

    def _check_port_exists(self) -> None:
        """A serial port that is not there at open is a wrong port (the bootloader's reset, which
        the handshake retries wait out, happens on a port that exists): said at once."""
        try:
            kind, path, _ = parse_url(self.url)
        except ConfigError:
            return  # the opener says what is wrong with it
        if kind == "serial" and not os.path.exists(path):
            raise Disconnected(f"no serial port {path} (from {self.url}): check the rig file's "
                               "[board] url (ls /dev/serial/by-id/)", device=self.name)

    def _reopen(self, within_s: float, *, why: str) -> HelloReply:
        """Re-open the URL and handshake, retrying with a bounded backoff until `within_s` passes."""
        self.link_up = False
        self._drop_transport()
        if why == "open" and self._opener is open_transport:
            self._check_port_exists()
        deadline = time.monotonic() + within_s
        attempt = 0
        last_error: RigError | None = None
        while True:
            try:
                self._transport = self._open_transport()
                hello = self._handshake()
                self.link_up = True
                return hello
            except DeviceError:
                self._drop_transport()
                raise  # the board answered and refused: retrying cannot help
            except (Disconnected, DeviceTimeout, ProtocolError) as err:
                last_error = err
                self._drop_transport()
            if time.monotonic() >= deadline:
                break
            time.sleep(min(_BACKOFF_S[min(attempt, len(_BACKOFF_S) - 1)],
                           max(0.0, deadline - time.monotonic())))
            attempt += 1
        what = "did not answer the handshake" if isinstance(last_error, DeviceTimeout) else "is unreachable"
        reason = last_error.args[0] if last_error else "no attempt"
        safe = "" if why == "open" else "Its watchdog has zeroed the coils. "
        raise Disconnected(
            f"board at {self.url} {what} ({why}: {reason}; tried for {within_s:g} s). {safe}Check the "
            "USB cable, the board's power and that the port is right, then restart the run",
            device=self.name,
        )

    def _handshake(self) -> HelloReply:
        reply = self._request_once(proto.HELLO, bytes((proto.PROTOCOL_VERSION,)))
        hello = HelloReply.decode(reply.payload)
        if hello.version != proto.PROTOCOL_VERSION or hello.channels != proto.CHANNELS:
            raise DeviceError(
                f"board speaks protocol version {hello.version} with {hello.channels} channels; this "
                f"driver needs version {proto.PROTOCOL_VERSION} with {proto.CHANNELS}: flash the "
                "firmware from firmware/coilboard",
                device=self.name,
            )
        self.hello = hello
        log.info("%s: handshake with %s: firmware %d.%d, watchdog %d ms", self.name, self.url,
                 hello.fw_major, hello.fw_minor, hello.watchdog_ms)
        return hello

    # -- requests -------------------------------------------------------------------------------

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _request_once(self, frame_type: int, payload: bytes) -> Frame:
        """One attempt: send, read the matching reply. Raises DeviceTimeout for a lost reply,
        Disconnected for a dead link, DeviceError for an ERROR reply."""
        transport = self._transport
        if transport is None:
            raise Disconnected(f"link to {self.url} is not open")
        with self._wire:
            if frame_type == proto.SET:
                # checked with the wire held: an e-stop written before this frame stays in force
                payload = _ZERO_COMMANDS if self._estopped else payload
                self._sent_commands = payload
            seq = self._next_seq()
            self._parser.reset()
            transport.write(proto.encode_frame(seq, frame_type, payload))
        now = time.monotonic()
        if self.link_up:
            self.max_gap_s = max(self.max_gap_s, now - self._last_sent)
        self._last_sent = now
        self.requests += 1
        reply = self._read_reply(seq, frame_type)
        if reply.type == proto.ERROR:
            error = ErrorReply.decode(reply.payload)
            raise BoardRefused(error, device=self.name)
        return reply

    def _read_reply(self, seq: int, frame_type: int) -> Frame:
        transport = self._transport
        assert transport is not None
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            remaining = deadline - time.monotonic()
            try:
                if remaining <= 0:
                    raise DeviceTimeout("deadline")
                data = transport.read_exact(self._parser.needed(), timeout_s=remaining)
                frames = self._parser.feed(data, time.monotonic())
            except DeviceTimeout:
                # Give up on any partial frame: a stray SYNC may hide the reply behind it.
                frames = self._parser.poll(math.inf)
                if not any(f.seq == seq for f in frames):
                    raise DeviceTimeout(
                        f"no reply to {proto.TYPE_NAMES[frame_type]} (SEQ {seq}) within "
                        f"{self.reply_timeout_s:g} s from {self.url}", device=self.name) from None
            for frame in frames:
                if frame.seq != seq:
                    self.stale_replies += 1
                    continue
                self._check_reply(frame, frame_type)
                return frame

    def _check_reply(self, frame: Frame, frame_type: int) -> None:
        expected = _EXPECTED_REPLY[frame_type]
        if frame.type not in (expected, proto.ERROR):
            raise ProtocolError(
                f"reply to {proto.TYPE_NAMES[frame_type]} has type {frame.type_name}, expected "
                f"{proto.TYPE_NAMES[expected]}", device=self.name)
        size = proto.REPLY_PAYLOAD_BYTES[frame.type]
        if len(frame.payload) != size:
            raise ProtocolError(f"{frame.type_name} reply has {len(frame.payload)} payload bytes, "
                                f"expected {size}", device=self.name)

    def _request(self, frame_type: int, payload: bytes = b"") -> Frame:
        """A request with retries after lost replies and a reconnect after a dropped link."""
        with self._lock:
            if self._closed:
                raise Disconnected(f"board at {self.url} was closed", device=self.name)
            if self.fault is not None:
                raise self.fault
            attempts = 0
            reconnects = 0
            restarts = 0
            while True:
                try:
                    if self._transport is None:
                        self._reconnect()
                    return self._request_once(frame_type, payload)
                except DeviceTimeout as err:
                    attempts += 1
                    self.lost_replies += 1
                    self._discard_input()
                    if attempts > self.retries:
                        self.fault = DeviceTimeout(
                            f"{err.args[0]}; gave up after {attempts} attempts. The board is hung or "
                            "the link is broken: its watchdog zeroes the coils; check the board and "
                            "restart", 
                            device=self.name)
                        raise self.fault from None
                    log.warning("%s: lost reply (%s); retrying", self.name, err)
                except Disconnected:
                    reconnects += 1
                    if reconnects > 2:  # the link keeps dropping right after each reconnect
                        self.fault = Disconnected(
                            f"link to {self.url} drops right after every reconnect; check the cable "
                            "and the board's power", device=self.name)
                        raise self.fault from None
                    self._reconnect()
                except BoardRefused as err:
                    if err.code != proto.NO_HELLO or restarts:
                        raise
                    # The board reset (its own watchdog, a brown-out) and forgot the handshake:
                    # its outputs are zero now; handshake again and send the request again.
                    restarts += 1
                    self.board_restarts += 1
                    log.warning("%s: the board restarted (NO_HELLO); handshaking again", self.name)
                    self._handshake()
                except ProtocolError:
                    attempts += 1
                    self._discard_input()
                    if attempts > self.retries:
                        raise
                    log.warning("%s: unexpected reply; retrying", self.name)

    def _discard_input(self) -> None:
        """Drop whatever arrived after a failed attempt (a late reply is also caught by its SEQ)."""
        if self._transport is not None:
            self._transport.discard_input()

    def _reconnect(self) -> None:
        log.warning("%s: link to %s lost; reconnecting for up to %g s", self.name, self.url,
                    self.reconnect_s)
        try:
            self._reopen(self.reconnect_s, why="reconnect after the link dropped")
        except RigError as err:
            self.fault = err
            raise
        self.reconnects += 1
        log.info("%s: reconnected to %s", self.name, self.url)

    # -- the commands ---------------------------------------------------------------------------

    def _encode(self, commands: Sequence[float]) -> bytes:  # a non-integer is refused here
        if len(commands) != proto.CHANNELS:
            raise LimitError(f"the board takes {proto.CHANNELS} coil commands, got {len(commands)}",
                             device=self.name)
        for i, value in enumerate(commands):
            if int(value) != value or abs(value) > self.max_command:
                raise LimitError(f"coil {i} ({self.coil_names[i]}) command {value} is not an integer within "
                                 f"+-{self.max_command}; nothing was sent", device=self.name)
        return proto.encode_commands([int(v) * d for v, d in zip(commands, self.directions)])

    def applied(self, ack: Ack) -> tuple[int, ...]:
        """The coil commands an ACK reports applied, in the caller's sense (each coil's pull:
        `directions` undone)."""
        return tuple(v * d for v, d in zip(ack.outputs, self.directions))

    @property
    def estopped(self) -> bool:
        """An e-stop latched: every SET leaves as all zeros until `connect`."""
        return self._estopped

    def set(self, commands: Sequence[float]) -> Ack:
        """Apply four coil commands (-max_command..max_command; +x, -x, +y, -y); returns the ACK.
        After an e-stop the board is sent all zeros instead (the ACK says so).

        LimitError before any I/O for a value out of range; DeviceError if the board applied
        something else than was sent."""
        payload = self._encode(commands)
        with self._lock:  # the payload written and its ACK belong to this request
            ack = Ack.decode(self._request(proto.SET, payload).payload)
            sent = struct.unpack("<4b", self._sent_commands)
        if tuple(ack.outputs) != sent:
            raise DeviceError(f"board applied {list(self.applied(ack))} for SET "
                              f"{[v * d for v, d in zip(sent, self.directions)]}", device=self.name)
        self.last_ack = ack
        return ack

    def stop(self) -> Ack:
        """All four coils off now."""
        ack = Ack.decode(self._request(proto.STOP).payload)
        self.last_ack = ack
        return ack

    def status(self) -> Status:
        """The board's STATUS: flags, uptime, outputs (as the board sees them), counters."""
        previous = self.last_status
        status = Status.decode(self._request(proto.STATUS).payload)
        if previous is not None and status.uptime_ms < previous.uptime_ms:
            log.warning("%s: the board restarted (uptime %d ms, was %d ms)", self.name,
                        status.uptime_ms, previous.uptime_ms)
        if previous is not None and status.watchdog_trips > previous.watchdog_trips:
            log.warning("%s: the board's watchdog zeroed the coils %d time(s) since the last STATUS",
                        self.name, status.watchdog_trips - previous.watchdog_trips)
        self.last_status = status
        return status

    # -- heartbeat ------------------------------------------------------------------------------

    def _heartbeat_loop(self) -> None:
        assert self.heartbeat_s
        while True:
            due = self._last_sent + self.heartbeat_s
            if self._stop_heartbeat.wait(max(0.0, due - time.monotonic())):
                return
            if time.monotonic() < self._last_sent + self.heartbeat_s:
                continue  # something was sent meanwhile
            try:
                self.status()
            except RigError as err:
                log.error("%s: heartbeat failed: %s", self.name, err)
                if self.fault is None:
                    self.fault = err
                return

    # -- e-stop ---------------------------------------------------------------------------------

    def emergency_stop(self) -> bool:
        """All coils off now, from any thread, without waiting for a request in progress: writes
        a STOP frame and latches (every later SET leaves as all zeros, until `connect`). Never
        raises; False if the frame could not be written (no link: the board's watchdog zeroes the
        coils within its 200 ms by itself)."""
        self._estopped = True
        transport = self._transport
        if transport is None:
            log.error("%s: e-stop: no link to write STOP to", self.name)
            return False
        try:
            with self._wire:
                transport.write(proto.encode_frame(self._next_seq(), proto.STOP, b""))
        except Exception as err:  # a dead or closing link: the latch still holds
            log.error("%s: e-stop: STOP could not be written: %s", self.name, err)
            return False
        return True

    # -- closing --------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the coils (best effort) and release the link; idempotent."""
        self._stop_heartbeat.set()
        if self._heartbeat is not None and self._heartbeat is not threading.current_thread():
            self._heartbeat.join(2.0)
        self._heartbeat = None
        with self._lock:
            if self._transport is not None and self.fault is None:
                try:
                    self._request_once(proto.STOP, b"")
                except RigError as err:
                    log.warning("%s: STOP at close failed (%s); the board's watchdog zeroes the coils",
                                self.name, err)
            self._closed = True
            self._drop_transport()

    def __enter__(self) -> "CoilBoard":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
