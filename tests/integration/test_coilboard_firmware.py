"""The real coil-board firmware (firmware/coilboard) built with avr-gcc and run in simavr.

The host talks to the simulated ATmega328P over the harness's pty exactly as a driver would talk to
the board's USB serial port; the SyRen bus is the harness's second pty, decoded from the PD3 pin.
Every expected byte is computed here from the definitions in docs/coilboard-protocol.md (CRC-16/
CCITT-FALSE written out bit by bit, the SyRen checksum from Dimension Engineering's manual), not
taken from the code under test. Skipped, with the reason, when avr-gcc or simavr are missing.
"""

from __future__ import annotations

import os
import select
import struct
import subprocess
import threading
import time

import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.errors import DeviceTimeout
from rigctl.core.transport import open_transport
from rigctl.emulators.coilboard.simavr import FIRMWARE_DIR, SimavrBoard, SimavrUnavailable, require_tools

try:
    require_tools()
except SimavrUnavailable as missing:
    pytest.skip(str(missing), allow_module_level=True)

SYNC = 0xA5
HELLO, SET, STATUS, STOP = 0x01, 0x02, 0x03, 0x04
R_HELLO, R_ACK, R_STATUS, R_ERROR = 0x81, 0x82, 0x83, 0xEE
BAD_LENGTH, UNKNOWN_TYPE, BAD_VALUE, NO_HELLO, BAD_VERSION = 1, 2, 3, 4, 5
HANDSHAKEN, WATCHDOG, SYREN_READY = 0x01, 0x02, 0x04
ADDRESSES = (128, 129, 130, 131)


def crc16_ccitt_false(data: bytes) -> int:
    """Poly 0x1021, init 0xFFFF, MSB first, no reflection, no final xor."""
    crc = 0xFFFF
    for byte in data:
        for bit in range(7, -1, -1):
            top = (crc >> 15) ^ ((byte >> bit) & 1)
            crc = (crc << 1) & 0xFFFF
            if top:
                crc ^= 0x1021
    return crc


def frame(seq: int, kind: int, payload: bytes = b"") -> bytes:
    body = bytes([len(payload), seq, kind]) + payload
    return bytes([SYNC]) + body + struct.pack("<H", crc16_ccitt_false(body))


def syren_packet(address: int, command: int, data: int) -> bytes:
    return bytes([address, command, data, (address + command + data) & 0x7F])


def syren_drive(address: int, value: int) -> bytes:
    return syren_packet(address, 1, -value) if value < 0 else syren_packet(address, 0, value)


def test_the_reference_definitions_match_their_published_examples():
    assert crc16_ccitt_false(b"123456789") == 0x29B1  # the catalogued check value of CRC-16/CCITT-FALSE
    assert syren_packet(130, 0, 64) == bytes([130, 0, 64, 66])  # SyRen manual, Figure 7.1


class BusRecorder:
    """Everything the firmware puts on the SyRen bus, with the monotonic time each chunk arrived."""

    def __init__(self, path: str) -> None:
        self.fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        self.chunks: list[tuple[float, bytes]] = []
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, name="syren-bus-recorder")
        self.thread.start()

    def _run(self) -> None:
        while not self.done.is_set():
            if select.select([self.fd], [], [], 0.05)[0]:
                data = os.read(self.fd, 4096)
                with self.lock:
                    self.chunks.append((time.monotonic(), data))

    def since(self, t: float) -> bytes:
        with self.lock:
            return b"".join(data for at, data in self.chunks if at >= t)

    def first_arrival(self, needle: bytes, after: float = 0.0) -> float | None:
        """When the chunk completing the first occurrence of `needle` (after time `after`) arrived."""
        with self.lock:
            seen = b""
            for at, data in self.chunks:
                if at < after:
                    continue
                seen += data
                if needle in seen:
                    return at
        return None

    def close(self) -> None:
        self.done.set()
        self.thread.join()
        os.close(self.fd)


