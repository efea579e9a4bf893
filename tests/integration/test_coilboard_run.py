"""The coil-board run on the one run engine, against the emulated bench in a process of its own (as
`rigctl execute` starts it): the real driver, the Python firmware on a pty, the SyRen wire, the
coils, the particles and the camera.

What an operator relies on: a pause lets the move in progress finish and then holds every coil at
zero, so the particles (in a viscous fluid) stand still; a pause now does that at once; the run
goes on to the goal on resume. Lost tracking suspends the run with the coils off until the camera
sees the particles again, and is a fault of the camera only when it stays lost. Abort and e-stop
end the run with the board confirmed safe."""

from __future__ import annotations

import contextlib
import json
import threading
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.config import load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import load_plan
from rigctl.rigs.coil_board.run import CoilBoardRun, CoilBoardRunSettings
from rigctl.run.control import RunState
from rigctl.run.summary import exit_code

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "coilboard-disk.json"
ZERO = [0.0, 0.0, 0.0, 0.0]


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    with EmulatedBenchProcess("coil-board", tmp_path_factory.mktemp("bench") / "bench.toml") as path:
        rig = load_rig(path)
        with BackdoorClient(rig.emulation.backdoor) as backdoor:
            backdoor.request("speed", factor=3.0)  # simulated seconds per real second
        yield rig


@pytest.fixture
def backdoor(rig):
    with BackdoorClient(rig.emulation.backdoor) as client:
        yield client
        client.request("fault", device="camera", kind="restore")


class WatchedRun:
    """A coil-board run in a thread of its own, watched through the engine's callbacks."""

    def __init__(self, rig, runs_dir: Path, settings: CoilBoardRunSettings = CoilBoardRunSettings()):
        self.full_drive = threading.Event()  # a cycle with a coil at full drive: mid-move
        self.driving_move: int | None = None
        self.pause_now_at_full_drive = threading.Event()  # armed by a test
        self.paused_now = threading.Event()
        self.states: list[RunState] = []
        self.summary = None
        self.run = CoilBoardRun(load_plan(PLAN), rig, runs_dir=runs_dir, on_cycle=self._cycle,
                                on_state=self._state, settings=settings)
        self._thread = threading.Thread(target=self._execute, name="coil-board run")
        self._thread.start()

    def _execute(self) -> None:
        self.summary = self.run.execute()

    def _cycle(self, sample, move, setpoints, measured) -> None:
        # Full drive means the move still has `slow_zone_mm` (4 mm) to go: seconds, not a cycle.
        if move >= 0 and np.max(np.abs(setpoints)) >= CoilBoardRunSettings().drive:
            self.driving_move = move
            self.full_drive.set()
            if self.pause_now_at_full_drive.is_set():
                self.pause_now_at_full_drive.clear()
                self.run.pause(immediate=True)
                self.paused_now.set()

    def _state(self, state: RunState, info: dict) -> None:
        self.states.append(state)

    def mid_move(self) -> int:
        """Wait until a move is being driven at full drive; its number (0-based)."""
        self.full_drive.clear()
        assert self.full_drive.wait(60.0), "no move driven at full drive"
        return self.driving_move

    @contextlib.contextmanager
    def ended_if_failed(self):
        """The test's steps; if one fails, the run is aborted and joined before the error goes on
        (a run left streaming would hold the board for the next test)."""
        try:
            yield self
        except BaseException:
            self.run.abort()
            self.join()
            raise

    def join(self):
        self._thread.join(240.0)
        assert not self._thread.is_alive(), "the run did not end"
        return self.summary

    def events(self) -> list[dict]:
        return [json.loads(line) for line in
                (self.run.record.path / "events.jsonl").read_text().splitlines()]


def outputs_are(backdoor, expected) -> bool:
    return np.allclose(backdoor.request("truth")["outputs"], expected, atol=1e-9)


