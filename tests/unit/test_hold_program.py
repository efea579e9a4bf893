"""The manual hold's program stepped by hand: its ramps, retargets and releases against values
worked out here (straight lines between setpoints, one sample per stream cycle), the board's whole
drive units, the arms' rest where they stand, and what it refuses."""

import numpy as np
import pytest

from rigctl.core.config import CoilBoardSettings, RigInfo, StreamSettings
from rigctl.core.errors import LimitError, RigError
from rigctl.rigs.coil_board.settings import CoilBoardRig
from rigctl.run.engine import RunContext
from rigctl.run.hold import HoldPlan, HoldProgram, HoldRequest, ramp_samples


class Events:
    def __init__(self) -> None:
        self.events: list[tuple[str, dict]] = []

    def event(self, name: str, **fields) -> None:
        self.events.append((name, fields))


RIG = CoilBoardRig(rig=RigInfo(kind="coil-board", name="unit"), board=CoilBoardSettings(url="/dev/null"),
                stream=StreamSettings(rate_hz=100.0, ramp_down_s=0.03))


def program(setpoints, *, rate_hz=100.0, ramp_s=0.04, step=0.0, pose=None, check=None):
    request = HoldRequest({"drive": list(setpoints)}, np.asarray(setpoints, dtype=float),
                          connect=None, rate_hz=rate_hz, late="slip",
                          check_ramp=check or (lambda start, ramp_s: None),
                          pose_now=None if pose is None else (lambda actuators: pose), step=step)
    prog = HoldProgram(HoldPlan(rig="coil-board", target=request.target, ramp_s=ramp_s), RIG,
                       request)
    record = Events()
    prog.start(RunContext(RIG, record, None, lambda text: None))
    prog.connected(None)
    return prog, record


def stream(prog, ks):
    out = []
    for k in ks:
        step = prog.next(k, None)
        out.append(None if step is None else step.setpoints.tolist())
    return out


def test_the_ramp_is_straight_from_zero_over_ramp_s_then_holds():
    # 0.04 s at 100 Hz: four samples, a quarter of the way each, then the target held
    prog, _ = program([8.0, -4.0])
    assert stream(prog, range(6)) == [[2.0, -1.0], [4.0, -2.0], [6.0, -3.0], [8.0, -4.0],
                                      [8.0, -4.0], [8.0, -4.0]]


def test_a_retarget_while_ramping_ramps_from_the_setpoint_of_the_moment():
    prog, record = program([8.0])
    assert stream(prog, range(2)) == [[2.0], [4.0]]
    prog.retarget({"drive": [-2.0]}, [-2.0], 0.02)  # from 4 to -2 in two samples: 1, then -2
    assert stream(prog, range(2, 5)) == [[1.0], [-2.0], [-2.0]]
    assert [name for name, _ in record.events] == ["hold", "hold"]
    assert record.events[1][1]["target"] == {"drive": [-2.0]}
    assert prog.finish(None).metrics["retargets"] == 1


def test_skipped_cycles_advance_the_ramp_by_the_time_they_stood_for():
    prog, _ = program([10.0], ramp_s=0.05)  # five samples of 2
    assert stream(prog, [0, 3, 4]) == [[2.0], [8.0], [10.0]]  # k jumped from 0 to 3


def test_release_ramps_to_zero_then_ends_and_counts_as_done():
    prog, record = program([6.0])
    stream(prog, range(4))
    prog.release(0.03)  # three samples from 6 to 0
    assert stream(prog, range(4, 8)) == [[4.0], [2.0], [0.0], None]
    assert record.events[-1][0] == "release"
    outcome = prog.finish(None)
    assert outcome.reached is True and not prog.aborted


def test_abort_ramps_down_over_the_rigs_ramp_down_and_is_not_done():
    prog, _ = program([6.0])
    stream(prog, range(4))
    prog.abort()  # ramp_down_s 0.03: three samples
    assert stream(prog, range(4, 8)) == [[4.0], [2.0], [0.0], None]
    assert prog.aborted and prog.finish(None).reached is False


def test_the_board_gets_whole_drive_units_all_along_the_ramp():
    prog, _ = program([10.0], ramp_s=0.03, step=1.0)  # 10/3, 20/3, 10 rounded: 3, 7, 10
    assert stream(prog, range(3)) == [[3.0], [7.0], [10.0]]


def test_the_arms_start_from_their_pose_and_a_release_stops_there():
    pose = np.array([0.5, -0.5])
    prog, _ = program([1.0, 0.5], ramp_s=0.02, pose=pose)  # two samples from the pose
    assert stream(prog, range(2)) == [[0.75, 0.0], [1.0, 0.5]]
    prog.release(1.0)
    assert stream(prog, [2]) == [None]  # no ramp: they stay where they are


def test_the_first_ramp_is_checked_from_where_the_actuators_stand():
    seen = []

    def check(start, ramp_s):
        seen.append((start.tolist(), ramp_s))
        raise LimitError("too fast")

    with pytest.raises(LimitError):
        program([1.0, 0.5], ramp_s=0.2, pose=np.array([0.3, 0.1]), check=check)
    assert seen == [([0.3, 0.1], 0.2)]


def test_pause_and_resume_are_refused_with_a_line_saying_to_release():
    prog, _ = program([1.0])
    for call in (lambda: prog.pause(True), prog.resume):
        with pytest.raises(RigError, match="cannot be paused: release it"):
            call()


def test_a_ramp_is_never_shorter_than_asked():
    assert ramp_samples(0.0, 100.0) == 1
    assert ramp_samples(0.04, 100.0) == 4
    assert ramp_samples(0.041, 100.0) == 5  # 4 samples would be 0.04 s, shorter than asked