class Host:
    """The host side of the link: numbered requests, replies parsed from the definitions."""

    def __init__(self, path: str) -> None:
        self.link = open_transport(path)
        self.timeout_s = 2.0  # for each reply
        self.seq = 0

    def next_seq(self) -> int:
        self.seq = (self.seq + 1) & 0xFF
        return self.seq

    def reply(self) -> tuple[int, int, bytes]:
        head = self.link.read_exact(4, timeout_s=self.timeout_s)
        assert head[0] == SYNC, f"reply does not start with SYNC: {head.hex()}"
        rest = self.link.read_exact(head[1] + 2, timeout_s=self.timeout_s)
        payload, crc = rest[:-2], struct.unpack("<H", rest[-2:])[0]
        assert crc == crc16_ccitt_false(head[1:] + payload), f"bad CRC on reply {(head + rest).hex()}"
        return head[2], head[3], payload

    def ask(self, kind: int, payload: bytes = b"") -> tuple[int, bytes]:
        seq = self.next_seq()
        self.link.write(frame(seq, kind, payload))
        got_seq, got_kind, got_payload = self.reply()
        assert got_seq == seq, f"reply echoes SEQ {got_seq}, expected {seq}"
        return got_kind, got_payload

    def hello(self) -> None:
        assert self.ask(HELLO, b"\x01")[0] == R_HELLO

    def status(self) -> dict:
        kind, p = self.ask(STATUS)
        assert kind == R_STATUS and len(p) == 15
        flags, uptime, o0, o1, o2, o3, good, bad, trips = struct.unpack("<BIbbbbHHH", p)
        return dict(flags=flags, uptime_ms=uptime, outputs=[o0, o1, o2, o3], good=good, bad=bad,
                    trips=trips)

    def close(self) -> None:
        self.link.close()


@pytest.fixture(scope="module")
def board():
    started_at = time.monotonic()  # no later than the simulated power-up
    with SimavrBoard() as running:
        recorder = BusRecorder(running.syren_path)
        running.bus = recorder
        running.started_at = started_at
        try:
            yield running
        finally:
            recorder.close()


@pytest.fixture()
def host(board):
    h = Host(board.uart_path)
    h.link.discard_input()
    yield h
    h.close()


def syren_ready(host: Host) -> None:
    wait_for(lambda: host.status()["flags"] & SYREN_READY, 10.0, "SYREN_READY")