def coils_off(backdoor, what: str) -> None:
    """Wait until the board has taken three more frames and it and the SyRen wire are at zero:
    a command sent just before (the wire lags the board by a few ms) has come and gone."""
    frames = backdoor.request("truth")["firmware"]["good_frames"]

    def off() -> bool:
        truth = backdoor.request("truth")
        return (truth["firmware"]["good_frames"] >= frames + 3 and
                truth["firmware"]["outputs"] == [0, 0, 0, 0] and
                np.allclose(truth["outputs"], ZERO, atol=1e-9))

    wait_for(off, 5.0, what)


def stand_still(backdoor, sim_seconds: float = 0.5) -> bool:
    """The particles do not move over `sim_seconds` of simulated time."""
    first = backdoor.request("truth")
    wait_for(lambda: backdoor.request("truth")["sim_time_s"] >= first["sim_time_s"] + sim_seconds,
             20.0, "simulated time to pass")
    return backdoor.request("truth")["agents"] == first["agents"]


def assert_delivered(summary, plan_tolerance: float) -> None:
    assert summary.reached and summary.state == "done" and summary.faults == []
    assert summary.safe and exit_code(summary) == 0
    for agent in summary.agents:
        assert agent.error_mm <= plan_tolerance and agent.truth_error_mm <= plan_tolerance


def test_pause_holds_the_coils_at_zero_and_the_run_reaches_the_goal_on_resume(rig, backdoor,
                                                                             tmp_path):
    watched = WatchedRun(rig, tmp_path)
    with watched.ended_if_failed():
        first = watched.mid_move()
        watched.run.pause()  # at the end of this move
        wait_for(lambda: watched.run.state == RunState.PAUSED, 60.0, "the pause")
        coils_off(backdoor, "every coil off")
        assert stand_still(backdoor)
        # The move in progress was driven to its end, not cut short.
        ended = [e for e in watched.events() if e["event"] == "move"]
        assert ended[-1]["number"] == first + 1 and not ended[-1]["interrupted"]
        watched.run.resume()

        # Now, mid-move: asked for on the stream thread right after a cycle at full drive, so
        # that it is seen while the move is being driven (a move may end by itself at any cycle).
        watched.pause_now_at_full_drive.set()
        assert watched.paused_now.wait(60.0), "no move driven at full drive"
        second = watched.driving_move
        coils_off(backdoor, "every coil off at once")
        wait_for(lambda: watched.run.state == RunState.PAUSED, 5.0, "the pause")
        assert stand_still(backdoor)
        cut = [e for e in watched.events() if e["event"] == "move" and e["number"] == second + 1]
        assert cut and cut[-1]["interrupted"]
        watched.run.resume()
    summary = watched.join()
    assert_delivered(summary, load_plan(PLAN).tolerance_mm)
    assert watched.states.count(RunState.PAUSED) == 2
    assert summary.metrics["moves"] >= 3 and summary.details[0].startswith("moves: ")


def test_lost_tracking_suspends_the_run_with_the_coils_off_until_the_camera_sees_again(
        rig, backdoor, tmp_path):
    watched = WatchedRun(rig, tmp_path, CoilBoardRunSettings(lost_limit_s=120.0))
    with watched.ended_if_failed():
        watched.mid_move()
        backdoor.request("fault", device="camera", kind="black_out")
        wait_for(lambda: watched.run.state == RunState.SUSPENDED, 30.0, "the run suspended")
        coils_off(backdoor, "every coil off")
        assert stand_still(backdoor)
        backdoor.request("fault", device="camera", kind="restore")
    summary = watched.join()
    assert_delivered(summary, load_plan(PLAN).tolerance_mm)
    assert RunState.SUSPENDED in watched.states and watched.states[-1] == RunState.DONE
    assert summary.tracking["holds"] >= 1
    names = [e["event"] for e in watched.events()]
    assert names.index("suspend") < names.index("resume")


