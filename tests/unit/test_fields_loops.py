"""The loop model behind the FieldModel interface: the six-coil cube's field and gradient per
ampere at the centre against the on-axis closed forms of a circular loop."""

from __future__ import annotations

import math

import numpy as np

from rigctl.core.config import FieldSettings, RigConfig, RigInfo, default_six_coil_coils, settings_of
from rigctl.physics.coils import u_actuation_matrix
from rigctl.physics.fields import LoopModel

MU0 = 4e-7 * math.pi


def cube() -> RigConfig:
    return settings_of("six-coil")(rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils(),
                     field=FieldSettings())


def test_the_cube_at_its_centre_against_the_on_axis_closed_forms():
    rig = cube()
    model = LoopModel.from_rig(rig)
    assert model.coil_names == tuple(c.name for c in rig.coils)
    A = model.actuation(np.zeros(3))
    for k, coil in enumerate(rig.coils):
        a, turns = coil.loop_radius_mm * 1e-3, coil.turns
        centre = np.asarray(coil.centre_mm) * 1e-3
        axis = np.asarray(coil.axis, dtype=float) / np.linalg.norm(coil.axis)
        z = float(-centre @ axis)  # the centre's coordinate along the coil's axis
        b_axis = MU0 * turns * a * a / (2 * (a * a + z * z) ** 1.5)
        assert np.allclose(A[0:3, k], b_axis * axis, rtol=1e-9, atol=1e-15)
        # d Bz/dz on the axis, projected on the five terms: G = g (3 n n^T - I) / 2 there
        g = -3 * MU0 * turns * a * a * z / (2 * (a * a + z * z) ** 2.5)
        grad = g * (3 * np.outer(axis, axis) - np.eye(3)) / 2
        terms = [grad[0, 0], grad[0, 1], grad[0, 2], grad[1, 1], grad[1, 2]]
        assert np.allclose(A[3:, k], terms, rtol=1e-6, atol=1e-9 * abs(g))
    # the same matrix the six-coil allocator uses today
    assert np.allclose(A, u_actuation_matrix(rig), rtol=1e-12, atol=0)
    assert np.allclose(model.offset(np.zeros(3)), 0.0)


def test_the_fits_starting_dipoles_are_the_loops_far_away():
    """start_from_loops puts at each coil a dipole of the loop's moment N I pi a^2: far from the
    coil (10 m, 50 radii) the two fields agree to the loop's (a/r)^2 correction."""
    from rigctl.physics.fields.fit import start_from_loops

    loops = LoopModel.from_rig(cube())
    dipoles = start_from_loops(loops)
    far = np.array([[10.0, 3.0, -4.0], [-6.0, 8.0, 2.0]])
    for k in range(loops.n_coils):
        currents = np.eye(loops.n_coils)[k]
        expected = loops.field(far, currents)
        assert np.allclose(dipoles.field(far, currents), expected, rtol=1e-3,
                           atol=1e-3 * np.max(np.abs(expected)))
