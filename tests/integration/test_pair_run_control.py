"""A pair-formation run driven the way the daemon drives a run: `PairRun` in process against the
emulated six-coil bench in the pair world, with `on_cycle` and `on_state` callbacks, pause and
resume, abort and e-stop from another thread.

The references are independent of the run's code: the record's stream and events (what went to the
supplies), the bench's ground truth (where the agents are, the supplies' own models), the plan
file's segment times, and seed 002's eq. 1 for the hold angles. At zero current the agents would
not stay still: their permanent moments turn along each other (psi = 0) and they close at
dr/dt = -2 K / r^4, so r^5 = r0^5 - 10 K t: from 2 BL apart (K = 10 BL/s for these agents) they
touch after (32 - 1) / (10 K) = 0.31 s. So a pause holds the field (see `PairProgram`), and "still"
below means within twice the closed loop's tolerance over a pause of 1.2 s.
"""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.cli.main import main
from rigctl.apps.testing import wait_for
from rigctl.core.config import StreamSettings
from rigctl.core.record import read_events, read_stream
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.plans.pair import interagent_forces
from rigctl.plans.schema import load_plan
from rigctl.rigs.six_coil.pair import PairRun, PairRunSettings, hold_field_angle
from rigctl.run.control import RunState

WORKSPACE = Path(__file__).resolve().parents[2] / "plans" / "examples" / \
    "pair-formation-change-workspace.json"
RAMP_S = 0.1  # PairRunSettings.ramp_s: the field's ramp up at the start of the program


@pytest.fixture(scope="module")
def plan_file(tmp_path_factory):
    """A short formation change: 6 segments, 3.5 s, a 0.5 s hold."""
    path = tmp_path_factory.mktemp("pair-control") / "short.json"
    assert main(["plan", "pair", "--workspace", str(WORKSPACE), "--start", "8,7,2,0", "--goal",
                 "8.8,7.3,2.3,40", "--seed", "2", "--hold", "0.5", "-o", str(path)]) == 0
    return path


@pytest.fixture
def bench():
    with SixCoilBench(world="pair") as bench:
        yield bench


class Driven:
    """A PairRun on its own thread, as the daemon's stream process runs it, with every callback
    kept (copies: the run hands over its own buffers)."""

    def __init__(self, plan_file, bench, runs_dir, **kwargs) -> None:
        # the supplies' reply watchdog is not under test: bench and run share this process
        rig = bench.rig.model_copy(update={"stream": StreamSettings(reply_timeout_s=1.0)})
        self.cycles: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        self.states: list[tuple[RunState, dict]] = []
        self.run = PairRun(load_plan(plan_file), rig, runs_dir=runs_dir, on_cycle=self._cycle,
                           on_state=lambda state, info: self.states.append((state, info)),
                           **kwargs)
        self.backdoor = BackdoorClient(rig.emulation.backdoor)
        self.summary = None
        self.thread = threading.Thread(target=self._execute, name="test-run")

    def _cycle(self, sample, move, commanded, measured) -> None:
        self.cycles.append((sample, move, np.array(commanded), np.array(measured)))

    def _execute(self) -> None:
        self.summary = self.run.execute()

    def start(self) -> "Driven":
        self.thread.start()
        return self

    def after_cycles(self, n: int) -> None:
        """Wait until `n` more stream cycles have run."""
        target = len(self.cycles) + n
        wait_for(lambda: len(self.cycles) >= target or not self.thread.is_alive(), 60,
                 f"{n} stream cycles")
        assert self.thread.is_alive(), "the run ended early"

    def truth(self) -> np.ndarray:
        return np.array(self.backdoor.request("truth")["agents"])

    def finish(self):
        self.thread.join(120)
        assert not self.thread.is_alive(), "the run did not end"
        self.backdoor.close()
        return self.summary

    def recorded_states(self) -> list[str]:
        return [e["state"] for e in read_events(self.summary.run) if e["event"] == "state"]


def segment_starts(plan_path: Path, rate_hz: float) -> list[int]:
    """Program samples at which each segment of the plan file begins (after the ramp up)."""
    plan = json.loads(plan_path.read_text())
    n = [max(1, round(s["dt_s"] * rate_hz)) for s in plan["segments"]]
    first = max(1, round(RAMP_S * rate_hz))
    return [first + int(k) for k in np.concatenate([[0], np.cumsum(n)[:-1]])]


