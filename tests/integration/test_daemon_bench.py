"""The daemon driving the emulated six-coil bench (in this process, supplies on real TCP sockets)
through the Python client: a plan to its goal with telemetry, pause/resume, abort, e-stop with the
supplies' currents measured at zero, a supply fault leaving the daemon serving in `faulted`, and a
manual field (the six-coil hold) checked against the closed-form field of a loop on its axis.
The other rigs' holds: test_daemon_hold.py."""

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.client import CommandRefused, Rig
from rigctl.apps.daemon.server import Daemon
from rigctl.apps.testing import plan_pair, wait_for
from rigctl.core.config import StreamSettings
from rigctl.core.record import read_events, read_stream
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"


@pytest.fixture
def bench():
    with SixCoilBench() as b:
        yield b


@pytest.fixture
def daemon(bench, tmp_path):
    rig = bench.rig.model_copy(update={"stream": StreamSettings(rate_hz=200.0)})
    d = Daemon(rig, command="tcp://127.0.0.1:0", telemetry="tcp://127.0.0.1:0",
               events="tcp://127.0.0.1:0", runs_dir=tmp_path / "runs")
    d.start_thread()
    yield d
    d.stop()


@pytest.fixture
def rig(daemon):
    with Rig(daemon.endpoints.command, timeout_s=5.0) as client:
        yield client


def plan(name):
    return json.loads((EXAMPLES / name).read_text())


def wait_streaming(rig, timeout_s=10):
    """Until the run's stream has started (the supplies are connected and energised)."""
    deadline = time.monotonic() + timeout_s
    while True:
        run = rig.status()["run"]
        if run is not None and run["sample"] > 0:
            return
        assert time.monotonic() < deadline, "the run did not start streaming"
        time.sleep(0.01)


def wait_run_over(rig, timeout_s=60):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = rig.status()
        if status["run"] is None:
            return status
        time.sleep(0.02)
    raise AssertionError("the run did not end")


def test_a_plan_through_the_client_reaches_its_goal_with_telemetry(rig, daemon):
    source = plan("fig4-quick.json")
    with rig.telemetry() as feed:
        assert feed.receive(timeout_s=3) is not None  # subscribed: the state heartbeat arrives
        plan_id = rig.load(source)
        rig.execute(plan_id)
        seen, states = {}, []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            msg = feed.receive(timeout_s=0.5)
            if msg is None:
                continue
            seen.setdefault(msg.topic, msg)
            if msg.topic == "state":
                states.append(msg.state.value)
                if msg.state.value == "idle" and "running" in states:
                    break
    assert {"state", "actuators", "field", "stream", "agents"} <= set(seen)
    assert seen["actuators"].channels == ["x+", "x-", "y+", "y-", "z+", "z-"]
    assert seen["actuators"].units == ["A"] * 6
    assert seen["agents"].source == "emulator ground truth"
    status = wait_run_over(rig)
    assert status["state"] == "idle"
    summary = rig.run(Path(status["last_run"]["run"]).name)["summary"]
    assert summary["reached"] is True
    # the emulated world ends where the plan expects, within its tolerance
    finals = np.array([a["final"] for a in summary["agents"]])
    np.testing.assert_allclose(finals, np.array(source["expected"][-1]) if source.get("expected")
                               else np.array([a["goal"] for a in source["agents"]]), atol=1.0)
    runs = rig.runs()
    assert runs[0]["finished"] and runs[0]["reached"]
    run_dir = Path(status["last_run"]["run"])
    data = read_stream(run_dir)
    assert data["source"] == "parquet"
    assert len(data["t_s"]) == sum(1 for _ in open(run_dir / "stream.csv")) - 1
    assert any(e["event"] == "agents" for e in read_events(run_dir))


