"""One protocol suite for both coil-board emulators: the Python firmware emulator on a pty, and the
real AVR firmware running in simavr (skipped, with the reason, when the toolchain is missing).

Each test talks to the board over its pty as a host would (raw frames, or the `CoilBoard` driver)
and watches the SyRen wire through a `SyrenBus`. Expected bytes are built here from
docs/coilboard-protocol.md: the CRC by `binascii.crc_hqx` (CRC-CCITT, init 0xFFFF = CCITT-FALSE),
the SyRen checksum from its definition. "No reply" is shown without waiting out a timeout: the board
answers in order, so the first reply after a bad frame must be the answer to the next good one.

Driver tests use reply timeouts far above the link's (1.8 ms on a real wire): the machine running
them is shared, and only where a lost reply is the point does a test wait one out.

The board is shared within a module per emulator (each test handshakes and reads counters as
deltas); unplug tests get a board of their own. The driver opens a stable symlink to the board's
pty, as it would open /dev/serial/by-id/...: an unplug removes it, a replug points it at the new pty
(for simavr, a replug is a restart of the harness: the board boots afresh).
"""

from __future__ import annotations

import binascii
import os
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.errors import DeviceTimeout, Disconnected
from rigctl.core.stream import StreamLoop
from rigctl.core.transport import Transport, open_transport
from rigctl.drivers.coilboard import CoilBoard
from rigctl.emulators.coilboard.firmware import FirmwareEmulator
from rigctl.emulators.coilboard.syren import SyrenBus, SyrenWireReader

HANDSHAKEN, WATCHDOG, SYREN_READY = 0x01, 0x02, 0x04
STATUS_FORMAT = "<BI4bHHH"


def frame(seq: int, kind: int, payload: bytes = b"") -> bytes:
    body = bytes((len(payload), seq, kind)) + payload
    return b"\xa5" + body + struct.pack("<H", binascii.crc_hqx(body, 0xFFFF))


def int8(*values: int) -> bytes:
    return bytes(v & 0xFF for v in values)


# -- the two emulators behind one interface ---------------------------------------------------------


class PythonBoard:
    kind = "python"

    def __init__(self, directory: Path) -> None:
        self.bus = SyrenBus()
        self.url = str(directory / "coilboard")
        self.emulator = FirmwareEmulator(sink=self.bus.feed, syren_startup_s=0.05, link_path=self.url).start()

    def unplug(self) -> None:
        self.emulator.unplug()

    def power_off(self) -> None:
        self.emulator.unplug(power_off=True)

    def replug(self) -> None:
        self.emulator.replug()

    def close(self) -> None:
        self.emulator.stop()


class SimavrBoard:
    kind = "simavr"

    def __init__(self, directory: Path) -> None:
        from rigctl.emulators.coilboard.simavr import SimavrBoard as Harness
        from rigctl.emulators.coilboard.simavr import SimavrUnavailable

        try:
            self.harness = Harness()
        except SimavrUnavailable as err:
            pytest.skip(str(err))
        self.bus = SyrenBus()
        self.url = str(directory / "coilboard")
        self.reader: SyrenWireReader | None = None
        self.replug()

    def replug(self) -> None:
        self.harness.start()
        self.reader = SyrenWireReader(self.harness.syren_path, self.bus)
        os.symlink(self.harness.uart_path, self.url + ".new")
        os.replace(self.url + ".new", self.url)

    def unplug(self) -> None:
        os.unlink(self.url)
        if self.reader is not None:
            self.reader.close()
        self.harness.stop()

    def power_off(self) -> None:
        self.unplug()  # the harness stops: the firmware stops with it

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()
        self.harness.stop()


BOARDS = {"python": PythonBoard, "simavr": SimavrBoard}


@pytest.fixture(scope="module", params=list(BOARDS))
def board(request, tmp_path_factory) -> Iterator[PythonBoard | SimavrBoard]:
    made = BOARDS[request.param](tmp_path_factory.mktemp(request.param))
    yield made
    made.close()


@pytest.fixture(params=list(BOARDS))
def own_board(request, tmp_path) -> Iterator[PythonBoard | SimavrBoard]:
    made = BOARDS[request.param](tmp_path)
    yield made
    made.close()


