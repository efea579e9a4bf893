"""Allocating field programs to coil currents (seed 000 eq. 3-4) and the limit checks.

The default cube: coils of 400 turns, radius 200 mm, centres 350 mm from the workspace centre,
R = 1.5 ohm, L = 0.03 H. One coil gives b = mu0 N a^2 / (2 (a^2 + z^2)^1.5) per ampere on its
axis, computed here by hand.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from rigctl.core.config import (
    Coil,
    FieldSettings,
    RigConfig,
    RigInfo,
    default_six_coil_coils,
)
from rigctl.core.errors import ConfigError, LimitError
from rigctl.physics.coils import actuation_matrix
from rigctl.rigs.six_coil.allocate import CurrentProgram, allocate, currents_for_field
from rigctl.rigs.six_coil.realize import FieldProgram, realize_global_moves
from rigctl.rigs.six_coil.settings import SixCoilRig

MU0 = 4e-7 * math.pi


def on_axis_per_amp(distance_m: float, turns: int = 400, radius_m: float = 0.2) -> float:
    return MU0 * turns * radius_m**2 / (2 * (radius_m**2 + distance_m**2) ** 1.5)


B_PER_AMP = on_axis_per_amp(0.35)  # 1.5347e-4 T/A


def cube(coils: list[Coil] | None = None, **field) -> RigConfig:
    return SixCoilRig(
        rig=RigInfo(kind="six-coil"),
        coils=coils or default_six_coil_coils(),
        field=FieldSettings(**field),
    )


def hand_program(
    fields_T: np.ndarray, segment: int, rate_hz: float = 100.0, down_samples: int = 0
) -> FieldProgram:
    """A program that holds 0, then the given fields (all in move `segment`), then returns to 0
    in `down_samples` + 1 steps."""
    last = np.asarray(fields_T)[-1]
    down = np.linspace(1.0, 0.0, down_samples + 2)[1:-1, None] * last
    field = np.vstack([np.zeros((1, 3)), fields_T, down, np.zeros((1, 3))])
    n = len(field)
    seg = np.full(n, -1)
    seg[1 : 1 + len(fields_T)] = segment
    return FieldProgram(
        t_s=np.arange(n) / rate_hz,
        field_T=field,
        segment=seg,
        kind=np.zeros(n, dtype=np.uint8),
        rate_hz=rate_hz,
    )


def ramp_to(field_T, samples: int = 20) -> np.ndarray:
    return np.linspace(0.0, 1.0, samples + 1)[1:, None] * np.asarray(field_T)


def test_ideal_cube_matrix_and_min_norm_currents():
    A = actuation_matrix(cube())
    expected = np.zeros((3, 6))
    for axis in range(3):
        expected[axis, 2 * axis : 2 * axis + 2] = B_PER_AMP
    np.testing.assert_allclose(A, expected, rtol=1e-12, atol=1e-18)
    B = np.array([1e-3, -2e-3, 3e-3])
    currents = currents_for_field(A, B)
    # both coils of an axis share the axis field equally: I = B_axis / (2 b)
    np.testing.assert_allclose(currents, np.repeat(B / (2 * B_PER_AMP), 2), rtol=1e-12)
    # 3 mT along one axis is about 9.77 A per coil
    assert currents_for_field(A, [0.0, 3e-3, 0.0])[2] == pytest.approx(9.774, abs=1e-3)


def test_off_centre_matrix_uses_the_coils_distances():
    A = actuation_matrix(cube(), point_mm=(0.0, 0.0, 50.0))
    assert A[2, 4] == pytest.approx(on_axis_per_amp(0.30), rel=1e-12)  # z+ coil 300 mm away
    assert A[2, 5] == pytest.approx(on_axis_per_amp(0.40), rel=1e-12)  # z- coil 400 mm away


def test_currents_are_the_minimum_norm_solution_and_vectorised():
    rng = np.random.default_rng(7)
    A = rng.normal(size=(3, 6)) * 1e-4
    B = rng.normal(size=(4, 5, 3)) * 1e-3
    currents = currents_for_field(A, B)
    assert currents.shape == (4, 5, 6)
    # second method: I = A^T (A A^T)^-1 B, solved rather than pseudo-inverted
    y = np.linalg.solve(A @ A.T, B.reshape(-1, 3).T)
    np.testing.assert_allclose(currents.reshape(-1, 6), (A.T @ y).T, rtol=1e-9)
    np.testing.assert_allclose(currents @ A.T, B, rtol=1e-9)


def test_measured_matrix_from_the_rig_file_is_used():
    measured = [
        [2e-4, 1e-4, 0.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 1e-4, 1e-4, 0.0, 0.0],
        [0.0, 0.0, 0.0, 0.0, 3e-4, 0.0],
    ]
    rig = cube().model_copy(update={"actuation_matrix_T_per_A": measured})
    np.testing.assert_array_equal(actuation_matrix(rig), measured)
    result = allocate(hand_program(ramp_to([1e-3, 0.0, 0.0]), segment=0), rig)
    # row x: I_j = b_j B / (b_1^2 + b_2^2) = 2e-4 * 1e-3 / 5e-8 = 4 A and 2 A
    np.testing.assert_allclose(result.currents_A[-2], [4.0, 2.0, 0, 0, 0, 0], atol=1e-12)
    with pytest.raises(ConfigError, match="workspace centre"):
        actuation_matrix(rig, point_mm=(10.0, 0.0, 0.0))


def test_field_the_coils_cannot_make_is_refused():
    flat = [[1e-4, 1e-4, 0, 0, 0, 0], [0, 0, 1e-4, 1e-4, 0, 0], [0, 0, 0, 0, 0, 0]]
    rig = cube().model_copy(update={"actuation_matrix_T_per_A": flat})
    with pytest.raises(LimitError, match="move 2 needs B = .* cannot produce .* rank 2"):
        allocate(hand_program(ramp_to([0.0, 0.0, 1e-3]), segment=2), rig)


def test_25_A_request_is_refused_naming_the_move_and_a_coil():
    B = [0.0, 25.0 * 2 * B_PER_AMP, 0.0]  # 25 A on y+ and y-
    with pytest.raises(LimitError) as caught:
        allocate(hand_program(ramp_to(B), segment=3), cube())
    assert re.fullmatch(
        r"move 3 needs 25\.0 A on coil y[+-] \(limit 20\.0 A\); lower field\.b0_mT or raise "
        r"the coil's current_limit_A",
        str(caught.value),
    )


def test_the_coil_over_its_own_limit_is_named():
    coils = default_six_coil_coils()
    coils[3] = coils[3].model_copy(update={"current_limit_A": 15.0})  # y-
    B = [0.0, 17.0 * 2 * B_PER_AMP, 0.0]
    with pytest.raises(LimitError, match=r"^move 1 needs 17\.0 A on coil y- \(limit 15\.0 A\)"):
        allocate(hand_program(ramp_to(B), segment=1), cube(coils))


def test_realized_program_above_the_limit_is_refused_before_anything_else():
    # 7.6734 mT needs 25 A per coil
    rig = cube(b0_mT=25.0 * 2 * B_PER_AMP * 1e3)
    program = realize_global_moves([[10.0, 0.0]], rig)
    with pytest.raises(LimitError, match=r"^move 0 needs 25\.0 A on coil [xz][+-]"):
        allocate(program, rig)


def test_voltage_step_is_refused_and_a_gentle_ramp_passes():
    B = np.array([[0.0, 10.0 * 2 * B_PER_AMP, 0.0]])  # 10 A in one sample
    # at 1 kHz: V = R I + L dI/dt = 1.5 * 10 + 0.03 * 10 / 0.001 = 15 + 300 = 315 V
    with pytest.raises(LimitError) as caught:
        allocate(hand_program(B, segment=4, rate_hz=1000.0), cube())
    message = str(caught.value)
    assert re.match(r"move 4 needs 315\.0 V on coil y[+-] \(limit 100\.0 V;", message)
    assert "R*I = 15.0 V" in message and "L*dI/dt = 300.0 V" in message
    # the same step at 100 Hz is 15 + 30 = 45 V: allowed
    result = allocate(hand_program(B, segment=4, rate_hz=100.0), cube())
    np.testing.assert_allclose(result.currents_A[1, 2:4], 10.0, rtol=1e-12)


def test_voltage_limit_of_each_coil_is_its_own():
    coils = default_six_coil_coils()
    coils[1] = coils[1].model_copy(update={"compliance_V": 20.0})  # x-
    # ramp 0 -> 10 A over 10 samples at 100 Hz: dI/dt = 100 A/s, V peaks at 15 + 3 = 18 V
    # (and back down over 10 samples: at most 15 - 3 = 12 V)
    top = [10.0 * 2 * B_PER_AMP, 0.0, 0.0]
    fine = hand_program(ramp_to(top, samples=10), segment=0, down_samples=9)
    allocate(fine, cube(coils))
    # ramp up over 5 samples: dI/dt = 200 A/s, V peaks at 15 + 6 = 21 V
    steep = hand_program(ramp_to(top, samples=5), segment=0, down_samples=9)
    with pytest.raises(LimitError, match=r"^move 0 needs 21\.0 V on coil x- \(limit 20\.0 V"):
        allocate(steep, cube(coils))


def test_default_rig_allocates_a_realized_plan():
    rig = cube()
    program = realize_global_moves([[20.0, 0.0], [0.0, -10.0], [0.0, 0.0]], rig)
    result = allocate(program, rig)
    assert isinstance(result, CurrentProgram)
    assert result.coil_names == ("x+", "x-", "y+", "y-", "z+", "z-")
    assert result.currents_A.shape == (len(program.t_s), 6)
    np.testing.assert_array_equal(result.segment, program.segment)
    np.testing.assert_array_equal(result.t_s, program.t_s)
    np.testing.assert_allclose(result.currents_A[[0, -1]], 0.0, atol=1e-12)
    # |B| = 3 mT throughout the moves; the peak per coil is 3 mT / (2 b)
    assert np.abs(result.currents_A).max() == pytest.approx(3e-3 / (2 * B_PER_AMP), rel=1e-9)
    np.testing.assert_allclose(result.currents_A[:, 0], result.currents_A[:, 1], rtol=1e-9)