def test_firmware_builds_without_warnings(tmp_path):
    result = subprocess.run(["make", "-C", str(FIRMWARE_DIR), f"BUILD={tmp_path}", "all", "size"],
                            capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output
    assert "warning" not in output.lower(), output
    assert "-Wall -Wextra -Werror" in output  # the flags the brief asks for are really in use
    assert (tmp_path / "coilboard.elf").exists() and (tmp_path / "coilboard.hex").exists()


def test_hello_round_trip(host):
    kind, payload = host.ask(HELLO, b"\x01")
    assert kind == R_HELLO
    version, major, minor, channels, watchdog_ms = struct.unpack("<BBBBH", payload)
    assert (version, channels, watchdog_ms) == (1, 4, 200)
    assert (major, minor) == (1, 0)
    assert host.status()["flags"] & HANDSHAKEN


def test_set_is_acknowledged_applied_and_put_on_the_bus(board, host):
    host.hello()
    syren_ready(host)
    values = [10, -20, 0, 127]
    sent_at = time.monotonic()
    kind, payload = host.ask(SET, struct.pack("<4b", *values))
    assert kind == R_ACK
    assert payload[0] & HANDSHAKEN
    assert list(struct.unpack("<4b", payload[1:])) == values
    assert host.status()["outputs"] == values
    packets = [syren_drive(a, v) for a, v in zip(ADDRESSES, values)]
    assert packets[1] == bytes([129, 1, 20, (129 + 1 + 20) & 0x7F])  # negative = drive backward
    wait_for(lambda: all(p in board.bus.since(sent_at) for p in packets), 2.0, "the four packets")


def test_wrong_crc_gets_no_reply_and_counts_as_bad(host):
    before = host.status()
    bad = bytearray(frame(0x40, STATUS))
    bad[-1] ^= 0x5A
    host.link.write(bytes(bad))
    # the next reply must answer the next request: nothing came back for the corrupted one
    after = host.status()
    assert after["bad"] == before["bad"] + 1
    # a STATUS reply counts itself; only the second STATUS was added, not the corrupted frame
    assert after["good"] == (before["good"] + 1) & 0xFFFF


def test_garbage_then_a_valid_frame_resynchronises(host):
    before = host.status()
    # a SYNC with an impossible LEN, plain noise, and a SYNC whose LEN swallows the real frame's start
    garbage = b"\xa5\xf0\x00\x13\x37\xa5\x03\x11"
    seq = host.next_seq()
    host.link.write(garbage + frame(seq, HELLO, b"\x01"))
    got_seq, kind, payload = host.reply()
    assert (got_seq, kind) == (seq, R_HELLO)
    assert host.status()["bad"] == before["bad"] + 1  # the swallowing candidate failed its CRC


def test_a_stray_sync_holds_a_frame_back_only_until_it_goes_stale(host):
    before = host.status()
    seq = host.next_seq()
    # LEN 16 wants 22 bytes: the STATUS behind it cannot complete the candidate, only the 20 ms
    # stale rule (drop the SYNC, scan the rest again) lets it through
    host.link.write(b"\xa5\x10" + frame(seq, STATUS))
    got_seq, kind, _ = host.reply()
    assert (got_seq, kind) == (seq, R_STATUS)
    assert host.status()["bad"] == before["bad"] + 1


def test_a_flood_of_garbage_is_survived(host):
    # 4000 bytes take 0.34 s at 117647 baud: more than every buffer between host and firmware holds
    seq = host.next_seq()
    host.link.write(bytes(range(0x00, 0xA5)) * 24 + frame(seq, HELLO, b"\x01"))
    got_seq, kind, _ = host.reply()
    assert (got_seq, kind) == (seq, R_HELLO)
    assert not host.status()["flags"] & 0x08  # RX_OVERRUN: the firmware kept up with the wire


def test_unknown_type_and_reply_types_get_an_error(host):
    assert host.ask(0x7E) == (R_ERROR, bytes([UNKNOWN_TYPE, 0x7E]))
    assert host.ask(R_ACK, b"\x00" * 5) == (R_ERROR, bytes([UNKNOWN_TYPE, R_ACK]))


def test_bad_length_and_bad_value_leave_the_outputs_alone(host):
    host.hello()
    host.ask(SET, struct.pack("<4b", 5, 6, 7, 8))
    assert host.ask(SET, b"\x01\x02\x03") == (R_ERROR, bytes([BAD_LENGTH, SET]))
    assert host.ask(STATUS, b"\x00") == (R_ERROR, bytes([BAD_LENGTH, STATUS]))
    assert host.ask(SET, struct.pack("<4b", 1, -128, 1, 1)) == (R_ERROR, bytes([BAD_VALUE, SET]))
    assert host.status()["outputs"] == [5, 6, 7, 8]
    kind, payload = host.ask(STOP)
    assert kind == R_ACK and payload[1:] == b"\x00\x00\x00\x00"


def test_set_before_hello_is_refused(host):
    # a HELLO in a version the board does not speak leaves it un-handshaken
    assert host.ask(HELLO, b"\x02") == (R_ERROR, bytes([BAD_VERSION, HELLO]))
    assert not host.status()["flags"] & HANDSHAKEN
    assert host.ask(SET, struct.pack("<4b", 1, 2, 3, 4)) == (R_ERROR, bytes([NO_HELLO, SET]))
    assert host.status()["outputs"] == [0, 0, 0, 0]
    host.hello()
    assert host.ask(SET, struct.pack("<4b", 1, 2, 3, 4))[0] == R_ACK


def test_watchdog_zeroes_the_outputs_after_silence(board, host):
    host.hello()
    syren_ready(host)
    values = [40, -40, 60, -60]
    host.ask(SET, struct.pack("<4b", *values))
    driving = [syren_drive(a, v) for a, v in zip(ADDRESSES, values)]
    wait_for(lambda: all(p in board.bus.since(0) for p in driving), 2.0, "the drive packets")
    last_frame_at = time.monotonic()  # no later than the firmware receives the STATUS below,
    before = host.status()            # the last valid frame before the silence
    trips_before = before["trips"]
    zeros = [syren_packet(a, 0, 0) for a in ADDRESSES]
    assert zeros[3] == bytes([131, 0, 0, 3])
    wait_for(lambda: all(board.bus.first_arrival(z, last_frame_at) for z in zeros), 3.0,
               "zero packets for all four drivers")
    zeroed_at = max(board.bus.first_arrival(z, last_frame_at) for z in zeros)
    assert zeroed_at - last_frame_at >= 0.2  # never before the 200 ms bound (a lower bound only)
    status = host.status()
    assert status["flags"] & WATCHDOG
    assert status["outputs"] == [0, 0, 0, 0]
    assert status["trips"] == trips_before + 1
    assert status["uptime_ms"] > before["uptime_ms"]  # the link watchdog acted, not a chip reset
    kind, payload = host.ask(SET, struct.pack("<4b", 1, 0, 0, 0))
    assert kind == R_ACK and not payload[0] & WATCHDOG  # the next SET applies and clears the flag


def test_syren_startup_sequence(board, host):
    syren_ready(host)
    bus = board.bus.since(0)
    timeouts = b"".join(syren_packet(a, 14, 3) for a in ADDRESSES)
    assert timeouts[:4] == bytes([128, 14, 3, (128 + 14 + 3) & 0x7F])
    assert bus.startswith(b"\xaa" + timeouts), bus[:24].hex()
    autobaud_at = board.bus.first_arrival(b"\xaa")
    # the drivers get their 2 s to wake up (less the at most ~1 ms the paced core runs ahead)
    assert autobaud_at - board.started_at >= 1.99


def test_a_hung_firmware_is_reset_by_the_avr_watchdog_and_the_bus_goes_quiet():
    # the test variant has one extra request, 0x7F, that stops the main loop for good
    with SimavrBoard(extra_cflags="-DCOILBOARD_TEST_HANG") as variant:
        bus = BusRecorder(variant.syren_path)
        host = Host(variant.uart_path)
        try:
            host.hello()
            syren_ready(host)
            host.ask(SET, struct.pack("<4b", 70, 0, 0, 0))
            wait_for(lambda: syren_drive(128, 70) in bus.since(0), 2.0, "the drive packet")
            host.link.write(frame(host.next_seq(), 0x7F))
            hung_at = time.monotonic()

            def answers_again() -> bool:
                host.link.discard_input()
                try:
                    return host.status()["uptime_ms"] < 1000
                except DeviceTimeout:
                    return False  # still hung: the request went unanswered

            host.timeout_s = 0.3
            wait_for(answers_again, 5.0, "the board to answer after a reset")
            host.timeout_s = 2.0
            status = host.status()
            assert not status["flags"] & (HANDSHAKEN | SYREN_READY)  # a fresh boot
            assert status["outputs"] == [0, 0, 0, 0]
            assert host.ask(SET, struct.pack("<4b", 70, 0, 0, 0)) == (R_ERROR, bytes([NO_HELLO, SET]))
            # the host handshakes again; a SET before the bus is up is taken and applied once it is
            host.hello()
            kind, payload = host.ask(SET, struct.pack("<4b", 0, 0, 33, 0))
            assert kind == R_ACK and not payload[0] & SYREN_READY
            # the bus stays silent until the new start-up (the SyRens' own 300 ms timeout stops the
            # coil meanwhile), then the start-up sequence comes again, then the SET's value
            timeouts = b"".join(syren_packet(a, 14, 3) for a in ADDRESSES)

            def drive_packet_seen() -> bool:
                host.status()  # the heartbeat that keeps the link watchdog from zeroing the SET
                return syren_drive(130, 33) in bus.since(hung_at)

            wait_for(drive_packet_seen, 5.0, "the drive packet after the reset")
            # a packet already queued when the loop hung still leaves the pin (the timer interrupt
            # runs on): look from 100 ms after the hang, when only silence may follow
            after_hang = bus.since(hung_at + 0.1)
            assert after_hang.startswith(b"\xaa" + timeouts), after_hang[:24].hex()
            assert bus.first_arrival(b"\xaa", hung_at) - hung_at >= 2.0
        finally:
            host.close()
            bus.close()


def test_harness_stops_cleanly_on_sigterm():
    with SimavrBoard() as short_lived:
        link = open_transport(short_lived.uart_path, timeout_s=2.0)
        link.write(frame(1, HELLO, b"\x01"))
        assert link.read_exact(12)[3] == R_HELLO
        link.close()
    assert short_lived.returncode == 0
    assert "stopped after" in short_lived.harness_log()
    assert short_lived.uart_path is None and not os.path.exists(link.url)  # the pty is gone
