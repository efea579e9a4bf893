"""The pieces of the closed loop that need no camera: fractional turns realized and rolled by the
emulated world, the world's model mismatch against hand-worked distances, and the supervised
sequencer's gates, splices and holds, and the re-plan budget."""

import math

import numpy as np
import pytest

from rigctl.core.config import FieldSettings, RigConfig, RigInfo, default_six_coil_coils
from rigctl.core.errors import PlanError
from rigctl.emulators.world.rolling import Mismatch, RollingMagnetWorld
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.schema import parse_workspace
from rigctl.plans.workspace import Workspace
from rigctl.rigs.six_coil.allocate import CurrentProgram
from rigctl.rigs.six_coil.realize import realize_global_moves
from rigctl.rigs.six_coil.settings import SixCoilRig
from rigctl.rigs.six_coil.supervisor import ReplanBudget, SupervisedSequencer, SupervisorSettings

TURN_MM = 10.0
R = TURN_MM / (2 * math.pi)


def rig(whole_turns: bool) -> RigConfig:
    return SixCoilRig(rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils(),
                     field=FieldSettings(whole_turns=whole_turns))


def world(positions, mismatch=None, radius=5.0):
    spec = parse_workspace({"boundary": {"rect": [0, 0, 400, 400]}})
    model = GlobalInputModel(Workspace.from_spec(spec), np.full(len(positions), radius))
    return RollingMagnetWorld(model, np.array(positions, float), rolling_radius_mm=R,
                              min_field_T=0.5e-3, mismatch=mismatch)


def roll_program(w, field_T):
    for b in field_T:
        w.feel(b)


# -- fractional turns ----------------------------------------------------------------------------

def test_whole_turns_by_default_refuse_a_fractional_move():
    with pytest.raises(PlanError, match="whole turns"):
        realize_global_moves([[3.0, 0.0]], rig(True))


def test_fractional_moves_end_tilted_and_the_world_rolls_exactly_the_sum():
    moves = np.array([[3.3, 0.0], [0.0, 7.25], [-12.6, 4.1], [2.5, 2.5]])
    program = realize_global_moves(moves, rig(False))
    w = world([[200.0, 200.0]])
    roll_program(w, program.field_T)
    # free space, no slip: the centre moves by the sum of the moves (hand sum: -6.8, 13.85)
    np.testing.assert_allclose(w.positions_mm, [[200.0 - 6.8, 200.0 + 13.85]], atol=1e-6)
    # 3.3 mm is 0.33 turn: B ends 0.33 * 360 = 118.8 degrees round from horizontal, so its
    # vertical part is b0 sin(118.8 deg) in size
    end = program.move_end_index(0) - 1
    b0 = 3e-3
    assert abs(abs(program.field_T[end, 2]) - b0 * math.sin(math.radians(118.8))) < 1e-9
    # the next steering keeps that vertical part while it turns the horizontal part about z
    start = program.move_spans[1, 0]
    steering = program.field_T[start:start + 5]
    np.testing.assert_allclose(steering[:, 2], program.field_T[end, 2], atol=1e-12)
    # the field never jumps: consecutive samples differ by less than one rolling step
    step = np.linalg.norm(np.diff(program.field_T, axis=0), axis=1)
    assert step.max() < b0 * 2 * math.pi * 2.0 / 100.0 * 1.01


def test_a_program_can_start_from_a_tilted_field_without_a_ramp():
    b0 = 3e-3
    tilted = b0 * np.array([0.0, math.cos(0.7), math.sin(0.7)])
    program = realize_global_moves([[0.0, 5.0]], rig(False), start_field_T=tilted)
    np.testing.assert_allclose(program.field_T[0], tilted, atol=1e-12)
    w = world([[100.0, 100.0]])
    w.feel(tilted)  # the magnets lie aligned with the field the coils hold
    roll_program(w, program.field_T)
    np.testing.assert_allclose(w.positions_mm, [[100.0, 105.0]], atol=1e-6)


# -- mismatch ------------------------------------------------------------------------------------

def one_turn_along_x(w, steps=400):
    """The field turns once about -y, from +x down through -z: a roll about u = -y, which moves
    a centre along u x z = +x by one circumference."""
    for a in np.linspace(0.0, 2 * math.pi, steps):
        w.feel(3e-3 * np.array([math.cos(a), 0.0, -math.sin(a)]))


def test_slip_shortens_every_turn_by_its_factor():
    w = world([[100.0, 100.0]], Mismatch(slip=0.85))
    one_turn_along_x(w)
    moved = np.linalg.norm(w.positions_mm[0] - [100.0, 100.0])
    assert moved == pytest.approx(0.85 * TURN_MM, abs=1e-6)


