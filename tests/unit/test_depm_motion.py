"""The dual-EPM run's servo targets (`rigctl.rigs.depm.motion`): the approach timed within the
rig's caps (checked by numerical differentiation against the data-sheet speeds), and the timeline's
holds, rejoins and skipped cycles on hand-made curves with known values."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.physics.kinematics import default_arms
from rigctl.plans.depm_safety import SafetyLimits
from rigctl.rigs.depm.motion import Timeline, approach_path, caps, path_violations

DEG = np.pi / 180
# LBR iiwa 14 R820 data sheet: joint speeds (deg/s); the acceleration of 10 rad/s^2 is assumed
SPEED_CAP = 0.3 * np.array([85.0, 85.0, 100.0, 75.0, 130.0, 135.0, 135.0]) * DEG
ACCEL_CAP = 0.5 * 10.0
Q_START = np.array([[0.3, 0.6, -0.2, -1.1, 0.4, 0.9, 0.5],
                    [-0.2, 0.5, 0.1, -1.2, -0.3, 0.8, -0.6]])


def test_approach_moves_one_arm_then_the_other_within_the_caps():
    arms = default_arms()
    q_now = np.zeros((2, 7))
    path = approach_path(q_now, Q_START, arms, SafetyLimits())
    dt = 1e-3
    t = np.arange(0.0, path.duration_s + dt / 2, dt)
    q, _, _ = path.sample(t)
    np.testing.assert_allclose(q[:, 0], q_now)
    np.testing.assert_allclose(q[:, -1], Q_START, atol=1e-9)
    speed = np.abs(np.diff(q, axis=1)) / dt  # (2, T - 1, 7), independent of the path's own qd
    accel = np.abs(np.diff(q, 2, axis=1)) / dt ** 2
    assert np.all(speed <= SPEED_CAP * (1 + 1e-6))
    assert np.all(accel <= ACCEL_CAP * (1 + 1e-3))
    # as fast as the caps allow (2 % margin): some joint reaches 98 % of its cap
    assert np.max(speed / SPEED_CAP) == pytest.approx(1 / 1.02, rel=2e-3)
    # the left arm first: the right one stays parked until the left one has arrived
    left_done = np.flatnonzero(np.all(np.abs(q[0] - Q_START[0]) < 1e-12, axis=1))[0]
    right_moves = np.flatnonzero(np.any(np.abs(q[1]) > 0, axis=1))[0]
    assert right_moves >= left_done
    # every joint of an arm starts and stops together (a synchronised move): the fraction of
    # the way done is the same for all of them
    left = q[0, :left_done] / Q_START[0]
    np.testing.assert_allclose(left, left[:, :1] * np.ones(7), atol=1e-9)


def test_approach_through_the_keep_out_sphere_is_named():
    arms = default_arms()
    seed = np.array([0, 0.5, 0, -1.2, 0, 0.8, 0.0])
    inside = arms[0].solve(np.array([-0.10, 0.0, 0.0]), np.array([0, 0, 1.0]), seed).q
    q_now = np.array([inside, Q_START[1]])
    found = path_violations(approach_path(q_now, Q_START, arms, SafetyLimits()), arms, SafetyLimits())
    assert any(v.arm == "left" and v.part == "EPM" and v.time_s == 0.0 for v in found), found


def curves_through(q0: np.ndarray, rate: np.ndarray):
    """Two arms' joints moving at constant rates: q(t) = q0 + rate t (known in closed form)."""
    return [lambda t, a=a: q0[a] + rate[a] * t for a in range(2)]