class Host:
    """The host end of the link, frame by frame."""

    def __init__(self, url: str) -> None:
        self.link: Transport = open_transport(url, timeout_s=2.0)
        self.seq = 0

    def next_seq(self) -> int:
        self.seq = (self.seq + 1) % 256
        if self.seq == 0xA5:  # keep SYNC out of headers so a test's garbage counts stay exact
            self.seq += 1
        return self.seq

    def reply(self) -> bytes:
        header = self.link.read_exact(4)
        assert header[0] == 0xA5, f"reply does not start with SYNC: {header!r}"
        return header + self.link.read_exact(header[1] + 2)

    def ask(self, kind: int, payload: bytes = b"") -> tuple[int, bytes]:
        seq = self.next_seq()
        self.link.write(frame(seq, kind, payload))
        return seq, self.reply()

    def hello(self) -> None:
        seq, reply = self.ask(0x01, b"\x01")
        assert reply == frame(seq, 0x81, bytes((1, 1, 0, 4)) + struct.pack("<H", 200))

    def status(self) -> tuple:
        seq, reply = self.ask(0x03)
        assert reply[:4] == bytes((0xA5, 15, seq, 0x83)) and reply == frame(seq, 0x83, reply[4:19])
        return struct.unpack(STATUS_FORMAT, reply[4:19])

    def wait_syren_ready(self) -> None:
        wait_for(lambda: self.status()[0] & SYREN_READY, timeout_s=10.0, what="SYREN_READY")

    def close(self) -> None:
        self.link.close()


@pytest.fixture
def host(board) -> Iterator[Host]:
    h = Host(board.url)
    h.hello()
    yield h
    h.close()


# -- the protocol facts ------------------------------------------------------------------------------


def test_hello_round_trip(host: Host) -> None:
    seq, reply = host.ask(0x01, b"\x01")
    assert reply == frame(seq, 0x81, bytes((1, 1, 0, 4, 200, 0)))  # version 1, fw 1.0, 4 channels, 200 ms


def test_set_is_acknowledged_and_put_on_the_syren_bus(board, host: Host) -> None:
    host.wait_syren_ready()
    since = time.monotonic()
    seq, reply = host.ask(0x02, int8(40, -40, 127, -127))
    assert reply == frame(seq, 0x82, bytes((HANDSHAKEN | SYREN_READY,)) + int8(40, -40, 127, -127))
    expected = {128: (0, 40), 129: (1, 40), 130: (0, 127), 131: (1, 127)}  # forward 0 / backward 1
    for address, (command, data) in expected.items():
        packet = board.bus.wait_packet(
            lambda p, a=address, c=command, d=data: (p.address, p.command, p.data) == (a, c, d),
            since=since, timeout_s=2.0)
        assert packet is not None, f"no packet {address} {command} {data} on the SyRen wire"
    assert board.bus.outputs() == pytest.approx((40 / 127, -40 / 127, 1.0, -1.0))
    host.ask(0x04)


def test_a_corrupted_frame_gets_no_reply_and_counts_as_bad(board, host: Host) -> None:
    host.ask(0x02, int8(5, 6, 7, 8))
    _, _, *before = host.status()
    corrupted = bytearray(frame(0x30, 0x02, int8(90, 90, 90, 90)))
    corrupted[5] ^= 0x10  # a payload bit flipped on the wire
    host.link.write(bytes(corrupted))
    flags, _, *after = host.status()  # the first reply to come answers this STATUS
    assert after[:4] == [5, 6, 7, 8]  # the corrupted SET was not applied
    assert after[5] == before[5] + 1  # bad_frames
    assert after[4] == before[4] + 1  # good_frames: only the STATUS


def test_a_wrong_checksum_gets_no_reply_and_counts_as_bad(host: Host) -> None:
    *_, good, bad, _ = host.status()
    wrong = bytearray(frame(0x31, 0x03))
    wrong[-2] ^= 0x01
    assert 0xA5 not in wrong[1:]
    host.link.write(bytes(wrong))
    *_, good_after, bad_after, _ = host.status()
    assert (good_after, bad_after) == (good + 1, bad + 1)


