"""Steering by hand, the program stepped by hand on a clock of the test's: the dead-man (an input
counts for 200 ms of the stream's clock, then the rig's stop input), letting go, the rolling
field's heading and speed against the field written out here (seed 000's rolling field, B = b0
(cos a d - sin a z)), the board's pull in whole units, inputs clipped to their ranges, the
pre-flight of any input, and a rig kind without teleoperation."""

import math

import numpy as np
import pytest

from rigctl.core.config import CoilBoardSettings, RigInfo, StreamSettings
from rigctl.core.errors import ConfigError, PlanError
from rigctl.physics.coils import actuation_matrix
from rigctl.plans.pair import default_rig
from rigctl.rigs import rig_kind
from rigctl.rigs.coil_board.settings import CoilBoardRig
from rigctl.run.engine import RunContext
from rigctl.run.teleop import SILENCE_S, TeleopPlan, TeleopProgram


class Record:
    """What the program writes: events and the rows of its one series."""

    t0 = 0.0

    def __init__(self) -> None:
        self.events: list[tuple[str, dict]] = []
        self.rows: list[list[float]] = []
        self.columns: list[str] = []

    def event(self, name: str, **fields) -> None:
        self.events.append((name, fields))

    def open_series(self, name, columns, units):
        self.columns = columns
        return self

    def row(self, values) -> None:
        self.rows.append(list(values))


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


SIX = default_rig()
BOARD = CoilBoardRig(rig=RigInfo(kind="coil-board", name="unit"),
                     board=CoilBoardSettings(url="/dev/null", rate_hz=100.0),
                     stream=StreamSettings(rate_hz=100.0))


def session(rig, mode=None):
    clock = Clock()
    drive = rig_kind(rig.rig.kind).teleop(rig, mode)
    prog = TeleopProgram(TeleopPlan(rig=rig.rig.kind, mode=mode), rig, drive, clock=clock)
    record = Record()
    prog.start(RunContext(rig, record, None, lambda text: None))
    return prog, drive, clock, record


def run_for(prog, clock, seconds, k0=0):
    """Cycles at the program's rate for `seconds` of the clock: their setpoints (n, channels)."""
    out = []
    for k in range(k0, k0 + round(seconds * prog.rate_hz)):
        clock.t += 1.0 / prog.rate_hz
        step = prog.next(k, None)
        out.append(None if step is None else step.setpoints)
    return out


def test_rolling_makes_the_rolling_field_at_the_speed_asked():
    prog, drive, clock, _ = session(SIX)
    rate, fs = prog.rate_hz, SIX.field
    b0 = fs.b0_mT * 1e-3
    A = actuation_matrix(SIX)
    n_up = math.ceil(fs.ramp_s * rate - 1e-9)
    heading = fs.initial_heading_deg
    cycles = []
    for k in range(n_up + 40):  # the input renewed every cycle: never silent
        prog.steer([heading, 0.5])
        clock.t += 1.0 / rate
        cycles.append(prog.next(k, None).setpoints)
    # up to full field along the heading first (no roll below it), then rolling at half speed:
    # a = 2 pi (0.5 f_roll) t about z x d
    d = np.array([math.cos(math.radians(heading)), math.sin(math.radians(heading)), 0.0])
    for j, currents in enumerate(cycles[n_up - 1:]):  # the last cycle of the ramp: a = 0
        a = 2 * math.pi * 0.5 * fs.rolling_turns_per_s * j / rate
        wanted = b0 * (math.cos(a) * d - math.sin(a) * np.array([0.0, 0.0, 1.0]))
        np.testing.assert_allclose(A @ currents, wanted, atol=1e-9)
    assert np.linalg.norm(A @ cycles[n_up - 2]) < b0  # still ramping


def test_silence_for_200_ms_stops_the_input_and_the_currents_reach_zero():
    prog, drive, clock, record = session(SIX)
    prog.steer([0.0, 1.0])
    sent = clock.t
    out = run_for(prog, clock, 1.0)
    live = [k for k, s in enumerate(out) if np.any(s)]
    # driven while the input is fresh, then down to exactly 0 A within STOP_S (0.05 s) more
    silent_from = int(SILENCE_S * prog.rate_hz)
    assert np.any(out[silent_from - 1])
    zero_at = (live[-1] + 1) / prog.rate_hz
    assert SILENCE_S < zero_at <= SILENCE_S + 0.05 + 1.5 / prog.rate_hz
    assert all(not np.any(s) for s in out[live[-1] + 1:])
    assert [name for name, _ in record.events] == ["teleop_silence"]
    # the series: the input live, then not live (nan input), each with the stream's time
    assert [r[1] for r in record.rows] == [1.0, 0.0]
    assert record.rows[0][2:] == [0.0, 1.0] and all(math.isnan(v) for v in record.rows[1][2:])
    assert record.rows[1][0] - sent > SILENCE_S
    assert prog.finish(None).metrics["silence_stops"] == 1


