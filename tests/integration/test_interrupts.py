"""Ctrl-C and SIGTERM to a run on the main thread, as `rigctl execute` runs it: a short
pair-formation run on the emulated six-coil bench, in this process, with the CLI's signal handlers
(`abort_on_sigterm`).

Two ways an interrupt used to go wrong, each reproduced here at a chosen instant:
- Python drops an exception a signal handler raises inside a weakref callback or a `__del__`
  (printing "Exception ignored"): CI once sent SIGTERM while the import machinery ran such a
  callback, and `rigctl execute` ran its plan to the end and exited 0;
- a second Ctrl-C while the run ramps its coils down raised out of the ramp, leaving the supplies
  (which hold their output: a Kepco BOP has no link watchdog) at their last current.
The references: the bench's own supply models, the run record, the plan's length in cycles.
"""

from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path

import pytest

from rigctl.apps.cli.main import main
from rigctl.core.config import StreamSettings
from rigctl.core.errors import abort_on_sigterm, take_interrupt
from rigctl.core.record import read_events, read_stream
from rigctl.emulators.bench import SixCoilBench
from rigctl.plans.schema import load_plan
from rigctl.rigs.six_coil.pair import PairProgram, PairRunSettings
from rigctl.rigs.six_coil.supplies import CoilSupplies
from rigctl.run.engine import Run

WORKSPACE = os.path.join(os.path.dirname(__file__), "..", "..", "plans", "examples",
                         "pair-formation-change-workspace.json")
AT_CYCLE = 100  # where the test interrupts (the run has about 3.6 s x rate cycles)


@pytest.fixture(scope="module")
def plan(tmp_path_factory):
    path = tmp_path_factory.mktemp("interrupts") / "short.json"
    assert main(["plan", "pair", "--workspace", WORKSPACE, "--start", "8,7,2,0", "--goal",
                 "8.8,7.3,2.3,40", "--seed", "2", "--hold", "0.5", "-o", str(path)]) == 0
    return load_plan(path)


@pytest.fixture
def handlers():
    """The CLI's handlers for the test, the previous ones back after it."""
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    abort_on_sigterm()
    yield
    for sig, handler in previous.items():
        signal.signal(sig, handler)
    take_interrupt()


@pytest.fixture
def bench():
    with SixCoilBench(world="pair") as bench:
        yield bench


def pair_run(plan, bench, runs_dir, on_cycle, connect=CoilSupplies.connect) -> Run:
    # the supplies' reply watchdog is not under test: bench and run share this process
    rig = bench.rig.model_copy(update={"stream": StreamSettings(reply_timeout_s=1.0)})
    return Run(PairProgram(plan, rig, PairRunSettings()), rig, connect, runs_dir=runs_dir,
               on_cycle=on_cycle)


def execute(run: Run):
    try:
        return run.execute()
    except KeyboardInterrupt as interrupt:  # pytest would take it as the operator's, and stop
        pytest.fail(f"{type(interrupt).__name__} escaped the run")


class _SignalsWhenDropped:
    """Sends SIGTERM to this process from its `__del__`, where the handler's exception is lost."""

    def __del__(self) -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the handler runs at the next bytecode boundary, in here
            pass


def assert_every_supply_off(bench) -> None:
    assert all(not s.model.output_on and s.model.current_setpoint_A == 0.0
               for s in bench.supplies), [(s.model.output_on, s.model.current_setpoint_A)
                                          for s in bench.supplies]


def test_a_sigterm_whose_exception_python_drops_still_aborts_the_run(plan, bench, handlers,
                                                                     tmp_path, monkeypatch):
    went_on: list[int] = []
    dropped_exceptions: list[BaseException | None] = []  # what Python would print as "ignored"
    monkeypatch.setattr(sys, "unraisablehook", lambda u: dropped_exceptions.append(u.exc_value))

    def on_cycle(sample, move, commanded, measured) -> None:
        if went_on:
            went_on.append(sample)
        elif sample == AT_CYCLE:
            dropped = _SignalsWhenDropped()
            del dropped  # SIGTERM, its Terminated raised and dropped inside __del__
            went_on.append(sample)  # reached: the exception did not come out here

    run = pair_run(plan, bench, tmp_path / "runs", on_cycle)
    planned = round(run.program.duration_s * run.program.rate_hz)
    summary = execute(run)
    # the premise: Python did drop it (without the run's check the plan ran to its end)
    assert [type(e).__name__ for e in dropped_exceptions] == ["Terminated"]
    assert went_on and went_on[0] == AT_CYCLE
    assert summary.state == "aborted" and summary.safe is True, summary
    aborts = [e for e in read_events(summary.run) if e["event"] == "abort"]
    assert aborts and "SIGTERM" in aborts[0]["reason"], aborts
    # ended at the next cycle, not at the plan's end
    assert len(went_on) <= 2 and len(read_stream(summary.run)) < AT_CYCLE + 5 < planned
    assert_every_supply_off(bench)


class _InterruptedWhileStopping(CoilSupplies):
    """The rig's supplies, and the operator pressing Ctrl-C again as their ramp down begins."""

    def stop(self, ramp_s: float, steps: int = 10) -> list[str]:
        os.kill(os.getpid(), signal.SIGINT)
        return super().stop(ramp_s, steps)


def test_a_second_ctrl_c_during_the_ramp_down_does_not_cut_it_short(plan, bench, handlers,
                                                                    tmp_path):
    def on_cycle(sample, move, commanded, measured) -> None:
        if sample == AT_CYCLE:
            os.kill(os.getpid(), signal.SIGINT)  # the first: the run aborts

    run = pair_run(plan, bench, tmp_path / "runs", on_cycle, _InterruptedWhileStopping.connect)
    summary = execute(run)
    assert summary.state == "aborted" and summary.safe is True, summary
    events = read_events(summary.run)
    aborts = [e for e in events if e["event"] == "abort"]
    assert len(aborts) == 1 and "Ctrl-C" in aborts[0]["reason"], aborts
    names = [e["event"] for e in events]
    assert names.index("stopping") < names.index("safe")
    assert_every_supply_off(bench)
    assert take_interrupt() is None  # the second was handled (said), not left for the next run


class _InterruptedWhileFinishing(PairProgram):
    """The pair program, and the operator pressing Ctrl-C again as the run, ramped down and safe,
    takes its last look at the agents (before the summary is written)."""

    def finish(self, ctx):
        os.kill(os.getpid(), signal.SIGINT)
        return super().finish(ctx)


def test_a_ctrl_c_while_the_run_winds_down_still_leaves_a_finished_record(plan, bench, handlers,
                                                                          tmp_path):
    def on_cycle(sample, move, commanded, measured) -> None:
        if sample == AT_CYCLE:
            os.kill(os.getpid(), signal.SIGTERM)  # the first: the run aborts

    rig = bench.rig.model_copy(update={"stream": StreamSettings(reply_timeout_s=1.0)})
    run = Run(_InterruptedWhileFinishing(plan, rig, PairRunSettings()), rig, CoilSupplies.connect,
              runs_dir=tmp_path / "runs", on_cycle=on_cycle)
    summary = execute(run)
    assert summary.state == "aborted" and summary.safe is True, summary
    on_disk = json.loads((Path(summary.run) / "summary.json").read_text())
    assert on_disk["state"] == "aborted" and on_disk["safe"] is True
    aborts = [e for e in read_events(summary.run) if e["event"] == "abort"]
    assert len(aborts) == 1 and "SIGTERM" in aborts[0]["reason"], aborts
    assert_every_supply_off(bench)
    assert take_interrupt() is None
