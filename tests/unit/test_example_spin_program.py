"""The example rig kind's spin-sequence plan and program (examples/rigctl-grbl-spinner), with no
I/O: the pre-flight's limits, and the setpoints a run streams (never faster a change than the
rig's acceleration, zero while paused, the segment's remainder after a resume)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples" / "rigctl-grbl-spinner" / "src"))

from rigctl_grbl_spinner import KIND  # noqa: E402
from rigctl_grbl_spinner.settings import GrblSettings, SpinnerConfig  # noqa: E402
from rigctl_grbl_spinner.spin import SpinProgram, parse_spin_plan, spin_checks  # noqa: E402

from rigctl.core.config import RigInfo  # noqa: E402
from rigctl.core.errors import ConfigError, LimitError, PlanError  # noqa: E402

# the package is imported from its source folder, not installed here: the registry does not know
# the kind, which the rig file's checks ask it, so the rig is put together unchecked ([grbl],
# what the program and hold read, is validated)
RIG = SpinnerConfig.model_construct(rig=RigInfo.model_construct(kind="grbl-spinner", name="test"),
                                    grbl=GrblSettings(url="/dev/null"))


def plan(*segments, **extra):
    return parse_spin_plan({"schema": "rigctl.plan/1", "kind": "spin-sequence",
                            "rig": "grbl-spinner", **extra,
                            "segments": [{"rate_hz": r, "duration_s": d} for r, d in segments]})


def test_a_rate_beyond_the_rig_and_a_segment_too_short_to_reach_its_rate_are_refused():
    checks = spin_checks(plan((6.0, 5.0), (-4.0, 0.3)), RIG)
    refused = [c for c in checks if not c.passed]
    assert [(c.check, c.subject) for c in refused] == [("rotation rate", "segment 1"),
                                                       ("segment duration", "segment 2")]
    # 10 Hz of change at 20 Hz/s, 4 Hz's queue 4 / 40 s, 0.06 s lead, 3 cycles, 0.2 s judged
    assert refused[1].limit == pytest.approx(0.5 + 0.1 + 0.06 + 0.06 + 0.2)


def test_a_plan_of_another_shape_is_refused_naming_the_field():
    with pytest.raises(PlanError, match=r"segments\.0\.duration_s"):
        plan((1.0, -1.0))


def test_setpoints_change_at_the_rigs_acceleration_and_rest_at_the_end():
    program = SpinProgram(plan((2.0, 1.0), (-1.0, 1.0)), RIG)
    values = []
    k = 0
    while (step := program.next(k, None)) is not None:
        values.append(step.setpoints[0])
        k += 1
    values = np.array(values)
    assert np.abs(np.diff(np.r_[0.0, values])).max() <= 20.0 / 50.0 + 1e-12
    assert values.max() == pytest.approx(2.0) and values.min() == pytest.approx(-1.0)
    assert values[-1] == 0.0
    # the plan's 2 s at 50 cycles/s, and the last ramp of 1 Hz at 0.4 Hz a cycle (3 cycles)
    assert len(values) == 100 + 3


def test_a_pause_now_holds_zero_and_the_segment_goes_on_after_resume():
    program = SpinProgram(plan((1.0, 1.0)), RIG)
    for k in range(25):
        program.next(k, None)
    t_paused = program.t_s
    program.pause(immediate=True)
    held = [program.next(25 + k, None).setpoints[0] for k in range(20)]
    assert held[-1] == 0.0 and program.t_s == t_paused
    program.resume()
    rest = []
    while (step := program.next(45 + len(rest), None)) is not None:
        rest.append(step.setpoints[0])
    assert max(rest) == pytest.approx(1.0)
    assert len(rest) == 25 + 3  # the half segment left, then to rest


def test_hold_takes_a_rate_within_the_rigs_limit():
    request = KIND.hold(RIG, {"rate_hz": [1.5]})
    assert request.setpoints.tolist() == [1.5]
    with pytest.raises(LimitError, match="beyond the rig's max_rate_hz 5"):
        KIND.hold(RIG, {"rate_hz": [-5.5]})
    with pytest.raises(ConfigError, match="rate_hz"):
        KIND.hold(RIG, {"field_mT": [1, 0, 0]})