def test_hold_angles_cancel_both_forces_and_flip_through_repulsion():
    """Seed 002 eq. 1 (`interagent_forces`, the planner's model): no radial force at either hold
    angle, transverse forces equal and opposite; the field turning between them passes 90 deg
    (pushing apart), not 0 deg (pulling together)."""
    phi = 0.7
    a, b = hold_field_angle(phi, False) - phi, hold_field_angle(phi, True) - phi
    fr, fphi = interagent_forces(2.0, np.array([a, b]))
    assert fr == pytest.approx([0.0, 0.0], abs=1e-12)
    assert fphi[0] == pytest.approx(-fphi[1]) and abs(fphi[0]) > 0.05
    # halfway through the coils' change the field is the mean of the two (currents are linear)
    mid = math.atan2(math.sin(a) + math.sin(b), math.cos(a) + math.cos(b))
    assert math.degrees(mid) == pytest.approx(90.0)
    assert interagent_forces(2.0, mid)[0] > 0  # apart


def without_suspensions(states: list[str]) -> list[str]:
    """The states with each suspension taken out, and the run it returned to merged with the one
    it left."""
    out: list[str] = []
    for state in states:
        if state != "suspended" and not (out and out[-1] == state):
            out.append(state)
    return out


def test_callbacks_match_the_record_and_a_pause_holds_the_pair_closed_loop(plan_file, bench,
                                                                        tmp_path):
    plan = json.loads(plan_file.read_text())
    d = plan["agents"]["body_diameter_mm"]
    run = Driven(plan_file, bench, tmp_path / "runs").start()
    run.after_cycles(120)  # past the ramp, on the path
    run.run.pause(immediate=True)
    wait_for(lambda: run.run.state == RunState.PAUSED, 20, "the run to pause")
    start = run.truth()
    separations, moved = [], []
    for _ in range(12):  # 1.2 s at 100 Hz: longer than the pair needs to touch at zero current
        run.after_cycles(10)
        now = run.truth()
        separations.append(float(np.hypot(*(now[1] - now[0]))) / d)
        moved.append(float(np.max(np.hypot(*(now - start).T))) / d)
    assert run.run.state == RunState.PAUSED
    run.run.resume()
    summary = run.finish()

    r0 = float(np.hypot(*(start[1] - start[0]))) / d
    assert max(moved) <= 2 * plan["tolerance_bl"], moved
    assert min(separations) >= max(plan["r_min_bl"], r0 - 2 * plan["tolerance_bl"]), separations
    assert summary.reached and not summary.faults  # resumed from where the agents were
    # the callbacks say what the record says, state for state; and that is the run, the pause
    # and the end (a camera frame late under a loaded machine may add a suspension and its end:
    # the run then held the field until the camera saw again, which is not what this test is about)
    assert [s.value for s, _ in run.states] == run.recorded_states()
    assert without_suspensions(run.recorded_states()) == ["running", "paused", "running", "done"]

    stream = read_stream(summary.run)
    coils = stream["coils"]
    assert len(run.cycles) == len(stream["sample"])
    assert [c[0] for c in run.cycles] == stream["sample"].tolist()
    assert [c[1] for c in run.cycles] == stream["move"].tolist()
    for j, name in enumerate(coils):
        np.testing.assert_allclose([c[2][j] for c in run.cycles], stream[f"cmd_{name}_A"],
                                   atol=1e-9)
        np.testing.assert_allclose([c[3][j] for c in run.cycles], stream[f"meas_{name}_A"],
                                   atol=1e-9)
    # moves are plan segments or -1; while paused, -1 and the pursuit does not advance
    assert set(stream["move"].tolist()) <= set(range(-1, len(plan["segments"])))
    assert set(range(len(plan["segments"]))) & set(stream["move"].tolist())
    events = read_events(summary.run)
    paused_at, resumed_at = [e["t"] for e in events if e["event"] == "state"][1:3]
    during = (stream["t_s"] > paused_at) & (stream["t_s"] < resumed_at)
    assert during.sum() >= 120 and (stream["move"][during] == -1).all()


