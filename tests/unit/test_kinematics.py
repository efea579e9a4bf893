"""KUKA LBR iiwa 14 R820 kinematics: forward kinematics against hand-computed poses, the IK round
trip, joint ranges respected, and the IK staying at the previous pose when that already works."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.physics.kinematics import (
    LBR_IIWA_14_R820,
    ArmKinematics,
    base_transform,
    default_arms,
)

# Link lengths of the 14 R820 written out (KUKA): base-shoulder, shoulder-elbow, elbow-wrist,
# wrist-flange; and our EPM tool offset.
D1, D3, D5, D7, TOOL = 0.360, 0.420, 0.400, 0.126, 0.085


def test_straight_up_at_zero():
    base = np.array([0.3, -0.2, -0.5])
    arm = ArmKinematics(base=base_transform(base), name="t")
    origins = arm.frames(np.zeros(7))[:, :3, 3]
    heights = [0, D1, D1, D1 + D3, D1 + D3, D1 + D3 + D5, D1 + D3 + D5, D1 + D3 + D5 + D7,
               D1 + D3 + D5 + D7 + TOOL]
    np.testing.assert_allclose(origins, base + np.array([[0, 0, h] for h in heights]), atol=1e-12)
    position, moment = arm.epm_pose(np.zeros(7))
    np.testing.assert_allclose(moment, [1, 0, 0], atol=1e-12)  # the moment along the base x axis


def test_shoulder_and_elbow_bends_by_hand():
    arm = ArmKinematics(name="t")
    # A2 = +90 deg turns everything above the shoulder about +y: the arm points along +x.
    q = np.zeros(7)
    q[1] = np.pi / 2
    position, _ = arm.epm_pose(q)
    np.testing.assert_allclose(position, [D3 + D5 + D7 + TOOL, 0, D1], atol=1e-12)
    # ... and A1 = +90 deg then swings it about the vertical onto +y.
    q[0] = np.pi / 2
    position, _ = arm.epm_pose(q)
    np.testing.assert_allclose(position, [0, D3 + D5 + D7 + TOOL, D1], atol=1e-12)
    # A4 = +90 deg bends only the forearm, at the elbow's height.
    q = np.zeros(7)
    q[3] = np.pi / 2
    position, _ = arm.epm_pose(q)
    np.testing.assert_allclose(position, [D5 + D7 + TOOL, 0, D1 + D3], atol=1e-12)


def test_base_pose_is_applied_and_frames_are_rotations():
    left, right = default_arms()
    rng = np.random.default_rng(1)
    q = rng.uniform(LBR_IIWA_14_R820.lower_rad, LBR_IIWA_14_R820.upper_rad, size=(5, 7))
    frames = right.frames(q)
    rotations = frames[..., :3, :3]
    identity = np.broadcast_to(np.eye(3), rotations.shape)
    np.testing.assert_allclose(rotations @ np.swapaxes(rotations, -1, -2), identity, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-12)
    # The right arm is the left one turned 180 deg about z (at its own base): x, y flip.
    local_left = np.linalg.inv(left.base) @ left.frames(q)[..., 8, :, :]
    local_right = np.linalg.inv(right.base) @ frames[..., 8, :, :]
    np.testing.assert_allclose(local_left, local_right, atol=1e-12)


def test_origin_jacobians_match_finite_differences():
    arm = default_arms()[0]
    q = np.array([0.3, 1.1, -0.4, -1.3, 0.5, 0.8, -0.2])
    jac = arm._origin_jacobians(arm.frames(q))
    h = 1e-7
    for j in range(7):
        step = np.zeros(7)
        step[j] = h
        numeric = (arm.frames(q + step)[:, :3, 3] - arm.frames(q - step)[:, :3, 3]) / (2 * h)
        np.testing.assert_allclose(jac[:, :, j], numeric, atol=1e-7)


def test_inverse_kinematics_round_trip_within_limits():
    arm = default_arms()[0]
    rng = np.random.default_rng(2)
    lower, upper = arm.model.lower_rad, arm.model.upper_rad
    for _ in range(8):
        q_true = rng.uniform(0.8 * lower, 0.8 * upper)
        position, moment = arm.epm_pose(q_true)
        seed = np.clip(q_true + rng.normal(scale=0.15, size=7), lower, upper)
        result = arm.solve(position, moment, seed)
        assert result.ok, (result.position_error_m, result.direction_error_rad)
        got_p, got_m = arm.epm_pose(result.q)
        np.testing.assert_allclose(got_p, position, atol=1e-4)
        assert np.degrees(np.arccos(np.clip(got_m @ moment, -1, 1))) < 0.06
        assert np.all(result.q >= lower) and np.all(result.q <= upper)


def test_inverse_kinematics_keeps_the_previous_pose_when_it_already_works():
    arm = default_arms()[1]
    q = np.array([0.2, 0.9, 0.1, -1.4, 0.3, 0.7, -0.5])
    position, moment = arm.epm_pose(q)
    result = arm.solve(position, moment, q)
    np.testing.assert_allclose(result.q, q, atol=1e-6)


def test_inverse_kinematics_uses_the_moment_axis_freedom():
    """Two targets that differ only by the moment's sign are both reached (joint 7 half a turn)."""
    arm = default_arms()[0]
    q = np.array([0.1, 1.0, 0.0, -1.3, 0.0, 0.6, 0.0])
    position, moment = arm.epm_pose(q)
    flipped = arm.solve(position, -moment, q)
    assert flipped.ok
    np.testing.assert_allclose(arm.epm_pose(flipped.q)[1], -moment, atol=1e-3)


def test_unreachable_target_is_refused_with_the_arm_named():
    from rigctl.core.errors import LimitError

    arm = default_arms()[0]
    with pytest.raises(LimitError, match="left"):
        arm.solve_or_raise([2.0, 0.0, 0.0], [0, 0, 1], np.zeros(7))


def test_one_joint_vector_gives_the_same_frames_as_a_batch():
    """`frames` of a single (7,) vector takes a faster path; it must agree with the batched one
    (which the hand-worked tests above check) bit for bit, so plans do not depend on the path."""
    arm = default_arms()[1]  # the turned base
    q = np.random.default_rng(3).uniform(-2.0, 2.0, (20, 7))
    batch = arm.frames(q)
    for i in range(len(q)):
        np.testing.assert_array_equal(arm.frames(q[i]), batch[i])