def test_speed_spread_gives_each_robot_its_own_distance_per_turn():
    w = world([[100.0, 100.0], [100.0, 300.0], [300.0, 200.0]],
              Mismatch(slip=0.9, speed_spread=0.05, seed=4))
    one_turn_along_x(w)
    moved = np.linalg.norm(w.positions_mm - [[100.0, 100.0], [100.0, 300.0], [300.0, 200.0]], axis=1)
    assert len(set(np.round(moved, 6))) == 3  # all different
    assert np.all(np.abs(moved / (0.9 * TURN_MM) - 1.0) < 0.25)  # within 5 sigma of the spread
    again = world([[100.0, 100.0], [100.0, 300.0], [300.0, 200.0]],
                  Mismatch(slip=0.9, speed_spread=0.05, seed=4))
    one_turn_along_x(again)
    np.testing.assert_allclose(again.positions_mm, w.positions_mm)  # the seed decides


def test_drift_moves_everyone_at_its_speed():
    start = np.array([[200.0, 200.0], [150.0, 250.0]])
    w = world(start, Mismatch(drift_mm_per_s=0.1, seed=2))
    for _ in range(10_000):
        w.drift(1e-3)  # 10 s
    moved = w.positions_mm - start
    np.testing.assert_allclose(np.linalg.norm(moved, axis=1), [1.0, 1.0], atol=0.051)
    np.testing.assert_allclose(moved[0], moved[1], atol=1e-9)


def test_noise_jitters_only_robots_touching_a_wall():
    # robot 0 rolls along the floor's lower wall (touching it), robot 1 in the open
    start = np.array([[100.0, 5.0], [100.0, 200.0]])
    finals = []
    for seed in range(12):
        w = world(start, Mismatch(noise_mm=0.3, seed=seed))
        one_turn_along_x(w)
        finals.append(w.positions_mm.copy())
    finals = np.array(finals)
    np.testing.assert_allclose(finals[:, 1], np.tile([110.0, 200.0], (12, 1)), atol=1e-6)
    spread_x = finals[:, 0, 0].std()
    assert 0.05 < spread_x < 1.0  # a random walk of 0.3 mm per turn along the wall
    assert np.all(finals[:, 0, 1] >= 5.0 - 1e-6)  # never into the wall


# -- the supervised sequencer --------------------------------------------------------------------

def program(n: int, value: float = 1.0, segment: int = 0) -> CurrentProgram:
    currents = np.full((n, 1), value) * np.arange(1, n + 1)[:, None]
    return CurrentProgram(t_s=np.arange(n) / 100.0, currents_A=currents,
                          segment=np.full(n, segment), coil_names=("x+",))


def drain(seq, n):
    return [seq.next() for _ in range(n)]


def test_the_sequencer_waits_at_each_move_end_until_released():
    seq = SupervisedSequencer(program(6), move_ends=[3, 6], ramp_samples=2)
    out = drain(seq, 5)
    assert [float(o[0][0]) for o in out] == [1.0, 2.0, 3.0, 3.0, 3.0]  # holds sample 3's current
    assert seq.waiting_at == 3 and seq.arrived.is_set()
    seq.release()
    assert float(seq.next()[0][0]) == 4.0


def test_a_released_decision_says_when_its_first_command_left():
    # the supervisor waits on it before its own Python after a go-on (supervisor._judge)
    seq = SupervisedSequencer(program(6), move_ends=[3, 6], ramp_samples=2)
    drain(seq, 4)
    seq.release(decision=0)
    assert not seq.command_left.is_set()  # released, but the stream has not taken a sample yet
    assert float(seq.next()[0][0]) == 4.0
    assert seq.command_left.is_set() and 0 in seq.command_times


def test_a_splice_replaces_the_rest_of_the_program():
    seq = SupervisedSequencer(program(6), move_ends=[3, 6], ramp_samples=2)
    drain(seq, 4)
    begin = seq.splice(program(2, value=10.0), [2])
    assert begin == 3
    values = [float(o[0][0]) for o in drain(seq, 4)]
    assert values == [10.0, 20.0, 20.0, 20.0]  # new program, then waits at its move end (5)
    assert seq.waiting_at == 5
    seq.release()
    assert seq.next() is None  # nothing of the old program is left


def test_hold_freezes_the_setpoints_mid_move_and_unhold_goes_on():
    seq = SupervisedSequencer(program(6), move_ends=[6], ramp_samples=2)
    drain(seq, 2)
    seq.hold()
    assert [float(o[0][0]) for o in drain(seq, 3)] == [2.0, 2.0, 2.0]
    assert seq.paused
    seq.unhold()
    assert float(seq.next()[0][0]) == 3.0


