"""A local run (the one engine, no daemon) on the emulated six-coil bench whose supply's link
drops mid-run: the run faults and ramps the other supplies down, and the one it could not reach,
a Kepco BOP holding its last setpoint (it has no link watchdog), is reached again once its link is
back, before the run ends. The record says safe only once that supply confirmed its zero; with
the retry off it says, as before, that the supply is not confirmed safe."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.config import StreamSettings
from rigctl.core.record import read_events
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.plans.schema import load_plan
from rigctl.rigs.six_coil.global_moves import Run

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "fig4-two-magnets.json"


@pytest.mark.parametrize("retry_s", [10.0, 0.0], ids=["reached-again", "no-retry"])
def test_a_supply_whose_link_returns_is_made_safe_before_the_run_ends(tmp_path, retry_s):
    with SixCoilBench() as bench:
        rig = bench.rig.model_copy(update={"stream": StreamSettings(
            rate_hz=200.0, unsafe_retry_s=retry_s)})
        run = Run(load_plan(PLAN), rig, runs_dir=tmp_path / "runs", progress_out=None)
        result: dict = {}
        thread = threading.Thread(target=lambda: result.update(summary=run.execute()))
        thread.start()
        y_plus = next(s for s in bench.supplies if s.name == "y+")
        try:
            wait_for(lambda: abs(y_plus.model.current_A) > 0.5, 60.0, "y+ driving current")
            with BackdoorClient(rig.emulation.backdoor) as backdoor:
                backdoor.request("fault", device="y+", kind="drop_link")
                # the run faults and stops; y+, unreachable, holds its current
                wait_for(lambda: all(not s.model.output_on for s in bench.supplies
                                     if s.name != "y+"), 20.0, "the other supplies off")
                held_A = abs(y_plus.model.current_A)
                time.sleep(1.0)
                assert y_plus.model.output_on and abs(y_plus.model.current_A) > 0.3 * held_A
                backdoor.request("fault", device="y+", kind="restore")
        finally:
            thread.join(30.0)
        summary = result["summary"]
        events = read_events(Path(summary.run))
        assert summary.state == "faulted" and summary.faults[0]["device"] == "y+"
        if retry_s:
            # reached again once its link answered: zero, off, and confirmed in the record
            assert not y_plus.model.output_on  # told before the run ended; then its L/R decay
            wait_for(lambda: abs(y_plus.model.current_A) < 0.05, 5.0, "y+ at zero")
            assert summary.safe and summary.unsafe_devices == []
            again = [e for e in events if e["event"] == "safe" and e.get("devices") == ["y+"]]
            assert again and 1.0 <= again[0]["after_s"] < retry_s
            assert not any(e["event"] == "unsafe" for e in events)
        else:
            assert y_plus.model.output_on  # nothing told it: it still drives
            assert not summary.safe and summary.unsafe_devices == ["y+"]
            assert any(e["event"] == "unsafe" and e["devices"] == ["y+"] for e in events)


def test_a_supply_lost_while_an_abort_ramps_down_makes_the_run_faulted(tmp_path):
    with SixCoilBench() as bench:
        rig = bench.rig.model_copy(update={"stream": StreamSettings(
            rate_hz=200.0, ramp_down_s=3.0, unsafe_retry_s=0.0)})
        run = Run(load_plan(PLAN), rig, runs_dir=tmp_path / "runs", progress_out=None)
        result: dict = {}
        thread = threading.Thread(target=lambda: result.update(summary=run.execute()))
        thread.start()
        y_plus = next(s for s in bench.supplies if s.name == "y+")
        try:
            wait_for(lambda: abs(y_plus.model.current_A) > 0.5, 60.0, "y+ driving current")
            run.abort()
            time.sleep(0.5)  # well inside the 3 s ramp
            with BackdoorClient(rig.emulation.backdoor) as backdoor:
                backdoor.request("fault", device="y+", kind="drop_link")
                thread.join(30.0)
                backdoor.request("fault", device="y+", kind="restore")
        finally:
            thread.join(30.0)
        summary = result["summary"]
        assert summary.state == "faulted" and not summary.safe and summary.unsafe_devices == ["y+"]
        # the abort and y+'s fault, the state the fault's, as the daemon reports it
        assert "Abort" in {f["kind"] for f in summary.faults}
        assert any(f["device"] == "y+" and f["kind"] != "Abort" for f in summary.faults)
