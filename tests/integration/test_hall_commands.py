"""The Hall board's command audit (issue 38 item 6): its protocol documents no command
(docs/hall-board.md, "The stream"), so whatever line a client sends is an unknown one and gets the
documented error, one error line per line sent, and the stream goes on unchanged. Read with a bare
socket, independently of rigctl's driver."""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest

from rigctl.emulators.hall.board import HallBoardServer, SensorSpec
from rigctl.emulators.server import EmulatorServer

# no process started (the board serves a real socket from a thread of this process): quick tier
pytestmark = pytest.mark.quick

# what a lab's own reader might try: a bare word, a JSON request, the hello's own type
LINES_SENT = (b"START", b'{"cmd": "rate", "hz": 50}', b"hello")


def test_every_line_sent_gets_one_documented_error_and_the_stream_goes_on() -> None:
    with EmulatorServer() as server:
        board = HallBoardServer(server, field_at=lambda points: np.zeros((len(points), 3)),
                                now=lambda: 0.0, rate_hz=200.0, spec=SensorSpec(noise_T=0.0))
        host, port = board.url.removeprefix("tcp://").rsplit(":", 1)
        with socket.create_connection((host, int(port)), timeout=2.0) as sock:
            lines = sock.makefile("rb")
            assert json.loads(lines.readline())["type"] == "hello"
            sock.sendall(b"".join(line + b"\n" for line in LINES_SENT))
            errors, seqs = [], []
            while len(seqs) < 40:  # 0.2 s of samples: long after the three answers
                message = json.loads(lines.readline())
                assert message["type"] in ("sample", "error"), message
                if message["type"] == "error":
                    errors.append(message)
                else:
                    seqs.append(message["seq"])
            assert len(errors) == len(LINES_SENT)
            assert all(set(e) == {"type", "error"} and "takes no commands" in e["error"] for e in errors)
            # the stream was not disturbed: no sample lost, none repeated
            assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
            lines.close()
