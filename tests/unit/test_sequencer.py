"""Run control on the stream thread: what the sequencer sends when a run is paused, resumed and
aborted. Sequences worked out by hand on a 10-sample, one-coil program."""

import numpy as np

from rigctl.rigs.six_coil.allocate import CurrentProgram
from rigctl.rigs.six_coil.sequencer import Sequencer


def make(ramp_samples=2):
    program = CurrentProgram(
        t_s=np.arange(10) * 0.01,
        currents_A=np.arange(1.0, 11.0).reshape(10, 1),
        segment=np.array([0, 0, 0, 1, 1, 1, 2, 2, 2, -1]),
        coil_names=("x+",),
    )
    return Sequencer(program, move_ends=[3, 6, 9], ramp_samples=ramp_samples)


def take(seq, n):
    out = []
    for _ in range(n):
        step = seq.next()
        out.append(None if step is None else float(step[0][0]))
    return out


def test_plays_the_program_then_finishes():
    seq = make()
    assert take(seq, 11) == [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, None]


def test_pause_waits_for_the_end_of_the_move_and_holds():
    seq = make()
    assert take(seq, 1) == [1]
    seq.requests.pause()
    # samples 2 and 3 finish move 0 (it ends at index 3), then the field holds at 3
    assert take(seq, 5) == [2, 3, 3, 3, 3]
    assert seq.paused
    seq.requests.resume()
    assert take(seq, 3) == [4, 5, 6]
    assert not seq.paused


def test_immediate_pause_ramps_down_and_resume_ramps_back():
    seq = make(ramp_samples=2)
    assert take(seq, 5) == [1, 2, 3, 4, 5]
    seq.requests.pause(immediate=True)
    assert take(seq, 4) == [2.5, 0, 0, 0]
    seq.requests.resume()
    # ramp from 0 to the next program sample (6) in two samples, then carry on
    assert take(seq, 5) == [3, 6, 6, 7, 8]


def test_abort_ramps_to_zero_and_ends():
    seq = make(ramp_samples=2)
    assert take(seq, 4) == [1, 2, 3, 4]
    seq.requests.abort()
    assert take(seq, 3) == [2, 0, None]
    assert seq.aborted


def test_abort_while_paused():
    seq = make(ramp_samples=4)
    take(seq, 3)
    seq.requests.pause()
    assert take(seq, 2) == [3, 3]
    seq.requests.abort()
    assert take(seq, 5) == [2.25, 1.5, 0.75, 0, None]


def test_a_pause_to_cool_finishes_the_move_then_ramps_off_and_back_up_on_resume():
    seq = make()
    assert take(seq, 1) == [1]
    seq.requests.pause(field_off=True)  # a winding at its warning
    # the move ends at index 3 (samples 2, 3), then a 2-sample ramp from 3 A to 0, then 0 held
    assert take(seq, 6) == [2, 3, 1.5, 0, 0, 0]
    assert seq.paused
    seq.requests.resume()
    # back up to the next sample (4 A) in 2 samples, then the program goes on from it (as after
    # a pause now)
    assert take(seq, 4) == [2, 4, 4, 5]
    assert not seq.paused


def test_a_pause_now_taken_back_before_it_took_effect_leaves_the_next_pause_a_plain_one():
    seq = make()
    assert take(seq, 1) == [1]
    seq.requests.pause(immediate=True)
    seq.requests.resume()  # before the stream thread saw the pause
    seq.requests.pause()
    # a plain pause: move 0 finishes (samples 2, 3) and the field holds there, no ramp to zero
    assert take(seq, 4) == [2, 3, 3, 3]
