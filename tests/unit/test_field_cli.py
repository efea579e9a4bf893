"""`rigctl field` (issue 37, item 6): the field a rig makes for given currents, and the currents
for a wanted field, from a rig file or a calibration file alone; values checked against a loop's
on-axis closed form and against a pseudo-inverse built from the command's own unit responses."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.cli.main import main
from rigctl.physics.fields import write_mpem
from rigctl.physics.fields.stations import octomag_like

ROOT = Path(__file__).resolve().parents[2]
SIX_COIL = ROOT / "rigctl" / "rigs" / "six_coil" / "template.toml"
MU0 = 4e-7 * math.pi


def _json(capsys, *argv: str) -> dict:
    assert main(["field", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_one_coil_of_the_cube_gives_a_loops_field_on_its_axis(capsys):
    """x+ of the template: 400 turns of radius 200 mm centred 350 mm out on x; at the centre
    B_x = mu0 N I a^2 / (2 (a^2 + d^2)^(3/2)) along the coil's axis, and no other component."""
    out = _json(capsys, str(SIX_COIL), "--at", "0,0,0", "--currents", "2,0,0,0,0,0")
    a, d, n, i = 0.2, 0.35, 400, 2.0
    expected_mT = MU0 * n * i * a**2 / (2 * (a**2 + d**2) ** 1.5) * 1e3
    np.testing.assert_allclose(out["field_mT"], [expected_mT, 0, 0], rtol=1e-9, atol=1e-12)
    assert out["coils"] == ["x+", "x-", "y+", "y-", "z+", "z-"]


def test_the_currents_for_a_wanted_field_are_the_minimum_norm_ones(tmp_path, capsys):
    path = tmp_path / "octo.yaml"
    write_mpem(octomag_like(3, seed=2), path)
    at = "5,-3,2"
    # the rig's response, measured through the command one coil at a time, and its offset
    zero = np.array(_json(capsys, str(path), "--at", at, "--currents", ",".join(["0"] * 8))["field_mT"])
    columns = []
    for k in range(8):
        unit = ["0"] * 8
        unit[k] = "1"
        columns.append(np.array(_json(capsys, str(path), "--at", at, "--currents", ",".join(unit))["field_mT"]) - zero)
    response = np.array(columns).T  # (3, 8) mT/A
    wanted = np.array([3.0, -2.0, 8.0])
    out = _json(capsys, str(path), "--at", at, "--want-field", "3,-2,8")
    np.testing.assert_allclose(out["currents_A"], np.linalg.pinv(response) @ (wanted - zero), rtol=1e-7,
                               atol=1e-9)
    np.testing.assert_allclose(out["field_mT"], wanted, rtol=1e-9, atol=1e-9)


def test_field_and_gradient_together_on_eight_coils(tmp_path, capsys):
    path = tmp_path / "octo.yaml"
    write_mpem(octomag_like(3, seed=2), path)
    out = _json(capsys, str(path), "--at", "0,0,0", "--want-field", "0,0,5", "--want-gradient", "40,0,0,-10,0")
    np.testing.assert_allclose(out["field_mT"], [0, 0, 5], atol=1e-9)
    np.testing.assert_allclose(out["gradient_terms_mT_per_m"], [40, 0, 0, -10, 0], atol=1e-7)
    g = np.array(out["gradient_mT_per_m"])
    assert np.allclose(g, g.T) and abs(np.trace(g)) < 1e-7  # Maxwell: symmetric, traceless


@pytest.mark.parametrize(("argv", "says"), [
    (["--at", "0,0", "--currents", "1,0,0,0,0,0"], "--at: expected 3 numbers"),
    (["--at", "0,0,0"], "give --currents"),
    (["--at", "0,0,0", "--currents", "1,0,0"], "--currents: expected 6 numbers"),
    (["--at", "0,0,0", "--currents", "25,0,0,0,0,0"], "beyond its limit of 20 A"),
    (["--at", "0,0,0", "--want-field", "0,0,100"], "within the limits this rig makes"),
    (["--at", "0,0,nan", "--currents", "1,0,0,0,0,0"], "finite"),
])
def test_bad_requests_are_one_line_and_exit_2(capsys, argv, says):
    assert main(["field", str(SIX_COIL), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err


def test_a_rig_without_coils_and_a_missing_file_are_refused(capsys):
    assert main(["field", str(ROOT / "rigctl" / "rigs" / "depm" / "template.toml"), "--at", "0,0,0",
                 "--currents", "1"]) == 2
    assert "no coils" in capsys.readouterr().err
    assert main(["field", "nope.yaml", "--at", "0,0,0", "--currents", "1"]) == 2
    assert "is not a file" in capsys.readouterr().err
