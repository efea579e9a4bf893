"""A plan executed on the six emulated supplies over TCP, with the bench in a thread of this process:
the safety paths (limit refusal before anything opens, a supply's link pulled mid-run)."""

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.config import FieldSettings
from rigctl.core.errors import DeviceError, LimitError
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.plans.schema import load_plan
from rigctl.rigs.six_coil.global_moves import execute_plan, prepare

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
QUICK = EXAMPLES / "fig4-quick.json"
LONG = EXAMPLES / "fig4-two-magnets.json"


@pytest.fixture
def bench():
    with SixCoilBench() as b:
        yield b


def test_a_plan_needing_25_A_is_refused_before_anything_is_energised(bench):
    plan = load_plan(QUICK)
    # With the default coils one amp in each coil of a pair makes b = 0.1534 mT at the centre
    # (mu0 N a^2 / (2 (a^2 + d^2)^1.5), N = 400, a = 0.2 m, d = 0.35 m), so 2 b * 25 A = 7.67 mT
    # needs 25 A per coil: above the 20 A limit.
    b_per_amp = 4e-7 * np.pi * 400 * 0.2**2 / (2 * (0.2**2 + 0.35**2) ** 1.5)
    b0 = 2 * b_per_amp * 25.0 * 1e3
    rig = bench.rig.model_copy(update={"field": FieldSettings(b0_mT=b0)})
    with pytest.raises(LimitError) as refused:
        prepare(plan, rig)
    message = str(refused.value)
    assert "move" in message and "coil" in message and "20" in message
    assert "25.0 A" in message or "25 A" in message
    for supply in bench.supplies:
        assert supply.model.current_A == 0.0 and not supply.model.output_on


def test_pulling_one_supply_link_mid_run_stops_safely_and_names_it(bench, tmp_path):
    plan = load_plan(LONG)
    result = {}
    runner = threading.Thread(
        target=lambda: result.setdefault("summary", execute_plan(
            plan, bench.rig, runs_dir=tmp_path, progress_out=None)))
    runner.start()

    def streamed_rows() -> int:
        files = list(tmp_path.glob("*/stream.csv"))
        return len(files[0].read_text().splitlines()) if files else 0

    wait_for(lambda: streamed_rows() > 150, what="the run to stream 150 cycles")
    with BackdoorClient(bench.rig.emulation.backdoor) as backdoor:
        backdoor.request("fault", device="y+", kind="drop_link")
    runner.join(timeout=30)
    assert not runner.is_alive()
    summary = result["summary"]
    assert not summary.reached
    assert len(summary.faults) == 1
    fault = summary.faults[0]
    assert fault["device"] == "y+"
    assert "y+" in fault["reason"]
    # every other supply was ramped down and switched off
    for supply in bench.supplies:
        if supply.name != "y+":
            assert not supply.model.output_on, supply.name
    wait_for(lambda: all(abs(s.model.current_A) < 0.05 for s in bench.supplies if s.name != "y+"),
             timeout_s=5, what="currents to decay")
    # the run record kept the stream up to the fault and the fault itself
    run = Path(summary.run)
    events = [json.loads(line) for line in (run / "events.jsonl").read_text().splitlines()]
    assert any(e["event"] == "fault" and e["device"] == "y+" for e in events)
    # the ramp began after the fault was recorded, and its delay is counted from before that
    fault_t = next(e["t"] for e in events if e["event"] == "fault")
    stopping = next(e for e in events if e["event"] == "stopping")
    assert stopping["t"] >= fault_t and stopping["ramp_s"] == bench.rig.stream.ramp_down_s
    assert stopping["after_decision_s"] >= stopping["t"] - fault_t - 1e-6
    assert json.loads((run / "summary.json").read_text())["faults"][0]["device"] == "y+"


def test_a_supply_that_stops_answering_is_a_timeout_fault(bench, tmp_path):
    plan = load_plan(QUICK)
    with BackdoorClient(bench.rig.emulation.backdoor) as backdoor:
        backdoor.request("fault", device="z-", kind="stall")
    summary = execute_plan(plan, bench.rig, runs_dir=tmp_path, progress_out=None)
    assert summary.faults and summary.faults[0]["device"] == "z-"
    assert summary.faults[0]["kind"] == "DeviceTimeout"


def test_an_estop_from_another_thread_latches_every_supply_at_zero_mid_stream(bench):
    """E-stop does not wait for the stream thread: written from another thread while the stream
    thread keeps cycling nonzero setpoints, every supply ends at 0 A with its output off, and
    stays there, because the drivers send nothing but 0 A once the e-stop is written."""
    from rigctl.rigs.six_coil.supplies import CoilSupplies

    supplies = CoilSupplies.connect(bench.rig)
    try:
        supplies.energise()
        setpoints = np.full(len(supplies.names), 2.0)
        for _ in range(20):
            supplies.cycle(setpoints)
        assert all(s.model.current_setpoint_A == 2.0 and s.model.output_on
                   for s in bench.supplies)
        stop = threading.Event()

        def stream():  # the stream thread, still asking for 2 A after the e-stop
            while not stop.is_set():
                supplies.cycle(setpoints)

        streamer = threading.Thread(target=stream)
        streamer.start()
        try:
            supplies.emergency_zero()
            wait_for(lambda: all(not s.model.output_on and s.model.current_setpoint_A == 0.0
                                 for s in bench.supplies), what="every supply zeroed and off")
        finally:
            stop.set()
            streamer.join()
        for _ in range(20):  # the stream thread's later setpoints leave as 0 A
            supplies.cycle(setpoints)
        assert all(s.model.current_setpoint_A == 0.0 and not s.model.output_on
                   for s in bench.supplies)
        with pytest.raises(DeviceError, match="e-stop latched"):
            supplies.energise()
    finally:
        supplies.stop(ramp_s=0.0)
