"""One field model for an electromagnet rig (`rigctl.physics.coils.field_model`): a loop rig's
matrices are the loops' fields as before, a rig whose `field_calibration` is a mag_manip MPEM
file takes its field from that file (its Offset subtracted when allocating), and a malformed
file is refused in one line naming the key. Values are computed here independently: the loop's
field by `loop_field` point by point, a dipole source by the dipole formula."""

import numpy as np
import pytest

from rigctl.core.config import RigInfo, default_six_coil_coils, dump_rig, load_rig
from rigctl.core.errors import ConfigError
from rigctl.physics.coils import (
    MPEMCalibration,
    actuation_matrix,
    coil_field_and_gradient,
    field_model,
    field_offset,
    u_actuation_matrix,
)
from rigctl.physics.fields import MPEM, LoopModel, Source, mpem_to_yaml
from rigctl.physics.magnetics import gradient_terms, loop_field
from rigctl.rigs.six_coil.allocate import allocate
from rigctl.rigs.six_coil.realize import FieldProgram
from rigctl.rigs.six_coil.settings import SixCoilRig

POINT_MM = np.array([12.0, -7.0, 5.0])


def _rig(**update) -> SixCoilRig:
    return SixCoilRig(rig=RigInfo(kind="six-coil", name="test"), coils=default_six_coil_coils(),
                      **update)


