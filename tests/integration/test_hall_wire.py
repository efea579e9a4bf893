"""The emulated Hall board against its document (docs/hall-board.md), read with a bare socket.

rigctl's driver is not used here: a lab's own reader would follow the document, so this test
checks each promise the document makes about the wire (the hello's fields and values, the sample
line's fields, one sequence number per read, the saturation masks' bit order, the error answer to
a line sent to the board), and that a client learns where moved sensors are. The expected values
are the document's and the sensor figures' (2.5 uT/LSB, +-50 mT: 20000 counts at the range).
"""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest

from rigctl.emulators.hall.board import HallBoardServer, SensorSpec
from rigctl.emulators.server import EmulatorServer

# no process started (the board serves a real socket from a thread of this process): quick tier
pytestmark = pytest.mark.quick

OFFSETS_MM = [[0, 0, 0], [2, 0, 0], [0, 2, 0]]
# a field of 1 mT along x at every sensor but the last, whose y axis is 60 mT (beyond the range)
FIELD_T = np.array([[1e-3, 0.0, 0.0], [1e-3, 0.0, 0.0], [1e-3, 60e-3, 0.0]])


@pytest.fixture
def board():
    with EmulatorServer() as server:
        emulated = HallBoardServer(server, field_at=lambda points: FIELD_T[:len(points)],
                                   now=lambda: 1.5, offsets_mm=OFFSETS_MM, rate_hz=200.0,
                                   spec=SensorSpec(noise_T=0.0))
        yield server, emulated


class Reader:
    """A bare client: LF-terminated ASCII lines, each one JSON object."""

    def __init__(self, url: str) -> None:
        host, port = url.removeprefix("tcp://").rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=2.0)
        self.file = self.sock.makefile("rb")

    def line(self) -> bytes:
        return self.file.readline()

    def message(self) -> dict:
        raw = self.line()
        assert raw.endswith(b"\n") and raw.isascii()
        return json.loads(raw)

    def close(self) -> None:
        self.file.close()
        self.sock.close()


def test_hello_then_samples_as_documented(board) -> None:
    _, emulated = board
    reader = Reader(emulated.url)
    hello = reader.message()
    assert hello == {"type": "hello", "version": 1, "board": hello["board"], "sensor": "MLX90395",
                     "lsb_uT": 2.5, "range_mT": 50.0, "offsets_mm": OFFSETS_MM, "rate_hz": 200.0}
    samples = [reader.message() for _ in range(5)]
    for sample in samples:
        assert set(sample) == {"type", "seq", "t_s", "raw", "sat"} and sample["type"] == "sample"
        assert sample["t_s"] == 1.5  # the board's own clock
        # 1 mT / 2.5 uT = 400 counts; 60 mT is clipped at 50 mT = 20000 counts and flagged on y
        assert sample["raw"] == [[400, 0, 0], [400, 0, 0], [400, 20000, 0]]
        assert sample["sat"] == [0, 0, 2]  # bit 0 x, bit 1 y, bit 2 z
    assert [s["seq"] for s in samples] == list(range(samples[0]["seq"], samples[0]["seq"] + 5))
    reader.close()


def test_a_line_sent_to_the_board_is_answered_with_an_error(board) -> None:
    _, emulated = board
    reader = Reader(emulated.url)
    reader.message()  # hello
    reader.sock.sendall(b"START\n")
    for _ in range(50):  # samples may come first
        message = reader.message()
        if message["type"] != "sample":
            break
    assert message["type"] == "error" and message["error"]
    reader.close()


def test_moved_sensors_reach_every_client_in_a_new_hello(board) -> None:
    server, emulated = board
    reader = Reader(emulated.url)
    assert reader.message()["offsets_mm"] == OFFSETS_MM
    moved = [[0, 0, 5], [10, 0, 5]]
    server.call(emulated.place, moved)
    while reader.line():  # the board closes the connection: the old hello no longer holds
        pass
    reader.close()
    reader = Reader(emulated.url)
    hello = reader.message()
    assert hello["offsets_mm"] == moved
    assert len(reader.message()["raw"]) == 2
    reader.close()
    assert emulated.points_m.tolist() == pytest.approx(np.array(moved) * 1e-3)