def test_garbage_then_a_frame_resynchronises(host: Host) -> None:
    *_, good, bad, _ = host.status()
    # bytes that are not SYNC, then a SYNC with an impossible LEN (not a frame, not counted)
    seq = host.next_seq()
    host.link.write(b"\x00\xff\x13\x5a\xa5\x7f\x42" + frame(seq, 0x03))
    reply = host.reply()
    assert reply[2:4] == bytes((seq, 0x83))
    *_, good_after, bad_after, _ = struct.unpack(STATUS_FORMAT, reply[4:19])
    assert (good_after, bad_after) == (good + 1, bad)
    # a stray SYNC + LEN 0 takes the next frame's first bytes as its own: it fails its CRC (one
    # bad frame), and the real frame behind it is still found
    seq = host.next_seq()
    good_frame = frame(seq, 0x03)
    assert binascii.crc_hqx(b"\x00" + good_frame[:2], 0xFFFF) != struct.unpack("<H", good_frame[2:4])[0]
    host.link.write(b"\xa5\x00" + good_frame)
    reply = host.reply()
    assert reply[2:4] == bytes((seq, 0x83))
    assert struct.unpack(STATUS_FORMAT, reply[4:19])[-2] == bad + 1


def test_a_stale_partial_frame_is_dropped(host: Host) -> None:
    *_, bad, _ = host.status()
    host.link.write(b"\xa5\x10\x01\x02\x00")  # LEN 16: waits for 17 more bytes that never come
    time.sleep(0.06)  # the protocol's 20 ms stale rule must pass; nothing to wait on instead
    *_, bad_after, _ = host.status()  # answered at once: the partial did not swallow it
    assert bad_after == bad + 1  # both emulators count the dropped partial frame as bad


def test_unknown_type_bad_length_and_bad_value_are_refused(host: Host) -> None:
    seq, reply = host.ask(0x42)
    assert reply == frame(seq, 0xEE, b"\x02\x42")  # UNKNOWN_TYPE, request type echoed
    seq, reply = host.ask(0x03, b"\x00")
    assert reply == frame(seq, 0xEE, b"\x01\x03")  # BAD_LENGTH
    seq, reply = host.ask(0x02, int8(0, 0, -128, 0))
    assert reply == frame(seq, 0xEE, b"\x03\x02")  # BAD_VALUE


def test_set_before_hello_is_refused(host: Host) -> None:
    seq, reply = host.ask(0x01, b"\x02")
    assert reply == frame(seq, 0xEE, b"\x05\x01")  # BAD_VERSION: the board is not handshaken now
    assert not host.status()[0] & HANDSHAKEN
    seq, reply = host.ask(0x02, int8(1, 1, 1, 1))
    assert reply == frame(seq, 0xEE, b"\x04\x02")  # NO_HELLO
    host.hello()
    assert host.status()[0] & HANDSHAKEN


def test_watchdog_zeroes_the_syren_outputs_after_silence(board, host: Host) -> None:
    host.wait_syren_ready()
    *_, trips = host.status()
    host.ask(0x02, int8(60, -60, 60, -60))
    last_frame = time.monotonic()
    wait_for(lambda: board.bus.outputs() == pytest.approx((60 / 127, -60 / 127, 60 / 127, -60 / 127)),
             timeout_s=2.0, what="the SET on the SyRen wire")
    zeros = [board.bus.wait_packet(lambda p, a=a: p.address == a and p.command == 0 and p.data == 0,
                                   since=last_frame, timeout_s=3.0) for a in (128, 129, 130, 131)]
    assert all(zeros), "the watchdog did not put zero on every driver"
    flags, _, *outputs, _, _, trips_after = host.status()
    assert flags & WATCHDOG and outputs == [0, 0, 0, 0] and trips_after == trips + 1
    print(f"{board.kind}: last frame to all four zero packets "
          f"{(max(p.time for p in zeros) - last_frame) * 1000:.0f} ms (not asserted; see bench)")
    seq, reply = host.ask(0x02, int8(1, 0, 0, 0))
    assert reply == frame(seq, 0x82, bytes((HANDSHAKEN | SYREN_READY,)) + int8(1, 0, 0, 0))  # cleared
    host.ask(0x04)