def test_pause_resume_and_abort_on_the_bench(rig, bench):
    plan_id = rig.load(plan("fig4-two-magnets.json"))
    rig.execute(plan_id)
    rig.wait_state("running")
    rig.pause(immediate=True)
    rig.wait_state("paused", timeout_s=5)
    deadline = time.monotonic() + 3  # an immediate pause ramps the field to zero
    while any(abs(s.model.current_A) > 0.05 for s in bench.supplies):
        assert time.monotonic() < deadline, "the field did not ramp down on an immediate pause"
        time.sleep(0.01)
    assert all(s.model.output_on for s in bench.supplies)  # paused, not stopped
    rig.resume()
    rig.wait_state("running", timeout_s=5)
    rig.abort()
    status = wait_run_over(rig)
    assert status["state"] == "idle"
    assert all(not s.model.output_on for s in bench.supplies)
    assert status["last_run"]["faults"][0]["kind"] == "Abort"


def test_estop_zeroes_the_supplies_within_a_bound(rig, bench):
    plan_id = rig.load(plan("fig4-two-magnets.json"))
    rig.execute(plan_id)
    rig.wait_state("running")
    deadline = time.monotonic() + 10
    while max(abs(s.model.current_A) for s in bench.supplies) < 1.0:  # wait for real current
        assert time.monotonic() < deadline
        time.sleep(0.01)
    peak = max(abs(s.model.current_A) for s in bench.supplies)
    sent = time.monotonic()
    assert rig.estop()["state"] == "estopped"
    while any(s.model.output_on or s.model.current_setpoint_A for s in bench.supplies):
        time.sleep(0.0005)
    switched_off = time.monotonic() - sent
    while any(abs(s.model.current_A) > 0.05 for s in bench.supplies):
        time.sleep(0.001)
    below = time.monotonic() - sent
    # every supply told zero and switched off within a 5 ms stream period (plus slack for a
    # loaded machine); then the coil current decays through R alone: tau = L/R = 0.03 / 1.5 s,
    # so from the peak to 0.05 A takes tau ln(peak / 0.05)
    assert switched_off < 0.005 + 0.05, f"supplies switched off after {switched_off * 1e3:.1f} ms"
    decay = 0.03 / 1.5 * np.log(peak / 0.05)
    assert below < switched_off + decay + 0.05, f"{below * 1e3:.0f} ms, expected {decay * 1e3:.0f}"
    status = wait_run_over(rig)
    assert status["state"] == "estopped"
    assert all(not s.model.output_on for s in bench.supplies)
    with pytest.raises(CommandRefused) as refused:
        rig.execute(plan_id)
    assert refused.value.code == "wrong_state"
    assert rig.reset()["state"] == "idle"


def test_a_supply_fault_during_a_run_leaves_the_daemon_serving_in_faulted(rig, bench):
    plan_id = rig.load(plan("fig4-two-magnets.json"))
    with rig.telemetry(["fault", "state"]) as feed:
        rig.execute(plan_id)
        wait_streaming(rig)
        with BackdoorClient(bench.rig.emulation.backdoor) as backdoor:
            backdoor.request("fault", device="y+", kind="drop_link")
        status = rig.wait_state("faulted", timeout_s=10)
        fault = None
        deadline = time.monotonic() + 5
        while fault is None and time.monotonic() < deadline:
            msg = feed.receive(timeout_s=0.5)
            if msg is not None and msg.topic == "fault":
                fault = msg
    assert status["device"] == "y+" and "y+" in status["reason"]
    assert fault is not None and fault.device == "y+"
    status = wait_run_over(rig)
    assert status["state"] == "faulted"
    health = {d["name"]: d["health"] for d in status["devices"]}
    assert all(not s.model.output_on for s in bench.supplies if s.name != "y+")
    run_dir = Path(status["last_run"]["run"])
    assert any(e["event"] == "fault" and e["device"] == "y+" for e in read_events(run_dir))
    assert rig.reset()["state"] == "idle"
    # y+ could not be told to stop: a BOP holds its last setpoint, and status says it may
    y_plus = next(s for s in bench.supplies if s.name == "y+")
    assert health["y+"] == "unsafe" and y_plus.model.output_on
    with pytest.raises(CommandRefused) as refused:
        rig.execute(plan_id)  # no run while a supply may carry current
    assert refused.value.code == "wrong_state" and "y+" in refused.value.reason
    with BackdoorClient(bench.rig.emulation.backdoor) as backdoor:
        backdoor.request("fault", device="y+", kind="restore")
    # its link back, the daemon zeroes it at once (it tries every REZERO_S)
    wait_for(lambda: not y_plus.model.output_on and abs(y_plus.model.current_A) < 0.05, 5.0,
             "y+ made safe")
    wait_for(lambda: {d["name"]: d["health"] for d in rig.status()["devices"]}["y+"] == "off",
             5.0, "y+ reported safe")
    rig.execute(plan_id)  # and runs may start again
    rig.abort()


