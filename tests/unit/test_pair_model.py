"""The two-agent model of seed 002 (eq. 1-5) against hand-computed values and a second method.

Hand values: at r = 2, f = (1 - 3 cos^2 psi) / 16 radially and sin(2 psi) / 16 transversely;
psi = 0: -1/8 (attraction, head to tail), psi = 90: +1/16 (side by side repel), psi = 45:
-1/32 and +1/16. The forces are also checked against the full dipole-dipole force
F = 3 mu0 / (4 pi r^4) [(m1.r) m2 + (m2.r) m1 + (m1.m2) r - 5 (m1.r)(m2.r) r], evaluated here
independently in 3-D, and the Lie brackets of eq. 5 against brackets taken by finite differences.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.plans.pair import (
    ZERO_RADIAL_ANGLE_RAD,
    PairPhysics,
    agent_positions,
    controllability,
    interagent_forces,
    lie_bracket_matrix,
    rollout,
    state_from_positions,
    step_state,
)

MU0 = 4e-7 * math.pi


@pytest.mark.parametrize("psi_deg, f_r, f_phi", [
    (0.0, -2.0 / 16, 0.0),
    (90.0, 1.0 / 16, 0.0),
    (45.0, -1.0 / 32, 1.0 / 16),
    (-45.0, -1.0 / 32, -1.0 / 16),
    (math.degrees(math.acos(1 / math.sqrt(3))), 0.0, math.sqrt(8.0 / 9.0) / 16),
])
def test_forces_at_r2_match_hand_values(psi_deg, f_r, f_phi):
    got_r, got_phi = interagent_forces(2.0, math.radians(psi_deg))
    assert got_r == pytest.approx(f_r, abs=1e-12)
    assert got_phi == pytest.approx(f_phi, abs=1e-12)


def dipole_force_on_2(m1, m2, r_vec):
    """Force (N) on dipole 2 at r_vec (m) from dipole 1 at the origin, the textbook formula."""
    r = np.linalg.norm(r_vec)
    n = r_vec / r
    return 3 * MU0 / (4 * math.pi * r**4) * (
        (m1 @ n) * m2 + (m2 @ n) * m1 + (m1 @ m2) * n - 5 * (m1 @ n) * (m2 @ n) * n)


@pytest.mark.parametrize("psi_deg, phi_deg, r_bl", [(20, 0, 2.0), (70, 35, 1.7), (-130, -80, 3.1)])
def test_forces_agree_with_full_dipole_force(psi_deg, phi_deg, r_bl):
    physics = PairPhysics()
    d = physics.diameter_m
    phi, psi_g = math.radians(phi_deg), math.radians(psi_deg + phi_deg)
    m = physics.moment_Am2 * np.array([math.cos(psi_g), math.sin(psi_g), 0.0])
    e_r = np.array([math.cos(phi), math.sin(phi), 0.0])
    e_phi = np.array([-math.sin(phi), math.cos(phi), 0.0])
    force = dipole_force_on_2(m, m, r_bl * d * e_r)
    f_r, f_phi = interagent_forces(r_bl, math.radians(psi_deg))
    scale = physics.force_constant_N_m4 / d**4
    assert force @ e_r == pytest.approx(f_r * scale, rel=1e-9)
    assert force @ e_phi == pytest.approx(f_phi * scale, rel=1e-9)
    assert force[2] == pytest.approx(0.0, abs=1e-12 * abs(scale))  # eq. 1c


def test_rates_are_twice_one_agents_stokes_speed():
    physics = PairPhysics(body_diameter_mm=0.5, moment_Am2=1e-7, viscosity_Pa_s=0.03)
    sigma = 6 * math.pi * 0.03 * 0.25e-3
    omega = 3 * MU0 * 1e-14 / (4 * math.pi)
    assert physics.drag_N_s_per_m == pytest.approx(sigma)
    assert physics.rate_per_s == pytest.approx(2 * omega / (sigma * 0.5e-3**5))
    f_r, f_phi = interagent_forces(2.0, 0.0)
    r_dot, phi_dot = physics.rate_per_s * f_r, physics.rate_per_s * f_phi / 2.0  # eq. 3
    # both agents approach at |F| / sigma each: r shrinks at 2 * (2 Omega / r^4) / sigma, in BL/s
    speed = 2 * (2 * omega / (2 * 0.5e-3) ** 4) / sigma / 0.5e-3
    assert r_dot == pytest.approx(-speed, rel=1e-12)
    assert phi_dot == 0.0


def test_largest_transverse_force_is_half_the_largest_radial():
    psi = np.linspace(-math.pi, math.pi, 3601)
    f_r, f_phi = interagent_forces(1.0, psi)
    assert np.abs(f_phi).max() == pytest.approx(0.5 * np.abs(f_r).max(), rel=1e-6)


def test_zero_radial_angle():
    assert math.degrees(ZERO_RADIAL_ANGLE_RAD) == pytest.approx(54.7356, abs=1e-4)
    assert interagent_forces(2.0, ZERO_RADIAL_ANGLE_RAD)[0] == pytest.approx(0.0, abs=1e-15)


def _drift(x):
    r, _, psi = x
    return np.array([(1 - 3 * math.cos(psi) ** 2) / r**4, math.sin(2 * psi) / r**5, 0.0])


def _bracket(f, g, x, h=1e-6):
    """[f, g](x) = Dg f - Df g with Jacobians by central differences."""
    def jac(v):
        return np.stack([(v(x + h * e) - v(x - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    return jac(g) @ f(x) - jac(f) @ g(x)


@pytest.mark.parametrize("r, psi_deg", [(2.0, 30.0), (1.6, 70.0), (2.7, -20.0)])
def test_lie_brackets_match_finite_differences(r, psi_deg):
    x = np.array([r, 0.3, math.radians(psi_deg)])
    g = lambda _x: np.array([0.0, 0.0, 1.0])  # noqa: E731
    fg = lambda y: _bracket(_drift, g, y)  # noqa: E731
    ffg = _bracket(_drift, fg, x, h=1e-4)
    matrix = lie_bracket_matrix(r, math.radians(psi_deg))
    np.testing.assert_allclose(matrix[:, 1], fg(x), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(matrix[:, 2], ffg, rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("psi_deg, rank", [(0.0, 2), (90.0, 2), (-90.0, 2), (180.0, 2),
                                           (30.0, 3), (54.7356, 3), (-120.0, 3)])
def test_rank_three_except_at_0_and_90(psi_deg, rank):
    assert controllability(2.0, 0.0, psi_deg)["rank"] == rank


def test_agent_positions_round_trip():
    q = np.array([3.0, -1.0, 2.5, math.radians(30)])
    p = agent_positions(q)
    np.testing.assert_allclose(p[1] - p[0], 2.5 * np.array([math.cos(math.radians(30)), 0.5]))
    np.testing.assert_allclose(state_from_positions(p), q)


def test_step_matches_closed_form_at_the_zero_radial_angle_and_pull_is_linear():
    """With the field held at psi = 90 deg local and phi = 0 the pair only separates:
    r' = K / r^4 gives r(t)^5 = r0^5 + 5 K t (closed form); the centroid moves by f dt."""
    k = 3.0
    q = step_state([1.0, 2.0, 2.0, 0.0], [math.pi / 2, 0.3, -0.2], 0.5, k)
    assert q[2] == pytest.approx((2.0**5 + 5 * k * 0.5) ** 0.2, rel=1e-7)
    assert q[3] == pytest.approx(0.0, abs=1e-12)
    assert q[:2] == pytest.approx([1.15, 1.9])
    states = rollout([1.0, 2.0, 2.0, 0.0], [[math.pi / 2, 0.3, -0.2]] * 2, [0.25, 0.25], k)
    assert states[-1][2] == pytest.approx(q[2], rel=1e-6)