def test_a_loop_rigs_matrices_are_its_loops_fields():
    rig = _rig()
    assert isinstance(field_model(rig), LoopModel)
    point_m = POINT_MM * 1e-3
    expected = np.stack([loop_field(point_m, np.array(c.centre_mm) * 1e-3, np.array(c.axis),
                                    c.loop_radius_mm * 1e-3, c.turns, 1.0) for c in rig.coils],
                        axis=1)
    np.testing.assert_allclose(actuation_matrix(rig, POINT_MM), expected, rtol=1e-13, atol=0)
    # the gradient: a central difference of loop_field taken here with a step 4x larger, which
    # agrees to its truncation (~(h / 0.3 m)^2)
    h = 0.2e-3
    fg = coil_field_and_gradient(rig, POINT_MM)
    for k, c in enumerate(rig.coils):
        args = (np.array(c.centre_mm) * 1e-3, np.array(c.axis), c.loop_radius_mm * 1e-3, c.turns,
                1.0)
        for j in range(3):
            step = np.zeros(3)
            step[j] = h
            d = (loop_field(point_m + step, *args) - loop_field(point_m - step, *args)) / (2 * h)
            np.testing.assert_allclose(fg[:, 1 + j, k], d, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(fg[:, 0, :], expected, rtol=1e-13, atol=0)
    assert np.all(field_offset(rig) == 0.0)  # loops have no offset
    u = u_actuation_matrix(rig, POINT_MM)
    np.testing.assert_allclose(u[3:], gradient_terms(np.moveaxis(fg[:, 1:, :], -1, 0)).T)


def _dipole_mpem(rig: SixCoilRig, order: tuple[int, ...], offset_T: float) -> MPEM:
    """One dipole source (B_1 = 2e-6 T m^3/A) 0.3 m out along each coil's axis, directed along it, and
    a uniform Offset of `offset_T` along +x; coils listed in `order`."""
    coils = [rig.coils[k] for k in order]
    sources = [[Source(tuple(0.3 * np.array(c.axis) * np.sign(np.dot(c.centre_mm, c.axis))
                             if np.dot(c.centre_mm, c.axis) else 0.3 * np.array(c.axis)),
                       tuple(np.array(c.axis)), "B", (2e-6,))] for c in coils]
    # an A source of order 1 is the uniform field -A_1 z
    offset = [Source((0.0, 0.0, 0.0), (-1.0, 0.0, 0.0), "A", (offset_T,))]
    return MPEM([c.name for c in coils], sources, offset, name="dipoles",
                workspace_m=((-0.05, 0.05),) * 3)


def _dipole_field(point_m, position_m, direction, b1):
    """The point dipole's field, B = B_1 (3 (z.u) u - z) / r^3 (moment 4 pi B_1 / mu0 along z)."""
    d = np.asarray(point_m) - np.asarray(position_m)
    r = np.linalg.norm(d)
    u = d / r
    z = np.asarray(direction) / np.linalg.norm(direction)
    return b1 * (3.0 * np.dot(z, u) * u - z) / r**3


def _mpem_rig(tmp_path, mpem: MPEM) -> SixCoilRig:
    (tmp_path / "cal.yaml").write_text(mpem_to_yaml(mpem))
    (tmp_path / "rig.toml").write_text('field_calibration = "cal.yaml"\n' + dump_rig(_rig()))
    return load_rig(tmp_path / "rig.toml")


def test_an_mpem_rig_takes_its_field_from_the_file_in_the_rigs_coil_order(tmp_path):
    nominal = _rig()
    shuffled = (3, 0, 5, 1, 4, 2)  # the file lists the coils in another order than the rig
    rig = _mpem_rig(tmp_path, _dipole_mpem(nominal, shuffled, 4e-5))
    assert isinstance(rig.field_calibration, MPEMCalibration)
    assert field_model(rig).coil_names == tuple(c.name for c in rig.coils)
    A = actuation_matrix(rig, POINT_MM)
    mpem = rig.field_calibration.model
    for k, c in enumerate(rig.coils):
        src = mpem.coil_sources[mpem.coil_names.index(c.name)][0]
        np.testing.assert_allclose(A[:, k], _dipole_field(POINT_MM * 1e-3, src.position_m,
                                                          src.direction, 2e-6), rtol=1e-12)
    np.testing.assert_allclose(field_offset(rig)[0:3], [4e-5, 0.0, 0.0], rtol=1e-12)
    # the dumped rig names the file, and its record keeps the file's text
    assert 'field_calibration = "' in dump_rig(rig)
    _, files = rig.for_record()
    assert files["field_calibration.yaml"] == (tmp_path / "cal.yaml").read_text()


def test_allocation_on_an_mpem_rig_subtracts_its_offset(tmp_path):
    rig = _mpem_rig(tmp_path, _dipole_mpem(_rig(), tuple(range(6)), 4e-5))
    n = 5
    field = np.array([[1e-3, 0.0, 0.0], [0.0, 1e-3, 0.0], [0.0, 0.0, 1e-3], [4e-5, 0.0, 0.0],
                      [-5e-4, 5e-4, 0.0]])
    program = FieldProgram(t_s=np.arange(n) / 10.0, field_T=field, segment=np.zeros(n, int),
                           kind=np.zeros(n, np.uint8), rate_hz=10.0)
    currents = allocate(program, rig).currents_A
    # the field the file says these currents make at the centre, offset included
    made = np.array([rig.field_calibration.model.field(np.zeros(3), np.array(
        [i[[c.name for c in rig.coils].index(name)] for name in rig.field_calibration.coil_list]))
        for i in currents])
    np.testing.assert_allclose(made, field, atol=1e-12)
    np.testing.assert_allclose(currents[3], 0.0, atol=1e-12)  # the offset alone: coils off


@pytest.mark.parametrize("edit, key", [
    (lambda t: t.replace("Source_Direction: [1.0, 0.0, 0.0]", "Source_Direction: [0, 0, 0]", 1),
     "Source_Direction"),
    (lambda t: t.replace("Coil_List:", "Coil_Lisst:"), "Coil_List"),
    (lambda t: t.replace("B_Coeff: [2.0e-06]", "B_Coeff: [oops]", 1), "B_Coeff"),
])
def test_a_malformed_mpem_file_is_refused_in_one_line_naming_the_key(tmp_path, edit, key):
    text = mpem_to_yaml(_dipole_mpem(_rig(), tuple(range(6)), 4e-5))
    bad = edit(text)
    assert bad != text
    (tmp_path / "cal.yaml").write_text(bad)
    (tmp_path / "rig.toml").write_text('field_calibration = "cal.yaml"\n' + dump_rig(_rig()))
    with pytest.raises(ConfigError) as err:
        load_rig(tmp_path / "rig.toml")
    assert key in str(err.value) and "\n" not in str(err.value)


def test_an_mpem_file_of_other_coils_is_refused_naming_them(tmp_path):
    mpem = _dipole_mpem(_rig(), tuple(range(6)), 0.0)
    other = MPEM(["a", "b", "c", "d", "e", "f"], mpem.coil_sources, (), name="other",
                 workspace_m=mpem.workspace_m)
    (tmp_path / "cal.yaml").write_text(mpem_to_yaml(other))
    (tmp_path / "rig.toml").write_text('field_calibration = "cal.yaml"\n' + dump_rig(_rig()))
    with pytest.raises(ConfigError, match="field_calibration.*Coil_List"):
        load_rig(tmp_path / "rig.toml")


# -- N coils: the six-coil cube is one instance ---------------------------------------------------

def _coils_toml(n: int, names: list[str] | None = None) -> str:
    """`n` loops of 0.1 m radius, 0.25 m from the centre, their axes spread over a half sphere
    (a golden spiral) and pointing at it; each fed by its own supply."""
    names = names or [f"c{k}" for k in range(n)]
    out = []
    for k, name in enumerate(names):
        z = 1.0 - (k + 0.5) / n
        phi = k * np.pi * (3.0 - np.sqrt(5.0))
        axis = np.array([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z])
        centre = -250.0 * axis
        out.append(f'[[coils]]\nname = "{name}"\nurl = "tcp://127.0.0.1:{5100 + k}"\n'
                   f"centre_mm = {centre.tolist()}\naxis = {axis.tolist()}\nloop_radius_mm = 100.0\n"
                   "turns = 300\nresistance_ohm = 1.0\ninductance_H = 0.01\n")
    return "\n".join(out)


def _n_coil_rig(tmp_path, n, names=None):
    from rigctl.core.registry import rig_kind

    (tmp_path / "rig.toml").write_text('[rig]\nkind = "six-coil"\nname = "n coils"\n\n'
                                       + _coils_toml(n, names))
    rig = load_rig(tmp_path / "rig.toml")
    return rig, rig_kind("six-coil")


@pytest.mark.parametrize("n", [3, 8])
def test_a_rig_of_n_coils_loads_allocates_and_has_n_channels(tmp_path, n):
    rig, kind = _n_coil_rig(tmp_path, n)
    assert len(rig.coils) == n
    assert [c.name for c in kind.channels(rig)] == [f"c{k}" for k in range(n)]
    assert [d.name for d in kind.devices(rig) if d.kind == "supply"] == [f"c{k}" for k in range(n)]
    A = actuation_matrix(rig)
    assert A.shape == (3, n)
    field = np.array([[2e-4, -1e-4, 5e-5], [0.0, 0.0, 3e-4]])
    program = FieldProgram(t_s=np.arange(2) / 10.0, field_T=field, segment=np.zeros(2, int),
                           kind=np.zeros(2, np.uint8), rate_hz=10.0)
    currents = allocate(program, rig).currents_A
    assert currents.shape == (2, n)
    # the field each coil's loop makes, summed here coil by coil
    made = sum(np.outer(currents[:, k], loop_field(np.zeros(3), np.array(c.centre_mm) * 1e-3,
                                                   np.array(c.axis), 0.1, 300, 1.0))
               for k, c in enumerate(rig.coils))
    np.testing.assert_allclose(made, field, atol=1e-12)


def test_too_few_coils_or_a_repeated_name_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="at least 3"):
        _n_coil_rig(tmp_path, 2)
    with pytest.raises(ConfigError, match="unique"):
        _n_coil_rig(tmp_path, 4, ["a", "b", "c", "a"])


