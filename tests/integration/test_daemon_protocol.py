"""The daemon's command loop and telemetry over real ZeroMQ sockets, with a stand-in run (no
devices): the protocol, malformed input, many and vanishing clients, the state table, telemetry."""

import json
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zmq

from rigctl.apps.client import CommandRefused, DaemonUnreachable, Rig
from rigctl.apps.daemon.messages import MAX_REQUEST_BYTES, DaemonState, StateMsg
from rigctl.apps.daemon.server import Daemon
from rigctl.apps.daemon.states import TRANSITIONS
from rigctl.apps.daemon.telemetry import CycleBatch
from rigctl.core.config import RigInfo, default_six_coil_coils
from rigctl.core.errors import PlanError
from rigctl.core.stream import StreamLoop
from rigctl.rigs.six_coil.settings import SixCoilRig
from rigctl.run.control import RunState

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

RATE_HZ = 500.0


class StandInRun:
    """Streams `samples` cycles of made-up currents at RATE_HZ; obeys pause, resume, abort and
    estop the way a Run does (pause at the end of a 'move' of 50 samples), and can fault."""

    def __init__(self, plan, runs_dir, on_cycles, on_state):
        self.plan = SimpleNamespace(name="stand-in", moves=[[10, 0]] * (plan["samples"] // 50),
                                    agents=[], expected=None)
        self.samples = plan["samples"]
        self.info = {"name": "stand-in", "moves": len(self.plan.moves), "samples": self.samples,
                     "duration_s": self.samples / RATE_HZ}
        self.fault_at = plan.get("fault_at")
        self.suspended = plan.get("suspended")  # [from, to): lost tracking, as a supervisor says
        self.unreachable = plan.get("unreachable", [])  # supplies whose link is down at e-stop
        self.runs_dir, self.on_cycles, self.on_state = runs_dir, on_cycles, on_state
        self.record = None
        self.pause_requested = self.aborted = False
        self.estopped = threading.Event()
        self.zeroed_at = None

    def pause(self, immediate=False):
        self.pause_requested = True

    def resume(self):
        self.pause_requested = False

    def abort(self):
        self.aborted = True

    def estop(self):
        self.estopped.set()
        return list(self.unreachable)

    def execute(self):
        self.record = SimpleNamespace(path=Path(self.runs_dir) / "stand-in-run")
        self.on_state(RunState.RUNNING, {})
        index, paused = 0, False
        n = self.samples

        def cycle(_):
            nonlocal index, paused
            if self.estopped.is_set():
                self.zeroed_at = time.monotonic()
                self.on_state(RunState.ESTOPPED, {})
                return False
            if self.aborted:
                self.on_state(RunState.ABORTED, {})
                return False
            if self.fault_at is not None and index == self.fault_at:
                self.on_state(RunState.FAULTED,
                              {"device": "y+", "reason": "y+: link dropped"})
                return False
            if self.pause_requested and index % 50 == 0 and not paused:
                paused = True
                self.on_state(RunState.PAUSED, {})
            elif not self.pause_requested and paused:
                paused = False
                self.on_state(RunState.RUNNING, {})
            if self.suspended and index in self.suspended:  # what a supervisor will report
                self.on_state(SimpleNamespace(value="suspended" if index == self.suspended[0]
                                              else "running"), {})
            if not paused:
                index += 1
            if index >= n:
                self.on_state(RunState.DONE, {})
                return False
            # a batch of one cycle (a stream process sends about ten)
            self.on_cycles(CycleBatch(np.array([time.monotonic()]), np.array([index]),
                                      np.array([index // 50]), np.full((1, 6), 1.0),
                                      np.full((1, 6), 0.99), np.array([np.nan])))
            return True

        StreamLoop(RATE_HZ).run(cycle)
        return None


class StandInRuns:
    def __init__(self):
        self.runs = []

    def start(self):
        pass

    def close(self):
        pass

    def parse_plan(self, data):
        if not isinstance(data.get("samples"), int) or data["samples"] <= 0:
            raise PlanError("plan: samples: must be a positive integer")
        return data

    def prepare(self, plan, rig, *, runs_dir, on_cycles, on_state):
        if getattr(plan, "kind", None) == "hold":
            return StandInHold(plan, runs_dir, on_state)
        run = StandInRun(plan, runs_dir, on_cycles, on_state)
        self.runs.append(run)
        return run


class StandInHold:
    """A manual hold as the stream process reports one: streaming at once, until released,
    aborted or e-stopped."""

    def __init__(self, plan, runs_dir, on_state):
        self.plan, self.info, self.on_state = plan, {"name": "hold"}, on_state
        self.record = SimpleNamespace(path=Path(runs_dir) / "stand-in-hold")
        self.started, self.ended = threading.Event(), threading.Event()
        self.streaming, self.error, self.result = False, None, None
        self.estopped = False

    def execute(self):
        self.on_state(RunState.RUNNING, {})
        self.streaming = True
        self.started.set()
        self.ended.wait(60)
        self.on_state(RunState.ESTOPPED if self.estopped else RunState.DONE, {})

    def retarget(self, target, setpoints, ramp_s):
        pass

    def release(self, ramp_s):
        self.ended.set()

    def pause(self, immediate=False):
        pass

    def resume(self):
        pass

    def abort(self):
        self.ended.set()

    def estop(self):
        self.estopped = True
        self.ended.set()
        return []


@pytest.fixture
def daemon(tmp_path):
    rig = SixCoilRig(rig=RigInfo(kind="six-coil", name="test rig"), coils=default_six_coil_coils())
    factory = StandInRuns()
    d = Daemon(rig, command="tcp://127.0.0.1:0", telemetry="tcp://127.0.0.1:0",
               events="tcp://127.0.0.1:0", runs_dir=tmp_path, run_factory=factory)
    d.factory_runs = factory.runs
    d.start_thread()
    yield d
    d.stop()


@pytest.fixture
def rig_client(daemon):
    with Rig(daemon.endpoints.command, timeout_s=2.0) as client:
        yield client


def raw_req(endpoint, payload: bytes, timeout_ms=3000):
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    try:
        sock.send(payload)
        assert sock.poll(timeout_ms), "no reply"
        return json.loads(sock.recv())
    finally:
        sock.close()


def test_plain_req_socket_ping_and_status(daemon):
    reply = raw_req(daemon.endpoints.command, b'{"id": 7, "cmd": "ping"}')
    assert reply["id"] == 7 and reply["ok"] is True
    assert reply["result"]["protocol"] == "rigctl.apps.daemon/1"
    status = raw_req(daemon.endpoints.command, b'{"id": "s", "cmd": "status", "args": {}}')
    result = status["result"]
    assert result["state"] == "idle"
    assert result["rig"]["name"] == "test rig"
    assert [d["name"] for d in result["devices"]] == ["x+", "x-", "y+", "y-", "z+", "z-"]
    assert result["run"] is None and result["last_fault"] is None


def test_status_and_estop_answered_without_the_models_are_what_the_models_would_say(daemon):
    from rigctl.apps.daemon.messages import Reply, ok_reply

    for request_id, payload in [("s", b'{"id": "s", "cmd": "status", "args": {}}'),
                                (8, b'{"cmd": "status", "id": 8}'), (None, b'{"cmd": "status"}')]:
        with zmq.Context.instance().socket(zmq.REQ) as sock:
            sock.connect(daemon.endpoints.command)
            sock.send(payload)
            assert sock.poll(5000)
            body = sock.recv()
        modelled = json.loads(ok_reply(request_id, daemon._cmd_status(None)).model_dump_json())
        quick = json.loads(body)
        assert Reply.model_validate(quick).id == request_id
        modelled["result"].pop("uptime_s"), quick["result"].pop("uptime_s")
        assert quick == modelled
    estop = raw_req(daemon.endpoints.command, b'{"id": "e", "cmd": "estop"}')
    assert Reply.model_validate(estop).ok and estop["id"] == "e"
    assert estop["result"]["state"] == "estopped" and estop["result"]["unreached"] == []
    assert json.loads(ok_reply("e", {**estop["result"]}).model_dump_json()) == estop


@pytest.mark.parametrize("payload, code", [
    (b"this is not json", "bad_json"),
    (b'{"id": 1, "cmd": "status", "args": {"verbose": true}}', "bad_args"),
    (b'{"id": 1.5, "cmd": "status"}', "bad_request"),
    (b'{"id": 1, "cmd": "estop", "args": {"now": true}}', "bad_args"),
    (b"\xff\xfe\x00", "bad_json"),
    (b"[1, 2, 3]", "bad_request"),
    (b'{"id": 1}', "bad_request"),
    (b'{"id": 1, "cmd": 5}', "bad_request"),
    (b'{"id": 1, "cmd": "status", "args": []}', "bad_request"),
    (b'{"id": 1, "cmd": "status", "extra": 1}', "bad_request"),
    (b'{"id": 1, "cmd": "fly"}', "unknown_command"),
    (b'{"id": 1, "cmd": "pause", "args": {"immediate": "soon"}}', "bad_args"),
    (b'{"id": 1, "cmd": "execute", "args": {}}', "bad_args"),
    (b'{"id": 1, "cmd": "set_field", "args": {"field_mT": [1, 2]}}', "bad_args"),
    (b'{"id": 1, "cmd": "load", "args": {"plan": {"samples": -3}}}', "plan_invalid"),
    (b'{"id": 1, "cmd": "execute", "args": {"plan_id": "nope"}}', "unknown_plan"),
    (b'{"id": 1, "cmd": "run", "args": {"run": "../etc"}}', "unknown_run"),
    (b'{"id": 1, "cmd": "resume"}', "wrong_state"),
])
def test_malformed_requests_get_an_error_reply_and_the_daemon_keeps_serving(daemon, payload, code):
    reply = raw_req(daemon.endpoints.command, payload)
    assert reply["ok"] is False
    assert reply["error"]["code"] == code, reply
    assert reply["error"]["message"]
    assert raw_req(daemon.endpoints.command, b'{"cmd": "ping"}')["ok"] is True


@pytest.mark.parametrize("request_id", [b"1.0", b"-0.0", b"2e3", b"true", b"false", b"[1]",
                                        b'{"id": 1}'])
def test_an_id_that_is_no_string_or_integer_is_refused_and_not_echoed_as_another(daemon,
                                                                                 request_id):
    # before: 1.0 and true were answered as id 1, false as 0 (another request's id)
    for cmd in (b"status", b"ping", b"estop"):  # the quick path's commands and the general one
        reply = raw_req(daemon.endpoints.command, b'{"id": ' + request_id + b', "cmd": "' + cmd
                        + b'"}')
        assert reply["ok"] is False and reply["id"] is None, reply
        assert reply["error"]["code"] == "bad_request"
        assert "id: an id is a string or an integer" in reply["error"]["message"]
    assert daemon.state.value == "idle"  # the e-stops were refused, not carried out
    assert raw_req(daemon.endpoints.command, b'{"id": 5, "cmd": "ping"}')["id"] == 5


def test_a_10_MB_payload_is_refused_as_too_large(daemon):
    payload = b'{"id": 1, "cmd": "load", "args": {"plan": "' + b"x" * (10 * 1024 * 1024) + b'"}}'
    assert len(payload) > MAX_REQUEST_BYTES
    reply = raw_req(daemon.endpoints.command, payload, timeout_ms=10000)
    assert reply["error"]["code"] == "too_large"
    assert raw_req(daemon.endpoints.command, b'{"cmd": "ping"}')["ok"] is True


def test_a_client_that_vanishes_mid_request_does_not_block_others(daemon):
    ctx = zmq.Context.instance()
    for _ in range(20):  # send and disappear without reading the reply
        sock = ctx.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(daemon.endpoints.command)
        sock.send(b'{"cmd": "status"}')
        sock.close()
    dealer = ctx.socket(zmq.DEALER)  # a client that sends half a request and stays silent
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(daemon.endpoints.command)
    dealer.send_multipart([b"", b"part one", b"part two"])
    results = []

    def client():
        with Rig(daemon.endpoints.command, timeout_s=2.0, retries=0) as rig:
            results.append(all(rig.status()["state"] == "idle" for _ in range(20)))

    threads = [threading.Thread(target=client) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=20)
    dealer.close()
    assert results == [True] * 8


def test_unreachable_daemon_raises_after_bounded_retries():
    started = time.monotonic()
    with Rig("tcp://127.0.0.1:1", timeout_s=0.1, retries=2) as rig:
        with pytest.raises(DaemonUnreachable):
            rig.ping()
    assert time.monotonic() - started < 2.0


def test_a_reply_to_another_request_is_no_reply_and_the_client_retries():
    """A server (a real REP socket on loopback) that answers every request with someone else's
    id: the client takes none of those replies, retries on a new socket each time, and ends in
    DaemonUnreachable after its attempts, not in a socket error."""
    context = zmq.Context.instance()
    server = context.socket(zmq.REP)
    port = server.bind_to_random_port("tcp://127.0.0.1")
    received = []

    def serve():
        while server.poll(2000):
            received.append(json.loads(server.recv()))
            server.send(json.dumps({"id": "not-yours", "ok": True, "result": {}}).encode())

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        with Rig(f"tcp://127.0.0.1:{port}", timeout_s=0.5, retries=2) as rig:
            with pytest.raises(DaemonUnreachable):
                rig.ping()
        assert len(received) == 3 and len({r["id"] for r in received}) == 1  # one id, retried
    finally:
        thread.join(5)
        server.close(linger=0)


def test_a_client_whose_daemon_falls_silent_after_answering_still_times_out():
    """The client sets its socket's timeouts only when they change: a request on a socket that
    already answered once must still give up within its timeout (a real REP socket on loopback
    answers the first request and then nothing)."""
    context = zmq.Context.instance()
    server = context.socket(zmq.REP)
    port = server.bind_to_random_port("tcp://127.0.0.1")

    def serve_once():
        if server.poll(5000):
            request = json.loads(server.recv())
            server.send(json.dumps({"id": request["id"], "ok": True, "result": {"n": 1}}).encode())

    thread = threading.Thread(target=serve_once, daemon=True)
    thread.start()
    try:
        with Rig(f"tcp://127.0.0.1:{port}", timeout_s=0.3, retries=1) as rig:
            assert rig.ping() == {"n": 1}
            started = time.monotonic()
            with pytest.raises(DaemonUnreachable):
                rig.ping()
            waited = time.monotonic() - started
        assert 0.5 <= waited < 3.0  # two attempts of 0.3 s each, not forever
    finally:
        thread.join(5)
        server.close(linger=0)


def load_and_execute(rig, samples=2000, **extra):
    plan_id = rig.load({"samples": samples, **extra})
    return plan_id, rig.execute(plan_id)


def test_pause_resume_abort_are_states_and_follow_the_table(daemon, rig_client):
    plan_id, started = load_and_execute(rig_client)
    assert started["state"] == "running" and started["moves"] == 40
    with pytest.raises(CommandRefused) as refused:
        rig_client.execute(plan_id)
    assert refused.value.code == "wrong_state"
    rig_client.pause()
    status = rig_client.wait_state("paused", timeout_s=5)
    assert status["run"]["plan_id"] == plan_id
    sample = status["run"]["sample"]
    assert sample % 50 == 0  # paused at the end of a move, not mid-move
    rig_client.resume()
    rig_client.wait_state("running", timeout_s=5)
    rig_client.abort()
    rig_client.wait_state("idle", timeout_s=5)
    with pytest.raises(CommandRefused) as refused:
        rig_client.pause()
    assert refused.value.code == "wrong_state"


def test_estop_from_any_state_is_immediate_and_reset_leaves_it(daemon, rig_client):
    load_and_execute(rig_client, samples=100_000)
    rig_client.wait_state("running")
    sent = time.monotonic()
    reply = rig_client.estop()
    assert reply["state"] == "estopped"
    run = daemon.factory_runs[-1]
    deadline = time.monotonic() + 2
    while run.zeroed_at is None and time.monotonic() < deadline:
        time.sleep(0.001)
    # the stand-in zeroes at its next stream cycle: within a period (plus scheduling slack)
    assert run.zeroed_at is not None and run.zeroed_at - sent < 5 / RATE_HZ + 0.05
    with pytest.raises(CommandRefused) as refused:
        load_and_execute(rig_client)
    assert refused.value.code == "wrong_state" and "reset" in refused.value.reason
    # wait for the run thread to end, then reset
    deadline = time.monotonic() + 5
    while rig_client.status()["run"] is not None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert rig_client.reset()["state"] == "idle"
    assert rig_client.estop()["state"] == "estopped"  # from idle too
    assert rig_client.reset()["state"] == "idle"


def test_estop_names_the_supplies_it_could_not_reach(daemon, rig_client):
    load_and_execute(rig_client, samples=100_000, unreachable=["y+"])
    rig_client.wait_state("running")
    reply = rig_client.estop()
    assert reply["state"] == "estopped" and reply["unreached"] == ["y+"]
    assert "y+" in reply["zeroing"] and "done" not in reply["zeroing"]
    devices = {d["name"]: d for d in rig_client.status()["devices"]}
    assert devices["y+"]["health"] == "fault" and "could not be sent" in devices["y+"]["detail"]


def test_a_fault_during_a_run_leaves_the_daemon_serving_in_faulted(daemon, rig_client):
    with rig_client.telemetry(["state", "fault"]) as feed:
        load_and_execute(rig_client, samples=5000, fault_at=100)
        status = rig_client.wait_state("faulted", timeout_s=5)
        assert status["device"] == "y+"
        assert status["last_fault"]["device"] == "y+"
        assert [d["health"] for d in status["devices"] if d["name"] == "y+"] == ["fault"]
        faults, states = [], []
        deadline = time.monotonic() + 5
        while not faults and time.monotonic() < deadline:
            msg = feed.receive(timeout_s=1)
            if msg is not None:
                (faults if msg.topic == "fault" else states).append(msg)
        assert faults and faults[0].device == "y+"
    with pytest.raises(CommandRefused):
        load_and_execute(rig_client)
    rig_client.wait_state("faulted")
    deadline = time.monotonic() + 5
    while rig_client.status()["run"] is not None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert rig_client.reset()["state"] == "idle"


def test_state_table_is_explicit():
    S = DaemonState
    assert TRANSITIONS[(S.IDLE, "execute")] == S.RUNNING
    assert (S.RUNNING, "execute") not in TRANSITIONS
    assert (S.FAULTED, "execute") not in TRANSITIONS and (S.ESTOPPED, "execute") not in TRANSITIONS
    assert all(TRANSITIONS[(s, "estop")] == S.ESTOPPED for s in S)
    assert TRANSITIONS[(S.FAULTED, "reset")] == S.IDLE and TRANSITIONS[(S.ESTOPPED, "reset")] == S.IDLE
    assert (S.ESTOPPED, "finished") not in TRANSITIONS  # a run ending after an e-stop changes nothing
    assert TRANSITIONS[(S.RUNNING, "suspended")] == S.SUSPENDED
    assert TRANSITIONS[(S.SUSPENDED, "running")] == S.RUNNING


def test_telemetry_currents_and_states_arrive_with_sequence_numbers(daemon, rig_client):
    with rig_client.telemetry() as feed:
        # readiness of the subscription: the state heartbeat arrives within its period
        first = feed.receive(timeout_s=3)
        assert isinstance(first, StateMsg)
        load_and_execute(rig_client, samples=500)
        topics, states = {}, []
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            msg = feed.receive(timeout_s=0.5)
            if msg is None:
                continue
            topics[msg.topic] = topics.get(msg.topic, 0) + (
                len(msg.samples) if msg.topic == "actuators" else 1)
            if msg.topic == "state":
                states.append(msg.state.value)
            # state goes out at once, the last cycles with the next batch (20 ms later)
            if states and states[-1] == "idle" and "running" in states \
                    and topics.get("actuators", 0) >= 499:
                break
        assert "running" in states and states[-1] == "idle"
        # the stand-in streams 499 cycles (samples 1..499); currents carry every one of them
        assert topics.get("actuators", 0) == 499
        assert topics.get("field", 0) > 10
        assert feed.lost.get("state", 0) == 0 and feed.lost.get("actuators", 0) == 0


def test_a_retried_request_is_answered_once(daemon):
    payload = json.dumps({"id": "retry-abcdef-1", "cmd": "load",
                          "args": {"plan": {"samples": 100}}}).encode()
    first = raw_req(daemon.endpoints.command, payload)
    again = raw_req(daemon.endpoints.command, payload)
    assert first == again
    execute = json.dumps({"id": "retry-abcdef-2", "cmd": "execute",
                          "args": {"plan_id": first["result"]["plan_id"]}}).encode()
    one = raw_req(daemon.endpoints.command, execute)
    two = raw_req(daemon.endpoints.command, execute)  # the same request again: not a second run
    assert one["ok"] and two == one
    assert len([r for r in daemon.factory_runs if r.record is not None]) <= 1


def test_a_suspended_run_is_a_state_and_comes_back_to_running(daemon, rig_client):
    with rig_client.telemetry(["state"]) as feed:
        assert feed.receive(timeout_s=3) is not None
        load_and_execute(rig_client, samples=600, suspended=[100, 300])
        states = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and states[-1:] != ["idle"]:
            msg = feed.receive(timeout_s=0.5)
            if msg is not None and (not states or states[-1] != msg.state.value):
                states.append(msg.state.value)
    assert states[-4:] == ["running", "suspended", "running", "idle"]


ACTIVE_STATES = ("running", "paused", "suspended")
WALK_COMMANDS = {  # a command with valid arguments (execute: the plan loaded for the walk)
    "ping": {}, "status": {}, "runs": {}, "run": {"run": "no-such-run"},
    "load": {"plan": {"samples": 100}}, "execute": {"plan_id": None},
    "pause": {}, "pause now": {"immediate": True}, "resume": {}, "abort": {}, "estop": {},
    "reset": {}, "hold": {"target": {"field_mT": [1.0, 0.0, 0.0]}},
    "set_field": {"field_mT": [1.0, 0.0, 0.0]},
}


def expected_cell(state: str, command: str) -> tuple[str, str]:
    """What the daemon answers (ok or the refusal's code) and the state it settles in, per
    docs/daemon-protocol.md, written out here rather than read from the daemon's table."""
    if command in ("ping", "status", "runs", "load"):
        return "ok", state
    if command == "run":
        return "unknown_run", state
    if command == "estop":
        return "ok", "estopped"
    if command in ("execute", "hold", "set_field"):
        return ("ok", "running") if state == "idle" else ("wrong_state", state)
    if command in ("pause", "pause now"):
        if state == "running":
            return "ok", "paused"
        return ("ok", state) if state in ("paused", "suspended") else ("wrong_state", state)
    if command == "resume":
        return ("ok", "running") if state == "paused" else ("wrong_state", state)
    if command == "abort":
        return ("ok", "idle") if state in ACTIVE_STATES else ("wrong_state", state)
    if command == "reset":
        return ("ok", "idle") if state in ("idle", "faulted", "estopped") else ("wrong_state", state)
    raise AssertionError(command)


def enter(rig, state: str) -> None:
    """Bring the daemon from idle into `state` the way a run gets there."""
    long = 10 ** 7
    if state == "running":
        load_and_execute(rig, samples=long)
    elif state == "paused":
        load_and_execute(rig, samples=long)
        rig.wait_state("running", timeout_s=5)
        rig.pause()
    elif state == "suspended":
        load_and_execute(rig, samples=long, suspended=[50, 2 * long])  # tracking never returns
    elif state == "faulted":
        load_and_execute(rig, samples=long, fault_at=50)
    elif state == "estopped":
        rig.estop()
    rig.wait_state(state, timeout_s=5)
    if state == "faulted":
        wait_no_run(rig)


def wait_no_run(rig) -> None:
    deadline = time.monotonic() + 5
    while rig.status()["run"] is not None:
        assert time.monotonic() < deadline, "the run did not end"
        time.sleep(0.01)


def leave(rig) -> None:
    """The operator's way out of any state, back to idle with nothing running."""
    state = rig.status()["state"]
    if state in ACTIVE_STATES:
        rig.abort()
        rig.wait_state("idle", "faulted", "estopped", timeout_s=5)
    wait_no_run(rig)
    if rig.status()["state"] != "idle":
        rig.reset()
    assert rig.status()["state"] == "idle" and rig.status()["run"] is None


def test_every_command_in_every_state_is_answered_as_documented_and_every_state_has_a_way_out(
        daemon, rig_client):
    walk_plan = rig_client.load({"samples": 100})
    seen = {}
    for state in ("idle", *ACTIVE_STATES, "faulted", "estopped"):
        for command, args in WALK_COMMANDS.items():
            enter(rig_client, state)
            args = {**args, "plan_id": walk_plan} if command == "execute" else args
            cmd = "pause" if command == "pause now" else command
            try:
                rig_client.request(cmd, **args)
                code = "ok"
            except CommandRefused as refused:
                code = refused.code
            want_code, want_state = expected_cell(state, command)
            settled = rig_client.wait_state(want_state, timeout_s=5)["state"] \
                if code == want_code else rig_client.status()["state"]
            seen[(state, command)] = (code, settled)
            assert (code, settled) == (want_code, want_state), (state, command)
            leave(rig_client)
    assert len(seen) == 6 * len(WALK_COMMANDS)
