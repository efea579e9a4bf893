"""Twenty clients asking `status` as fast as they are answered get the daemon's request budget
between them, every one of them some of it, and an e-stop sent in the middle of the flood is
carried out at once (`rigctl.apps.daemon.admission`, issue 15: the stream comes first)."""

from __future__ import annotations

import json
import threading
import time

import pytest
import zmq

from rigctl.apps.daemon.server import Daemon
from rigctl.core.config import RigInfo, default_six_coil_coils
from rigctl.rigs.six_coil.settings import SixCoilRig

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

RATE_HZ = 200.0
CLIENTS = 20
FLOOD_S = 1.5


def test_a_flood_gets_the_budget_shared_and_an_estop_does_not_wait(tmp_path):
    rig = SixCoilRig(rig=RigInfo(kind="six-coil", name="budget"), coils=default_six_coil_coils())
    d = Daemon(rig, command="tcp://127.0.0.1:0", telemetry="tcp://127.0.0.1:0",
               events="tcp://127.0.0.1:0", runs_dir=tmp_path, request_rate_hz=RATE_HZ)
    d.start_thread()
    context = zmq.Context()
    answered = [0] * CLIENTS
    window: dict[str, float] = {}
    go, stop = threading.Event(), threading.Event()

    def client(i: int) -> None:
        sock = context.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(d.endpoints.command)
        go.wait()
        while not stop.is_set():
            sock.send(json.dumps({"id": f"c{i}", "cmd": "status"}).encode())
            if not sock.poll(5000):
                break
            reply = json.loads(sock.recv())
            assert reply["ok"] and reply["id"] == f"c{i}"
            if not stop.is_set():
                answered[i] += 1
        sock.close()

    threads = [threading.Thread(target=client, args=(i,)) for i in range(CLIENTS)]
    try:
        for t in threads:
            t.start()
        window["start"] = time.monotonic()
        go.set()
        time.sleep(FLOOD_S / 2)
        operator = context.socket(zmq.REQ)
        operator.setsockopt(zmq.LINGER, 0)
        operator.connect(d.endpoints.command)
        operator.send(b'{"id":"stop-now","cmd":"estop"}')
        assert operator.poll(2000), "the e-stop waited behind the flood"
        estop = json.loads(operator.recv())
        assert estop["id"] == "stop-now" and estop["ok"], estop
        operator.close()
        time.sleep(max(0.0, window["start"] + FLOOD_S - time.monotonic()))
        stop.set()
        window["end"] = time.monotonic()
        for t in threads:
            t.join(10)
        total = sum(answered)
        span = window["end"] - window["start"]
        # a full bucket at the start (the burst), then the rate; 10 % for the clocks' edges
        assert total <= (RATE_HZ * span + d.admission.burst) * 1.1, (total, span)
        assert min(answered) > 0, answered  # nobody starved
        assert d.admission.held > 0  # the flood really waited
        assert d.state.value == "estopped"
    finally:
        stop.set()
        d.stop()
        context.term()
