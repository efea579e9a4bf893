"""The benches' one simulated clock: simulated seconds are real seconds elapsed times the speed
factor, and a new speed applies from the instant it is set (nothing elapsed jumps)."""

from __future__ import annotations

import math

import pytest

from rigctl.core.errors import ConfigError
from rigctl.emulators.base import SimClock, bench_class


class FakeMonotonic:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_speed_changes_mid_run_bend_the_simulated_time_at_that_instant() -> None:
    real = FakeMonotonic(100.0)
    clock = SimClock(2.0, monotonic=real)
    assert clock.now() == 0.0 and clock.speed == 2.0
    real.t = 101.5
    assert clock.now() == pytest.approx(3.0)  # 1.5 s at 2x
    real.t = 102.0
    clock.set_speed(0.5)  # 4.0 simulated seconds so far
    assert clock.now() == pytest.approx(4.0) and clock.speed == 0.5
    real.t = 106.0
    assert clock.now() == pytest.approx(6.0)  # + 4 s at 0.5x
    clock.set_speed(10.0)
    real.t = 106.25
    assert clock.now() == pytest.approx(8.5)  # + 0.25 s at 10x
    clock.set_speed(10.0)  # the same speed again changes nothing
    real.t = 106.5
    assert clock.now() == pytest.approx(11.0)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan])
def test_a_speed_that_is_not_positive_is_refused_and_changes_nothing(bad: float) -> None:
    real = FakeMonotonic(0.0)
    with pytest.raises(ValueError, match="speed factor must be positive"):
        SimClock(bad, monotonic=real)
    clock = SimClock(3.0, monotonic=real)
    real.t = 1.0
    with pytest.raises(ValueError, match="speed factor must be positive"):
        clock.set_speed(bad)
    real.t = 2.0
    assert clock.now() == pytest.approx(6.0) and clock.speed == 3.0


def test_every_rig_kind_has_its_bench_class() -> None:
    from rigctl.emulators.bench import SixCoilBench
    from rigctl.emulators.coilboard.bench import CoilBoardBench
    from rigctl.emulators.depm import DepmBench

    assert [bench_class(kind) for kind in ("six-coil", "coil-board", "depm")] == [
        SixCoilBench, CoilBoardBench, DepmBench]
    with pytest.raises(ConfigError, match="no emulated bench for rig kind 'maglev'; there are "
                       "coil-board, depm, six-coil"):
        bench_class("maglev")