# -- what a rig cannot make ---------------------------------------------------------------------

def _triad_rig(tmp_path, calibrated: bool) -> SixCoilRig:
    """The Helmholtz triad as the emulated bench draws it (a loop per pair), with its MPEM (three
    uniform-field sources) as the field calibration if `calibrated`."""
    from rigctl.emulators.bench import nominal_coils
    from rigctl.physics.fields.stations import helmholtz_triad

    rig = SixCoilRig(rig=RigInfo(kind="six-coil", name="triad"),
                     coils=nominal_coils(helmholtz_triad()))
    (tmp_path / "rig.toml").write_text(dump_rig(rig))
    if calibrated:
        (tmp_path / "triad.yaml").write_text(mpem_to_yaml(helmholtz_triad(seed=2)))
        (tmp_path / "rig.toml").write_text('field_calibration = "triad.yaml"\n' + dump_rig(rig))
    return load_rig(tmp_path / "rig.toml")


def test_a_uniform_field_triad_makes_a_rotating_field_but_no_gradient(tmp_path):
    from rigctl.physics.coils import max_planar_gradient

    rig = _triad_rig(tmp_path, calibrated=True)
    A = actuation_matrix(rig)
    # each pair's uniform field per ampere, (4/5)^1.5 mu0 N / R, N = 100, R = 0.10, 0.12, 0.14 m
    expected = 0.7155417527999327 * 4e-7 * np.pi * 100 / np.array([0.10, 0.12, 0.14])
    np.testing.assert_allclose(np.linalg.norm(A, axis=0), expected, rtol=0.06)  # +-5 % as built
    assert np.all(u_actuation_matrix(rig)[3:] == 0.0)
    # the pseudo-inverse gives no current for a gradient: the rig can make none, not any
    assert max_planar_gradient(rig, 3e-3) == 0.0
    assert max_planar_gradient(_rig(), 3e-3) > 0.0  # the six-coil cube can


