"""The SyRen bus: four SyRen 10/25 motor drivers listening on one packetized-serial wire.

Usage (the coil-board world reads the four coil drives from here, whichever emulator writes):

    bus = SyrenBus()                      # drivers at addresses 128..131 = coils 0..3 (+x, -x, +y, -y)
    firmware = FirmwareEmulator(sink=bus.feed)          # the Python firmware writes the wire bytes
    # or, for the real firmware under simavr:  reader = SyrenWireReader(harness.syren_path, bus)
    bus.outputs()        # (o0, o1, o2, o3), each -1..1, serial timeouts applied; thread-safe
    bus.wait_packet(lambda p: p.data == 0, timeout_s=1.0)   # a test waiting for what the wire carried

What a SyRen does with the wire (Dimension Engineering's SyRen 10/25 manual, "Packetized serial";
docs/coilboard-protocol.md): it ignores everything until the autobaud byte 0xAA; a packet is
`address` (128..135, bit 7 set), `command`, `data` (0..127), `checksum` = (address + command +
data) & 0x7F (bit 7 clear in all three). Commands: 0 drive forward (data/127 of full power),
1 drive backward, 14 serial timeout (data x 100 ms; 0 disables): a driver that hears no valid packet
addressed to it within its timeout stops its motor. A packet with a bad checksum is ignored.
Guesses where the manual is silent: a byte with bit 7 set arriving inside a packet starts a new
packet (the partial one counts as bad); a stray 0xAA after autobaud is ignored; commands other than
0, 1, 14 are counted and ignored.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger(__name__)

AUTOBAUD = 0xAA
ADDRESSES = (128, 129, 130, 131)  # coils 0..3 (DIP switches)
DRIVE_FORWARD = 0
DRIVE_BACKWARD = 1
SERIAL_TIMEOUT = 14
FULL_POWER = 127
BAUD = 9600
BYTE_TIME_S = 10.0 / BAUD  # 8N1: a start bit, 8 data bits, a stop bit


def syren_checksum(address: int, command: int, data: int) -> int:
    return (address + command + data) & 0x7F


def syren_packet(address: int, command: int, data: int) -> bytes:
    """The four wire bytes of one packet."""
    if not 128 <= address <= 135 or not 0 <= command <= 127 or not 0 <= data <= 127:
        raise ValueError(f"bad SyRen packet fields: address={address}, command={command}, data={data}")
    return bytes((address, command, data, syren_checksum(address, command, data)))


def drive_packet(address: int, command: int) -> bytes:
    """The packet for a coil command -127..127: forward for >= 0, backward for < 0."""
    if command >= 0:
        return syren_packet(address, DRIVE_FORWARD, command)
    return syren_packet(address, DRIVE_BACKWARD, -command)


@dataclass(frozen=True)
class SyrenPacket:
    """One valid packet as the drivers heard it; `time` is its last byte's arrival (monotonic s)."""

    time: float
    address: int
    command: int
    data: int

    @property
    def drive(self) -> float | None:
        """The output this packet sets (-1..1), None if it is not a drive command."""
        if self.command == DRIVE_FORWARD:
            return self.data / FULL_POWER
        if self.command == DRIVE_BACKWARD:
            return -self.data / FULL_POWER
        return None


@dataclass(frozen=True)
class SyrenSnapshot:
    outputs: tuple[float, ...]
    timeouts_s: tuple[float, ...]  # 0 = disabled
    timed_out: tuple[bool, ...]  # the driver stopped because its serial timeout fired
    autobauded: bool
    good_packets: int
    bad_packets: int
    ignored_bytes: int  # before autobaud, or not part of any packet


