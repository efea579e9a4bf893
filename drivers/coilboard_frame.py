"""The coil-board host link (docs/coilboard-protocol.md): frame codec and constants, one copy.

Both ends use this module: the driver (`rigctl.drivers.coilboard`) and the Python firmware
emulator (`rigctl.emulators.coilboard.firmware`). The real firmware (`firmware/coilboard/`) is C
and follows the same document.

A frame is `SYNC LEN SEQ TYPE PAYLOAD[LEN] CRC_lo CRC_hi`; the CRC is CRC-16/CCITT-FALSE over
LEN..PAYLOAD. There is no byte stuffing, so a receiver finds frames by hunting for SYNC:
`FrameParser` is that receiver, fed whatever bytes arrive, in any chunking:

    parser = FrameParser()
    for frame in parser.feed(chunk, now=time.monotonic()):
        ...  # Frame(seq, type, payload), CRC already checked

On a LEN above 16 or a bad CRC it drops only the SYNC byte and hunts again from the next byte, so
a valid frame right after garbage is found; a partial frame whose SYNC arrived more than 20 ms ago
is dropped the same way (a cut-off frame cannot swallow the next one). `needed()` says how many
more bytes could complete something, so a reader on a blocking transport asks for no more than that.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import astuple, dataclass
from typing import ClassVar, Self

from rigctl.core.config import BOARD_FULL_SCALE

SYNC = 0xA5
MAX_PAYLOAD = 16
HEADER_BYTES = 4  # SYNC LEN SEQ TYPE
CRC_BYTES = 2
MIN_FRAME_BYTES = HEADER_BYTES + CRC_BYTES  # 6
MAX_FRAME_BYTES = MIN_FRAME_BYTES + MAX_PAYLOAD  # 22
STALE_PARTIAL_S = 0.020

PROTOCOL_VERSION = 1
CHANNELS = 4
WATCHDOG_MS = 200
MAX_COMMAND = BOARD_FULL_SCALE  # a coil command is -127..127; -128 is refused (BAD_VALUE)
HEARTBEAT_S = 0.100  # the host sends something at least this often

# Request types (host -> board)
HELLO = 0x01
SET = 0x02
STATUS = 0x03
STOP = 0x04
# Reply types (board -> host)
HELLO_REPLY = 0x81
ACK = 0x82
STATUS_REPLY = 0x83
ERROR = 0xEE

REQUEST_PAYLOAD_BYTES = {HELLO: 1, SET: CHANNELS, STATUS: 0, STOP: 0}
REPLY_PAYLOAD_BYTES = {HELLO_REPLY: 6, ACK: 1 + CHANNELS, STATUS_REPLY: 15, ERROR: 2}
TYPE_NAMES = {
    HELLO: "HELLO", SET: "SET", STATUS: "STATUS", STOP: "STOP",
    HELLO_REPLY: "HELLO reply", ACK: "ACK", STATUS_REPLY: "STATUS reply", ERROR: "ERROR",
}

# Error codes (payload byte 0 of an ERROR reply)
BAD_LENGTH = 0x01
UNKNOWN_TYPE = 0x02
BAD_VALUE = 0x03
NO_HELLO = 0x04
BAD_VERSION = 0x05
ERROR_NAMES = {
    BAD_LENGTH: "BAD_LENGTH (LEN does not match the type)",
    UNKNOWN_TYPE: "UNKNOWN_TYPE",
    BAD_VALUE: "BAD_VALUE (a coil command of -128)",
    NO_HELLO: "NO_HELLO (SET before a successful HELLO)",
    BAD_VERSION: "BAD_VERSION (protocol version not spoken by the board)",
}

# Flag bits (first payload byte of ACK and STATUS replies)
FLAG_HANDSHAKEN = 0x01
FLAG_WATCHDOG = 0x02
FLAG_SYREN_READY = 0x04
FLAG_RX_OVERRUN = 0x08


def crc16_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor (check 0x29B1).
    The standard library's `binascii.crc_hqx` is this CRC given the 0xFFFF start (it computes in C,
    about 65x faster than a Python loop over the bits)."""
    return binascii.crc_hqx(data, 0xFFFF)


