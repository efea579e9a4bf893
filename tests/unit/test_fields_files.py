"""mag_manip's MPEM calibration files: written and read back to the same numbers, malformed files
refused with one line naming the key, the older "rigctl-loop-v1" files still read (as loops)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from rigctl.core.errors import ConfigError
from rigctl.physics.field_calibration import FORMAT, CoilFit, FieldCalibration
from rigctl.physics.fields import (
    MPEM,
    LoopModel,
    Source,
    load_field_model,
    load_mpem,
    mpem_to_yaml,
    parse_mpem,
    write_mpem,
)
from rigctl.physics.fields.stations import octomag_like
from rigctl.physics.magnetics import loop_field

# A small file in mag_manip's layout, typed out here: two coils and an Offset, A and B sources.
SMALL = """
System_Name: two coils
Workspace_Dimensions: [[-0.02, 0.02], [-0.03, 0.03], [-0.01, 0.01]]
Coil_List: [Left, Right, Offset]
Left:
  Source_List: [Src_0]
  Src_0:
    A_Coeff: ~
    B_Coeff: [1.0e-07, 2.0e-09]
    Source_Direction: [2.0, 0.0, 0.0]
    Source_Position: [-0.1, 0.0, 0.0]
Right:
  Source_List: [Src_0, Src_1]
  Src_0:
    A_Coeff: ~
    B_Coeff: [-1e-07]
    Source_Direction: [1.0, 0.0, 0.0]
    Source_Position: [0.1, 0.0, 0.0]
  Src_1:
    A_Coeff: [1.0e-04]
    B_Coeff: null
    Source_Direction: [0.0, 0.0, 1.0]
    Source_Position: [0.0, 0.0, 0.0]
Offset:
  Source_List: [Src_0]
  Src_0:
    A_Coeff: [3.0e-05]
    B_Coeff: ~
    Source_Direction: [0.0, 1.0, 0.0]
    Source_Position: [0.0, 0.0, 0.0]