def test_the_preflight_field_check_counts_the_offset(tmp_path):
    from rigctl.rigs.six_coil.certify import current_program_checks

    rig = _mpem_rig(tmp_path, _dipole_mpem(_rig(), tuple(range(6)), 4e-5))
    checks = current_program_checks(rig, np.zeros((3, 6)), 100.0, move_ends=[2])
    field = next(c for c in checks if c.check == "field |B| at the centre")
    assert field.value == pytest.approx(4e-2, rel=1e-9)  # 40 uT with the supplies off, in mT


def test_rigctl_field_on_a_rig_file_uses_the_mpem_it_names(tmp_path, capsys):
    import json

    from rigctl.apps.cli.main import main

    rig = _mpem_rig(tmp_path, _dipole_mpem(_rig(), tuple(range(6)), 4e-5))
    assert main(["field", str(tmp_path / "rig.toml"), "--at", "0,0,0", "--currents",
                 "1,0,0,0,0,0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    src = rig.field_calibration.model.coil_sources[0][0]
    want = _dipole_field(np.zeros(3), src.position_m, src.direction, 2e-6) + [4e-5, 0.0, 0.0]
    np.testing.assert_allclose(out["field_mT"], want * 1e3, rtol=1e-9)


@pytest.mark.parametrize("station", ["helmholtz-triad", "octomag-like", "navion-like"])
def test_the_bench_draws_each_coil_as_a_loop_as_strong_at_the_centre(station):
    from rigctl.emulators.bench import nominal_coils
    from rigctl.physics.fields.stations import STATIONS

    drawing = STATIONS[station]()
    coils = nominal_coils(drawing)
    assert [c.name for c in coils] == list(drawing.coil_names)
    want = drawing.field_actuation(np.zeros(3))
    for k, c in enumerate(coils):
        got = loop_field(np.zeros(3), np.array(c.centre_mm) * 1e-3, np.array(c.axis),
                         c.loop_radius_mm * 1e-3, c.turns, 1.0)
        # along the drawing's field, as strong to within half a turn
        np.testing.assert_allclose(got, want[:, k], rtol=0.5 / c.turns + 1e-9,
                                   atol=np.linalg.norm(want[:, k]) * 0.5 / c.turns)


def test_a_rig_file_naming_an_mpem_loads_equal_twice(tmp_path):
    _mpem_rig(tmp_path, _dipole_mpem(_rig(), tuple(range(6)), 4e-5))
    assert load_rig(tmp_path / "rig.toml") == load_rig(tmp_path / "rig.toml")