def test_tracking_lost_for_longer_than_the_limit_is_a_fault_of_the_camera(rig, backdoor, tmp_path):
    watched = WatchedRun(rig, tmp_path, CoilBoardRunSettings(lost_limit_s=0.5))
    try:
        watched.mid_move()
        backdoor.request("fault", device="camera", kind="black_out")
        summary = watched.join()
    finally:
        backdoor.request("fault", device="camera", kind="restore")
    assert summary.state == "faulted" and not summary.reached and exit_code(summary) == 3
    assert [f["device"] for f in summary.faults] == ["camera"]
    assert "tracking lost" in summary.faults[0]["reason"]
    assert summary.safe
    wait_for(lambda: outputs_are(backdoor, ZERO), 5.0, "every coil off")


def test_abort_mid_move_ends_the_run_with_the_board_confirmed_safe(rig, backdoor, tmp_path):
    watched = WatchedRun(rig, tmp_path)
    watched.mid_move()
    watched.run.abort()
    summary = watched.join()
    assert summary.state == "aborted" and exit_code(summary) == 3
    assert [f["kind"] for f in summary.faults] == ["Abort"]
    assert summary.safe and summary.unsafe_devices == []
    wait_for(lambda: outputs_are(backdoor, ZERO), 5.0, "every coil off")
    assert stand_still(backdoor)


def test_estop_from_another_thread_zeroes_the_coils_at_once(rig, backdoor, tmp_path):
    watched = WatchedRun(rig, tmp_path)
    watched.mid_move()
    assert watched.run.estop() == []  # the STOP frame went out on this thread
    summary = watched.join()
    wait_for(lambda: outputs_are(backdoor, ZERO), 5.0, "every coil off")
    assert summary.state == "estopped" and exit_code(summary) == 3
    assert summary.safe
    names = [e["event"] for e in watched.events()]
    assert "estop_zeroed" in names and "safe" in names


def with_limits(rig, **limits):
    """The rig with its `[stream]` hold limits changed."""
    return rig.model_copy(update={"stream": rig.stream.model_copy(update=limits)})


def test_a_camera_freeze_of_seconds_is_ridden_out_by_default(rig, backdoor, tmp_path):
    """The issue's case: a 5 s freeze ended the run (exit 3); with the default settings the run
    suspends with the coils off and goes on to the goal once the camera moves again."""
    watched = WatchedRun(rig, tmp_path)
    with watched.ended_if_failed():
        watched.mid_move()
        backdoor.request("fault", device="camera", kind="freeze")
        wait_for(lambda: watched.run.state == RunState.SUSPENDED, 30.0, "the run suspended")
        coils_off(backdoor, "every coil off")
        threading.Event().wait(5.0)  # frozen for 5 s
        assert watched.run.state == RunState.SUSPENDED
        backdoor.request("fault", device="camera", kind="restore")
    summary = watched.join()
    assert_delivered(summary, load_plan(PLAN).tolerance_mm)
    assert watched.states[-1] == RunState.DONE


@pytest.mark.parametrize("held", ["suspended", "paused"])
def test_a_run_held_past_the_rig_files_limit_ramps_down_and_ends_with_the_reason(
        rig, backdoor, tmp_path, held):
    limited = with_limits(rig, **{f"{held}_limit_s": 1.0})
    watched = WatchedRun(limited, tmp_path)
    try:
        watched.mid_move()
        if held == "suspended":
            backdoor.request("fault", device="camera", kind="black_out")
        else:
            watched.run.pause(immediate=True)
        summary = watched.join()
    finally:
        backdoor.request("fault", device="camera", kind="restore")
    assert RunState(held) in watched.states
    assert summary.state == "aborted" and exit_code(summary) == 3 and summary.safe
    reason = summary.faults[-1]["reason"]
    assert f"{held} for more than 1 s" in reason and f"{held}_limit_s" in reason, reason
    events = watched.events()
    assert any(e["event"] == "abort" and f"{held}_limit_s" in e["reason"] for e in events)
    wait_for(lambda: outputs_are(backdoor, ZERO), 5.0, "every coil off")


