"""Allocation for any N coils: the currents make what is asked (checked by evaluating the model
forward), they are the minimum-norm ones (orthogonal to the actuation matrix's null space, from
scipy), the Offset is subtracted, limits are respected, and what the rig cannot make is refused
with what it can make."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import null_space

from rigctl.core.errors import LimitError
from rigctl.physics.fields import MPEM, Source
from rigctl.physics.fields.allocate import allocate
from rigctl.physics.fields.stations import octomag_like

POINT = np.array([0.004, -0.003, 0.002])


def test_field_only_is_met_with_the_minimum_norm_currents():
    model = octomag_like(3, seed=1)
    wanted = np.array([8e-3, -3e-3, 5e-3])
    result = allocate(model, POINT, wanted)
    assert np.allclose(model.field(POINT, result.currents_A), wanted, rtol=1e-9, atol=1e-15)
    # minimum norm: no component along currents that make no field (8 - 3 = 5 of them)
    null = null_space(model.actuation(POINT)[0:3])
    assert null.shape[1] == 5
    assert np.max(np.abs(null.T @ result.currents_A)) < 1e-9 * np.linalg.norm(result.currents_A)


def test_field_and_gradient_on_eight_coils_subtracts_the_offset():
    model = octomag_like(3, seed=1)
    wanted_b = np.array([5e-3, 0.0, 0.0])
    wanted_g = np.array([0.05, 0.0, 0.02, -0.03, 0.0])  # T/m
    result = allocate(model, POINT, wanted_b, gradient_T_per_m=wanted_g)
    field, grad = model.field_and_gradient(POINT, result.currents_A)
    assert np.allclose(field, wanted_b, rtol=0, atol=1e-12)
    assert np.allclose([grad[0, 0], grad[0, 1], grad[0, 2], grad[1, 1], grad[1, 2]], wanted_g,
                       rtol=0, atol=1e-10)
    # mag_manip's backward model inverts the actuation matrix alone: off by the offset's 50 uT
    naive = np.linalg.solve(model.actuation(POINT), np.concatenate([wanted_b, wanted_g]))
    assert np.linalg.norm(model.field(POINT, naive) - wanted_b) == pytest.approx(5e-5, rel=1e-6)


def test_force_on_a_dipole():
    model = octomag_like(3, seed=3)
    moment = np.array([0.0, 0.0, 2e-3])  # A m^2
    wanted_b, wanted_f = np.array([0.0, 0.0, 10e-3]), np.array([1e-4, -2e-4, 3e-4])  # T, N
    result = allocate(model, POINT, wanted_b, force_N=wanted_f, moment_Am2=moment)
    field, grad = model.field_and_gradient(POINT, result.currents_A)
    assert np.allclose(field, wanted_b, rtol=0, atol=1e-12)
    assert np.allclose(grad @ moment, wanted_f, rtol=0, atol=1e-12)  # F = (m . grad) B = G m


def test_a_current_limit_is_respected_and_the_fraction_that_fits_is_named():
    model = octomag_like(3, seed=1)
    wanted = np.array([0.0, 0.0, 40e-3])
    free = allocate(model, POINT, wanted)
    limit = 0.5 * np.max(np.abs(free.currents_A))
    with pytest.raises(LimitError) as err:
        allocate(model, POINT, wanted, current_limits_A=limit)
    message = str(err.value)
    assert "limit" in message and "50.0%" in message and "\n" not in message
    # that fraction of the request above the offset fits, exactly at the limit
    offset = model.field(POINT, np.zeros(8))
    half = allocate(model, POINT, offset + 0.5 * (wanted - offset), current_limits_A=limit)
    assert np.max(np.abs(half.currents_A)) == pytest.approx(limit, rel=1e-9)


def helmholtz_triad() -> MPEM:
    """Three orthogonal uniform-field coils (A sources of order 1): 1 mT/A each."""
    axes = np.eye(3)
    return MPEM(["X", "Y", "Z"], [[Source((0.0, 0.0, 0.0), tuple(-a), "A", (1e-3,))]
                                  for a in axes])


def test_a_uniform_field_rig_makes_fields_but_no_force():
    model = helmholtz_triad()
    result = allocate(model, POINT, [1e-3, 2e-3, -3e-3])
    assert np.allclose(result.currents_A, [1.0, 2.0, -3.0], rtol=1e-12)
    with pytest.raises(LimitError) as err:
        allocate(model, POINT, [1e-3, 0, 0], force_N=[1e-5, 0, 0], moment_Am2=[1e-3, 0, 0])
    message = str(err.value)
    assert "cannot make" in message and "nearest it makes is B = [1, 0, 0] mT" in message
    assert "F = [0, 0, 0] uN" in message
    with pytest.raises(LimitError, match="3 coils cannot set field and gradient"):
        allocate(model, POINT, [1e-3, 0, 0], gradient_T_per_m=np.zeros(5))