# -- the driver on both emulators ---------------------------------------------------------------------


def test_driver_round_trip_and_heartbeats_keep_the_watchdog_quiet(board) -> None:
    # a generous reply timeout: this machine is shared, and a lost reply is not what is tested here
    with CoilBoard.open(board.url, reply_timeout_s=1.0) as driver:
        trips = driver.status().watchdog_trips
        assert driver.set((10, -20, 30, -40)).outputs == (10, -20, 30, -40)
        sent = driver.requests
        wait_for(lambda: driver.requests >= sent + 4, timeout_s=5.0, what="four heartbeats")
        status = driver.status()
        if driver.max_gap_s >= 0.2:  # this process was not scheduled for 200 ms: the board was right
            pytest.skip(f"the host stalled {driver.max_gap_s * 1000:.0f} ms between frames")
        assert status.outputs == (10, -20, 30, -40) and status.watchdog_trips == trips


def test_driver_streams_commands_at_a_fixed_rate(board) -> None:
    program = [(k, 0, -k, 0) for k in range(0, 40, 4)]  # ten SETs
    with CoilBoard.open(board.url, reply_timeout_s=1.0) as driver:
        # The driver owns no loop: the caller runs the stream loop and the driver sends.
        def cycle(k: int) -> bool:
            if k >= len(program):
                return False
            driver.set(program[k])
            return True

        stats = StreamLoop(50.0).run(cycle)
        assert stats.cycles == len(program) + 1  # the last cycle finds the program ended
        assert driver.status().outputs == program[-1]
        assert driver.lost_replies == 0


def test_emergency_stop_from_another_thread_zeroes_the_coils_and_latches(board) -> None:
    with CoilBoard.open(board.url, reply_timeout_s=1.0) as driver:
        wait_for(lambda: driver.status().syren_ready, timeout_s=10.0, what="SYREN_READY")
        driver.set((90, 0, 0, -60))
        wait_for(lambda: board.bus.outputs() == pytest.approx((90 / 127, 0.0, 0.0, -60 / 127)),
                 timeout_s=5.0, what="the SyRens at the commanded drive")
        sets = threading.Event()
        stop_streaming = threading.Event()
        errors: list[BaseException] = []

        def cycle(k: int) -> bool:
            driver.set((90, 0, 0, -60))
            sets.set()
            return not stop_streaming.is_set()

        def stream() -> None:  # a stream thread that keeps commanding the pull
            try:
                StreamLoop(100.0).run(cycle)
            except BaseException as err:  # noqa: BLE001 - reported by the test
                errors.append(err)

        streamer = threading.Thread(target=stream)
        streamer.start()
        try:
            assert sets.wait(5.0)
            assert driver.emergency_stop()  # this thread, while the other one is mid-request
            assert driver.estopped
            # Every SET after the e-stop leaves as zeros: the board reports them applied.
            sent = driver.requests
            wait_for(lambda: driver.requests >= sent + 5, timeout_s=5.0, what="five more requests")
            wait_for(lambda: board.bus.outputs() == pytest.approx((0.0, 0.0, 0.0, 0.0)),
                     timeout_s=5.0, what="every SyRen at zero")
            assert driver.last_ack.outputs == (0, 0, 0, 0)
            assert driver.status().outputs == (0, 0, 0, 0)
        finally:
            stop_streaming.set()
            streamer.join(5.0)
        assert errors == []
        assert driver.set((10, 0, 0, 0)).outputs == (0, 0, 0, 0)  # still latched


def test_driver_reconnects_after_unplug_and_replug(own_board) -> None:
    with CoilBoard.open(own_board.url, reconnect_s=20.0, reply_timeout_s=1.0) as driver:
        driver.set((20, 0, 0, 0))
        own_board.unplug()
        wait_for(lambda: not driver.link_up, timeout_s=5.0, what="the driver to notice the unplug")
        own_board.replug()
        assert driver.set((0, 30, 0, 0)).outputs == (0, 30, 0, 0)
        assert driver.reconnects == 1 and driver.link_up
        assert driver.status().handshaken