def wait_current(bench, amps=1.0, timeout_s=10):
    """Until some supply drives at least `amps` (the run is energised)."""
    deadline = time.monotonic() + timeout_s
    while max(abs(s.model.current_A) for s in bench.supplies) < amps:
        assert time.monotonic() < deadline, "the run never drove current"
        time.sleep(0.01)


def all_off(bench, within_s=0.5):
    """Whether every emulated supply is at 0 A with its output off within `within_s` (an e-stop
    message is written, not waited on: the emulator may still be reading it)."""
    deadline = time.monotonic() + within_s
    while any(s.model.output_on or s.model.current_setpoint_A for s in bench.supplies):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.001)
    return True


def test_the_stream_process_dying_mid_run_leaves_the_supplies_off_and_the_daemon_serving(
        rig, bench, daemon):
    plan_id = rig.load(plan("fig4-two-magnets.json"))
    rig.execute(plan_id)
    wait_current(bench)
    os.kill(daemon.factory.host.pid, signal.SIGKILL)
    status = rig.wait_state("faulted", timeout_s=10)
    assert "stream process died" in status["reason"]
    status = wait_run_over(rig)
    assert all_off(bench)  # zeroed by the daemon over new connections: nobody else was left
    newest = rig.runs()[0]
    assert not newest["finished"]  # cut off: no summary, everything up to the crash kept
    run_dir = daemon.runs_dir / newest["id"]
    assert status["last_fault"]["run"] == newest["id"]
    died = [e for e in read_events(run_dir) if e.get("kind") == "StreamProcessDied"]
    assert died and "every device was made safe over a new connection" in died[0]["reason"]
    # a new stream process runs the next plan
    assert rig.reset()["state"] == "idle"
    rig.execute(plan_id)
    wait_current(bench)
    rig.abort()
    assert wait_run_over(rig)["state"] == "idle"
    assert all_off(bench)


def test_a_stream_process_killed_while_idle_is_replaced_and_the_next_run_has_its_record(
        rig, bench, daemon):
    plan_id = rig.load(plan("fig4-two-magnets.json"))
    rig.execute(plan_id)  # a process that has run a plan, then sits idle
    wait_current(bench)
    rig.abort()
    assert wait_run_over(rig)["state"] == "idle"
    killed = daemon.factory.host.pid
    os.kill(killed, signal.SIGKILL)
    rig.execute(plan_id)  # at once: the daemon may not have seen the death yet
    wait_current(bench)
    assert daemon.factory.host.pid != killed
    rig.abort()
    status = wait_run_over(rig)
    assert status["state"] == "idle" and status["last_fault"] is None
    newest = rig.runs()[0]
    assert newest["finished"]  # the run's record, whole, with its outcome
    summary = json.loads((daemon.runs_dir / newest["id"] / "summary.json").read_text())
    assert summary["state"] == "aborted" and summary["safe"]
    assert all_off(bench)


