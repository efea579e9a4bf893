"""The stream loop's schedule: cycles on an absolute grid, and `wake` pulling the next one in."""

import time

from rigctl.stream import StreamLoop


def test_cycles_follow_the_schedule_and_stop_when_asked():
    starts = []

    def cycle(k):
        starts.append(time.perf_counter())
        return k < 4

    stats = StreamLoop(50.0).run(cycle)
    assert len(starts) == 5 and stats.cycles == 5
    gaps = [b - a for a, b in zip(starts, starts[1:])]
    # each cycle is due 20 ms after the previous one; a sleep never returns early
    assert all(g >= 0.0195 for g in gaps), gaps


def test_wake_runs_the_next_cycle_at_once_and_the_schedule_follows():
    loop = StreamLoop(2.0)  # a 500 ms period makes the difference unmistakable
    starts = []

    def cycle(k):
        starts.append(time.perf_counter())
        if k == 0:
            loop.wake()  # e.g. the supervisor releasing a hold
        return k < 2

    loop.run(cycle)
    early, regular = starts[1] - starts[0], starts[2] - starts[1]
    assert early < 0.25, early  # would be 0.5 s without the wake
    assert regular > 0.45, regular  # the schedule moved with the early cycle