def test_letting_go_stops_at_once_and_a_new_input_rolls_on():
    prog, drive, clock, record = session(SIX)
    prog.steer([0.0, 1.0])
    run_for(prog, clock, 0.1)
    prog.steer(None)
    out = run_for(prog, clock, 0.15, k0=10)
    assert not np.any(out[-1]) and np.any(out[0])
    assert [name for name, _ in record.events] == []  # let go is not the dead-man
    prog.steer([90.0, 1.0])
    assert np.any(run_for(prog, clock, 0.05, k0=30)[-1])


def test_end_brings_the_rig_to_rest_then_ends_done():
    prog, drive, clock, _ = session(SIX)
    prog.steer([0.0, 1.0])
    run_for(prog, clock, 0.1)
    prog.end()
    out = run_for(prog, clock, 0.2, k0=10)
    assert out[-1] is None
    assert prog.finish(None).reached is True


def test_the_board_pulls_in_whole_units_and_stops_in_the_cycle_the_input_goes_silent():
    prog, drive, clock, _ = session(BOARD)
    m = BOARD.board.max_command
    prog.steer([45.0, 0.5])  # +x and +y, half the limit each
    out = run_for(prog, clock, 0.3)
    assert out[0].tolist() == [round(0.5 * m), 0, round(0.5 * m), 0]
    prog.steer([180.0 + math.degrees(math.atan(0.5)), 1.0])  # -x full, -y half
    sent = clock.t
    assert run_for(prog, clock, 0.01, k0=30)[0].tolist() == [0, m, 0, round(0.5 * m)]
    out = run_for(prog, clock, 0.3, k0=31)
    first_zero = next(k for k, s in enumerate(out) if not np.any(s))
    # every coil at 0 in the first cycle more than 200 ms after the input, and from then on
    zero_after = sent + 0.01 + (first_zero + 1) / prog.rate_hz - sent
    assert SILENCE_S < zero_after <= SILENCE_S + 1.0 / prog.rate_hz + 1e-9
    assert all(not np.any(s) for s in out[first_zero:])


def test_inputs_are_clipped_to_their_ranges_and_bad_ones_refused():
    drive = rig_kind("six-coil").teleop(SIX, None)
    values, clipped = drive.clip({"heading_deg": 30.0, "speed": 3.0})
    assert values.tolist() == [30.0, 1.0] and clipped == ["speed"]
    with pytest.raises(ConfigError, match="heading_deg, speed"):
        drive.clip({"speed": 1.0})
    with pytest.raises(ConfigError, match="finite"):
        drive.clip({"heading_deg": float("nan"), "speed": 1.0})
    with pytest.raises(ConfigError, match="rolling or pair, not 'jog'"):
        rig_kind("six-coil").teleop(SIX, "jog")


def test_the_preflight_holds_for_any_input_and_refuses_a_rig_too_weak_for_it():
    checks = rig_kind("six-coil").teleop(SIX, None).checks()
    assert checks and all(c.passed for c in checks)
    weak = SIX.model_copy(update={"coils": [c.model_copy(update={"current_limit_A": 0.01})
                                            for c in SIX.coils]})
    refused = [c for c in rig_kind("six-coil").teleop(weak, None).checks() if not c.passed]
    assert refused and refused[0].check == "current"


def test_a_rig_kind_without_teleoperation_says_so_in_one_line():
    import dataclasses

    lab_kind = dataclasses.replace(rig_kind("coil-board"), name="lab", teleop=None)
    with pytest.raises(PlanError, match="this rig kind has no teleoperation"):
        lab_kind.builder("teleop")(TeleopPlan(rig="lab"), BOARD)


def test_pair_mode_makes_the_field_at_the_angle_and_the_pull_along_it():
    from rigctl.physics.coils import max_planar_gradient, u_actuation_matrix

    prog, drive, clock, _ = session(SIX, "pair")
    b0 = SIX.field.b0_mT * 1e-3
    g = max_planar_gradient(SIX, b0)
    A8 = u_actuation_matrix(SIX)
    heading = SIX.field.initial_heading_deg  # no turn to wait for
    for k in range(40):  # the pull slews to 0.5 within STOP_S (5 cycles at 100 Hz)
        prog.steer([heading, 0.5])
        clock.t += 1.0 / prog.rate_hz
        currents = prog.next(k, None).setpoints
    psi = math.radians(heading)
    wanted = np.array([b0 * math.cos(psi), b0 * math.sin(psi), 0.0, 0.5 * g, 0.0, 0.0, 0.5 * g, 0.0])
    np.testing.assert_allclose(A8 @ currents, wanted, atol=1e-9)
    assert all(c.passed for c in drive.checks())
    out = run_for(prog, clock, 0.5, k0=40)  # silent: U to zero
    assert not np.any(out[-1])