def test_timeline_holds_rejoins_and_skips():
    arms = default_arms()
    q0 = Q_START
    rate = np.full((2, 7), 0.01)  # rad per plan second
    speed, accel = caps(arms, SafetyLimits())
    approach = approach_path(q0, q0, arms, SafetyLimits())  # already there: no approach
    assert approach.duration_s == 0.0
    tl = Timeline(approach, curves_through(q0, rate), 2.0, 12.0, speed, accel)
    dt = 0.02
    np.testing.assert_allclose(tl.advance(0.0), q0 + rate * 2.0)
    for _ in range(50):
        target = tl.advance(dt)
    assert tl.plan_time_s == pytest.approx(3.0)
    np.testing.assert_allclose(target, q0 + rate * 3.0)
    # a hold at the present target: the clock stands, the target is the same
    tl.hold(target)
    for _ in range(10):
        np.testing.assert_allclose(tl.advance(dt), target)
    assert tl.plan_time_s == pytest.approx(3.0)
    tl.release()
    assert tl.rejoin is None  # held on the path: it runs on from where it stopped
    np.testing.assert_allclose(tl.advance(dt), q0 + rate * 3.02)
    # a hold off the path (pause now: the measured pose): released, it rejoins the path first
    off = q0 + rate * 3.02 - 0.01
    tl.hold(off)
    tl.advance(dt)
    tl.release()
    assert tl.rejoin is not None and tl.rejoins == 1
    rejoin_s = tl.rejoin.duration_s
    np.testing.assert_allclose(tl.advance(0.0), off)
    steps = int(np.ceil(rejoin_s / dt))
    for _ in range(steps):
        target = tl.advance(dt)
    # the plan's clock ran only for what was left of the last cycle after the rejoin ended
    assert tl.plan_time_s == pytest.approx(3.02 + steps * dt - rejoin_s)
    np.testing.assert_allclose(target, q0 + rate * tl.plan_time_s)
    # late cycles skipped: the target jumps to where the plan is now
    before = tl.plan_time_s
    np.testing.assert_allclose(tl.advance(4 * dt), q0 + rate * (before + 4 * dt))
    # the end: the last target is the plan's last pose, then it is finished
    while not tl.finished:
        target = tl.advance(dt)
    np.testing.assert_allclose(target, q0 + rate * 12.0)


def test_timeline_starts_with_the_approach():
    arms = default_arms()
    speed, accel = caps(arms, SafetyLimits())
    approach = approach_path(np.zeros((2, 7)), Q_START, arms, SafetyLimits())
    tl = Timeline(approach, curves_through(Q_START, np.zeros((2, 7))), 0.0, 5.0, speed, accel)
    np.testing.assert_allclose(tl.advance(0.0), 0.0)
    assert tl.in_approach and tl.plan_time_s == pytest.approx(-approach.duration_s)
    mid = tl.advance(approach.duration_s / 2)
    np.testing.assert_allclose(mid, approach.at(approach.duration_s / 2))
    tl.advance(approach.duration_s / 2)
    assert not tl.in_approach and tl.plan_time_s == pytest.approx(0.0)
    np.testing.assert_allclose(tl.advance(0.0), Q_START)


def test_an_approach_whose_straight_way_cuts_the_keep_out_sphere_goes_round_by_the_candle():
    """Where the example plan ends, its next run begins: the straight joint-space way from there
    to its first pose, one arm after the other in either order, passes within the keep-out
    sphere; the approach retreats to the candle first and keeps every constraint."""
    import json
    from pathlib import Path

    from rigctl.rigs.depm.motion import joint_path

    plan = json.loads((Path(__file__).resolve().parents[2] / "plans" / "examples"
                       / "depm-plan.json").read_text())
    q_end = np.array([arm["joints_rad"][-1] for arm in plan["arms"]])
    q_start = np.array([arm["joints_rad"][0] for arm in plan["arms"]])
    arms, limits = default_arms(), SafetyLimits()
    speed, accel = caps(arms, limits)
    for order in ([0, 1], [1, 0]):  # the straight ways, built leg by leg here
        straight = joint_path(q_end[order], q_start[order], speed[order], accel[order],
                              one_at_a_time=True)
        assert path_violations(straight, [arms[i] for i in order], limits)
    path = approach_path(q_end, q_start, arms, limits)
    assert path_violations(path, arms, limits) == []
    q, _, _ = path.sample(np.array([0.0, path.duration_s]))
    np.testing.assert_allclose(q[:, 0], q_end, atol=1e-12)
    np.testing.assert_allclose(q[:, -1], q_start, atol=1e-9)
    # by way of the candle: at the end of some leg both arms stand with every joint at 0
    q, _, _ = path.sample(np.array([leg.start_s + leg.duration_s for leg in path.legs]))
    assert np.any(np.all(np.abs(q) < 1e-9, axis=(0, 2)))