def test_a_particle_hidden_before_the_run_is_a_fault_of_the_camera_before_anything_is_energised(
        rig, backdoor, tmp_path):
    """The fault campaign's cell (camera:occlude @ before): the camera must not take the dish's
    dark rim for the hidden particle (it did, and the run drove on a false position)."""
    backdoor.request("fault", device="camera", kind="occlude", robot=0)
    try:
        watched = WatchedRun(rig, tmp_path, CoilBoardRunSettings(acquire_timeout_s=2.0))
        summary = watched.join()
    finally:
        backdoor.request("fault", device="camera", kind="restore")
    assert summary.state == "faulted" and exit_code(summary) == 3
    assert [f["device"] for f in summary.faults] == ["camera"]
    assert "not found" in summary.faults[0]["reason"]
    names = [e["event"] for e in watched.events()]
    assert "energised" not in names and "found" not in names
    assert summary.safe


def driven_perfectly(program) -> list:
    """Stub a coil-board program's I/O: no record, and each move ends exactly where Alg. 1 expects
    it to (a perfect rig). Returns the list the driven moves are appended to."""
    from rigctl.rigs.coil_board import run as board_run

    program.record = type("Record", (), {"event": lambda self, *a, **k: None})()
    driven = []

    def perfect(move, start, end, before):
        driven.append(move)
        yield board_run.ZERO
        return end

    program._drive = perfect
    return driven


@pytest.mark.parametrize("off_mm, moves_on", [(0.47, True), (0.44, False)])
def test_the_moves_end_only_with_a_margin_inside_the_tolerance(rig, off_mm, moves_on):
    """Measured 0.47 mm from the goals (tolerance 0.5, margin 0.9 x 0.5 = 0.45), the run moves on
    towards them, since the camera's next frame, which judges the run, could read a particle over
    0.5; at 0.44 it stops where it is, reached."""
    from rigctl.rigs.coil_board.run import CoilBoardProgram

    program = CoilBoardProgram(load_plan(PLAN), rig, settings=CoilBoardRunSettings(done_fraction=0.9))
    assert program.tolerance == 0.5
    offset = np.array([off_mm, 0.0])
    program._position = program.goals + offset
    driven = driven_perfectly(program)
    commands = program._run_moves()
    for _ in range(200):
        try:
            next(commands)
        except StopIteration:
            break
    assert program.reached
    assert bool(driven) == moves_on


def test_a_measured_position_alg_1_pulls_into_its_region_does_not_re_plan_every_cycle(rig):
    """A particle measured just outside the planning region (on the rim, within the tracker's
    noise) is moved into it for Alg. 1, so the planned states start off the measured ones; the
    loop must drive Alg. 1's moves, not re-plan again each cycle without ever yielding (it starved
    the stream process until the daemon killed it). The moves are driven by a perfect rig here:
    each ends exactly where Alg. 1 expects."""
    from rigctl.plans.schema import parse_plan
    from rigctl.rigs.coil_board import run as board_run
    from rigctl.rigs.coil_board.faults import quick_plan

    plan = parse_plan(quick_plan())  # the campaign's plan, where the storm was seen
    program = board_run.CoilBoardProgram(plan, rig)
    # where the camera had them then: radius 0.5 on a 23 mm dish, so the region's radius is 22.5
    measured = np.array([[-23.217, 2.556], [5.108, -21.929]])
    assert not program.region.contains(measured[0])[0]
    program._position = measured
    driven = driven_perfectly(program)
    replan = program._replan

    def bounded(position):  # the storm re-planned inside one `next`: make it fail, not hang
        if program.replans >= 50:
            raise AssertionError("50 re-plans")
        return replan(position)

    program._replan = bounded
    commands = program._run_moves()
    replans_without_driving = 0
    for _ in range(200):
        before = (program.replans, len(driven))
        try:
            next(commands)
        except StopIteration:
            break
        if len(driven) == before[1]:
            replans_without_driving += program.replans - before[0]
    else:
        pytest.fail("the loop did not end within 200 commands")
    assert program.reached
    assert replans_without_driving == 0 and program.replans <= 1
