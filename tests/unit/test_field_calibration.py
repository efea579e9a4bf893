"""The six-coil field calibration without hardware: the file format, the allocator's use of it, the
emulated coil errors, and the fit against loops whose true parameters the test chose."""

import numpy as np
import pytest

from rigctl.core.config import RigConfig, RigInfo, default_six_coil_coils, dump_rig, load_rig
from rigctl.core.errors import ConfigError
from rigctl.emulators.coil_errors import CoilErrors, as_calibration, true_coils
from rigctl.physics.coils import actuation_matrix
from rigctl.physics.field_calibration import (
    load_field_calibration,
    parse_field_calibration,
    probe_grid_mm,
)
from rigctl.physics.magnetics import MU0, loop_field
from rigctl.rigs.six_coil.field_fit import (
    Measurements,
    fit_calibration,
    fit_coil,
    measured_maps,
)
from rigctl.rigs.six_coil.settings import SixCoilRig


def _rig(**update) -> RigConfig:
    return SixCoilRig(rig=RigInfo(kind="six-coil", name="test"), coils=default_six_coil_coils(),
                     **update)


def _on_axis_T_per_A(distance_m: float, radius_m: float = 0.2, turns: int = 400) -> float:
    """A loop's field on its axis, the textbook closed form mu0 N a^2 / (2 (a^2 + z^2)^1.5)."""
    return MU0 * turns * radius_m**2 / (2.0 * (radius_m**2 + distance_m**2) ** 1.5)


