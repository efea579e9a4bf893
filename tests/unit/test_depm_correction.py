"""The dual-EPM run's Hall correction without a bench: the step towards a U that a known pose makes,
the noise threshold, joints at the end of their range, and the offsets' blend."""

from pathlib import Path

import numpy as np
import pytest

from rigctl.plans.depm import default_rig, joints_at
from rigctl.plans.schema import load_plan
from rigctl.rigs.depm.correction import (
    HoldOffsets,
    correction_step,
    kind_scales,
    model_U,
    significant_residual,
)

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "depm-plan.json"
RIG = default_rig()


def _hold_pose() -> np.ndarray:
    plan = load_plan(PLAN)
    return joints_at(plan, [plan.segments[3].reached_s + 1.0])[:, 0]  # (2, 7) at dBx/dx's hold


def test_steps_reach_the_U_of_a_pose_the_test_chose():
    q_true = _hold_pose()
    requested = model_U(RIG.arms, RIG.moment_Am2, q_true)  # what q_true makes, in the model
    q = q_true + np.random.default_rng(0).normal(0.0, 0.01, q_true.shape)  # 0.6 deg off
    scales = kind_scales([requested])
    first = np.max(np.abs(requested - model_U(RIG.arms, RIG.moment_Am2, q)) / scales)
    for _ in range(4):
        q = q + correction_step(RIG.arms, RIG.moment_Am2, q, requested,
                                model_U(RIG.arms, RIG.moment_Am2, q), scales)
    last = np.max(np.abs(requested - model_U(RIG.arms, RIG.moment_Am2, q)) / scales)
    assert first > 0.01 and last < 1e-3, (first, last)


def test_a_step_never_pushes_a_joint_past_its_range():
    q = _hold_pose()
    lower = np.array([a.model.lower_rad for a in RIG.arms])
    q[0, 1] = lower[0, 1]  # left A2 at its lower end
    requested = model_U(RIG.arms, RIG.moment_Am2, q) * 1.05  # 5 % more of everything
    dq = correction_step(RIG.arms, RIG.moment_Am2, q, requested,
                         model_U(RIG.arms, RIG.moment_Am2, q), kind_scales([requested]))
    assert (q + dq >= lower - 1e-12).all()
    assert np.abs(dq).max() > 0  # the others still move


def test_a_residual_within_the_noise_is_none():
    requested = np.array([10.0, 0, 0, 0, 0, 0, 0, 0])
    measured = np.array([9.9, 0.05, 0, 1.0, 0, 0, 0, 0])
    sem = np.array([0.02, 0.05, 0.02, 0.6, 0.6, 0.6, 0.6, 0.6])
    r = significant_residual(requested, measured, sem)
    assert r[0] == pytest.approx(0.1 - 2 * 0.02)
    assert r[1] == 0.0 and r[3] == 0.0  # within two standard errors


def test_the_offset_is_on_through_the_hold_then_blends_out_smoothly():
    lower, upper = np.full((2, 7), -3.0), np.full((2, 7), 3.0)
    offsets = HoldOffsets(np.array([1.0, 10.0]), np.array([4.0, 13.0]), lower, upper)
    dq = np.full((2, 7), 0.02)
    offsets.offsets[0] = dq
    assert offsets.at(0.5) is None  # before the hold
    np.testing.assert_allclose(offsets.at(1.0), dq)
    np.testing.assert_allclose(offsets.at(4.0), dq)
    np.testing.assert_allclose(offsets.at(7.0), dq / 2)  # halfway through the blend
    assert np.abs(offsets.at(9.99)).max() < 1e-6  # gone by the next hold
    assert offsets.at(10.0) is None
    # the blend's slope is zero at both of its ends (a cosine)
    h = 1e-4
    assert np.abs(offsets.at(4.0 + h) - dq).max() < 1e-8
    # the last window's correction stays on to the plan's end; poses stay inside the ranges
    offsets.offsets[1] = np.full((2, 7), 0.5)
    np.testing.assert_allclose(offsets.at(20.0), 0.5)
    assert (offsets.apply(12.0, np.full((2, 7), 2.8)) <= 3.0).all()
