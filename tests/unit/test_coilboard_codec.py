"""The coil-board link by hand: frame codec, SyRen decoder, the Python firmware stepped on a fake
clock, and the driver against scripted bytes.

Expected bytes are built here from docs/coilboard-protocol.md: the CRC by `binascii.crc_hqx`
(the standard library's CRC-CCITT, poly 0x1021, MSB first; with init 0xFFFF it is
CRC-16/CCITT-FALSE) and the catalogue check value, the SyRen checksum from its definition.
"""

from __future__ import annotations

import binascii
import struct

import pytest

from rigctl.apps.testing import ScriptedTransport
from rigctl.core.errors import DeviceError, DeviceTimeout, LimitError
from rigctl.drivers.coilboard import CoilBoard
from rigctl.drivers.coilboard_frame import FrameParser, crc16_ccitt_false, encode_frame
from rigctl.emulators.coilboard.firmware import Firmware
from rigctl.emulators.coilboard.syren import SyrenBus


def frame(seq: int, kind: int, payload: bytes = b"") -> bytes:
    body = bytes((len(payload), seq, kind)) + payload
    return b"\xa5" + body + struct.pack("<H", binascii.crc_hqx(body, 0xFFFF))


def syren(address: int, command: int, data: int) -> bytes:
    return bytes((address, command, data, (address + command + data) & 0x7F))


# -- codec -------------------------------------------------------------------------------------------


