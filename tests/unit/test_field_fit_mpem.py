"""The six-coil rig's MPEM calibration (`rigctl.rigs.six_coil.field_fit.fit_mpem_calibration`)
without hardware: the emulated bench's true coils (5 % errors, `rigctl.emulators.coil_errors`)
read at the probe's 27 grid points with a background and the probe's noise; the fitted model is
judged against the true coils' Biot-Savart field at points the probe never visited."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.core.config import RigInfo, default_six_coil_coils
from rigctl.emulators.coil_errors import CoilErrors, true_coils
from rigctl.physics.field_calibration import probe_grid_mm
from rigctl.physics.fields import LoopModel, load_mpem, write_mpem
from rigctl.rigs.six_coil.field_fit import (
    Measurements,
    drive_patterns,
    fit_mpem_calibration,
    held_out_split,
    mpem_start,
)
from rigctl.rigs.six_coil.settings import SixCoilRig

BACKGROUND_T = np.array([20e-6, -5e-6, 45e-6])
NOISE_T = 3e-6  # the emulated probe's (MLX90395-like) noise


def _rig() -> SixCoilRig:
    return SixCoilRig(rig=RigInfo(kind="six-coil", name="test"), coils=default_six_coil_coils())


def _probe(rig, truth, seed: int = 0) -> Measurements:
    points = probe_grid_mm(100.0) * 1e-3
    patterns = drive_patterns(rig)
    maps = np.stack([c.field_per_amp(points) for c in truth], axis=-1)  # (K, 3, 6) T/A
    fields = np.einsum("kin,pn->pki", maps, patterns) + BACKGROUND_T
    fields += np.random.default_rng(seed).normal(0.0, NOISE_T, fields.shape)
    return Measurements(points, patterns, fields, np.full(len(patterns), 10), 1.0)


def _relative_error(model, truth, points: np.ndarray, currents: np.ndarray) -> float:
    """RMS |B_model - B_true| / mean |B_true| over points and currents, the coils' field only
    (the background is not the coils'; the model's Offset is left out the same way)."""
    true = np.einsum("kin,pn->pki", np.stack([c.field_per_amp(points) for c in truth], axis=-1),
                     currents)
    per_A = model.field_and_gradient_per_ampere(points)[:, :-1, 0:3]  # (K, n, 3)
    made = np.einsum("knj,pn->pkj", per_A, currents)
    return float(np.sqrt(np.mean(np.sum((made - true) ** 2, axis=-1)))
                 / np.mean(np.linalg.norm(true, axis=-1)))


@pytest.fixture(scope="module")
def fits():
    """The rig, the bench's true coils (5 %, seed 0) and an MPEM of each order fitted to them."""
    rig = _rig()
    truth = true_coils(rig.coils, CoilErrors(0.05, seed=0))
    m = _probe(rig, truth)
    return rig, truth, {order: fit_mpem_calibration(rig, m, order=order) for order in (1, 2, 3)}


def test_an_order_three_mpem_knows_the_true_coils_far_better_than_the_drawing(fits, tmp_path):
    rig, truth, by_order = fits
    calibration = by_order[3]
    rng = np.random.default_rng(5)
    points = rng.uniform(-0.1, 0.1, (100, 3))  # inside the probed box, never probed
    currents = rng.uniform(-10.0, 10.0, (8, 6))
    fitted = _relative_error(calibration.model, truth, points, currents)
    drawn = _relative_error(LoopModel.from_rig(rig), truth, points, currents)
    assert drawn > 0.03 and fitted < 0.005, (fitted, drawn)
    # the Offset is the background (uniform here)
    np.testing.assert_allclose(calibration.model.offset(np.zeros(3))[0:3], BACKGROUND_T,
                               atol=5e-6)
    # the held-out figures the command prints say the same, on the probe's own samples
    assert calibration.held_out_pct < 1.0 < 3.0 < calibration.drawn_pct
    assert len(calibration.held_points) == 7 and len(calibration.fitted_points) == 20
    # mag_manip's file: the rig's coils in order, order 3, the whole probed box as workspace
    path = tmp_path / "cal.yaml"
    write_mpem(calibration.model, path)
    loaded = load_mpem(path)
    assert loaded.coil_names == tuple(c.name for c in rig.coils)
    assert loaded.max_order == 3 and loaded.has_offset
    assert loaded.workspace_m == ((-0.1, 0.1),) * 3
    np.testing.assert_array_equal(loaded.actuation(points), calibration.model.actuation(points))


def test_every_order_fits_and_a_higher_one_errs_less(fits):
    _, _, by_order = fits
    for order, calibration in by_order.items():
        assert calibration.model.max_order == order
    errors = [by_order[order].held_out_pct for order in (3, 2, 1)]
    assert errors == sorted(errors) and errors[-1] < by_order[1].drawn_pct, errors


def test_the_held_out_sensors_are_a_seeded_quarter_and_the_start_sits_behind_each_coil():
    fitted, held = held_out_split(27, seed=0)
    assert len(held) == 7 and sorted(np.concatenate([fitted, held]).tolist()) == list(range(27))
    assert np.array_equal(held, held_out_split(27, seed=0)[1])
    assert not np.array_equal(held, held_out_split(27, seed=1)[1])
    assert len(held_out_split(2)[1]) == 1
    loops = LoopModel.from_rig(_rig())
    start = mpem_start(loops, np.zeros(3))
    for (centre, _, radius, _, _), (source,) in zip(loops.loops, start.coil_sources):
        # half a radius further from the workspace centre than the coil, on its axis line
        assert np.linalg.norm(source.position_m) == pytest.approx(np.linalg.norm(centre)
                                                                   + 0.5 * radius)


def test_the_patterns_current_is_the_one_asked_within_the_coils_limit():
    """`calibrate field --current A`: each coil alone at +-A and the mixes within it (an iron-core
    station saturates the probe at the default, half the smallest limit); above the limit refused."""
    from rigctl.core.errors import ConfigError
    from rigctl.rigs.six_coil.field_fit import drive_patterns

    rig = _rig()
    limit = min(c.current_limit_A for c in rig.coils)
    assert np.abs(drive_patterns(rig)).max() == pytest.approx(0.5 * limit)
    asked = drive_patterns(rig, current_A=1.25)
    assert np.abs(asked).max() == pytest.approx(1.25)
    singles = asked[1:1 + 2 * len(rig.coils)]  # each coil alone at +I then -I
    assert sorted(np.abs(singles).sum(axis=1)) == pytest.approx([1.25] * 2 * len(rig.coils))
    with pytest.raises(ConfigError, match="--current"):
        drive_patterns(rig, current_A=limit * 1.01)