def test_a_stream_process_that_hangs_mid_run_is_killed_and_the_supplies_zeroed(rig, bench, daemon):
    plan_id = rig.load(plan("fig4-two-magnets.json"))
    rig.execute(plan_id)
    wait_current(bench)
    host = daemon.factory.host.pid
    os.kill(host, signal.SIGSTOP)  # hung: holds its connections, streams nothing, answers nothing
    try:
        status = rig.wait_state("faulted", timeout_s=10)
    finally:
        try:
            os.kill(host, signal.SIGCONT)
        except ProcessLookupError:  # killed by the daemon's watchdog, as it should be
            pass
    assert "stopped answering" in status["reason"]
    assert all_off(bench)
    assert wait_run_over(rig)["state"] == "faulted"
    assert rig.reset()["state"] == "idle"


def test_an_estop_the_stream_process_cannot_answer_is_carried_out_by_the_daemon(
        rig, bench, daemon):
    plan_id = rig.load(plan("fig4-two-magnets.json"))
    rig.execute(plan_id)
    wait_current(bench)
    host = daemon.factory.host.pid
    os.kill(host, signal.SIGSTOP)  # hung: holds its connections, answers nothing
    try:
        reply = rig.estop()
    finally:
        try:
            os.kill(host, signal.SIGCONT)
        except ProcessLookupError:  # killed by the daemon, as it should be
            pass
    assert reply["state"] == "estopped" and reply["unreached"] == []
    assert all_off(bench)  # the daemon killed the hung process and zeroed them itself
    status = wait_run_over(rig)
    assert status["state"] == "estopped"
    assert rig.reset()["state"] == "idle"


def test_a_plan_for_another_rig_is_refused_at_load_naming_both_rigs(rig):
    for name, rig_kind in [("depm-plan.json", "depm"), ("coilboard-disk.json", "coil-board")]:
        with pytest.raises(CommandRefused) as refused:
            rig.load(plan(name))
        assert refused.value.code == "plan_invalid"
        assert f"the plan is for a {rig_kind} rig; " in str(refused.value)
        assert str(refused.value).endswith("is a six-coil rig")
    assert rig.status()["state"] == "idle"


def test_manual_field_matches_the_closed_form_and_limits_are_enforced(rig, bench):
    # on the axis of a loop: b = mu0 N I a^2 / (2 (a^2 + d^2)^1.5) per coil at the centre, with
    # N = 400, a = 0.2 m, d = 0.35 m; the two x coils share 1 mT equally (minimum norm, symmetry)
    b_per_amp = 4e-7 * np.pi * 400 * 0.2**2 / (2 * (0.2**2 + 0.35**2) ** 1.5)
    expected_A = 1e-3 / (2 * b_per_amp)
    reply = rig.set_field([1.0, 0.0, 0.0], ramp_s=0.05)
    np.testing.assert_allclose(reply["currents_A"][:2], [expected_A, expected_A], rtol=1e-3)
    np.testing.assert_allclose(reply["currents_A"][2:], 0.0, atol=1e-6)
    deadline = time.monotonic() + 3  # settle: L/R = 20 ms
    while abs(bench.supplies[0].model.current_A - expected_A) > 0.01 * expected_A:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert rig.status()["manual_field_mT"] == [1.0, 0.0, 0.0]
    with pytest.raises(CommandRefused) as refused:
        rig.set_field([0.0, 0.0, 10.0])  # 10 mT needs 32.6 A per z coil: over the 20 A limit
    assert refused.value.code == "limit" and "z" in refused.value.reason
    # the supplies' compliance holds for the ramp too: 5 mT in x is 16.3 A per x coil (under the
    # 20 A limit); from the 1 mT held, in one 5 ms sample at 200 Hz that is
    # L dI/dt + R I = 0.03 * 13.0 / 0.005 + 1.5 * 16.3 = 103 V, over the 100 V compliance
    current_5mT = 5 * expected_A
    volts = 0.03 * (current_5mT - expected_A) * 200 + 1.5 * current_5mT
    assert current_5mT < 20 and volts > 100
    with pytest.raises(CommandRefused) as refused:
        rig.set_field([5.0, 0.0, 0.0], ramp_s=0.0)
    assert refused.value.code == "limit" and " V " in refused.value.reason
    assert rig.status()["manual_field_mT"] == [1.0, 0.0, 0.0]  # still held
    rig.set_field([0.0, 0.0, 0.0], ramp_s=0.05)
    status = wait_run_over(rig)
    assert status["manual_field_mT"] is None
    assert all(not s.model.output_on for s in bench.supplies)


