"""The dual-EPM bench's finite cylindrical magnets against the planner's dipole and closed forms
(the consistency checks magpylib's own suite makes: a magnet against a dipole far away), and the
Hall board reading that field on the emulated bench."""

from pathlib import Path

import numpy as np
import pytest
from magpylib.func import cylinder_field
from scipy.spatial.transform import Rotation

from rigctl.emulators.world.epm import CylinderEpms
from rigctl.physics.magnetics import MU0, dipole_field, field_vector

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "depm-plan.json"
MOMENT = 970.0  # A m^2: an N52 cylinder of 101.6 mm x 101.6 mm (Br ~1.48 T)
EPM = CylinderEpms()


def _directions(n: int, seed: int) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1)[:, None]


def _relative_difference(r_m: float, seed: int = 0) -> np.ndarray:
    """|B_cylinder - B_dipole| / |B_dipole| at distance r in 20 random directions from a magnet of
    random orientation."""
    points = r_m * _directions(20, seed)
    moment = MOMENT * _directions(1, seed + 1)
    b = EPM.field(points, np.zeros((1, 3)), moment)
    d = dipole_field(points, np.zeros(3), moment[0])
    return np.linalg.norm(b - d, axis=1) / np.linalg.norm(d, axis=1)


def test_far_away_the_cylinder_is_the_planners_dipole():
    far = _relative_difference(1.0)
    assert far.max() < 3e-3
    # the first correction to a dipole (l = 3) falls as r^-5: relative to it, as r^-2
    ratio = np.median(_relative_difference(0.5) / far)
    assert 3.0 < ratio < 5.0, ratio


def test_within_15_cm_it_is_percent_off_the_dipole():
    """The issue's 1-13 % within 15 cm (the range over directions at 15 cm)."""
    near = _relative_difference(0.15, seed=3)
    assert near.max() > 0.01 and near.max() < 0.13, near
    assert _relative_difference(0.10, seed=3).max() > near.max()  # worse nearer


def test_on_its_axis_the_field_is_the_textbook_closed_form():
    """B_z(z) = J/2 [(z + L/2) / sqrt((z + L/2)^2 + R^2) - (z - L/2) / sqrt((z - L/2)^2 + R^2)]."""
    R, L = EPM.diameter_m / 2, EPM.length_m
    J = MU0 * MOMENT / (np.pi * R**2 * L)
    for z in (0.08, 0.15, 0.3):
        expected = J / 2 * ((z + L / 2) / np.hypot(z + L / 2, R) - (z - L / 2) / np.hypot(z - L / 2, R))
        b = EPM.field(np.array([[0.0, 0.0, z]]), np.zeros((1, 3)), np.array([[0.0, 0.0, MOMENT]]))
        np.testing.assert_allclose(b[0], [0.0, 0.0, expected], rtol=1e-10, atol=1e-15)


def test_posed_magnets_agree_with_magpylibs_own_rotation_and_superpose():
    centres = np.array([[0.25, 0.02, 0.1], [-0.2, 0.05, 0.15]])
    directions = _directions(2, 7)
    points = np.random.default_rng(8).uniform(-0.03, 0.03, size=(5, 3))
    ours = EPM.field(points, centres, MOMENT * directions)
    J = MU0 * MOMENT / EPM.volume_m3
    theirs = np.zeros_like(points)
    for centre, direction in zip(centres, directions):
        rotation, _ = Rotation.align_vectors([direction], [[0.0, 0.0, 1.0]])
        theirs += cylinder_field("B", points, dimensions=(EPM.diameter_m, EPM.length_m),
                                 polarizations=(0.0, 0.0, J), positions=centre,
                                 orientations=rotation)
    np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-12)


def test_its_U_differs_from_the_models_by_a_few_percent_at_the_rigs_distances():
    centres = np.array([[0.25, 0.0, 0.12], [-0.22, 0.05, 0.15]])
    moments = MOMENT * np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    exact = EPM.field_vector(np.zeros(3), centres, moments)
    model = field_vector(np.zeros(3), centres, moments)
    assert np.linalg.norm(exact[:3]) == pytest.approx(np.linalg.norm(model[:3]), rel=0.1)
    assert np.linalg.norm(exact[:3] - model[:3]) / np.linalg.norm(model[:3]) > 0.002
    # the gradient by central differences does not depend on the step (truncation and round-off
    # both small): the same U from a step four times longer
    coarse = EPM.field_vector(np.zeros(3), centres, moments, step_m=4e-4)
    np.testing.assert_allclose(coarse, exact, rtol=1e-5, atol=1e-9)


def test_the_emulated_hall_board_reads_the_cylinders():
    from rigctl.drivers.hall import HallBoard
    from rigctl.emulators.backdoor import BackdoorClient
    from rigctl.emulators.depm import DepmBench
    from rigctl.plans.depm import joints_at
    from rigctl.plans.schema import load_plan

    plan = load_plan(PLAN)  # the shipped plan at its first hold: 10 mT at the centre
    q = joints_at(plan, [plan.segments[0].reached_s + 1.0])[:, 0]  # (A, 7)
    with DepmBench() as bench, BackdoorClient(bench.rig.emulation.backdoor) as backdoor:
        for arm, qa in zip(plan.arms, q):
            backdoor.request("place", arm=arm.name, q=qa.tolist())
        truth = backdoor.request("truth")
        board = HallBoard.open(bench.rig.depm.hall_url, timeout_s=2.0)
        fields = np.mean([board.read().field_T for _ in range(60)], axis=0)  # (3, 3)
        board.close()
    centres, moments = np.array(truth["epm_centres_m"]), np.array(truth["epm_moments_Am2"])
    points = board.info.offsets_m
    expected = EPM.field(points, centres, moments)
    dipoles = dipole_field(points[:, None, :], centres, moments).sum(axis=1)
    noise = 3e-6 / np.sqrt(60) * 4 + 2.5e-6  # 4 sigma of the mean, plus one LSB
    np.testing.assert_allclose(fields, expected, atol=noise)
    assert np.abs(fields - dipoles).max() > 5 * noise  # and not the dipole model's field
    assert truth["magnets"] == "cylinder"


def test_the_cylinder_kernel_is_magpylibs_inside_outside_and_on_the_mantles_line():
    """The closed form against magpylib's own kernel (an independent implementation of the same
    paper), over points inside, outside, on the axis and at rho = 1 exactly (gamma = 0: the
    integral's parameter p = 0, the branch Bulirsch's algorithm turns first)."""
    from magpylib.core import magnet_cylinder_axial_Bfield

    from rigctl.physics.magnetics import cylinder_axial_field

    rng = np.random.default_rng(11)
    rho = np.concatenate([rng.uniform(0, 6, 400), np.zeros(20), np.ones(20)])
    z = np.concatenate([rng.uniform(-6, 6, 400), rng.uniform(-3, 3, 20), rng.uniform(1.5, 4, 20)])
    half = np.full(rho.size, 0.9)
    b_rho, _, b_z = magnet_cylinder_axial_Bfield(half, rho, z)
    ours = cylinder_axial_field(half, rho, z)
    np.testing.assert_allclose(ours[0], b_rho, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(ours[1], b_z, rtol=1e-9, atol=1e-14)