def depm_jog():
    """The depm bench rig's jog drive, from a pose of the example plan (a safe one), the one
    whose joints are farthest from their ranges' ends (0.31 rad)."""
    import json
    from pathlib import Path

    rig = rig_kind("depm").bench_rig()
    drive = rig_kind("depm").teleop(rig, None)
    plan = json.loads((Path(__file__).resolve().parents[2] / "plans" / "examples"
                       / "depm-plan.json").read_text())
    drive.start_at(np.array([arm["joints_rad"][183] for arm in plan["arms"]]))
    return drive


def test_the_arms_jog_both_magnets_along_the_input_keeping_their_moments():
    from rigctl.plans.depm_safety import violations
    from rigctl.rigs.depm.teleop import JOG_MM_S

    drive = depm_jog()
    q0 = drive.q.copy()
    before = [arm.epm_pose(q0[a]) for a, arm in enumerate(drive.arms)]
    poses = [drive.step(np.array([0.0, 0.0, 1.0])).reshape(2, 7) for _ in range(50)]  # 1 s
    q = poses[-1]
    for a, arm in enumerate(drive.arms):
        p, m = arm.epm_pose(q[a])
        moved_mm = (p - before[a][0]) * 1e3
        # up by the jog speed for 1 s, less what the acceleration cap takes at the start
        assert JOG_MM_S * 0.9 < moved_mm[2] <= JOG_MM_S * 1.0001, moved_mm
        assert np.abs(moved_mm[:2]).max() < 0.5 and np.abs(m - before[a][1]).max() < 1e-3
    qdot = np.diff(np.stack([q0, *poses]), axis=0) * drive.rate_hz
    assert (np.abs(qdot) <= drive.speed * (1 + 1e-9)).all()
    assert not violations(np.zeros(1), q[:, None, :], None, drive.arms, drive.limits)
    # no input: the joints hold where they are
    np.testing.assert_array_equal(drive.step(None), q.ravel())


def test_a_jog_into_a_constraint_stops_at_it_and_never_sends_a_pose_that_breaks_it():
    from rigctl.plans.depm_safety import violations

    drive = depm_jog()
    centre = np.array(drive.limits.centre_m)
    towards = centre - drive.arms[0].epm_pose(drive.q[0])[0]
    towards /= np.linalg.norm(towards)
    sent = []
    while drive.blocked is None and len(sent) < 2000:  # 40 s at 20 mm/s: far enough to meet one
        sent.append(drive.step(towards).reshape(2, 7))
    assert drive.blocked is not None
    held = drive.q.copy()
    for _ in range(10):  # pushing on: it stays where it stopped
        sent.append(drive.step(towards).reshape(2, 7))
    np.testing.assert_array_equal(sent[-1], held)
    print(f"stopped after {len(sent) - 10} cycles at: {drive.blocked}")
    q = np.stack(sent, axis=1)  # (2, T, 7)
    assert not violations(np.zeros(q.shape[1]), q, None, drive.arms, drive.limits)


def test_a_windings_warning_stops_the_input_and_ignores_it_from_then_on():
    prog, drive, clock, _ = session(SIX)
    prog.steer([0.0, 1.0])
    assert np.any(run_for(prog, clock, 0.15)[-1])
    prog.pause_to_cool()  # what the engine's heat watch calls at a winding's warning
    for k in range(15, 40):  # the operator keeps steering: nothing is driven any more
        prog.steer([0.0, 1.0])
        clock.t += 1.0 / prog.rate_hz
        setpoints = prog.next(k, None).setpoints
    assert not np.any(setpoints)


def test_a_board_session_is_replayed_as_the_particles_mean_displacement_per_heading_held():
    drive = rig_kind("coil-board").teleop(BOARD, None)
    nan = float("nan")
    # held +x from 1.0 s (renewed at 1.05), let go at 2.0; held +y from 3.0, let go at 3.5
    inputs = {"t_s": np.array([1.0, 1.05, 2.0, 3.0, 3.5]),
              "live": np.array([1.0, 1.0, 0.0, 1.0, 0.0]),
              "heading_deg": np.array([0.0, 0.0, nan, 90.0, nan]),
              "drive": np.array([0.5, 0.5, nan, 0.5, nan])}

    def at(t, a, b):
        return {"t": t, "event": "agents", "tracked": [a, b]}

    events = [at(0.9, [0, 0], [5, 5]), at(2.1, [4, 0], [7, 5]),  # +x: 4 and 2 mm
              at(2.9, [4, 0], [7, 5]), at(3.6, [4, 3], [7, 5])]  # +y: 3 mm, and 0 (on a wall)
    moves, notes = drive.moves_mm(inputs, events)
    np.testing.assert_allclose(moves, [[3.0, 0.0], [0.0, 1.5]])
    assert notes
