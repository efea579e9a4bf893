"""Realizing global moves as a rotating-field program on the six-coil rig (seed 000 eq. 1-2).

Expected values are worked out by hand from the rig defaults: B0 = 3 mT, 10 mm per turn
(radius 10/(2 pi) mm), 2 turns/s, 180 deg/s, 0.1 s ramps and holds, 100 samples/s.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.core.config import (
    FieldSettings,
    MagnetSettings,
    RigConfig,
    RigInfo,
    default_six_coil_coils,
)
from rigctl.core.errors import ConfigError, PlanError
from rigctl.rigs.six_coil.realize import (
    HOLD,
    NO_MOVE,
    ROLLING,
    STEERING,
    realize_global_moves,
)
from rigctl.rigs.six_coil.settings import SixCoilRig

B0 = 3e-3
MOVES = np.array([[20.0, 0.0], [6.0, 8.0], [0.0, 0.0], [-30.0, 0.0]])


def six_coil_rig(**field) -> RigConfig:
    return SixCoilRig(
        rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils(), field=FieldSettings(**field)
    )


@pytest.fixture(scope="module")
def program():
    return realize_global_moves(MOVES, six_coil_rig())


def rolling_samples_with_end(program, i):
    """Rolling samples of move i plus the sample after them (where the rolling has finished)."""
    idx = np.flatnonzero((program.segment == i) & (program.kind == ROLLING))
    return program.field_T[np.append(idx, idx[-1] + 1)], idx


def test_rolling_field_has_magnitude_b0_and_no_component_along_the_roll_axis(program):
    for i, d in enumerate(MOVES):
        if not d.any():
            continue
        u = np.array([-d[1], d[0], 0.0]) / np.hypot(*d)  # z_hat x d_hat
        field, _ = rolling_samples_with_end(program, i)
        np.testing.assert_allclose(np.linalg.norm(field, axis=1), B0, rtol=1e-12)
        np.testing.assert_allclose(field @ u, 0.0, atol=1e-15)


def test_rolling_angle_is_whole_turns_and_moves_the_magnet_by_the_move(program):
    radius_mm = 10.0 / (2 * math.pi)
    for i, d in enumerate(MOVES):
        if not d.any():
            continue
        d_hat = np.array([d[0], d[1], 0.0]) / np.hypot(*d)
        u = np.cross([0.0, 0.0, 1.0], d_hat)
        field, _ = rolling_samples_with_end(program, i)
        # angle of B about u, measured in the plane (d_hat, u x d_hat = -z)
        angle = np.unwrap(np.arctan2(field @ np.cross(u, d_hat), field @ d_hat))
        assert np.all(np.diff(angle) > 0), "rolling turns the field the positive way about u"
        total = angle[-1] - angle[0]
        np.testing.assert_allclose(total, 2 * math.pi * np.hypot(*d) / 10.0, rtol=1e-12)
        displacement = radius_mm * total * np.cross(u, [0.0, 0.0, 1.0])
        np.testing.assert_allclose(displacement[:2], d, atol=1e-9)


def test_steering_keeps_the_field_horizontal_and_turns_at_most_90_degrees(program):
    steering = program.kind == STEERING
    assert steering.sum() == 60  # moves 1 and 3 each turn by atan2(8, 6) = 53.13 deg
    np.testing.assert_array_equal(program.field_T[steering, 2], 0.0)
    np.testing.assert_allclose(np.linalg.norm(program.field_T[steering], axis=1), B0, rtol=1e-12)
    for i in (1, 3):
        idx = np.flatnonzero((program.segment == i) & (program.kind == STEERING))
        ends = program.field_T[[idx[0], idx[-1] + 1]]  # steering start, and rolling start
        cos_turn = ends[0] @ ends[1] / B0**2
        np.testing.assert_allclose(math.degrees(math.acos(cos_turn)), 53.130102354, rtol=1e-9)


def test_field_is_continuous(program):
    steps = np.linalg.norm(np.diff(program.field_T, axis=0), axis=1)
    rate = 100.0
    largest_angle = max(2 * math.pi * 2.0 / rate, math.radians(180.0) / rate)  # rolling, steering
    ramp_step = 1.0 / (0.1 * rate)  # the ramp raises |B| by B0/10 per sample
    assert steps.max() <= B0 * max(largest_angle, ramp_step) * (1 + 1e-12)


def test_duration_and_phases_match_the_hand_sum(program):
    # ramp 0.1 | move 0: 2 turns 1.0 + hold 0.1 | move 1: steer 53.13 deg -> 0.2952 s, rounded up
    # to 0.30 s, 1 turn 0.5 + hold 0.1 | move 2: hold 0.1 | move 3: steer 0.30 + 3 turns 1.5 + hold
    # 0.1 | ramp 0.1 -> 4.2 s, i.e. 420 periods and 421 samples at 100 Hz
    assert len(program.t_s) == 421
    assert program.duration_s == pytest.approx(4.2, abs=1e-12)
    np.testing.assert_allclose(np.diff(program.t_s), 0.01, rtol=1e-9)
    assert program.rate_hz == 100.0
    assert (program.kind == ROLLING).sum() == 100 + 50 + 150
    assert [program.move_end_index(i) for i in range(4)] == [120, 210, 220, 410]


def test_program_starts_and_ends_at_zero_and_ramps_along_the_initial_heading():
    program = realize_global_moves(MOVES[:1], six_coil_rig(initial_heading_deg=30.0))
    np.testing.assert_array_equal(program.field_T[0], 0.0)
    np.testing.assert_array_equal(program.field_T[-1], 0.0)
    heading = np.array([math.cos(math.pi / 6), math.sin(math.pi / 6), 0.0])
    ramp = program.field_T[:10]
    np.testing.assert_allclose(ramp, (B0 * np.arange(10) / 10)[:, None] * heading, atol=1e-18)
    # move 0 is along +x: steering turns the field from 30 deg to 0 deg (not to 180 deg)
    steer = program.field_T[program.kind == STEERING]
    assert len(steer) == math.ceil(30 / 180 * 100)
    assert np.all(steer[:, 1] >= 0.0)
    assert (program.segment[:10] == NO_MOVE).all() and (program.kind[:10] == HOLD).all()


def test_zero_move_is_a_hold_only(program):
    assert not (program.segment == 2).any()
    start, end = program.move_end_index(1), program.move_end_index(2)
    assert end - start == 10
    held = program.field_T[start - 10 : end]  # move 1's hold and the zero move's hold
    np.testing.assert_allclose(held, np.broadcast_to(B0 * np.array([0.6, 0.8, 0.0]), held.shape))
    assert program.describe_sample(start) == "the hold after move 2"


def test_move_end_index_is_after_the_hold(program):
    end = program.move_end_index(0)
    assert (program.segment[end - 10 : end] == NO_MOVE).all()
    assert program.segment[end - 11] == 0
    np.testing.assert_allclose(program.field_T[end - 10 : end], [[B0, 0.0, 0.0]] * 10)
    assert program.describe_sample(end - 1) == "the hold after move 0"
    assert program.describe_sample(len(program.t_s) - 1) == "the end ramp"
    assert program.describe_sample(0) == "the start ramp"
    with pytest.raises(IndexError):
        program.move_end_index(4)


def test_move_that_is_not_whole_turns_is_refused_with_a_useful_message():
    moves = [[10.0, 0.0], [0.0, 10.0], [20.0, 0.0], [7.2, 0.0]]
    with pytest.raises(PlanError) as caught:
        realize_global_moves(moves, six_coil_rig())
    assert str(caught.value) == (
        "move 3: 7.20 mm is 0.72 turns of the 1.59 mm magnet (10.00 mm per turn); rolling uses "
        "whole turns (seed 000 Sec. V-a): make moves multiples of 10.00 mm or change "
        "magnets.radius_mm"
    )


def test_whole_turn_tolerance_and_magnet_radius():
    # 4e-4 turn off is accepted and realized as exactly one turn (50 rolling samples)
    assert (realize_global_moves([[10.004, 0.0]], six_coil_rig()).kind == ROLLING).sum() == 50
    with pytest.raises(PlanError):
        realize_global_moves([[10.02, 0.0]], six_coil_rig())
    # a 2 mm magnet rolls 4 pi mm per turn
    rig = six_coil_rig().model_copy(update={"magnets": MagnetSettings(radius_mm=2.0)})
    program = realize_global_moves([[0.0, 8 * math.pi]], rig)
    assert (program.kind == ROLLING).sum() == 100  # 2 turns at 2 turns/s
    with pytest.raises(PlanError, match="12.57 mm per turn"):
        realize_global_moves([[10.0, 0.0]], rig)


def test_bad_input_is_refused():
    with pytest.raises(PlanError):
        realize_global_moves(np.zeros((3, 3)), six_coil_rig())
    with pytest.raises(PlanError, match="move 1"):
        realize_global_moves([[10.0, 0.0], [np.nan, 0.0]], six_coil_rig())
    with pytest.raises(ConfigError, match="min_field_mT"):
        realize_global_moves(MOVES, six_coil_rig(b0_mT=0.2))


def test_no_moves_ramps_holds_and_ramps_down():
    program = realize_global_moves(np.zeros((0, 2)), six_coil_rig())
    assert len(program.t_s) == 10 + 10 + 10 + 1
    np.testing.assert_allclose(program.field_T[10:20], [[B0, 0.0, 0.0]] * 10)
    assert program.n_moves == 0