def _crc_bit_by_bit(data: bytes) -> int:
    """CRC-16/CCITT-FALSE as the catalogue defines it: poly 0x1021, init 0xFFFF, MSB first."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def test_crc_matches_the_catalogue_check_value_and_a_second_implementation() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE "check"
    for data in (b"", b"\x00", b"\x04\x07\x02\x0a\xf6\x7f\x81", bytes(range(200)), bytes(range(256)) * 3):
        assert crc16_ccitt_false(data) == _crc_bit_by_bit(data)


def test_encode_lays_out_sync_len_seq_type_payload_crc() -> None:
    # SET, SEQ 7, commands 10, -10, 127, -127: payload bytes are two's complement int8
    encoded = encode_frame(7, 0x02, bytes((10, 0xF6, 127, 0x81)))
    assert encoded == frame(7, 0x02, bytes((10, 0xF6, 127, 0x81)))
    assert encoded[:4] == b"\xa5\x04\x07\x02" and len(encoded) == 10
    assert len(encode_frame(0, 0x03)) == 6 and len(encode_frame(0, 0x03, bytes(16))) == 22
    with pytest.raises(ValueError):
        encode_frame(0, 0x02, bytes(17))


def test_parser_takes_any_chunking() -> None:
    stream = frame(1, 0x81, bytes((1, 1, 0, 4, 200, 0))) + frame(2, 0x82, bytes(5))
    parser = FrameParser()
    frames = [f for byte in stream for f in parser.feed(bytes((byte,)))]
    assert [(f.seq, f.type, f.payload) for f in frames] == [
        (1, 0x81, bytes((1, 1, 0, 4, 200, 0))), (2, 0x82, bytes(5))]
    assert parser.bad_frames == 0 and parser.pending == 0


def test_parser_resynchronises_after_garbage_and_a_bad_crc() -> None:
    good = frame(9, 0x03)
    bad_crc = bytearray(frame(8, 0x02, bytes(4)))
    bad_crc[-1] ^= 0x01
    # garbage, a SYNC with an impossible LEN (not counted as a frame), a frame with a bad CRC
    stream = b"\x00\x13\x37" + b"\xa5\x40" + bytes(bad_crc) + good
    parser = FrameParser()
    frames = parser.feed(stream)
    assert [(f.seq, f.type) for f in frames] == [(9, 0x03)]
    assert parser.bad_frames == 1


def test_parser_finds_a_frame_that_starts_inside_a_rejected_one() -> None:
    # A stray SYNC + LEN 0 swallows the next frame's first four bytes as its SEQ, TYPE and CRC;
    # only the stray SYNC is dropped, so the real frame is still found.
    good = frame(0x31, 0x03)
    stray = b"\xa5\x00"
    assert crc16_ccitt_false(b"\x00" + good[:2]) != struct.unpack("<H", good[2:4])[0]
    parser = FrameParser()
    assert [f.seq for f in parser.feed(stray + good)] == [0x31]
    assert parser.bad_frames == 1


def test_parser_drops_a_stale_partial_frame() -> None:
    # SYNC with LEN 16 waits for 22 bytes; 30 ms later a 6-byte frame must not be swallowed.
    parser = FrameParser()
    assert parser.feed(b"\xa5\x10\x01\x02", now=1.000) == []
    assert parser.needed() == 22 - 4
    frames = parser.feed(frame(5, 0x03), now=1.030)
    assert [f.seq for f in frames] == [5]
    assert parser.stale_partials == 1
    # within 20 ms the partial frame is still waited for
    parser = FrameParser()
    parser.feed(b"\xa5\x10\x01\x02", now=1.000)
    assert parser.feed(frame(5, 0x03), now=1.010) == []
    # ... and a poll at the stale time uncovers the frame held behind it
    assert [f.seq for f in parser.poll(1.100)] == [5]


# -- SyRen decoder ---------------------------------------------------------------------------------


def test_syren_ignores_bytes_before_autobaud_then_decodes_drive_packets() -> None:
    bus = SyrenBus(clock=lambda: 0.0)
    bus.feed(syren(128, 0, 64))  # before 0xAA: not heard
    assert bus.outputs() == (0.0, 0.0, 0.0, 0.0)
    bus.feed(b"\xaa" + syren(128, 0, 127) + syren(129, 1, 127) + syren(130, 0, 0) + syren(131, 1, 50))
    assert bus.outputs() == (1.0, -1.0, 0.0, pytest.approx(-50 / 127))
    snap = bus.snapshot()
    assert snap.autobauded and snap.good_packets == 4 and snap.bad_packets == 0
    assert snap.ignored_bytes == 4


def test_syren_rejects_bad_checksums_and_cut_packets() -> None:
    bus = SyrenBus(clock=lambda: 0.0)
    wrong = bytearray(syren(128, 0, 100))
    wrong[3] ^= 0x01
    cut = syren(129, 0, 100)[:2]
    bus.feed(b"\xaa" + bytes(wrong) + cut + syren(130, 0, 90))
    assert bus.outputs() == (0.0, 0.0, pytest.approx(90 / 127), 0.0)
    assert bus.snapshot().bad_packets == 2  # a wrong checksum, a packet cut by the next address


def test_syren_serial_timeout_stops_a_silent_driver() -> None:
    now = [0.0]
    bus = SyrenBus(clock=lambda: now[0])
    bus.feed(b"\xaa" + syren(128, 14, 3) + syren(128, 0, 100) + syren(129, 0, 100))  # 128: 300 ms
    now[0] = 0.29
    assert bus.outputs()[:2] == (pytest.approx(100 / 127), pytest.approx(100 / 127))
    now[0] = 0.31
    snap = bus.snapshot()
    assert snap.outputs[:2] == (0.0, pytest.approx(100 / 127))  # 129 has no timeout set
    assert snap.timed_out == (True, False, False, False) and snap.timeouts_s[0] == pytest.approx(0.3)
    bus.feed(syren(128, 1, 20))  # a packet wakes it
    assert bus.outputs()[0] == pytest.approx(-20 / 127)


# -- the Python firmware on a hand-driven clock ---------------------------------------------------


class Wire:
    def __init__(self) -> None:
        self.data = bytearray()

    def __call__(self, data: bytes) -> None:
        self.data += data


def run(firmware: Firmware, start: float, end: float, step: float = 0.001) -> float:
    t = start
    while t < end:
        t += step
        firmware.tick(t)
    return t


def test_firmware_syren_startup_then_drive_packets() -> None:
    wire = Wire()
    fw = Firmware(wire, now=0.0, syren_startup_s=2.0)
    hello = frame(1, 0x81, bytes((1, 1, 0, 4)) + struct.pack("<H", 200))
    assert fw.receive(frame(1, 0x01, b"\x01"), 0.0) == hello
    run(fw, 0.0, 1.99)
    assert wire.data == b"" and not fw.syren_ready
    # (the link watchdog zeroed the outputs at 0.2 s: the SET comes within 200 ms of the bus start)
    ack = fw.receive(frame(2, 0x02, bytes((30, 0, 0xE2, 0))), 1.99)
    assert ack == frame(2, 0x82, bytes((0x01, 30, 0, 0xE2, 0)))
    t = run(fw, 1.99, 2.15)
    expected = b"\xaa" + b"".join(syren(a, 14, 3) for a in (128, 129, 130, 131))
    assert bytes(wire.data[:17]) == expected
    assert fw.syren_ready
    drive = bytes(wire.data[17:33])
    assert sorted(drive[i:i + 4] for i in range(0, 16, 4)) == sorted(
        [syren(128, 0, 30), syren(129, 0, 0), syren(130, 1, 30), syren(131, 0, 0)])
    status = fw.receive(frame(3, 0x03), t)
    assert status[4] == 0x05  # HANDSHAKEN | SYREN_READY


def test_firmware_watchdog_fires_once_200_ms_after_the_last_valid_frame() -> None:
    wire = Wire()
    fw = Firmware(wire, now=0.0, syren_startup_s=0.0)
    fw.receive(frame(1, 0x01, b"\x01"), 0.0)
    fw.receive(frame(2, 0x02, bytes((50, 50, 50, 50))), 0.010)
    t = run(fw, 0.010, 0.205)
    assert fw.outputs == [50, 50, 50, 50] and fw.watchdog_trips == 0
    bad = bytearray(frame(3, 0x03))
    bad[-1] ^= 0xFF
    assert fw.receive(bytes(bad), t) == b""  # a bad CRC gets no reply and does not feed the watchdog
    t = run(fw, t, 0.215)
    assert fw.outputs == [0, 0, 0, 0] and fw.watchdog_trips == 1 and fw.watchdog_flag
    run(fw, t, 1.0)
    assert fw.watchdog_trips == 1  # once per silence
    ack = fw.receive(frame(4, 0x02, bytes((1, 2, 3, 4))), 1.0)
    assert ack == frame(4, 0x82, bytes((0x05, 1, 2, 3, 4)))  # the SET clears WATCHDOG
    status = fw.receive(frame(5, 0x03), 1.0)
    flags, _, *rest = struct.unpack("<BI4bHHH", status[4:-2])
    assert flags == 0x05 and rest == [1, 2, 3, 4, 4, 1, 1]  # outputs, good (HELLO, 2 SET, STATUS), bad, trips


def test_firmware_watchdog_is_not_armed_at_power_up_and_stop_always_reaches_the_bus() -> None:
    wire = Wire()
    fw = Firmware(wire, now=0.0, syren_startup_s=0.0)
    t = run(fw, 0.0, 1.0)
    assert fw.watchdog_trips == 0 and fw.syren_ready  # nobody talked to it: no trip
    start = len(wire.data)
    fw.receive(frame(1, 0x04), t)  # STOP with every output already zero
    run(fw, t, t + 0.030)  # four packets take 16.7 ms at 9600 baud
    sent = bytes(wire.data[start:])
    assert [sent[i:i + 4] for i in range(0, 16, 4)] == [syren(a, 0, 0) for a in (128, 129, 130, 131)]


def test_firmware_errors() -> None:
    fw = Firmware(Wire(), now=0.0)
    assert fw.receive(frame(1, 0x02, bytes(4)), 0.0) == frame(1, 0xEE, b"\x04\x02")  # NO_HELLO
    assert fw.receive(frame(2, 0x01, b"\x02"), 0.0) == frame(2, 0xEE, b"\x05\x01")  # BAD_VERSION
    assert fw.receive(frame(3, 0x01, b""), 0.0) == frame(3, 0xEE, b"\x01\x01")  # BAD_LENGTH
    assert fw.receive(frame(4, 0x42), 0.0) == frame(4, 0xEE, b"\x02\x42")  # UNKNOWN_TYPE
    fw.receive(frame(5, 0x01, b"\x01"), 0.0)
    assert fw.receive(frame(6, 0x02, bytes((0, 0x80, 0, 0))), 0.0) == frame(6, 0xEE, b"\x03\x02")  # -128
    assert fw.receive(frame(7, 0x04, b"\x00"), 0.0) == frame(7, 0xEE, b"\x01\x04")


# -- the driver against scripted bytes -------------------------------------------------------------

HELLO_OK = frame(1, 0x81, bytes((1, 1, 0, 4)) + struct.pack("<H", 200))


def driver(steps, **options) -> tuple[CoilBoard, ScriptedTransport]:
    script = ScriptedTransport(steps)
    board = CoilBoard.open("scripted://board", opener=lambda url, timeout_s: script, heartbeat_s=None,
                           reconnect_s=0.0, **options)
    return board, script


def test_driver_handshakes_sets_and_reads_status() -> None:
    status_payload = struct.pack("<BI4bHHH", 0x05, 1234, 10, 0, -5, 0, 7, 1, 0)
    board, script = driver([
        (frame(1, 0x01, b"\x01"), HELLO_OK),
        (frame(2, 0x02, bytes((10, 0, 0xFB, 0))), frame(2, 0x82, bytes((0x05, 10, 0, 0xFB, 0)))),
        (frame(3, 0x03), frame(3, 0x83, status_payload)),
    ])
    assert board.hello.watchdog_ms == 200
    assert board.set((10, 0, -5, 0)).outputs == (10, 0, -5, 0)
    status = board.status()
    assert (status.uptime_ms, status.outputs) == (1234, (10, 0, -5, 0))
    assert (status.good_frames, status.bad_frames) == (7, 1)
    script.assert_done()


def test_driver_skips_garbage_and_a_late_reply_then_takes_its_own() -> None:
    late = frame(1, 0x82, bytes(5))  # an old SEQ: not the answer
    board, script = driver([
        (frame(1, 0x01, b"\x01"), HELLO_OK),
        (frame(2, 0x02, bytes((1, 2, 3, 4))),
         b"\x13\xa5\x33" + late + frame(2, 0x82, bytes((0x05, 1, 2, 3, 4)))),
    ])
    assert board.set((1, 2, 3, 4)).flags == 0x05
    assert board.stale_replies == 1
    script.assert_done()


def test_driver_retries_a_lost_reply_with_a_new_seq() -> None:
    board, script = driver([
        (frame(1, 0x01, b"\x01"), HELLO_OK),
        (frame(2, 0x04), None),  # no reply: the board saw a bad CRC
        (frame(3, 0x04), frame(3, 0x82, bytes((0x05, 0, 0, 0, 0)))),
    ], retries=1)
    assert board.stop().outputs == (0, 0, 0, 0)
    assert board.lost_replies == 1
    script.assert_done()


def test_driver_gives_up_after_its_retries_with_a_named_fault() -> None:
    board, script = driver(
        [(frame(1, 0x01, b"\x01"), HELLO_OK), (frame(2, 0x03), None), (frame(3, 0x03), None)], retries=1)
    with pytest.raises(DeviceTimeout, match="coil board: .*gave up after 2 attempts"):
        board.status()
    script.assert_done()


def test_driver_reports_error_replies_and_checks_limits_before_sending() -> None:
    board, script = driver([
        (frame(1, 0x01, b"\x01"), HELLO_OK),
        (frame(2, 0x03), frame(2, 0xEE, b"\x02\x03")),
    ], max_command=100)
    with pytest.raises(DeviceError, match="board refused STATUS: UNKNOWN_TYPE"):
        board.status()
    with pytest.raises(LimitError, match=r"coil 2 \(\+y\) command 101"):
        board.set((0, 0, 101, 0))
    script.assert_done()


def test_driver_handshakes_again_once_when_the_board_restarted() -> None:
    no_hello = frame(2, 0xEE, b"\x04\x02")
    board, script = driver([
        (frame(1, 0x01, b"\x01"), HELLO_OK),
        (frame(2, 0x02, bytes((9, 0, 0, 0))), no_hello),  # the board reset: it forgot the HELLO
        (frame(3, 0x01, b"\x01"), frame(3, 0x81, bytes((1, 1, 0, 4, 200, 0)))),
        (frame(4, 0x02, bytes((9, 0, 0, 0))), frame(4, 0x82, bytes((0x01, 9, 0, 0, 0)))),
        (frame(5, 0x02, bytes((8, 0, 0, 0))), frame(5, 0xEE, b"\x04\x02")),
        (frame(6, 0x01, b"\x01"), frame(6, 0x81, bytes((1, 1, 0, 4, 200, 0)))),
        (frame(7, 0x02, bytes((8, 0, 0, 0))), frame(7, 0xEE, b"\x04\x02")),  # again: give up
    ])
    assert board.set((9, 0, 0, 0)).outputs == (9, 0, 0, 0) and board.board_restarts == 1
    with pytest.raises(DeviceError, match="NO_HELLO"):
        board.set((8, 0, 0, 0))
    script.assert_done()


def test_driver_refuses_a_board_of_another_protocol_version() -> None:
    script = ScriptedTransport([(frame(1, 0x01, b"\x01"), frame(1, 0x81, bytes((2, 1, 0, 4, 200, 0))))])
    with pytest.raises(DeviceError, match="protocol version 2"):
        CoilBoard.open("scripted://board", opener=lambda url, timeout_s: script, heartbeat_s=None)


def test_driver_applies_coil_directions() -> None:
    board, script = driver([
        (frame(1, 0x01, b"\x01"), HELLO_OK),
        (frame(2, 0x02, bytes((0xF6, 20, 0, 0))), frame(2, 0x82, bytes((0x05, 0xF6, 20, 0, 0)))),
    ], directions=(-1, 1, 1, 1))
    board.set((10, 20, 0, 0))  # coil 0 is wired reversed: -10 on the wire
    script.assert_done()
