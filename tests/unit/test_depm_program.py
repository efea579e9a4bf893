"""The field-sequence program's refusals (no I/O: nothing is opened) and its stalled-joint check."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from rigctl.core.config import Emulation, RigConfig, RigInfo
from rigctl.core.errors import ConfigError, LimitError
from rigctl.emulators.depm import default_settings
from rigctl.plans.schema import load_plan
from rigctl.rigs.depm.run import (
    FieldSequenceProgram,
    SafetyRefusal,
    _Tracking,
    stream_rates,
)
from rigctl.rigs.depm.settings import DepmRig

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "depm-plan.json"


def rig(emulated: bool = True, **depm) -> RigConfig:
    return DepmRig(rig=RigInfo(kind="depm", name="test"),
                     depm=default_settings().model_copy(update=depm),
                     emulation=Emulation(backdoor="tcp://127.0.0.1:1") if emulated else None)


def test_the_shipped_plan_is_accepted_with_its_rates():
    program = FieldSequenceProgram(load_plan(PLAN), rig(), time_scale=6.0)
    assert program.late == "skip"
    # 100 targets per real second at most: 100 / 6 per plan second, 6 x that per real second
    assert program.plan_rate_hz == pytest.approx(100 / 6)
    assert program.rate_hz == pytest.approx(100.0)
    assert program.info["segments"] == 8 and program.n_moves == 8
    assert stream_rates(50.0, 1.0) == (50.0, 50.0)


def test_a_plan_outside_the_rigs_limits_is_refused_naming_every_violation():
    # the same plan on a rig whose keep-out sphere is 40 cm: the magnets come closer than that
    with pytest.raises(SafetyRefusal) as refusal:
        FieldSequenceProgram(load_plan(PLAN), rig(keep_out_radius_mm=400.0))
    err = refusal.value
    assert isinstance(err, LimitError)  # exit 2 from the CLI
    assert err.violations and all(v.limit == pytest.approx(400.0) for v in err.violations
                                  if v.constraint.startswith("inside the keep-out"))
    text = str(err)
    assert "refused, nothing moved" in text
    assert text.count("t = ") == min(len(err.violations), 10)


def test_a_plan_for_other_geometry_or_a_time_scale_on_real_hardware_is_refused():
    moved = default_settings().arm_positions_mm
    moved = [(x + 10.0, y, z) for x, y, z in moved]
    with pytest.raises(ConfigError, match="re-plan for this rig"):
        FieldSequenceProgram(load_plan(PLAN), rig(arm_positions_mm=moved))
    with pytest.raises(ConfigError, match="emulated benches only"):
        FieldSequenceProgram(load_plan(PLAN), rig(emulated=False), time_scale=4.0)


def test_tracking_faults_a_joint_that_stays_behind_not_one_that_catches_up():
    tolerance = math.radians(5.0)
    stalled = _Tracking(tolerance)
    lag = np.zeros(7)
    lag[3] = math.radians(8.0)
    results = [stalled.update(t, lag) for t in np.arange(0.0, 0.6, 0.02)]
    assert all(r is None for r in results[:25])  # behind for 0.5 s and less: not yet
    j, behind, since = next(r for r in results if r is not None)
    assert (j, since) == (3, 0.0) and behind == pytest.approx(math.radians(8.0))
    racing = _Tracking(tolerance)
    # far behind, but gaining 8 deg/s (half the tolerance every 0.31 s): it catches up
    for t in np.arange(0.0, 2.0, 0.02):
        lag = np.zeros(7)
        lag[0] = max(math.radians(20.0 - 8.0 * t), 0.0)
        assert racing.update(t, lag) is None
