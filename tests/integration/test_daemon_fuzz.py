"""Nothing a client sends stops the daemon: the issue's five causes of a daemon exit as regression
tests, every exception in handling a request answered as `internal` (and logged), a `load` that
takes too long answered `deadline` without blocking other commands or shutdown, and generated
requests, raw frames and plans (hypothesis, the strategies of bench/fuzz_daemon.py, which runs the
big numbers) thrown at a daemon on the emulated six-coil bench."""

from __future__ import annotations

import importlib.util
import json
import logging
import threading
from pathlib import Path

import pytest
import zmq
from hypothesis import HealthCheck, given, settings

from rigctl.apps.daemon.messages import HARD_MAX_MESSAGE_BYTES, Command
from rigctl.apps.daemon.server import Daemon
from rigctl.core.config import RigInfo, default_six_coil_coils
from rigctl.core.errors import PlanError
from rigctl.plans.schema import MAX_IMAGE_PIXELS
from rigctl.rigs.six_coil.settings import SixCoilRig

_spec = importlib.util.spec_from_file_location(
    "fuzz_daemon", Path(__file__).resolve().parents[2] / "bench" / "fuzz_daemon.py")
fuzz = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fuzz)

REPLY_S = 1.0  # every request is answered within this (the goal)
LOAD_REPLY_S = 10.0  # a plan is realized and allocated to be checked: the load deadline's order
CI = settings(deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    with fuzz.daemon_on_bench(tmp_path_factory.mktemp("runs")) as d:
        yield d


@pytest.fixture(scope="module")
def huge_image(tmp_path_factory):
    return fuzz.huge_png(tmp_path_factory.mktemp("image") / "huge.png")


@pytest.fixture
def probe(daemon):
    p = fuzz.Probe(daemon.endpoints.command)
    yield p
    p.close()


def answered(probe, frames, wait_s=REPLY_S) -> str:
    reply, _ = probe.send(frames, wait_s)
    code = fuzz.reply_code(reply)
    assert code is not None, f"no reply with a code within {wait_s} s: {reply}"
    return code


def still_serving(probe, daemon) -> None:
    assert answered(probe, [b'{"cmd": "ping"}']) == "ok"
    assert daemon._thread.is_alive()


@pytest.mark.parametrize("payload, code", [
    (b'{"cmd":[]}', "bad_request"),  # the 11-byte request: unhashable in the quick path
    (b'{"cmd":{}}', "bad_request"),
    (b'{"id":"\\ud800","cmd":"ping"}', "bad_json"),  # no reply could carry the id
    (b'{"id":"\\ud800","cmd":"status"}', "bad_json"),  # ... nor the quick path's
    (b'{"id":' + b"9" * 5000 + b',"cmd":"ping"}', "bad_json"),  # past the int-str limit
    (b'{"cmd":"runs","args":{"limit":' + b"9" * 4000 + b"}}", "bad_json"),  # under it
    (b"[" * 100_000 + b"]" * 100_000, "bad_json"),  # RecursionError in json
    (b'{"cmd":"load","args":{"plan":' + b'{"a":' * 900 + b"1" + b"}" * 901 + b"}", "bad_json"),
    (b'{"id":NaN,"cmd":"ping"}', "bad_request"),
    (b'{"id":1,"cmd":"set_field","args":{"field_mT":[Infinity,0,0]}}', "bad_args"),
    (b'{"id":1,"cmd":"hold","args":{"target":{"field_mT":[NaN,0,0]}}}', "bad_args"),
    (b'{"id":1,"cmd":"pause","args":{"immediate":1e400}}', "bad_args"),
])
def test_each_request_that_stopped_the_daemon_is_answered_and_it_serves_on(daemon, probe,
                                                                          payload, code):
    assert answered(probe, [payload]) == code
    still_serving(probe, daemon)


def test_multipart_empty_and_oversize_frames_are_answered_or_dropped_and_it_serves_on(daemon, probe):
    assert answered(probe, []) == "bad_request"  # the delimiter and nothing
    assert answered(probe, [b"", b""]) == "bad_request"
    assert answered(probe, [b""]) == "bad_json"
    # over ZMQ_MAXMSGSIZE: ZeroMQ drops the peer without a reply; nobody else notices
    reply, _ = probe.send([b"x" * (HARD_MAX_MESSAGE_BYTES + 1)], wait_s=2.0)
    assert reply is None
    still_serving(probe, daemon)


def test_an_exception_in_handling_a_request_is_an_internal_reply_logged_with_its_traceback(
        daemon, probe, monkeypatch, caplog):
    def broken(*_):
        raise RuntimeError("a bug")

    monkeypatch.setattr(daemon, "_replay_key", broken)  # on the command thread, outside handlers
    with caplog.at_level(logging.ERROR, logger="rigctl.apps.daemon.requests"):
        assert answered(probe, [b'{"id":"abcdefgh","cmd":"abort"}']) == "internal"
    assert any(r.exc_info and "a bug" in str(r.exc_info[1]) for r in caplog.records)
    monkeypatch.undo()
    still_serving(probe, daemon)


def test_a_reply_that_cannot_be_encoded_is_replaced_by_an_error_reply(daemon, probe, monkeypatch):
    monkeypatch.setitem(daemon._handlers, Command.PING, lambda _: {"text": "\udc80"})
    reply, _ = probe.send([b'{"cmd":"ping"}'], REPLY_S)
    assert reply["error"]["code"] == "internal" and "could not be encoded" in reply["error"]["message"]
    monkeypatch.setattr(daemon, "_cmd_status", lambda _: {"text": "\udc80"})  # the quick path's
    assert answered(probe, [b'{"id":"q","cmd":"status"}']) == "internal"
    monkeypatch.undo()
    still_serving(probe, daemon)


class SlowPlans:
    """Plans whose check takes `sleep_s` (until `release` is set): a `load` that overruns."""

    def __init__(self):
        self.release = threading.Event()

    def start(self):
        pass

    def close(self):
        pass

    def parse_plan(self, data):
        if self.release.wait(data["sleep_s"]):
            raise PlanError("plan: released")
        return data

    def prepare(self, plan, rig, **_):
        raise PlanError("plan: never prepared here")


def test_a_load_past_its_deadline_answers_deadline_and_blocks_neither_commands_nor_shutdown(tmp_path):
    plans = SlowPlans()
    rig = SixCoilRig(rig=RigInfo(kind="six-coil", name="slow"), coils=default_six_coil_coils())
    d = Daemon(rig, command="tcp://127.0.0.1:0", telemetry="tcp://127.0.0.1:0",
               events="tcp://127.0.0.1:0", runs_dir=tmp_path, run_factory=plans)
    d.load_deadline_s = 0.5
    d.start_thread()
    slow = b'{"id":"load-1","cmd":"load","args":{"plan":{"sleep_s":600}}}'
    second = fuzz.Probe(d.endpoints.command)
    sock = zmq.Context.instance().socket(zmq.DEALER)
    try:
        sock.setsockopt(zmq.LINGER, 0)
        sock.connect(d.endpoints.command)
        sock.send_multipart([b"", slow])
        # while it is being checked: other commands are answered, a second load is `busy`
        assert answered(second, [b'{"cmd":"runs"}']) == "ok"
        assert answered(second, [b'{"cmd":"status"}']) == "ok"
        assert answered(second, [slow]) == "busy"
        assert sock.poll(10_000), "no reply to the slow load"
        assert fuzz.reply_code(json.loads(sock.recv_multipart()[-1])) == "deadline"
        # its thread still runs (Python cannot stop it); the next load is taken and times out too
        assert answered(second, [slow], wait_s=10.0) == "deadline"
    finally:
        sock.close(), second.close()
        d.stop()  # SIGTERM's path: it does not wait for the two loads still sleeping
        assert not d._thread.is_alive()
        plans.release.set()


def load(probe, plan: dict) -> dict:
    payload = json.dumps({"id": "plan-load", "cmd": "load", "args": {"plan": plan}}).encode()
    reply, _ = probe.send([payload], LOAD_REPLY_S)
    assert reply is not None, "no reply to load"
    return reply


@pytest.mark.parametrize("change, field", [
    ({"moves": [[1e300, 0.0]]}, "moves.0.0"),  # no reply, and the worker blocked for good
    ({"moves": []}, "moves: empty"),  # passed validate; execute printed a traceback
    ({"moves": [[31.4159, 0.0]] * 6000}, "moves: List should have at most"),
    ({"agents": [{"start": [100, 100], "goal": [100, 100], "radius": 1e300}]}, "agents.0.radius"),
    # a subnormal radius was answered `internal` (an OverflowError in the model's wall step)
    ({"agents": [{"start": [100, 100], "goal": [100, 100], "radius": 1e-320}]},
     "plan: agents.0.radius: Input should be greater than or equal to 0.001"),
    ({"moves": [[1e-320, 0.0]]}, "plan: moves.0.0: 1e-320 is subnormal"),
    ({"tolerance_mm": float("nan")}, "plan: tolerance_mm: Input should be a finite number"),
])
def test_the_plans_that_hurt_the_daemon_are_refused_naming_the_field(daemon, probe, change, field):
    plan = {**json.loads((fuzz.EXAMPLES / "fig4-quick.json").read_text()), **change}
    plan.pop("expected")
    reply = load(probe, plan)
    assert reply["error"]["code"] == "plan_invalid" and field in reply["error"]["message"], reply
    still_serving(probe, daemon)


def test_a_move_that_is_not_whole_turns_is_refused_by_load_and_by_validate_alike(daemon, probe,
                                                                                 tmp_path):
    # validate passed it (it checked the plan alone); load refused it for the rig
    plan = {**json.loads((fuzz.EXAMPLES / "fig4-quick.json").read_text()),
            "moves": [[0.0, -80.0], [31.0, 0.0]]}
    plan.pop("expected")
    reply = load(probe, plan)
    assert reply["error"]["code"] == "plan_invalid", reply
    message = reply["error"]["message"]
    assert "move 1: 31.00 mm is 3.10 turns" in message
    status, err = fuzz.validate_in_process(json.dumps(plan).encode(), tmp_path)
    assert status == 2 and err == f"error: {message}\n"
    still_serving(probe, daemon)


def test_a_huge_workspace_image_is_refused_and_an_ordinary_plan_still_loads(daemon, probe, huge_image):
    plan = json.loads((fuzz.EXAMPLES / "fig4-quick.json").read_text())
    reply = load(probe, {**plan, "workspace": {"image": str(huge_image), "mm_per_px": 0.1}})
    assert reply["error"]["code"] == "plan_invalid" and "4100 x 4100 pixels" in reply["error"]["message"]
    assert load(probe, plan)["ok"] is True


def test_validate_refuses_a_huge_workspace_image_before_decoding_it(huge_image, tmp_path):
    plan = json.loads((fuzz.EXAMPLES / "fig4-quick.json").read_text())
    plan["workspace"] = {"image": str(huge_image), "mm_per_px": 0.1}
    status, err = fuzz.validate_in_process(json.dumps(plan).encode(), tmp_path)
    assert status == 2 and f"is 4100 x 4100 pixels; at most {MAX_IMAGE_PIXELS} pixels" in err


@settings(CI, max_examples=300)
@given(payload=fuzz.requests())
def test_every_generated_request_gets_a_reply_with_a_code(daemon, probe, payload):
    assert answered(probe, [payload]) != "internal"
    assert daemon._thread.is_alive()


@settings(CI, max_examples=100)
@given(frames=fuzz.raw_frames)
def test_every_generated_set_of_frames_gets_a_reply_with_a_code(daemon, probe, frames):
    assert answered(probe, frames) not in ("internal", "ok")


@settings(CI, max_examples=120)
@given(data=fuzz.st.data())
def test_generated_plans_are_loaded_or_refused_naming_the_field_and_validate_agrees(
        daemon, probe, huge_image, tmp_path, data):
    text = data.draw(fuzz.plans(huge_image))
    reply, _ = probe.send([b'{"id":"plan-fuzz","cmd":"load","args":{"plan":' + text + b"}}"],
                          LOAD_REPLY_S)
    code = fuzz.reply_code(reply)
    assert code in fuzz.PLAN_CODES | {"ok"}, reply
    if code != "ok":
        assert reply["error"]["message"]
    status, err = fuzz.validate_in_process(text, tmp_path)  # exceptions would fail the test
    assert status in (0, 2), err
    if status == 2:
        assert err.startswith("error: ") and "Traceback" not in err
    # validate runs what load runs: on a six-coil plan, on the rig of the daemon's bench
    try:
        six_coil = json.loads(text).get("rig") == "six-coil"
    except (ValueError, AttributeError):
        six_coil = False
    if six_coil and code in ("plan_invalid", "limit"):
        assert status == 2, (reply, err)
    if code == "ok":
        assert status == 0, (reply, err)
    still_serving(probe, daemon)