def test_a_calibration_file_round_trips_and_the_allocator_uses_its_loops(tmp_path):
    rig = _rig()
    truth = true_coils(rig.coils, CoilErrors(size=0.0))
    # x+ is 10 % stronger and 5 mm nearer the centre than drawn
    truth[0] = type(truth[0])("x+", np.array([0.345, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), 0.2, 400,
                              1.1)
    calibration = as_calibration(truth, rig.coils)
    path = tmp_path / "cal.yaml"
    path.write_text(calibration.to_yaml())
    text = path.read_text()
    assert "Coil_List" in text and "Actuation_Matrix" in text and "x+:" in text
    loaded = load_field_calibration(path)
    assert loaded.coils == calibration.coils
    (tmp_path / "rig.toml").write_text('field_calibration = "cal.yaml"\n' + dump_rig(rig))
    calibrated = load_rig(tmp_path / "rig.toml")  # named relative to the rig file
    A = actuation_matrix(calibrated)
    assert A[0, 0] == pytest.approx(1.1 * _on_axis_T_per_A(0.345), rel=1e-9)
    assert A[0, 1] == pytest.approx(_on_axis_T_per_A(0.350), rel=1e-9)  # x- as drawn
    assert actuation_matrix(rig)[0, 0] == pytest.approx(_on_axis_T_per_A(0.350), rel=1e-9)
    # the rig file written back still names the file, not its contents
    assert 'field_calibration = "' in dump_rig(calibrated)


@pytest.mark.parametrize("edit, complaint", [
    (lambda d: d.pop("x-"), "x-"),
    (lambda d: d["x+"].update(Gain=-1.0), "Gain"),
    (lambda d: d["x+"].update(Colour="red"), "Colour"),
    (lambda d: d.update(Calibration_Model="mpem"), "Calibration_Model"),
])
def test_a_bad_calibration_file_is_named(edit, complaint):
    rig = _rig()
    import yaml

    data = yaml.safe_load(as_calibration(true_coils(rig.coils, CoilErrors()), rig.coils).to_yaml())
    edit(data)
    with pytest.raises(ConfigError, match=complaint):
        parse_field_calibration(data, "cal.yaml")


def test_a_rig_file_naming_a_missing_calibration_is_refused_by_name(tmp_path):
    (tmp_path / "rig.toml").write_text('field_calibration = "nowhere.yaml"\n' + dump_rig(_rig()))
    with pytest.raises(ConfigError, match="nowhere.yaml does not exist"):
        load_rig(tmp_path / "rig.toml")


def test_emulated_coil_errors_are_seeded_and_within_their_size():
    coils = default_six_coil_coils()
    ideal = true_coils(coils, CoilErrors(size=0.0))
    for true, drawn in zip(ideal, coils):
        assert true.gain == 1.0
        np.testing.assert_allclose(true.centre_m, np.array(drawn.centre_mm) * 1e-3)
        np.testing.assert_allclose(true.axis, drawn.axis)
    a, b = true_coils(coils, CoilErrors(0.05, seed=3)), true_coils(coils, CoilErrors(0.05, seed=3))
    assert [c.gain for c in a] == [c.gain for c in b]
    assert [c.gain for c in a] != [c.gain for c in true_coils(coils, CoilErrors(0.05, seed=4))]
    for true, drawn in zip(a, coils):
        assert abs(true.gain - 1.0) <= 0.05
        assert np.linalg.norm(true.centre_m - np.array(drawn.centre_mm) * 1e-3) <= 0.05 * 0.2 + 1e-12
        assert np.arccos(np.clip(true.axis @ np.array(drawn.axis), -1, 1)) <= 0.05 + 1e-12
    with pytest.raises(ValueError, match="coil error size"):
        CoilErrors(size=-0.1)


def test_the_fit_recovers_a_loop_the_test_displaced():
    points = probe_grid_mm(100.0) * 1e-3
    centre, axis = np.array([0.35, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    tilt = np.radians(2.0)
    true_axis = np.array([np.cos(tilt), np.sin(tilt), 0.0])
    true_centre = centre + np.array([-0.004, 0.007, 0.003])
    column = 0.97 * loop_field(points, true_centre, true_axis, 0.2, 400, 1.0)
    noisy = column + np.random.default_rng(0).normal(0.0, 1e-8, column.shape)  # ~0.1 % per ampere
    x, sigma, _ = fit_coil(points, noisy, centre, axis, 0.2, 400)
    assert x[0] == pytest.approx(0.97, abs=3e-3)
    np.testing.assert_allclose(x[1:4], true_centre - centre, atol=5e-4)
    assert (sigma > 0).all() and sigma[0] < 3e-3


def test_stage_one_separates_the_coils_and_the_background():
    rig = _rig()
    truth = true_coils(rig.coils, CoilErrors(0.05, seed=1))
    points = probe_grid_mm(100.0) * 1e-3
    maps = np.stack([c.field_per_amp(points) for c in truth], axis=-1)  # (K, 3, 6)
    currents = np.random.default_rng(2).uniform(-10, 10, size=(20, 6))
    background = np.array([20e-6, -5e-6, 45e-6])
    fields = np.einsum("kin,pn->pki", maps, currents) + background
    m = Measurements(points, currents, fields, np.full(20, 10), 1.0)
    F, b, rms = measured_maps(m)
    assert rms < 1e-12  # noise-free data: the linear model is exact
    np.testing.assert_allclose(F, maps, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b, np.broadcast_to(background, b.shape), atol=1e-12)
    calibration = fit_calibration(rig, m)
    for true in truth:
        fit = calibration.coils[true.name]
        assert fit.gain == pytest.approx(true.gain, abs=1e-6)
        np.testing.assert_allclose(fit.centre_m, true.centre_m, atol=1e-6)
        np.testing.assert_allclose(fit.axis, true.axis, atol=1e-6)


def test_the_file_reads_with_any_yaml_reader():
    """A lab's own tools read it: plain YAML, SI numbers, one mapping per coil."""
    import yaml

    rig = _rig()
    text = as_calibration(true_coils(rig.coils, CoilErrors()), rig.coils).to_yaml()
    data = yaml.safe_load(text)
    assert data["Coil_List"] == [c.name for c in rig.coils]
    assert np.array(data["Actuation_Matrix"]).shape == (3, 6)
    assert len(data["x+"]["Loop_Centre"]) == 3
