"""The Hall board: sensor quantisation and saturation, the eq. 24 estimator, the stream driver."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rigctl.apps.testing import ScriptedTransport
from rigctl.core.errors import ConfigError, DeviceTimeout, ProtocolError
from rigctl.drivers.hall import HallBoard
from rigctl.emulators.hall.board import HallSensorModel, SensorSpec, sample_line
from rigctl.physics.magnetics import (
    MU0,
    dipole_field,
    dipole_gradient,
    field_vector_from_sensors,
    gradient_design,
)

PAPER_OFFSETS_M = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0.0]])


def test_quantised_to_the_lsb_and_clipped_at_the_range():
    model = HallSensorModel(SensorSpec(noise_T=0.0))
    counts, saturated = model.measure(np.array([[10e-3, -2.5e-6, 1.24e-6],
                                                [60e-3, -70e-3, 49.9e-3]]))
    # 10 mT / 2.5 uT = 4000 counts; 1.24 uT rounds to 0; +-50 mT is +-20000 counts
    assert counts.tolist() == [[4000, -1, 0], [20000, -20000, 19960]]
    assert saturated.tolist() == [[False, False, False], [True, True, False]]


def test_noise_has_the_stated_rms():
    spec = SensorSpec(noise_T=3e-6)
    counts, _ = HallSensorModel(spec, seed=1).measure(np.zeros((20000, 3)))
    rms = np.std(counts * spec.lsb_T)
    # quantising Gaussian noise of sigma to a step q adds about q^2/12 of variance
    assert rms == pytest.approx(np.sqrt(spec.noise_T**2 + spec.lsb_T**2 / 12), rel=0.03)


def eq24(fields, delta):
    """Seed 003 eq. 24 written out for sensor 2 at +delta x and sensor 3 at +delta y."""
    b1, b2, b3 = fields
    dxx = (b2[0] - b1[0]) / delta
    dxy = 0.5 * ((b3[0] - b1[0]) / delta + (b2[1] - b1[1]) / delta)
    dxz = (b2[2] - b1[2]) / delta
    dyy = (b3[1] - b1[1]) / delta
    dyz = (b3[2] - b1[2]) / delta
    return np.array([*b1, dxx, dxy, dxz, dyy, dyz])


def test_estimator_is_eq24_on_the_papers_board():
    fields = np.random.default_rng(3).normal(size=(3, 3)) * 1e-2
    assert np.allclose(field_vector_from_sensors(fields, PAPER_OFFSETS_M), eq24(fields, 0.05))


def test_estimator_is_exact_for_a_linear_field_with_any_offsets():
    g_terms = np.array([0.1, -0.05, 0.02, 0.07, -0.03])
    g = np.array([[0.1, -0.05, 0.02], [-0.05, 0.07, -0.03], [0.02, -0.03, -0.17]])
    b0 = np.array([1e-3, -2e-3, 5e-4])
    offsets = np.array([[0.01, 0.0, 0.002], [0.03, 0.01, -0.004], [-0.005, 0.02, 0.01]])
    fields = b0 + (offsets - offsets[0]) @ g.T
    assert np.allclose(field_vector_from_sensors(fields, offsets), [*b0, *g_terms])


def test_estimator_converges_to_the_dipole_gradient_as_the_board_shrinks():
    centre, moment = np.array([0.3, -0.1, 0.15]), np.array([0, 0, 970.0])
    exact_g = dipole_gradient(np.zeros(3), centre, moment)
    exact = np.array([exact_g[0, 0], exact_g[0, 1], exact_g[0, 2], exact_g[1, 1], exact_g[1, 2]])
    errors = []
    for delta in (0.05, 0.01, 0.002):
        offsets = PAPER_OFFSETS_M * delta / 0.05
        u = field_vector_from_sensors(dipole_field(offsets, centre, moment), offsets)
        assert np.allclose(u[:3], dipole_field(np.zeros(3), centre, moment))
        errors.append(np.max(np.abs(u[3:] - exact)) / np.max(np.abs(exact)))
    # first-order accurate: the error shrinks in proportion to the sensor spacing
    assert errors[0] > errors[1] > errors[2]
    assert errors[1] / errors[2] == pytest.approx(5.0, rel=0.15)
    # scale check against the closed form: |G| ~ 3 mu0 m / (4 pi r^4)
    r = np.linalg.norm(centre)
    assert np.max(np.abs(exact)) < 3 * 3 * MU0 * 970 / (4 * np.pi * r**4)


def test_degenerate_offsets_are_a_config_error():
    with pytest.raises(ConfigError, match="two different directions"):
        gradient_design(np.array([[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0.0]]))


HELLO = json.dumps({"type": "hello", "version": 1, "board": "b", "sensor": "MLX90395",
                    "lsb_uT": 2.5, "range_mT": 50.0, "offsets_mm": [[0, 0, 0], [50, 0, 0], [0, 50, 0]],
                    "rate_hz": 100}).encode() + b"\n"


def line(seq, counts=((4000, 0, 0), (0, 0, 0), (0, 0, 0)), sat=(False, False, False)):
    sat_arr = np.array([[s, False, False] for s in sat])
    return sample_line(seq, 0.01 * seq, np.array(counts), sat_arr).encode() + b"\n"


def test_driver_reads_samples_and_counts_gaps():
    t = ScriptedTransport([(None, HELLO), (None, line(1)), (None, line(2)), (None, line(6)),
                           (None, line(7, sat=(True, False, False)))])
    board = HallBoard(t, timeout_s=0.1)
    assert board.info.lsb_T == pytest.approx(2.5e-6)
    first = board.read()
    assert first.field_T[0, 0] == pytest.approx(10e-3)  # 4000 counts x 2.5 uT
    board.read()
    board.read()
    assert board.missed == 3 and board.gaps == [(2, 6)]
    last = board.read()
    assert last.saturated[0].tolist() == [True, False, False]
    with pytest.raises(DeviceTimeout, match="stopped streaming"):
        board.read()


def test_driver_rejects_garbage_and_wrong_versions():
    t = ScriptedTransport([(None, HELLO), (None, b"\xff\xfe garbage\n")])
    board = HallBoard(t)
    with pytest.raises(ProtocolError, match="hall board: not a JSON line"):
        board.read()
    old = HELLO.replace(b'"version": 1', b'"version": 0')
    with pytest.raises(ProtocolError, match="version"):
        HallBoard(ScriptedTransport([(None, old)]))


def test_out_of_range_numbers_are_a_protocol_error():
    # JSON reads 1e999 as inf; int(inf) is an OverflowError, which must not end the reader thread
    bad = line(1).replace(b'"seq":1', b'"seq":1e999')
    board = HallBoard(ScriptedTransport([(None, HELLO), (None, bad)]))
    with pytest.raises(ProtocolError, match="hall board: bad sample line"):
        board.read()


def test_rigctl_emulate_s_probe_noise_sets_the_bench_s_sensors_and_refuses_a_bad_value():
    """`rigctl emulate six-coil --probe-noise MT`: the Hall probe's RMS noise per axis (mT) is the
    sensors' (20,000 readings of no field spread by it); a negative one is refused in one line."""
    import pytest

    from rigctl.apps.cli.main import build_parser
    from rigctl.core.errors import ConfigError
    from rigctl.emulators.bench import SixCoilBench

    args = build_parser().parse_args(["emulate", "six-coil", "--probe-noise", "0.05"])
    spec = SixCoilBench.from_args(args).probe_spec
    counts, _ = HallSensorModel(spec, seed=1).measure(np.zeros((20000, 3)))
    assert np.std(counts * spec.lsb_T) == pytest.approx(5e-5, rel=0.02)
    assert SixCoilBench.from_args(build_parser().parse_args(["emulate", "six-coil"])).probe_spec \
        == SensorSpec()  # an MLX90395's own
    with pytest.raises(ConfigError, match="--probe-noise"):
        SixCoilBench.from_args(build_parser().parse_args(["emulate", "six-coil", "--probe-noise",
                                                          "-1"]))
