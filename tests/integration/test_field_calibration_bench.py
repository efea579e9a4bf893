"""`rigctl calibrate field` on the emulated six-coil bench (its own process: six BOP supplies over
SCPI, the Hall probe array on its own TCP port): the fit finds the coils the bench really has (its
backdoor's ground truth), allocation with the calibration puts 3 mT where it was asked for and
without it does not, and a run on the calibrated rig snapshots the calibration in its record."""

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.cli.main import main
from rigctl.core.config import dump_rig, load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.physics.coils import actuation_matrix
from rigctl.plans.schema import load_plan
from rigctl.rigs.six_coil.allocate import currents_for_field
from rigctl.rigs.six_coil.global_moves import execute_plan

QUICK = Path(__file__).resolve().parents[2] / "plans" / "examples" / "fig4-quick.json"
B0_T = 3e-3


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A bench with 5 % coil errors (seed 0, the default), calibrated by the CLI."""
    folder = tmp_path_factory.mktemp("calibrate")
    with EmulatedBenchProcess("six-coil", folder / "bench.toml") as rig_path:
        # a watchdog that tolerates a loaded CI machine (as test_closed_loop.py's `fast`)
        drawn = load_rig(rig_path)
        drawn = drawn.model_copy(update={"stream": drawn.stream.model_copy(
            update={"reply_timeout_s": 1.0})})
        rig_path.write_text(dump_rig(drawn))
        with BackdoorClient(drawn.emulation.backdoor) as backdoor:
            truth = backdoor.request("coil_errors")["coils"]
            centre = np.array(backdoor.request("coil_fields", points_mm=[[0, 0, 0]])["T_per_A"][0])
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            code = main(["calibrate", "field", "--rig", str(rig_path), "--model", "loops", "--json", "-o",
                         str(folder / "cal.yaml")])
        yield {"code": code, "result": json.loads(out.getvalue()), "drawn": drawn,
               "rig": load_rig(rig_path), "rig_path": rig_path, "truth": truth,
               "true_centre_T_per_A": centre, "folder": folder}


def test_the_fit_finds_the_coils_the_bench_really_has(calibrated):
    assert calibrated["code"] == 0
    result = calibrated["result"]
    assert result["duration_s"] < 60.0 and result["probe_points"] == 27
    calibration = calibrated["rig"].field_calibration
    assert calibration is not None and Path(calibration.source).name == "cal.yaml"
    for true in calibrated["truth"]:
        fit = calibration.coils[true["name"]]
        assert fit.gain == pytest.approx(true["gain"], abs=3e-3), true["name"]
        np.testing.assert_allclose(np.array(fit.centre_m) * 1e3, true["centre_mm"], atol=1.0)
        angle = np.degrees(np.arccos(np.clip(np.dot(fit.axis, true["axis"]), -1, 1)))
        assert angle < 0.2, (true["name"], angle)


def test_allocation_with_the_calibration_puts_the_field_where_it_was_asked(calibrated):
    targets = B0_T * np.concatenate([np.eye(3), -np.eye(3), np.ones((1, 3)) / np.sqrt(3)])
    true_matrix = calibrated["true_centre_T_per_A"]  # (3, 6): the bench's coils at the centre
    errors = {}
    for label in ("drawn", "rig"):
        currents = currents_for_field(actuation_matrix(calibrated[label]), targets)
        made = currents @ true_matrix.T
        errors[label] = np.linalg.norm(made - targets, axis=1).max() / B0_T
    assert errors["drawn"] > 0.01, errors  # 5 % coil errors: uncalibrated is measurably wrong
    assert errors["rig"] < 0.01, errors


def test_a_run_on_the_calibrated_rig_snapshots_its_calibration(calibrated, tmp_path):
    rig = calibrated["rig"]
    summary = execute_plan(load_plan(QUICK), rig, runs_dir=tmp_path / "runs", progress_out=None,
                           closed_loop=False)
    assert not summary.faults, summary.faults
    record = Path(summary.run)
    snapshot = record / "field_calibration.yaml"
    assert snapshot.is_file()
    assert 'field_calibration = "field_calibration.yaml"' in (record / "rig.toml").read_text()
    copy = load_rig(record / "rig.toml").field_calibration
    assert copy.coils == rig.field_calibration.coils


def test_calibrating_a_rig_without_a_probe_is_refused_in_one_line(calibrated, tmp_path, capsys):
    rig = calibrated["drawn"].model_copy(update={"field_probe": None})
    path = tmp_path / "rig.toml"
    path.write_text(dump_rig(rig))
    assert main(["calibrate", "field", "--rig", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "[field_probe]" in err[0]
    assert main(["calibrate", "field", "--rig", str(path), "--grid-mm", "-5"]) == 2