def test_open_loop_pause_waits_for_the_segment_end_and_resume_plays_the_rest(plan_file, bench,
                                                                          tmp_path):
    """A plain pause takes effect where a segment begins; the program goes on from that sample;
    the time paused does not count towards the run's timeout (here barely longer than the
    program); the hold never pulls the agents together."""
    plan = json.loads(plan_file.read_text())
    d = plan["agents"]["body_diameter_mm"]
    program_s = sum(s["dt_s"] for s in plan["segments"]) + plan["hold_s"]
    # the timeout's margin (1.5 s) is shorter than the pause (3 s) but not so short that a
    # stream slipping on a loaded machine (CI) ends the run by itself
    settings = PairRunSettings(closed_loop=False, timeout_factor=1.0, timeout_extra_s=1.5)
    run = Driven(plan_file, bench, tmp_path / "runs", settings=settings).start()
    run.after_cycles(80)
    run.run.pause()
    wait_for(lambda: run.run.state == RunState.PAUSED, 20, "the run to pause")
    start = run.truth()
    separations = []
    for _ in range(30):  # 3 s: with this pause the run lasts longer than its timeout
        run.after_cycles(10)
        now = run.truth()
        separations.append(float(np.hypot(*(now[1] - now[0]))) / d)
    run.run.resume()
    summary = run.finish()

    r0 = float(np.hypot(*(start[1] - start[0]))) / d
    assert min(separations) >= r0 - 0.05, separations
    assert not summary.faults
    events = read_events(summary.run)
    assert not [e for e in events if e["event"] == "stop"]  # no timeout
    assert run.recorded_states() == ["running", "paused", "running", "done"]
    stream = read_stream(summary.run)
    assert stream["t_s"][-1] - stream["t_s"][0] > program_s + settings.timeout_extra_s
    rate = summary.stream["rate_hz"]
    paused_at, resumed_at = [e["t"] for e in events if e["event"] == "state"][1:3]
    during = (stream["t_s"] > paused_at) & (stream["t_s"] < resumed_at)
    held = set(stream["sample"][during].tolist())
    assert len(held) == 1 and held.pop() in segment_starts(plan_file, rate)
    assert (stream["move"][during] == -1).all()
    # every program sample was sent exactly once, in order, the pause's repeats aside
    sent = stream["sample"][~during]
    assert sent.tolist() == list(range(len(sent)))
    assert len(sent) == len(run.run.program.prepared.program_A)


def test_abort_ramps_down_and_ends_aborted(plan_file, bench, tmp_path):
    run = Driven(plan_file, bench, tmp_path / "runs", closed_loop=False).start()
    run.after_cycles(100)
    run.run.abort()
    summary = run.finish()
    assert run.run.state == RunState.ABORTED and run.states[-1][0] == RunState.ABORTED
    assert run.recorded_states()[-1] == "aborted"
    assert [f["kind"] for f in summary.faults] == ["Abort"] and not summary.reached
    assert summary.as_dict()["faults"] == summary.faults
    stream = read_stream(summary.run)
    peaks = np.max(np.abs([stream[f"cmd_{c}_A"] for c in stream["coils"]]), axis=0)
    ramp = round(PairRunSettings().ramp_s * summary.stream["rate_hz"])
    tail = peaks[-ramp:]
    assert tail[-1] == 0.0 and (np.diff(tail) <= 1e-12).all()  # down to zero, never up
    assert len(peaks) < len(run.run.program.prepared.program_A)  # stopped early
    assert all(not s.model.output_on for s in bench.supplies)


def test_estop_zeroes_every_supply_from_the_calling_thread(plan_file, bench, tmp_path):
    run = Driven(plan_file, bench, tmp_path / "runs").start()
    run.after_cycles(150)
    # the coils' currents follow their L/R in the emulator's own time: wait for one to carry some
    wait_for(lambda: any(abs(s.model.current_A) > 0.5 for s in bench.supplies), 2.0,
             "a supply carrying current")
    asked_unix = time.time()
    assert run.run.estop() == []  # every supply reached
    returned_unix = time.time()
    wait_for(lambda: all(not s.model.output_on and s.model.current_setpoint_A == 0.0
                         and abs(s.model.current_A) < 1e-3 for s in bench.supplies),
             2.0, "every emulated supply off at 0 A")
    summary = run.finish()
    assert run.run.state == RunState.ESTOPPED and run.states[-1][0] == RunState.ESTOPPED
    assert run.recorded_states()[-1] == "estopped"
    assert [f["kind"] for f in summary.faults] == ["EStop"]
    zeroed = [e for e in read_events(summary.run) if e["event"] == "estop_zeroed"]
    assert len(zeroed) == 1 and zeroed[0]["direct"] is True
    assert set(zeroed[0]) >= {"after_request_s", "seen_after_request_s",
                              "stream_zeroed_after_request_s"}
    assert 0 <= zeroed[0]["after_request_s"] <= zeroed[0]["stream_zeroed_after_request_s"]
    # the same instant on the wall clock (the console's bench measures the page's click to it)
    assert asked_unix - 0.01 <= zeroed[0]["told_unix"] <= returned_unix + 0.01


def test_an_estop_before_the_supplies_connect_never_energises(plan_file, bench, tmp_path):
    run = Driven(plan_file, bench, tmp_path / "runs")
    assert run.run.estop() == []  # nothing connected yet: nothing to reach
    summary = run.start().finish()
    assert [s for s, _ in run.states] == [RunState.ESTOPPED]
    names = [e["event"] for e in read_events(summary.run)]
    assert "energised" not in names and "estop" in names
    assert read_stream(summary.run) is None and not run.cycles
    assert all(not s.model.output_on and s.model.current_A == 0.0 for s in bench.supplies)