class SyrenBus:
    """The four drivers on the wire. Every method is thread-safe; time from `clock` (monotonic)."""

    def __init__(self, *, addresses: tuple[int, ...] = ADDRESSES,
                 clock: Callable[[], float] = time.monotonic, history: int = 4096) -> None:
        self.addresses = tuple(addresses)
        self._index = {address: i for i, address in enumerate(self.addresses)}
        self._clock = clock
        self._lock = threading.Condition()
        self._packet = bytearray()
        self._autobauded = False
        n = len(self.addresses)
        self._outputs = [0.0] * n
        self._timeouts = [0.0] * n
        self._last_heard = [0.0] * n
        self._timed_out = [False] * n
        self._good = 0
        self._bad = 0
        self._ignored = 0
        self._history: deque[SyrenPacket] = deque(maxlen=history)
        self.unknown_commands = 0

    def feed(self, data: bytes, now: float | None = None) -> None:
        """Bytes off the wire, received at `now` (default: the clock)."""
        with self._lock:
            now = self._clock() if now is None else now
            self._expire(now)
            for byte in data:
                self._byte(byte, now)
            self._lock.notify_all()

    def _byte(self, byte: int, now: float) -> None:
        if not self._autobauded:
            if byte == AUTOBAUD:
                self._autobauded = True
            else:
                self._ignored += 1
            return
        if byte & 0x80:
            if self._packet:
                self._bad += 1  # a new address byte cut the previous packet short
                self._packet.clear()
            if byte == AUTOBAUD:
                return
            self._packet.append(byte)
            return
        if not self._packet:
            self._ignored += 1
            return
        self._packet.append(byte)
        if len(self._packet) < 4:
            return
        address, command, data, checksum = self._packet
        self._packet.clear()
        if checksum != syren_checksum(address, command, data):
            self._bad += 1
            return
        self._good += 1
        packet = SyrenPacket(now, address, command, data)
        self._history.append(packet)
        i = self._index.get(address)
        if i is None:
            return  # a driver that is not on this rig
        self._last_heard[i] = now
        self._timed_out[i] = False
        if command in (DRIVE_FORWARD, DRIVE_BACKWARD):
            self._outputs[i] = packet.drive  # type: ignore[assignment]
        elif command == SERIAL_TIMEOUT:
            self._timeouts[i] = data / 10.0  # units of 100 ms (divided, so 3 gives exactly 0.3 s)
        else:
            self.unknown_commands += 1

    def _expire(self, now: float) -> None:
        for i, timeout in enumerate(self._timeouts):
            if timeout > 0 and not self._timed_out[i] and now - self._last_heard[i] > timeout:
                self._timed_out[i] = True
                self._outputs[i] = 0.0
                log.info("SyRen %d: serial timeout (%.1f s without a packet): motor stopped",
                         self.addresses[i], timeout)

    def outputs(self, now: float | None = None) -> tuple[float, ...]:
        """Each driver's output, -1..1 (negative: reversed), after applying the serial timeouts."""
        with self._lock:
            self._expire(self._clock() if now is None else now)
            return tuple(self._outputs)

    def snapshot(self, now: float | None = None) -> SyrenSnapshot:
        with self._lock:
            self._expire(self._clock() if now is None else now)
            return SyrenSnapshot(tuple(self._outputs), tuple(self._timeouts), tuple(self._timed_out),
                                 self._autobauded, self._good, self._bad, self._ignored)

    def packets(self, since: float | None = None) -> list[SyrenPacket]:
        """Valid packets heard (the last `history` of them), those after `since` if given."""
        with self._lock:
            return [p for p in self._history if since is None or p.time > since]

    def wait_packet(self, predicate: Callable[[SyrenPacket], bool], *, since: float | None = None,
                    timeout_s: float = 5.0) -> SyrenPacket | None:
        """The first packet after `since` satisfying `predicate`, waiting up to `timeout_s` for it;
        None if none came."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while True:
                for packet in self._history:
                    if (since is None or packet.time > since) and predicate(packet):
                        return packet
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._lock.wait(remaining)

    def wait_autobaud(self, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while not self._autobauded:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._lock.wait(remaining)
            return True


class SyrenWireReader:
    """Feeds a `SyrenBus` from a pty carrying the wire bytes (the simavr harness's `syren_path`).

    A thread blocks in `select` on the pty and a stop pipe (no polling); `close()` ends it. When
    the far end closes the pty (the harness stopped), the thread ends and `closed` is set.
    """

    def __init__(self, path: str, bus: SyrenBus) -> None:
        self.path = path
        self.bus = bus
        self._fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            tty.setraw(self._fd)
        except OSError:
            pass  # not a terminal (a FIFO in a test): raw mode is irrelevant
        self._stop_r, self._stop_w = os.pipe()
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"syren-wire {path}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while True:
                readable, _, _ = select.select([self._fd, self._stop_r], [], [])
                if self._stop_r in readable:
                    return
                try:
                    data = os.read(self._fd, 4096)
                except BlockingIOError:
                    continue
                except OSError:
                    return  # EIO: the harness closed its end
                if not data:
                    return
                self.bus.feed(data)
        finally:
            self.closed.set()

    def close(self) -> None:
        if self._stop_w >= 0:
            os.write(self._stop_w, b"x")
            self._thread.join(2.0)
            for fd in (self._fd, self._stop_r, self._stop_w):
                os.close(fd)
            self._stop_w = -1

    def __enter__(self) -> "SyrenWireReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
