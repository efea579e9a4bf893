"""Coil heating on the emulated coil board, end to end: the board's coils are voltage-driven (the
SyRens put drive/127 of their supply across them, nothing measures a current), so the run's live
winding model steps V^2 / R(T) on the drive the board acknowledged, while the bench heats its own
windings (R_th and C_th a seeded few percent off the rig file's, `emulators/coilboard/coils.py`)
by what the SyRen wire carried. The model follows the emulator within 2 K through a closed-loop
run; a winding at its warning pauses the run at the end of the move with every coil off; a hold
that takes a winding to its limit is released before the coil's own cut-out would open.

The bench runs in a process of its own as `rigctl execute` starts it, at real speed (the model
runs on the host's clock, the windings on the bench's), with small windings (seconds, not the
defaults' quarter of an hour) given to it through its backdoor and to the run in its rig."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.config import CoilThermal, load_rig
from rigctl.core.record import read_events, read_series
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import load_plan
from rigctl.rigs import rig_kind
from rigctl.rigs.coil_board.run import CoilBoardRun
from rigctl.run.control import RunState
from rigctl.run.hold import HoldPlan

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "coilboard-disk.json"
NAMES = ("+x", "-x", "+y", "-y")
# 6 ohm on 12 V: 24 W at full drive, a steady rise of about 50 K, tau = R_th C_th = 10 s
SMALL = {"thermal_resistance_K_per_W": 2.5, "thermal_capacity_J_per_K": 4.0, "ambient_C": 25.0}


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    with EmulatedBenchProcess("coil-board", tmp_path_factory.mktemp("bench") / "bench.toml") as path:
        yield load_rig(path)


def heating(bench, backdoor, **limits):
    """The rig with small windings of these limits, and the bench's windings made anew from the
    same data (at the room's temperature, 5 % off, seed 0); the bench's windings as built."""
    thermal = {**SMALL, **limits}
    built = backdoor.request("windings", thermal=thermal, size=0.05, seed=0)["coils"]
    board = bench.board.model_copy(update={"coil_thermal": CoilThermal(**thermal)})
    return bench.model_copy(update={"board": board}), built


class TruthLog:
    """The bench's winding temperatures, read ten times a second with the host's clock."""

    def __init__(self, bench) -> None:
        self.rows: list[tuple[float, dict]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, args=(bench.emulation.backdoor,))
        self._thread.start()

    def _poll(self, url: str) -> None:
        with BackdoorClient(url) as backdoor:
            while not self._stop.wait(0.1):
                asked = time.monotonic()
                truth = backdoor.request("truth")
                self.rows.append((0.5 * (asked + time.monotonic()), truth["winding_C"]))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def model_error_K(run_dir, t0: float, truths: list[tuple[float, dict]]) -> float:
    """The largest |model - emulator| over the run: the record's `winding` series (ten rows a
    second, run time from `t0`) at each instant the bench was read."""
    series = read_series(run_dir, "winding")
    times = np.asarray(series["t_s"]) + t0
    errors = [abs(np.interp(t, times, series[name]) - truth[name])
              for t, truth in truths if times[0] <= t <= times[-1] for name in NAMES]
    assert len(errors) > 100
    return max(errors)


def test_the_live_model_follows_the_emulated_windings_within_2_K_through_a_run(bench, tmp_path):
    with BackdoorClient(bench.emulation.backdoor) as backdoor:
        rig, built = heating(bench, backdoor, warning_C=95.0, max_winding_C=100.0)
        off = [abs(c["r_th_K_per_W"] / c["rig_r_th_K_per_W"] - 1) for c in built]
        assert max(off) > 0.02  # the emulator's windings are not the rig file's
        run = CoilBoardRun(load_plan(PLAN), rig, runs_dir=tmp_path)
        log = TruthLog(bench)
        try:
            summary = run.execute()
        finally:
            log.stop()
        peaks = backdoor.request("truth")["winding_peak_C"]
    assert summary.state == "done" and summary.reached, summary.faults
    assert max(peaks.values()) > SMALL["ambient_C"] + 10  # the coils did heat
    error = model_error_K(summary.run, run.record.t0, log.rows)
    print(f"coil board: live model vs emulated windings, largest error {error:.2f} K "
          f"(peak {max(peaks.values()):.1f} C)")
    assert error < 2.0
    assert {"certified", "energised", "safe"} <= {e["event"] for e in read_events(summary.run)}


def test_a_winding_at_its_warning_pauses_the_run_at_the_end_of_the_move(bench, tmp_path):
    with BackdoorClient(bench.emulation.backdoor) as backdoor:
        rig, _ = heating(bench, backdoor, warning_C=33.0, max_winding_C=100.0)
        run = CoilBoardRun(load_plan(PLAN), rig, runs_dir=tmp_path)
        result = {}
        runner = threading.Thread(target=lambda: result.setdefault("summary", run.execute()))
        runner.start()
        try:
            wait_for(lambda: run.record is not None and "thermal_warning" in
                     [e["event"] for e in read_events(run.record.path)], 90.0, "a thermal warning")
            wait_for(lambda: run.state == RunState.PAUSED, 60.0, "the pause")
            truth = backdoor.request("truth")
            assert truth["outputs"] == [0.0, 0.0, 0.0, 0.0]  # every coil off: cooling
            events = read_events(run.record.path)
        finally:
            run.abort("test: paused to cool")
            runner.join(60.0)
    names = [e["event"] for e in events]
    warning = events[names.index("thermal_warning")]
    assert warning["winding_C"] >= 33.0 and warning["coil"] in NAMES
    # the move being driven when the warning came was driven to its end, not cut short
    moves = [e for e in events[names.index("thermal_warning"):] if e["event"] == "move"]
    assert moves and not moves[0]["interrupted"]
    # the emulated winding agrees with the model that warned
    assert max(truth["winding_peak_C"].values()) == pytest.approx(33.0, abs=2.0)
    assert result["summary"].state == "aborted" and result["summary"].safe


def test_a_hold_that_takes_a_winding_to_its_limit_is_released_before_the_cut_out(bench, tmp_path):
    with BackdoorClient(bench.emulation.backdoor) as backdoor:
        rig, _ = heating(bench, backdoor, thermal_capacity_J_per_K=2.0, warning_C=45.0,
                         max_winding_C=45.0)
        plan = HoldPlan(rig="coil-board", target={"drive": [127, 0, 0, 0]}, ramp_s=0.1)
        run = rig_kind("coil-board").builder("hold")(plan, rig, runs_dir=tmp_path)
        summary = run.execute()  # a hold has no certificate: only the live model ends it
        truth = backdoor.request("truth")
    events = read_events(summary.run)
    limit = next(e for e in events if e["event"] == "thermal_limit")
    assert limit["coil"] == "+x" and limit["winding_C"] >= 45.0
    assert summary.state == "aborted" and "its limit" in summary.faults[0]["reason"]
    assert summary.safe and truth["outputs"] == [0.0, 0.0, 0.0, 0.0]
    # the emulated winding stopped where the model did, 10 K short of its cut-out
    assert truth["winding_peak_C"]["+x"] == pytest.approx(45.0, abs=2.0)
    assert not any(truth["cutout_open"].values())
    assert max(truth["winding_peak_C"][n] for n in NAMES[1:]) < 25.5