def test_driver_reports_a_board_that_stays_gone(own_board) -> None:
    driver = CoilBoard.open(own_board.url, reconnect_s=0.3, heartbeat_s=None)
    own_board.unplug()
    with pytest.raises(Disconnected) as info:
        driver.set((1, 0, 0, 0))
    message = str(info.value)
    assert message.startswith("coil board: ") and own_board.url in message and "USB" in message
    with pytest.raises(Disconnected):
        driver.status()  # the fault stays until the run is restarted
    driver.close()
    own_board.replug()  # so the fixture's teardown finds what it started


def test_a_board_that_dies_leaves_the_coils_off(own_board) -> None:
    """The SyRen drivers' own serial timeouts (set at start-up) stop the coils when the board
    falls silent, without any zero packet from the board."""
    host = Host(own_board.url)
    host.hello()
    host.wait_syren_ready()
    host.ask(0x02, int8(70, 0, -70, 0))
    wait_for(lambda: own_board.bus.outputs() == pytest.approx((70 / 127, 0, -70 / 127, 0)),
             timeout_s=2.0, what="the SET on the SyRen wire")
    timeouts = own_board.bus.snapshot().timeouts_s
    assert all(t > 0 for t in timeouts), f"the board set no SyRen serial timeout: {timeouts}"
    host.close()
    own_board.power_off()
    last_packet = max(p.time for p in own_board.bus.packets())
    wait_for(lambda: own_board.bus.snapshot().timed_out == (True, True, True, True), timeout_s=5.0,
             what="the SyRen serial timeouts")
    assert own_board.bus.outputs() == (0.0, 0.0, 0.0, 0.0)
    assert not own_board.bus.packets(since=last_packet)  # silence: no zero packet did it
    own_board.replug()


# -- link faults only the Python emulator can inject ----------------------------------------------


def test_driver_survives_garbage_and_a_corrupted_reply_from_the_board(tmp_path) -> None:
    board = PythonBoard(tmp_path)
    try:
        with CoilBoard.open(board.url, heartbeat_s=None, reply_timeout_s=0.5) as driver:
            board.emulator.inject(b"\x00\xa5\x03\x99garbage")
            assert driver.set((3, 0, 0, 0)).outputs == (3, 0, 0, 0)
            board.emulator.corrupt(1)  # the next reply is garbage: lost, retried with a new SEQ
            assert driver.set((4, 0, 0, 0)).outputs == (4, 0, 0, 0)
            assert driver.lost_replies == 1
            board.emulator.reset()  # the AVR resets under a running link: NO_HELLO, handshake again
            assert driver.set((6, 0, 0, 0)).outputs == (6, 0, 0, 0)
            assert driver.board_restarts == 1 and board.emulator.state().handshaken
            board.emulator.stall()  # the board hears but never answers: a bounded fault
            with pytest.raises(DeviceTimeout, match="gave up after 3 attempts"):
                driver.status()
            board.emulator.restore()
            with pytest.raises(DeviceTimeout):
                driver.set((0, 0, 0, 0))  # the fault stays until the operator reconnects
            driver.connect()
            assert driver.set((5, 0, 0, 0)).outputs == (5, 0, 0, 0)
    finally:
        board.close()


def test_python_emulator_can_put_the_syren_wire_on_a_pty_like_the_simavr_harness(tmp_path) -> None:
    bus = SyrenBus()
    with FirmwareEmulator(sink=None, syren_startup_s=0.0, link_path=str(tmp_path / "board")) as emulator:
        with SyrenWireReader(emulator.syren_path, bus):
            host = Host(emulator.url)
            host.hello()
            host.wait_syren_ready()
            since = time.monotonic()
            host.ask(0x02, int8(0, 0, 0, -99))
            packet = bus.wait_packet(lambda p: (p.address, p.command, p.data) == (131, 1, 99),
                                     since=since, timeout_s=2.0)
            assert packet is not None and bus.snapshot().timeouts_s == pytest.approx((0.3, 0.3, 0.3, 0.3))
            host.close()