def encode_frame(seq: int, frame_type: int, payload: bytes = b"") -> bytes:
    """The wire bytes of one frame; ValueError for a field out of range."""
    if not 0 <= seq <= 0xFF or not 0 <= frame_type <= 0xFF:
        raise ValueError(f"SEQ and TYPE are bytes, got seq={seq}, type={frame_type}")
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = bytes((len(payload), seq, frame_type)) + bytes(payload)
    return bytes((SYNC,)) + body + struct.pack("<H", crc16_ccitt_false(body))


@dataclass(frozen=True)
class Frame:
    seq: int
    type: int
    payload: bytes

    def encode(self) -> bytes:
        return encode_frame(self.seq, self.type, self.payload)

    @property
    def type_name(self) -> str:
        return TYPE_NAMES.get(self.type, f"type 0x{self.type:02X}")


class FrameParser:
    """Incremental receiver: bytes in, CRC-checked frames out (see the module docstring).

    Counters: `bad_frames` (a complete candidate frame whose CRC failed),
    `stale_partials` (partial frames dropped after `stale_s`), `skipped_bytes` (bytes dropped while
    hunting, SYNC bytes of rejected frames included).
    """

    def __init__(self, *, stale_s: float = STALE_PARTIAL_S) -> None:
        self.stale_s = stale_s
        self._buffer = bytearray()
        self._arrival: list[float] = []  # arrival time of each buffered byte
        self.bad_frames = 0
        self.stale_partials = 0
        self.skipped_bytes = 0

    def reset(self) -> None:
        """Forget any partial frame (after a reconnect or a timed-out read)."""
        self._buffer.clear()
        self._arrival.clear()

    @property
    def pending(self) -> int:
        """Bytes held as the start of a frame not yet complete."""
        return len(self._buffer)

    def needed(self) -> int:
        """The fewest further bytes that could complete a frame (1 while hunting)."""
        if len(self._buffer) < 2:
            return 1 if not self._buffer else MIN_FRAME_BYTES - 1
        return max(1, MIN_FRAME_BYTES + self._buffer[1] - len(self._buffer))

    def poll(self, now: float) -> list[Frame]:
        """Apply the stale-partial rule at `now` without new bytes; return any frame it uncovers
        (a valid frame held behind a stray SYNC)."""
        return self.feed(b"", now)

    def feed(self, data: bytes, now: float = 0.0) -> list[Frame]:
        """Take `data` (received at `now`, seconds on any monotonic clock); return the frames now
        complete, in order. A partial frame already stale at `now` is dropped before `data` is
        appended, so it cannot swallow the new bytes."""
        frames: list[Frame] = []
        if self._buffer:
            self._parse(frames, now)
        if data:
            self._buffer += data
            self._arrival.extend([now] * len(data))
            self._hunt()
            self._parse(frames, now)
        return frames

    def _parse(self, frames: list[Frame], now: float) -> None:
        while len(self._buffer) >= 1:
            if len(self._buffer) >= 2 and self._buffer[1] > MAX_PAYLOAD:
                self._drop(1)  # not a frame at all (the firmware does not count these either)
                self._hunt()
                continue
            size = MIN_FRAME_BYTES + (self._buffer[1] if len(self._buffer) >= 2 else 0)
            if len(self._buffer) < size:
                if now - self._arrival[0] <= self.stale_s:
                    return  # wait for the rest
                self.stale_partials += 1
                self._drop(1)
                self._hunt()
                continue
            length = self._buffer[1]
            body = bytes(self._buffer[1 : HEADER_BYTES + length])
            (crc,) = struct.unpack_from("<H", self._buffer, HEADER_BYTES + length)
            if crc != crc16_ccitt_false(body):
                self.bad_frames += 1
                self._drop(1)
                self._hunt()
                continue
            frames.append(Frame(seq=body[1], type=body[2], payload=body[3:]))
            del self._buffer[:size]
            del self._arrival[:size]
            self._hunt()

    def _drop(self, n: int) -> None:
        del self._buffer[:n]
        del self._arrival[:n]
        self.skipped_bytes += n

    def _hunt(self) -> None:
        index = self._buffer.find(SYNC)
        if index < 0:
            index = len(self._buffer)
        if index:
            self._drop(index)


