"""Field and gradient allocation on the six-coil rig (the 8-vector U; seed 002's pulling).

Independent references: the on-axis gradient of a loop in closed form,
dBz/dz = 3 mu0 N a^2 s / (2 (a^2 + s^2)^(5/2)) at distance s in front of the loop (towards its
axis direction's opposite side), the force on a dipole by differentiating m . B of the coils'
loop fields directly (a second method, not the actuation matrix), and the current limits.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.core.config import RigInfo, default_six_coil_coils
from rigctl.core.errors import LimitError
from rigctl.physics.coils import (
    coil_field_and_gradient,
    max_planar_gradient,
    u_actuation_matrix,
)
from rigctl.physics.magnetics import gradient_from_terms, loop_field
from rigctl.rigs.six_coil.allocate import currents_for_u, field_and_pull_u
from rigctl.rigs.six_coil.settings import SixCoilRig

MU0 = 4e-7 * math.pi
RIG = SixCoilRig(rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils())


def on_axis_gradient(s_m, turns=400, a=0.2):
    """d/dz of mu0 N a^2 / (2 (a^2 + z^2)^1.5) at z = -s (the point lies s before the coil)."""
    return 3 * MU0 * turns * a**2 * s_m / (2 * (a**2 + s_m**2) ** 2.5)


@pytest.mark.parametrize("x_mm", [0.0, 10.0, -25.0])
def test_central_differences_match_the_closed_form_on_axis(x_mm):
    fg = coil_field_and_gradient(RIG, (x_mm, 0.0, 0.0))
    x_plus = 0  # coil x+ at +350 mm, axis +x: the point is 350 - x mm before it
    want = on_axis_gradient((350.0 - x_mm) * 1e-3)
    assert fg[0, 1, x_plus] == pytest.approx(want, rel=1e-6)
    # axial symmetry and div B = 0 on the axis: the two transverse terms are -1/2 of it
    assert fg[1, 2, x_plus] == pytest.approx(-0.5 * want, rel=1e-6)
    assert fg[2, 3, x_plus] == pytest.approx(-0.5 * want, rel=1e-6)


def test_the_cube_centre_spans_field_and_two_diagonal_gradients():
    A8 = u_actuation_matrix(RIG)
    assert A8.shape == (8, 6)
    assert np.linalg.matrix_rank(A8) == 5
    np.testing.assert_allclose(A8[[4, 5, 7]], 0.0, atol=1e-12)  # no off-diagonal gradient


def force_by_differentiating(currents, moment, h=1e-5):
    """F = grad(m . B) at the centre, B summed from loop_field of every coil with its current."""
    def energy(p):
        b = sum(loop_field(p, np.asarray(c.centre_mm) * 1e-3, c.axis, c.loop_radius_mm * 1e-3,
                           c.turns, i) for c, i in zip(RIG.coils, currents))
        return float(moment @ b)
    return np.array([(energy(h * e) - energy(-h * e)) / (2 * h) for e in np.eye(3)])


@pytest.mark.parametrize("psi_deg, force_nN", [(30.0, (4.0, -3.0)), (-135.0, (2.0, 5.0)),
                                               (80.0, (0.5, 6.0))])
def test_currents_make_the_field_angle_and_the_pull(psi_deg, force_nN):
    m_abs, b0 = 5.6e-7, 2e-3
    psi = math.radians(psi_deg)
    force = np.array(force_nN) * 1e-9
    u = field_and_pull_u(psi, force, m_abs, b0)
    currents = currents_for_u(u_actuation_matrix(RIG), u, RIG)
    field = sum(loop_field(np.zeros(3), np.asarray(c.centre_mm) * 1e-3, c.axis,
                           c.loop_radius_mm * 1e-3, c.turns, i) for c, i in zip(RIG.coils, currents))
    np.testing.assert_allclose(field, b0 * np.array([math.cos(psi), math.sin(psi), 0.0]),
                               atol=1e-9 * b0)
    moment = m_abs * np.array([math.cos(psi), math.sin(psi), 0.0])
    got = force_by_differentiating(currents, moment)
    np.testing.assert_allclose(got[:2], force, rtol=1e-5)
    assert abs(got[2]) < 1e-6 * np.abs(force).max()
    np.testing.assert_allclose(gradient_from_terms(u[3:]) @ moment, [*force, 0.0],
                               rtol=1e-12, atol=1e-20)


def test_a_pull_across_the_moment_is_refused():
    with pytest.raises(LimitError, match="pull along y"):
        field_and_pull_u(0.0, np.array([0.0, 1e-9]), 5.6e-7, 2e-3)


def test_a_gradient_beyond_the_supplies_names_the_coil():
    u = np.zeros(8)
    u[0], u[3], u[6] = 2e-3, 0.08, 0.08  # 80 mT/m: several times what 20 A makes
    with pytest.raises(LimitError, match=r"on coil (x|y|z)[+-] \(limit 20\.0 A\)"):
        currents_for_u(u_actuation_matrix(RIG), u, RIG)


def test_an_off_diagonal_gradient_cannot_be_made_at_the_centre():
    u = np.zeros(8)
    u[4] = 0.01
    with pytest.raises(LimitError, match="dBx/dy"):
        currents_for_u(u_actuation_matrix(RIG), u)


def test_max_planar_gradient_is_feasible_everywhere_and_close_to_the_true_limit():
    b0 = 2e-3
    g = max_planar_gradient(RIG, b0)
    A8 = u_actuation_matrix(RIG)
    psi = np.linspace(0, 2 * np.pi, 72, endpoint=False)

    def worst_current(gain):
        u = np.zeros((72, 4, 8))
        u[..., 0] = b0 * np.cos(psi)[:, None]
        u[..., 1] = b0 * np.sin(psi)[:, None]
        u[..., 3] = gain * np.array([1, 1, -1, -1])
        u[..., 6] = gain * np.array([1, -1, 1, -1])
        return np.abs(u @ np.linalg.pinv(A8).T).max()

    assert worst_current(g) <= 20.0 + 1e-9
    assert worst_current(1.25 * g) > 20.0  # conservative, but not by much
    # the field alone takes b0 / (2 b) per coil: about 6.5 A of the 20 A at 2 mT
    b_per_amp = MU0 * 400 * 0.04 / (2 * (0.04 + 0.35**2) ** 1.5)
    assert worst_current(0.0) == pytest.approx(b0 / (2 * b_per_amp), rel=1e-6)


def _slew_by_hand(program, rig, share=0.9):
    """The slew rule sample by sample, written from its statement: each step moves every current
    towards its (clipped) target by at most (share V_max - R |I_target|) / (L f) amps."""
    r = np.array([c.resistance_ohm for c in rig.coils])
    inductance = np.array([c.inductance_H for c in rig.coils])
    v_max = np.array([c.compliance_V for c in rig.coils])
    limit = np.array([c.current_limit_A for c in rig.coils])
    out, last = [], np.zeros(program.shape[1])
    for target in program:
        target = np.minimum(np.maximum(target, -limit), limit)
        room = np.maximum(share * v_max - r * np.abs(target), 0.0) / (inductance * rig.stream.rate_hz)
        last = last + np.minimum(np.maximum(target - last, -room), room)
        out.append(last)
    return np.array(out).reshape(program.shape)


def test_the_slew_limit_gives_the_sample_by_sample_program_on_holds_dithers_and_ramps():
    from rigctl.rigs.six_coil.pair import slew_limited

    rng = np.random.default_rng(7)
    steps = rng.normal(0, 12, size=(30, 6))
    dither = np.array([[3, -2, 1, 0, 5, -5], [-3, 2, 1, 0, 4, -4]], float)
    programs = [
        np.repeat(steps, rng.integers(1, 300, size=30), axis=0),  # piecewise constant, jumps
        np.tile(np.repeat(dither, 50, axis=0), (40, 1)),  # the hold's dither, 40 flips each way
        np.repeat(steps, 20, axis=0) + rng.normal(0, 0.5, size=(600, 6)),  # changing every row
        np.zeros((0, 6)),
    ]
    for program in programs:
        got = slew_limited(program, RIG)
        assert np.array_equal(got, _slew_by_hand(program, RIG))
    held = slew_limited(np.repeat(steps[:1], 400, axis=0), RIG)
    assert np.array_equal(held[-1], np.clip(steps[0], -20, 20))  # a long stretch reaches its target
