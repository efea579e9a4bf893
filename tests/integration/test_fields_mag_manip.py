"""rigctl's MPEM against ETH's mag_manip 3.0.0 on the same files, to 1e-9 relative.

mag_manip needs numpy < 2, so it runs in a virtual environment of its own (`.ci/run` makes
`.venv-mag-manip`; $RIGCTL_MAG_MANIP_PYTHON names another) through `tools/mag_manip_eval.py`, one
file per process: mag_manip drops the Offset of every model loaded after the first in a process.
Without that environment these tests skip, saying so."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from rigctl.core.errors import ConfigError
from rigctl.physics.fields import MPEM, Source, load_mpem, write_mpem
from rigctl.physics.fields.stations import octomag_like

ROOT = Path(__file__).resolve().parents[2]


def side_python() -> str | None:
    for candidate in (os.environ.get("RIGCTL_MAG_MANIP_PYTHON"),
                      str(ROOT / ".venv-mag-manip" / "bin" / "python")):
        if candidate and Path(candidate).exists():
            return candidate
    return None


PYTHON = side_python()
pytestmark = pytest.mark.skipif(PYTHON is None, reason="no Python with mag_manip 3.0.0 "
                                "(.ci/run makes .venv-mag-manip; or set RIGCTL_MAG_MANIP_PYTHON)")


def in_mag_manip(path: Path, points: np.ndarray, currents: np.ndarray) -> dict:
    request = {"points_m": points.tolist(), "currents_A": currents.tolist(), "repeat": 0}
    done = subprocess.run([PYTHON, str(ROOT / "tools" / "mag_manip_eval.py"), str(path)],
                          input=json.dumps(request), capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def assert_agree(model: MPEM, theirs: dict, points: np.ndarray, currents: np.ndarray) -> None:
    ours = np.stack([[model.actuation(p) @ i + model.offset(p) for i in currents]
                     for p in points])
    mm = np.array(theirs["field_gradient5"])
    for rows in (slice(0, 3), slice(3, 8)):  # field (T) and gradient (T/m) rows apart
        scale = np.max(np.abs(mm[..., rows]))
        assert np.max(np.abs(ours[..., rows] - mm[..., rows])) <= 1e-9 * scale
    mm_a, ours_a = np.array(theirs["actuation"]), model.actuation(points)
    for rows in (slice(0, 3), slice(3, 8)):
        scale = np.max(np.abs(mm_a[:, rows]))
        assert np.max(np.abs(ours_a[:, rows] - mm_a[:, rows])) <= 1e-9 * scale


def test_a_file_rigctl_writes_gives_the_same_numbers_in_mag_manip(tmp_path):
    base = octomag_like(3, seed=2)
    rng = np.random.default_rng(9)
    # an A source of orders 1-3 beside each coil's B source: both kinds, every order
    coils = [list(s) + [Source(tuple(rng.uniform(-0.05, 0.05, 3)), tuple(rng.normal(size=3)),
                               "A", (2e-4, -3e-3, 4e-2))] for s in base.coil_sources]
    model = MPEM(base.coil_names, coils, base.offset_sources, name="rigctl-written",
                 workspace_m=base.workspace_m)
    path = tmp_path / "written.yaml"
    write_mpem(model, path)
    points = rng.uniform(-0.03, 0.03, (5, 3))
    currents = rng.uniform(-5, 5, (3, 8))
    theirs = in_mag_manip(path, points, currents)
    assert theirs["coils"] == 8
    assert_agree(load_mpem(path), theirs, points, currents)
    # the Offset counts in mag_manip too: at zero current it is all there is
    zero = in_mag_manip(path, points[:1], np.zeros((1, 8)))
    assert np.allclose(np.array(zero["field_gradient5"])[0, 0, 0:3], [0.0, 0.0, -5e-5],
                       rtol=1e-12)


HAND_TYPED = """
Coil_List: [Offset, North, South, East]
System_Name: typed
Workspace_Dimensions: [[-0.02, 0.02], [-0.02, 0.02], [-0.02, 0.02]]
Offset:
  Source_List: [Src_0]
  Src_0: {A_Coeff: [2e-05, 1e-04], B_Coeff: ~, Source_Direction: [0, 1, 1],
          Source_Position: [0.001, 0, 0]}
North:
  Source_List: [Src_0]
  Src_0: {A_Coeff: ~, B_Coeff: [7e-07, -4e-09, 1e-10], Source_Direction: [0, -1, 0.1],
          Source_Position: [0, 0.09, 0]}
South:
  Source_List: [Src_0]
  Src_0: {A_Coeff: null, B_Coeff: [7e-07], Source_Direction: [0, 1, 0],
          Source_Position: [0, -0.09, 0]}
East:
  Source_List: [Src_1, Src_0]
  Src_0: {A_Coeff: ~, B_Coeff: [6e-07, 2e-09], Source_Direction: [-1, 0, 0],
          Source_Position: [0.09, 0, 0.01]}
  Src_1: {A_Coeff: [1e-03], B_Coeff: ~, Source_Direction: [0, 0, 1], Source_Position: [0, 0, 0]}
"""


def test_a_hand_typed_file_reads_as_mag_manip_reads_it(tmp_path):
    """The Offset listed first, nulls written ~ and null, numbers PyYAML reads as strings (1e-03),
    Source_List out of order: the currents are North, South, East in both."""
    path = tmp_path / "typed.yaml"
    path.write_text(HAND_TYPED)
    model = load_mpem(path)
    assert model.coil_names == ("North", "South", "East")
    rng = np.random.default_rng(5)
    points = rng.uniform(-0.02, 0.02, (4, 3))
    currents = rng.uniform(-3, 3, (3, 3))
    assert_agree(model, in_mag_manip(path, points, currents), points, currents)


def test_a_missing_coefficient_key_is_refused_as_mag_manip_refuses_it(tmp_path):
    path = tmp_path / "missing.yaml"
    path.write_text(HAND_TYPED.replace("A_Coeff: null, ", ""))
    with pytest.raises(ConfigError, match="South.Src_0.A_Coeff: missing"):
        load_mpem(path)
    done = subprocess.run([PYTHON, str(ROOT / "tools" / "mag_manip_eval.py"), str(path)],
                          input='{"points_m": [], "currents_A": []}', capture_output=True,
                          text=True, timeout=120)
    assert done.returncode != 0 and "Both A_Coeff and B_Coeff defined" in done.stderr
