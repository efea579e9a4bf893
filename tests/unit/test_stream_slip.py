"""The stream loop after a stall: the schedule slips, the samples after it are never bunched.

A field program is a path in time: sending the samples that a stall held back at full speed turns
the field many times faster than the realizer allowed, and the coils' L/R lag then cuts the
corners of the path: under load, fig4-two-magnets ended 0.22 mm off that way, and once past
the end-to-end test's 0.5 mm.
"""

import time

from rigctl.core.stream import StreamLoop

PERIOD_S = 0.02
STALL_PERIODS = 5


def test_after_a_stall_cycles_keep_at_least_half_a_period_apart_and_the_slip_is_reported():
    starts = []

    def cycle(k):
        starts.append(time.perf_counter())
        if k == 1:
            # the stream thread held up for five periods (a busy machine, a slow device reply)
            time.sleep(STALL_PERIODS * PERIOD_S)
        return k < 6

    stats = StreamLoop(1.0 / PERIOD_S, late_fraction=0.5).run(cycle)
    assert stats.cycles == 7
    gaps = [b - a for a, b in zip(starts, starts[1:])]
    # Lower bounds only: a loaded machine can make a cycle later, never earlier. With catch-up,
    # cycles 2..5 started back to back (gaps of microseconds).
    assert all(gap >= 0.5 * PERIOD_S for gap in gaps), gaps
    # cycle 2 was due one period after cycle 1 began and started after the stall: it moved the
    # schedule back by at least the stall less that period
    assert stats.late_cycles >= 1
    assert stats.slip_s >= (STALL_PERIODS - 1) * PERIOD_S, stats
    assert stats.as_dict()["slip_s"] == stats.slip_s

