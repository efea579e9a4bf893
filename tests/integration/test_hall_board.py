"""The Hall-board driver against the emulated board streaming on a real TCP socket."""

from __future__ import annotations

import numpy as np
import pytest
from rigctl.drivers.hall import HallBoard, HallStream
from rigctl.emulators.hall.board import HallBoardServer, SensorSpec
from rigctl.emulators.server import EmulatorServer

from rigctl.errors import DeviceTimeout, Disconnected
from rigctl.magnetics import dipole_field, dipole_gradient, field_vector_from_sensors
from rigctl.testing import wait_for

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
