"""The Hall-board driver against the emulated board streaming on a real TCP socket, and the run's
watch over it (`HallWatch`: a lost board reported, opened again, samples back)."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.errors import DeviceTimeout, Disconnected, ProtocolError
from rigctl.drivers.hall import GARBLED_STREAK, HallBoard, HallStream
from rigctl.emulators.hall.board import HallBoardServer, SensorSpec
from rigctl.emulators.server import EmulatorServer
from rigctl.physics.magnetics import dipole_field, dipole_gradient, field_vector_from_sensors
from rigctl.rigs.depm.sensors import HallWatch

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

CENTRE = np.array([0.25, 0.05, -0.1])
MOMENT = np.array([0.0, 970.0, 0.0])
OFFSETS_MM = [[0, 0, 0], [2, 0, 0], [0, 2, 0]]


@pytest.fixture
def board_server():
    server = EmulatorServer()
    server.start()
    board = HallBoardServer(server, field_at=lambda p: dipole_field(p, CENTRE, MOMENT),
                            now=lambda: 0.0, offsets_mm=OFFSETS_MM, rate_hz=200.0, seed=2,
                            spec=SensorSpec(noise_T=3e-6))
    try:
        yield server, board
    finally:
        server.stop()


def test_streamed_field_and_gradient_match_the_dipole(board_server):
    server, emulated = board_server
    board = HallBoard.open(emulated.url, timeout_s=1.0)
    samples = [board.read() for _ in range(100)]
    assert board.missed == 0
    u = field_vector_from_sensors(np.mean([s.field_T for s in samples], axis=0),
                                  board.info.offsets_m)
    b = dipole_field(np.zeros(3), CENTRE, MOMENT)
    g = dipole_gradient(np.zeros(3), CENTRE, MOMENT)
    assert np.allclose(u[:3], b, atol=2e-6)  # within the LSB, noise averaged over 100 samples
    exact = np.array([g[0, 0], g[0, 1], g[0, 2], g[1, 1], g[1, 2]])
    assert np.max(np.abs(u[3:] - exact)) < 0.02 * np.max(np.abs(exact))
    board.close()


def test_lost_samples_are_counted(board_server):
    server, emulated = board_server
    board = HallBoard.open(emulated.url, timeout_s=1.0)
    board.read()
    server.call(emulated.skip, 5)
    wait_for(lambda: board.read() is not None and board.missed > 0, 5.0, "a sequence gap")
    assert board.missed == 5
    board.close()


def test_link_faults_reach_the_reader(board_server):
    server, emulated = board_server
    board = HallBoard.open(emulated.url, timeout_s=0.3)
    stream = HallStream(board).start()
    wait_for(lambda: len(stream.drain()) > 0, 5.0, "samples")
    emulated.endpoint.stall()
    wait_for(lambda: stream.error is not None, 5.0, "the reader's timeout")
    with pytest.raises(DeviceTimeout, match="hall board"):
        stream.drain()
    stream.stop()
    emulated.endpoint.restore()
    board = HallBoard.open(emulated.url, timeout_s=1.0)
    emulated.endpoint.drop_link()
    with pytest.raises(Disconnected, match="hall board: link lost"):
        for _ in range(1000):
            board.read()
    board.close()


def test_watch_reports_a_lost_board_and_opens_it_again(board_server):
    """What a run sees: samples; the link dropped (reason given, no samples, new connections
    refused meanwhile); the link restored: samples again on a connection of its own."""
    server, emulated = board_server
    watch = HallWatch(emulated.url, timeout_s=0.5).open()
    np.testing.assert_allclose(watch.offsets_m, np.array(OFFSETS_MM) * 1e-3)

    def polled(condition):
        return condition(*watch.poll())

    wait_for(lambda: polled(lambda s, r: len(s) > 0 and r is None), 5.0, "samples")
    emulated.endpoint.drop_link()
    wait_for(lambda: polled(lambda s, r: r is not None and "link lost" in r), 5.0,
             "the loss reported")
    assert watch.outages == 1
    _, reason = watch.poll()
    assert reason is not None  # still away: the board refuses connections until restored
    emulated.endpoint.restore()
    wait_for(lambda: polled(lambda s, r: len(s) > 0 and r is None), 10.0, "samples again")
    assert watch.outages == 1
    watch.close()
    wait_for(lambda: server.call(lambda: len(emulated.sessions)) == 0, 5.0,
             "the watch's link closed")


def test_watch_reports_silence_before_the_reader_times_out(board_server):
    server, emulated = board_server
    watch = HallWatch(emulated.url, timeout_s=30.0).open()  # the reader itself waits long
    wait_for(lambda: len(watch.poll()[0]) > 0, 5.0, "samples")
    emulated.endpoint.stall()
    wait_for(lambda: (watch.poll()[1] or "").startswith("no samples for"), 5.0, "silence noticed")
    emulated.endpoint.restore()
    wait_for(lambda: watch.poll()[1] is None, 5.0, "samples again on the same link")
    assert watch.outages == 0
    watch.close()


def test_a_garbled_line_costs_one_sample_and_a_garbled_streak_ends_the_reader(board_server):
    server, emulated = board_server
    board = HallBoard.open(emulated.url, timeout_s=1.0)
    stream = HallStream(board).start()
    wait_for(lambda: len(stream.drain()) > 0, 5.0, "samples")
    emulated.endpoint.corrupt(1)
    wait_for(lambda: stream.garbled == 1 and board.missed >= 1, 5.0, "the line skipped")
    stream.drain()
    wait_for(lambda: len(stream.drain()) > 0, 5.0, "samples after it")
    assert stream.error is None
    emulated.endpoint.corrupt(GARBLED_STREAK)
    wait_for(lambda: stream.error is not None, 5.0, "the reader ended")
    assert stream.garbled == 1 + GARBLED_STREAK
    with pytest.raises(ProtocolError, match="hall board: not a JSON line"):
        stream.drain()
    stream.stop()