"""


def test_a_file_reads_as_mag_manip_reads_it():
    model = parse_mpem(yaml.safe_load(SMALL), "small.yaml")
    assert model.name == "two coils"
    assert model.coil_names == ("Left", "Right")  # Coil_List order, Offset apart
    assert model.workspace_m == ((-0.02, 0.02), (-0.03, 0.03), (-0.01, 0.01))
    assert model.has_offset
    assert model.in_workspace([[0.0, 0.0, 0.0], [0.0, 0.0, 0.011]]).tolist() == [True, False]
    # directions normalised; "1e-07" (a string to PyYAML, a number to yaml-cpp) is a number
    assert model.coil_sources[0][0].direction == (2.0, 0.0, 0.0)
    assert model.coil_sources[1][0].coefficients == (-1e-07,)
    # The field at the centre by hand. On a source's axis grad c = 0, so B = -f'(r) P_n(c) u with
    # u the unit vector from the source: Left (c = 1, u = +x): f = B1 r^-2 + B2 r^-3 gives
    # (2 B1 r^-3 + 3 B2 r^-4) x. Right (c = -1, u = -x, P1(-1) = -1): 2 B1 r^-3 x. Right's A
    # source is the uniform -A z, the Offset's -3e-5 y.
    field = model.field(np.zeros(3), [1.0, 0.0])
    left = 2 * 1e-7 / 0.1**3 + 3 * 2e-9 / 0.1**4
    assert np.allclose(field, [left, -3e-5, 0.0], rtol=1e-12, atol=1e-18)
    field_right = model.field(np.zeros(3), [0.0, 1.0]) - model.field(np.zeros(3), [0.0, 0.0])
    assert np.allclose(field_right, [2 * -1e-7 / 0.1**3, 0.0, -1e-4], rtol=1e-12, atol=1e-18)


def test_a_written_file_reads_back_to_the_same_numbers(tmp_path):
    model = octomag_like(3, seed=5)
    path = tmp_path / "octomag.yaml"
    write_mpem(model, path, comment="made by a test")
    back = load_mpem(path)
    assert back.coil_names == model.coil_names and back.name == model.name
    pts = np.random.default_rng(1).uniform(-0.03, 0.03, (10, 3))
    assert np.array_equal(back.actuation(pts), model.actuation(pts))
    assert np.array_equal(back.offset(pts), model.offset(pts))
    text = path.read_text()
    assert text.startswith("# made by a test\n")
    data = yaml.safe_load(text)
    assert data["Coil_List"][-1] == "Offset"
    assert data["Coil_0"]["Src_0"]["A_Coeff"] is None  # the null mag_manip expects


def test_a_coil_named_like_the_offset_is_not_written():
    model = MPEM(["Offset_coil"], [[Source((0.1, 0, 0), (1, 0, 0), "B", (1e-7,))]])
    with pytest.raises(ConfigError, match="Offset_coil"):
        mpem_to_yaml(model)


def edit(path: list, value) -> dict:
    data = yaml.safe_load(SMALL)
    node = data
    for key in path[:-1]:
        node = node[key]
    if value is KeyError:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return data


@pytest.mark.parametrize(("data", "key"), [
    (edit(["System_Name"], KeyError), "System_Name"),
    (edit(["Coil_List"], KeyError), "Coil_List"),
    (edit(["Coil_List"], []), "Coil_List"),
    (edit(["Coil_List"], ["Left", "Middle"]), "Middle"),
    (edit(["Workspace_Dimensions"], [[-1, 1], [-1, 1]]), "Workspace_Dimensions"),
    (edit(["Workspace_Dimensions"], [[1, -1], [-1, 1], [-1, 1]]), "Workspace_Dimensions"),
    (edit(["Left", "Source_List"], KeyError), "Left.Source_List"),
    (edit(["Left", "Source_List"], ["Src_0", "Src_9"]), "Left.Src_9"),
    (edit(["Left", "Src_0", "A_Coeff"], [1.0]), "Left.Src_0"),  # both given
    (edit(["Left", "Src_0", "B_Coeff"], None), "Left.Src_0"),  # neither
    (edit(["Left", "Src_0", "A_Coeff"], KeyError), "Left.Src_0.A_Coeff"),  # mag_manip: "both"
    (edit(["Left", "Src_0", "B_Coeff"], []), "Left.Src_0.B_Coeff"),
    (edit(["Left", "Src_0", "B_Coeff"], [1e-7, "x"]), "Left.Src_0.B_Coeff"),
    (edit(["Left", "Src_0", "Source_Direction"], [0.0, 0.0, 0.0]),
     "Left.Src_0.Source_Direction"),  # mag_manip aborts the process on this one
    (edit(["Left", "Src_0", "Source_Direction"], [1.0, 0.0]), "Left.Src_0.Source_Direction"),
    (edit(["Right", "Src_1", "Source_Position"], KeyError), "Right.Src_1.Source_Position"),
    (edit(["Right", "Src_1", "Source_Position"], [0, 0, ".nan"]), "Right.Src_1.Source_Position"),
    (edit(["Coil_List"], ["Left", "Right", "Offset", "Offset_2"]), "Offset_2"),
])
def test_a_malformed_file_is_refused_with_one_line_naming_the_key(data, key, tmp_path):
    if "Offset_2" in data.get("Coil_List", []):
        data["Offset_2"] = copy.deepcopy(data["Offset"])
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_field_model(path)
    message = str(err.value)
    assert key in message and str(path) in message and "\n" not in message


def test_a_missing_or_unreadable_file_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_field_model(tmp_path / "nope.yaml")
    (tmp_path / "bad.yaml").write_text("Coil_List: [a\n  b: c")
    with pytest.raises(ConfigError, match="cannot be read as YAML"):
        load_field_model(tmp_path / "bad.yaml")


def test_a_rigctl_loop_v1_file_reads_as_loops(tmp_path):
    fits = {
        name: CoilFit(centre_m=centre, axis=axis, radius_m=0.05, turns=200, gain=gain,
                      offset_m=(0.0, 0.0, 0.0), tilt_rad=0.0)
        for name, centre, axis, gain in [("X+", (0.2, 0.0, 0.0), (-1.0, 0.0, 0.0), 0.97),
                                         ("Z+", (0.0, 0.0, 0.2), (0.0, 0.1, -1.0), 1.03)]}
    calibration = FieldCalibration(name="old", model=FORMAT, workspace_m=(-0.1, 0.1) * 3,
                                   coil_list=["X+", "Z+"], coils=fits,
                                   actuation_matrix=[[0.0, 0.0]] * 3)
    path = tmp_path / "old.yaml"
    path.write_text(calibration.to_yaml())
    model = load_field_model(path)
    assert isinstance(model, LoopModel) and model.coil_names == ("X+", "Z+")
    pts = np.array([[0.01, -0.02, 0.03], [0.0, 0.0, 0.0]])
    expected = (0.97 * 2.0 * loop_field(pts, (0.2, 0, 0), (-1, 0, 0), 0.05, 200, 1.0)
                - 1.03 * loop_field(pts, (0, 0, 0.2), (0, 0.1, -1.0), 0.05, 200, 1.0))
    assert np.allclose(model.field(pts, [2.0, -1.0]), expected, rtol=1e-13)
    assert np.allclose(model.offset(pts), 0.0)
