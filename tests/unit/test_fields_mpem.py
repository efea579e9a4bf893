"""The MPEM against physics computed without it: the potential written out by hand (Legendre
polynomials from numpy) and differentiated numerically, the point-dipole formula, Maxwell's
equations (divergence- and curl-free by finite differences; symmetric, traceless gradients) and
finite differences of the field against the gradient."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.polynomial import legendre

from rigctl.physics.fields import MPEM, Source
from rigctl.physics.fields.stations import octomag_like

MU0 = 4e-7 * np.pi


def random_sources(rng: np.random.Generator, kind: str, order: int) -> list[Source]:
    out = []
    for _ in range(2):
        position = rng.uniform(-0.12, 0.12, 3)
        direction = rng.normal(size=3)
        scale = 1e-7 if kind == "B" else 1e-3
        coefficients = tuple(scale * rng.uniform(-1, 1) * 0.05 ** k for k in range(order))
        out.append(Source(tuple(position), tuple(direction), kind, coefficients))
    return out


def potential(source: Source, points: np.ndarray) -> np.ndarray:
    """Phi of one source written from its definition (no code of the model)."""
    d = points - np.asarray(source.position_m)
    r = np.linalg.norm(d, axis=-1)
    z = np.asarray(source.direction) / np.linalg.norm(source.direction)
    c = d @ z / r
    total = np.zeros_like(r)
    for k, coefficient in enumerate(source.coefficients):
        n = k + 1
        p_n = legendre.legval(c, np.eye(n + 1)[n])
        radial = r**n if source.kind == "A" else r ** (-(n + 1))
        total += coefficient * radial * p_n
    return total


def numeric_field(sources: list[Source], points: np.ndarray, h: float = 1e-5) -> np.ndarray:
    """-grad Phi by central differences (fourth order)."""
    out = np.zeros(points.shape)
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        phi = [sum(potential(s, points + k * step) for s in sources) for k in (-2, -1, 1, 2)]
        out[:, j] = -(phi[0] - 8 * phi[1] + 8 * phi[2] - phi[3]) / (12 * h)
    return out


@pytest.fixture
def points() -> np.ndarray:
    return np.random.default_rng(3).uniform(-0.04, 0.04, (12, 3))


@pytest.mark.parametrize("kind", ["A", "B"])
@pytest.mark.parametrize("order", [1, 2, 3])
def test_field_is_minus_the_gradient_of_the_potential(kind, order, points):
    sources = random_sources(np.random.default_rng(order), kind, order)
    model = MPEM(["coil"], [sources])
    expected = numeric_field(sources, points)
    got = model.field(points, [1.0])
    assert np.max(np.abs(got - expected)) < 1e-7 * np.max(np.abs(expected))


def test_a_b_source_of_order_one_is_a_point_dipole(points):
    moment = np.array([0.3, -1.2, 0.5])  # A m^2
    centre = np.array([0.02, -0.15, 0.01])
    size = np.linalg.norm(moment)
    model = MPEM(["coil"], [[Source(tuple(centre), tuple(moment / size), "B",
                                    (MU0 * size / (4 * np.pi),))]])
    rel = points - centre
    r = np.linalg.norm(rel, axis=1, keepdims=True)
    u = rel / r
    dipole = MU0 / (4 * np.pi) * (3 * (u @ moment)[:, None] * u - moment) / r**3
    assert np.allclose(model.field(points, [1.0]), dipole, rtol=1e-12, atol=0)
    # and the gradient against the closed form 3 mu0/(4 pi r^4) (m u^T + u m^T + (u.m)(I - 5uu^T))
    m_dot = (u @ moment)[:, None, None]
    uu = u[:, :, None] * u[:, None, :]
    closed = 3 * MU0 / (4 * np.pi * r[:, :, None] ** 4) * (
        moment[None, :, None] * u[:, None, :] + u[:, :, None] * moment[None, None, :]
        + m_dot * (np.eye(3) - 5 * uu))
    assert np.allclose(model.gradient(points, [1.0]), closed, rtol=1e-10, atol=0)


def test_an_a_source_of_order_one_is_a_uniform_field(points):
    model = MPEM(["coil"], [[Source((0.0, 0.0, 0.0), (0.0, 0.6, 0.8), "A", (2e-3,))]])
    assert np.allclose(model.field(points, [1.5]), [0.0, -1.8e-3, -2.4e-3], rtol=1e-14, atol=1e-18)
    assert np.allclose(model.gradient(points, [1.5]), 0.0, atol=1e-15)


def test_an_a_source_at_its_own_position_takes_the_limit():
    z = np.array([1.0, 2.0, 2.0]) / 3.0
    model = MPEM(["coil"], [[Source((0.01, 0.0, 0.0), tuple(z), "A", (1e-3, 2e-2, 5e-1))]])
    field, grad = model.field_and_gradient(np.array([0.01, 0.0, 0.0]), [1.0])
    assert np.allclose(field, -1e-3 * z, rtol=1e-14)
    # Phi_2 = a2 (3 (d.z)^2 - r^2) / 2: its Hessian a2 (3 z z^T - I), G = -Hessian
    assert np.allclose(grad, -2e-2 * (3 * np.outer(z, z) - np.eye(3)), rtol=1e-14)


def test_a_b_source_at_its_own_position_is_nan():
    model = MPEM(["coil"], [[Source((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "B", (1e-7,))]])
    assert np.isnan(model.field(np.zeros(3), [1.0])).all()


def station_points() -> np.ndarray:
    return np.random.default_rng(11).uniform(-0.03, 0.03, (20, 3))


def test_field_is_divergence_and_curl_free_and_the_gradient_its_derivative():
    model = octomag_like(3, seed=2)
    currents = np.linspace(-4.0, 5.0, 8)
    pts = station_points()
    h = 1e-5
    numeric = np.zeros((len(pts), 3, 3))  # numeric[p, i, j] = dB_i/dx_j
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        numeric[:, :, j] = (model.field(pts + step, currents)
                            - model.field(pts - step, currents)) / (2 * h)
    size = np.max(np.abs(numeric))
    divergence = np.trace(numeric, axis1=1, axis2=2)
    curl = numeric - numeric.transpose(0, 2, 1)
    assert np.max(np.abs(divergence)) < 1e-6 * size
    assert np.max(np.abs(curl)) < 1e-6 * size
    analytic = model.gradient(pts, currents)
    assert np.max(np.abs(analytic - numeric)) < 1e-6 * size
    # and the analytic gradient itself is symmetric and traceless to round-off
    assert np.max(np.abs(analytic - analytic.transpose(0, 2, 1))) < 1e-12 * size
    assert np.max(np.abs(np.trace(analytic, axis1=1, axis2=2))) < 1e-12 * size


def test_actuation_rows_are_the_field_and_mag_manips_five_gradient_terms():
    model = octomag_like(3, seed=4)
    pts = station_points()[:3]
    A = model.actuation(pts)
    offset = model.offset(pts)
    currents = np.array([1.0, -2.0, 0.5, 3.0, 0.0, -1.0, 2.5, -0.5])
    field, grad = model.field_and_gradient(pts, currents)
    u = np.einsum("pkn,n->pk", A, currents) + offset
    assert np.allclose(u[:, 0:3], field, rtol=1e-12)
    terms = np.stack([grad[:, 0, 0], grad[:, 0, 1], grad[:, 0, 2], grad[:, 1, 1], grad[:, 1, 2]],
                     axis=1)
    assert np.allclose(u[:, 3:], terms, rtol=1e-12)
    # one point: the same numbers as the batch, without the point axis
    single_b, single_g = model.field_and_gradient(pts[1], currents)
    assert np.allclose(single_b, field[1], rtol=1e-13) and np.allclose(single_g, grad[1],
                                                                        rtol=1e-13)
    assert A.shape == (3, 8, 8) and model.actuation(pts[0]).shape == (8, 8)


def test_the_offset_adds_whatever_the_currents():
    model = octomag_like(1)
    assert np.allclose(model.field(np.zeros(3), np.zeros(8)), [0.0, 0.0, -5e-5], atol=1e-18)
    assert model.offset(np.zeros(3)).shape == (8,)


def test_wrong_number_of_currents_is_refused():
    with pytest.raises(ValueError, match="8 currents"):
        octomag_like(1).field(np.zeros(3), np.ones(6))