def test_a_manual_field_an_unreachable_supply_prevents_is_refused_and_e_stop_reaches_one(
        rig, bench):
    with BackdoorClient(bench.rig.emulation.backdoor) as backdoor:
        backdoor.request("fault", device="y-", kind="drop_link")  # refuses connections
        with pytest.raises(CommandRefused) as refused:
            rig.set_field([1.0, 0.0, 0.0], ramp_s=0.05)
        assert refused.value.code == "device" and "y-" in refused.value.reason
        status = rig.status()
        assert status["state"] == "idle" and status["run"] is None
        assert status["manual_field_mT"] is None
        assert all(not s.model.output_on for s in bench.supplies)
        backdoor.request("fault", device="y-", kind="restore")
    rig.set_field([0.0, 1.0, 0.0], ramp_s=0.05)  # the stream process holds it now
    wait_current(bench, amps=0.5)
    assert rig.estop()["state"] == "estopped"
    assert all_off(bench)
    status = wait_run_over(rig)
    assert status["manual_field_mT"] is None and status["hold"] is None
    events = [e["event"] for e in read_events(Path(status["last_run"]["run"]))]
    assert "safe" in events and "unsafe" not in events  # the hold's record, ended by the e-stop
    assert rig.reset()["state"] == "idle"


# -- a pair formation change through the daemon (seed 002): the bench in the pair world --------------

@pytest.fixture
def pair_daemon(tmp_path):
    with SixCoilBench(world="pair") as pair_bench:
        d = Daemon(pair_bench.rig, command="tcp://127.0.0.1:0", telemetry="tcp://127.0.0.1:0",
                   events="tcp://127.0.0.1:0", runs_dir=tmp_path / "runs")
        d.start_thread()
        try:
            yield d, pair_bench
        finally:
            d.stop()


def test_a_pair_formation_change_runs_through_the_daemon_with_a_pause(pair_daemon, tmp_path):
    daemon, pair_bench = pair_daemon
    plan_file = plan_pair(tmp_path, goal="8.8,7.3,2.3,40", hold_s=0.5)
    source = json.loads(plan_file.read_text())
    with Rig(daemon.endpoints.command, timeout_s=5.0) as rig, rig.telemetry(["agents"]) as feed:
        loaded = rig.request("load", plan=source)
        assert loaded["segments"] == len(source["segments"])
        rig.execute(loaded["plan_id"])
        wait_streaming(rig)
        rig.pause(immediate=True)
        assert rig.wait_state("paused", timeout_s=10)["run"]["segments"] == loaded["segments"]
        deadline, agents = time.monotonic() + 5, None
        while time.monotonic() < deadline and (agents is None or not agents.tracked_mm):
            agents = feed.receive(timeout_s=1)  # the first may predate the agents' placing
        assert agents is not None and len(agents.tracked_mm) == 2 and agents.expected_mm is None
        rig.resume()
        status = wait_run_over(rig, timeout_s=120)
        assert status["state"] == "idle", status
        summary = rig.run(Path(status["last_run"]["run"]).name)["summary"]
    assert summary["reached"] is True and summary["faults"] == []
    events = [e["event"] for e in read_events(Path(status["last_run"]["run"]))]
    assert "pause" in events and "pause_end" in events
    # where the emulated world had the agents when the program ended (the run reads ground truth
    # then, before the supplies stop: with no field the magnets attract each other)
    tolerance = summary["tolerance_bl"]
    truth_errors = [a["truth_error_bl"] for a in summary["agents"]]
    assert len(truth_errors) == 2 and all(e <= 2 * tolerance for e in truth_errors), truth_errors
    assert summary["metrics"]["truth_min_separation_bl"] >= source["r_min_bl"] - 0.15
    assert all(not s.model.output_on for s in pair_bench.supplies)