def test_the_replanner_process_says_when_it_is_ready_and_then_plans():
    """The re-planning child reports its imports done (so they do not compete with the stream's
    first seconds) and then answers a re-plan: one free robot 20 mm (two turns) from its goal."""
    import json

    from rigctl.rigs.six_coil.supervisor import ReplanWorker

    plan = {"schema": "rigctl.plan/1", "kind": "global-moves", "rig": "six-coil", "name": "one",
            "workspace": {"boundary": {"rect": [0, 0, 200, 200]}},
            "agents": [{"start": [50.0, 100.0], "goal": [70.0, 100.0], "radius": 3.0}],
            "moves": []}
    worker = ReplanWorker()
    try:
        assert worker.wait_ready(timeout_s=60.0)
        assert worker.wait_ready(timeout_s=0.0)  # said once, remembered
        result = worker.replan(json.dumps(plan), ".", np.array([[50.0, 100.0]]),
                               np.array([[70.0, 100.0]]), TURN_MM, 0.3, 0, 2.0)
    finally:
        worker.close()
    assert result.distance <= 0.3
    np.testing.assert_allclose(result.states[-1], [[70.0, 100.0]], atol=0.3)
    np.testing.assert_allclose(result.moves.sum(axis=0), [20.0, 0.0], atol=0.3)


def test_a_closed_replan_worker_leaves_no_descriptor_open():
    """One worker per run: its pipes must all be closed with it (a daemon runs for months)."""
    import os

    from rigctl.rigs.six_coil.supervisor import ReplanWorker

    def open_fds() -> int:
        return len(os.listdir("/proc/self/fd"))

    ReplanWorker().close()  # whatever a first start opens for good (imports, caches)
    before = open_fds()
    kept = [ReplanWorker() for _ in range(3)]  # still referenced, as a finished run's is
    for worker in kept:
        worker.close()
    assert open_fds() == before


def test_corrections_that_keep_gaining_ground_are_not_cut_off_on_the_way():
    # 20 re-plans on the way, each 2 mm nearer the goals than the one before: none is stalled, so a
    # budget of 3 stalled re-plans never refuses (the old flat count of 12 stopped such runs)
    budget = ReplanBudget(SupervisorSettings(max_replans=40, stalled_replans=3, progress_mm=1.0))
    assert [budget.charge(60.0 - 2 * i, last=False) for i in range(20)] == [None] * 20
    assert (budget.total, budget.stalled, budget.best_mm) == (20, 0, 22.0)


def test_re_plans_that_gain_less_than_progress_mm_are_charged_and_end_the_run():
    budget = ReplanBudget(SupervisorSettings(stalled_replans=2, progress_mm=1.0))
    assert budget.charge(10.0, last=False) is None  # the first: progress from nowhere
    assert budget.charge(9.5, last=False) is None  # 0.5 mm better: stalled 1
    assert budget.charge(12.0, last=False) is None  # worse: stalled 2
    assert budget.charge(8.4, last=False) is None  # 1.1 mm better than the best, 9.5: not stalled
    why = budget.charge(8.0, last=False)  # 0.4 mm better, and two stalled already
    assert why is not None and "ran out of corrections on the way" in why and "2 corrections" in why
    assert budget.total == 4
    assert budget.charge(20.0, last=False, landed=1) is None  # farther, but a move landed: headway
    assert budget.stalled == 2


def test_the_end_of_program_and_the_whole_run_keep_their_own_caps():
    budget = ReplanBudget(SupervisorSettings(max_replans=5, final_replans=2))
    assert budget.charge(3.0, last=True) is None
    assert budget.charge(2.0, last=True) is None
    assert "2 re-plans at the end of the program" in budget.charge(1.0, last=True)
    assert budget.charge(50.0, last=False) is None  # on the way, still allowed: 3 of 5 used
    assert budget.charge(40.0, last=False) is None
    assert budget.charge(30.0, last=False) is None
    assert "5 re-plans are used up" in budget.charge(20.0, last=False)


def test_a_replanner_whose_run_was_killed_exits_quietly():
    """The run's process SIGKILLed (its guardian makes the rig safe and says so): the re-planning
    child finds its stdout broken when it answers and exits 0 without a traceback on the
    terminal they shared."""
    import pickle
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-m", "rigctl.rigs.six_coil.supervisor"],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert pickle.load(child.stdout) == (True, "ready")
    child.stdout.close()  # the parent's end of the answers is gone, as with a killed parent
    pickle.dump((), child.stdin)  # a request whose answer (an error) meets the broken pipe
    child.stdin.close()
    assert child.wait(timeout=60) is not None
    err = child.stderr.read()
    child.stderr.close()
    assert child.returncode == 0 and b"Traceback" not in err, err.decode(errors="replace")
