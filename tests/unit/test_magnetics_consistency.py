"""Physics consistency of rigctl.physics.magnetics: each model checked against an independent one.

The loop's closed form is compared with the textbook on-axis formula, a far-away dipole, a
brute-force Biot-Savart sum over straight segments, Ampere's law around the wire, and its own
symmetries (linearity, mirror, rotation). The dipole is compared with its hand values.
"""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.physics.magnetics import dipole_field, loop_field

MU0 = 4e-7 * np.pi  # written out here so the tests do not borrow the module's constant


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def frame_for(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane perpendicular to `axis`."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def biot_savart_loop(points, centre, axis, radius, current, segments=4000):
    """Sum of mu0 I/(4 pi) dl x R/|R|^3 over `segments` straight chords of the circle."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    e1, e2 = frame_for(axis)
    theta = np.linspace(0.0, 2.0 * np.pi, segments + 1)
    nodes = centre + radius * (np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2)
    dl = np.diff(nodes, axis=0)  # (S, 3), counter-clockwise about axis
    mid = 0.5 * (nodes[1:] + nodes[:-1])
    sep = np.asarray(points, float)[:, None, :] - mid[None, :, :]  # (P, S, 3)
    dist3 = np.linalg.norm(sep, axis=-1) ** 3
    contrib = np.cross(dl[None, :, :], sep) / dist3[..., None]
    return MU0 * current / (4.0 * np.pi) * contrib.sum(axis=1)


def test_on_axis_matches_textbook_formula():
    rng = np.random.default_rng(1)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    centre = np.array([0.1, -0.2, 0.05])
    a, turns, current = 0.2, 400, 1.7
    z = np.array([-3.0, -0.35, -0.01, 0.0, 0.02, 0.2, 0.35, 5.0])
    points = centre + z[:, None] * axis
    field = loop_field(points, centre, axis, a, turns, current)
    expected = MU0 * turns * current * a**2 / (2.0 * (a**2 + z**2) ** 1.5)
    np.testing.assert_allclose(field, expected[:, None] * axis, rtol=1e-12, atol=1e-18)
    # at the centre this is the familiar mu0 N I / (2 a)
    np.testing.assert_allclose(field[3] @ axis, MU0 * turns * current / (2 * a), rtol=1e-12)


@pytest.mark.parametrize("distance_in_radii", [50.0, 100.0, 200.0])
def test_far_field_matches_dipole(distance_in_radii):
    rng = np.random.default_rng(2)
    a, turns, current = 0.05, 30, 2.0
    axis = np.array([0.3, -0.4, 0.866])
    axis /= np.linalg.norm(axis)
    centre = np.array([0.01, 0.02, -0.03])
    directions = rng.normal(size=(20, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = centre + distance_in_radii * a * directions
    loop = loop_field(points, centre, axis, a, turns, current)
    dipole = dipole_field(points, centre, turns * current * np.pi * a**2 * axis)
    scale = np.linalg.norm(dipole, axis=1, keepdims=True)
    # the first correction to the dipole term is O((a/r)^2)
    assert np.max(np.abs(loop - dipole) / scale) < 3.0 / distance_in_radii**2


def test_off_axis_matches_biot_savart_sum():
    rng = np.random.default_rng(3)
    a, turns, current = 0.2, 400, 1.0
    centre = np.array([0.35, 0.0, 0.0])
    axis = np.array([1.0, 0.0, 0.0])
    # points in a box around the loop, kept >= 0.1 a away from the wire
    points = centre + rng.uniform(-0.5, 0.5, size=(60, 3))
    rel = points - centre
    z = rel @ axis
    rho = np.linalg.norm(rel - z[:, None] * axis, axis=1)
    points = points[np.hypot(rho - a, z) > 0.1 * a]
    # plus points inside the near-axis band and just outside it
    band = np.array([[0.07, 0.3e-5 * a, 0.0], [0.07, 3e-5 * a, 0.0], [-0.2, 0.0, 1e-3]])
    points = np.vstack([points, centre + band])
    field = loop_field(points, centre, axis, a, turns, current)
    reference = biot_savart_loop(points, centre, axis, a, turns * current)
    scale = np.linalg.norm(reference, axis=1, keepdims=True)
    assert len(points) > 40
    np.testing.assert_array_less(np.abs(field - reference) / scale, 1e-5)


def test_radial_field_is_continuous_across_the_near_axis_band():
    a, z = 0.2, 0.1
    rho = a * np.array([0.9e-5, 0.999e-5, 1.001e-5, 1.1e-5, 1e-4])
    points = np.stack([rho, np.zeros_like(rho), np.full_like(rho, z)], axis=1)
    field = loop_field(points, np.zeros(3), [0, 0, 1], a, 1, 1.0)
    # div B = 0 gives Brho ~ -rho/2 dBz/dz on the axis, i.e. Brho/rho -> 3 mu0 I a^2 z / (4 s^5)
    slope = 3.0 * MU0 * a**2 * z / (4.0 * (a**2 + z**2) ** 2.5)
    np.testing.assert_allclose(field[:, 0] / rho, slope, rtol=1e-6)


def test_ampere_circulation_around_the_wire():
    a, turns, current = 0.2, 25, 3.0
    # the wire crosses the xz plane at (a, 0, 0) heading +y (counter-clockwise about +z)
    small = 0.05 * a
    phi = np.linspace(0.0, 2.0 * np.pi, 2001)[:-1]
    # a circle in the xz plane around (a, 0, 0), oriented so its normal is +y
    points = np.stack([a + small * np.cos(phi), np.zeros_like(phi), -small * np.sin(phi)], axis=1)
    tangent = np.stack([-np.sin(phi), np.zeros_like(phi), -np.cos(phi)], axis=1)
    field = loop_field(points, np.zeros(3), [0, 0, 1], a, turns, current)
    circulation = np.sum(np.sum(field * tangent, axis=1)) * small * (2 * np.pi / len(phi))
    np.testing.assert_allclose(circulation, MU0 * turns * current, rtol=1e-9)


def test_divergence_free_off_the_wire():
    a = 0.2
    h = 1e-6
    points = np.array([[0.05, 0.02, 0.1], [0.3, -0.1, 0.05], [0.0, 0.15, -0.02]])
    div = np.zeros(len(points))
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        plus = loop_field(points + step, [0, 0, 0], [0, 0, 1], a, 1, 1.0)
        minus = loop_field(points - step, [0, 0, 0], [0, 0, 1], a, 1, 1.0)
        div += (plus[:, k] - minus[:, k]) / (2 * h)
    scale = np.linalg.norm(loop_field(points, [0, 0, 0], [0, 0, 1], a, 1, 1.0), axis=1) / a
    np.testing.assert_array_less(np.abs(div) / scale, 1e-6)


def test_linear_in_current_and_broadcasts_per_point_currents():
    rng = np.random.default_rng(4)
    points = rng.uniform(-0.3, 0.3, size=(10, 3))
    args = ([0.0, 0.0, 0.01], [0.0, 1.0, 1.0], 0.12, 50)
    one = loop_field(points, *args, 1.0)
    np.testing.assert_allclose(loop_field(points, *args, -2.5), -2.5 * one, rtol=1e-13)
    np.testing.assert_allclose(
        loop_field(points, *args, 1.0) + loop_field(points, *args, 3.0),
        loop_field(points, *args, 4.0),
        rtol=1e-13,
    )
    currents = rng.uniform(-5, 5, size=10)
    np.testing.assert_allclose(loop_field(points, *args, currents), currents[:, None] * one)
    # flipping the axis is the same as reversing the current
    flipped = loop_field(points, args[0], [0.0, -1.0, -1.0], args[2], args[3], 1.0)
    np.testing.assert_allclose(flipped, -one, rtol=1e-13, atol=1e-20)


def test_mirror_symmetry_in_the_loop_plane():
    rng = np.random.default_rng(5)
    points = rng.uniform(-0.4, 0.4, size=(25, 3))
    mirrored = points * np.array([1.0, 1.0, -1.0])
    field = loop_field(points, np.zeros(3), [0, 0, 1], 0.2, 10, 1.0)
    field_m = loop_field(mirrored, np.zeros(3), [0, 0, 1], 0.2, 10, 1.0)
    # B is a pseudovector: under z -> -z its in-plane components flip and Bz is kept
    np.testing.assert_allclose(field_m, field * np.array([-1.0, -1.0, 1.0]), rtol=1e-12, atol=1e-20)


def test_rotating_the_whole_setup_rotates_the_field():
    rng = np.random.default_rng(6)
    rotation = random_rotation(rng)
    points = rng.uniform(-0.4, 0.4, size=(25, 3))
    centre = np.array([0.05, -0.02, 0.1])
    axis = np.array([0.0, 0.0, 1.0])
    field = loop_field(points, centre, axis, 0.15, 7, 2.0)
    turned = loop_field(points @ rotation.T, rotation @ centre, rotation @ axis, 0.15, 7, 2.0)
    np.testing.assert_allclose(turned, field @ rotation.T, rtol=1e-10, atol=1e-18)
    # and about its own axis the field is axisymmetric
    spin = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    spun = loop_field((points - centre) @ spin.T + centre, centre, axis, 0.15, 7, 2.0)
    np.testing.assert_allclose(spun, field @ spin.T, rtol=1e-10, atol=1e-18)


def test_wire_is_masked_and_its_neighbourhood_is_finite():
    a = 0.2
    on_wire = np.array([[a, 0.0, 0.0], [0.0, -a, 0.0], [a / np.sqrt(2), a / np.sqrt(2), 0.0]])
    near = np.array([[a * (1 + 1e-6), 0.0, 0.0], [0.0, a, 1e-6]])
    assert np.isnan(loop_field(on_wire, np.zeros(3), [0, 0, 1], a, 1, 1.0)).all()
    assert np.isfinite(loop_field(near, np.zeros(3), [0, 0, 1], a, 1, 1.0)).all()


def test_shapes_are_preserved():
    grid = np.zeros((4, 5, 3))
    grid[..., 2] = np.linspace(-0.1, 0.1, 5)
    assert loop_field(grid, np.zeros(3), [0, 0, 1], 0.2, 1, 1.0).shape == (4, 5, 3)
    assert loop_field([0.0, 0.0, 0.0], np.zeros(3), [0, 0, 1], 0.2, 1, 1.0).shape == (3,)
    assert dipole_field(grid + 1.0, np.zeros(3), [0, 0, 1]).shape == (4, 5, 3)


def test_bad_geometry_is_refused():
    with pytest.raises(ValueError):
        loop_field(np.zeros(3), np.zeros(3), [0, 0, 0], 0.2, 1, 1.0)
    with pytest.raises(ValueError):
        loop_field(np.zeros(3), np.zeros(3), [0, 0, 1], 0.0, 1, 1.0)


def test_dipole_hand_values():
    m, r = 2.0, 0.5
    centre = np.array([0.1, 0.2, 0.3])
    moment = np.array([0.0, m, 0.0])
    axial = dipole_field(centre + [0.0, r, 0.0], centre, moment)
    equatorial = dipole_field(centre + [0.0, 0.0, -r], centre, moment)
    k = MU0 / (4 * np.pi) * m / r**3
    np.testing.assert_allclose(axial, [0.0, 2 * k, 0.0], rtol=1e-13, atol=1e-20)
    np.testing.assert_allclose(equatorial, [0.0, -k, 0.0], rtol=1e-13, atol=1e-20)
    assert np.isnan(dipole_field(centre, centre, moment)).all()