# -- payloads ---------------------------------------------------------------------------------------


def encode_commands(commands: tuple[int, ...] | list[int]) -> bytes:
    """Four int8 coil commands, each -127..127 (ValueError otherwise)."""
    if len(commands) != CHANNELS:
        raise ValueError(f"the board takes {CHANNELS} coil commands, got {len(commands)}")
    for value in commands:
        if int(value) != value or not -MAX_COMMAND <= value <= MAX_COMMAND:
            raise ValueError(f"coil commands are integers in -{MAX_COMMAND}..{MAX_COMMAND}, got {value}")
    return struct.pack("<4b", *(int(v) for v in commands))


class _FlatPayload:
    """A payload whose fields are its `FORMAT`'s fields, in order."""

    FORMAT: ClassVar[str]

    @classmethod
    def decode(cls, payload: bytes) -> Self:
        return cls(*struct.unpack(cls.FORMAT, payload))

    def encode(self) -> bytes:
        return struct.pack(self.FORMAT, *astuple(self))  # type: ignore[call-overload]


@dataclass(frozen=True)
class HelloReply(_FlatPayload):
    version: int
    fw_major: int
    fw_minor: int
    channels: int
    watchdog_ms: int

    FORMAT: ClassVar[str] = "<BBBBH"


@dataclass(frozen=True)
class Ack:
    flags: int
    outputs: tuple[int, ...]  # four int8 coil commands

    FORMAT: ClassVar[str] = "<B4b"

    @classmethod
    def decode(cls, payload: bytes) -> "Ack":
        flags, *outputs = struct.unpack(cls.FORMAT, payload)
        return cls(flags, tuple(outputs))

    def encode(self) -> bytes:
        return struct.pack(self.FORMAT, self.flags, *self.outputs)


@dataclass(frozen=True)
class Status:
    flags: int
    uptime_ms: int
    outputs: tuple[int, ...]  # four int8 coil commands
    good_frames: int
    bad_frames: int
    watchdog_trips: int

    FORMAT: ClassVar[str] = "<BI4bHHH"

    @classmethod
    def decode(cls, payload: bytes) -> "Status":
        flags, uptime, o0, o1, o2, o3, good, bad, trips = struct.unpack(cls.FORMAT, payload)
        return cls(flags, uptime, (o0, o1, o2, o3), good, bad, trips)

    def encode(self) -> bytes:
        return struct.pack(self.FORMAT, self.flags, self.uptime_ms & 0xFFFFFFFF, *self.outputs,
                           self.good_frames & 0xFFFF, self.bad_frames & 0xFFFF,
                           self.watchdog_trips & 0xFFFF)

    @property
    def handshaken(self) -> bool:
        return bool(self.flags & FLAG_HANDSHAKEN)

    @property
    def watchdog(self) -> bool:
        return bool(self.flags & FLAG_WATCHDOG)

    @property
    def syren_ready(self) -> bool:
        return bool(self.flags & FLAG_SYREN_READY)


@dataclass(frozen=True)
class ErrorReply(_FlatPayload):
    code: int
    request_type: int

    FORMAT: ClassVar[str] = "<BB"

    def describe(self) -> str:
        name = ERROR_NAMES.get(self.code, f"error code 0x{self.code:02X}")
        return f"board refused {TYPE_NAMES.get(self.request_type, hex(self.request_type))}: {name}"
