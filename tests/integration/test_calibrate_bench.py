"""`rigctl calibrate camera --plan` against the emulated six-coil bench: the bench lays the plan's
workspace on its floor, and the calibration found maps the camera's pixels to the floor as the
emulated camera projects it (cv2.projectPoints of its pinhole model, not the homography)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.cli.main import main
from rigctl.core.config import dump_rig, load_rig

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "fig4-quick.json"
TOLERANCE_MM = 0.25  # a quarter of the camera's ~0.65 mm pixel on that floor


def test_calibrating_the_emulated_bench_recovers_its_camera(tmp_path, capsys):
    from rigctl.emulators.bench import SixCoilBench

    with SixCoilBench() as bench:
        uncalibrated = bench.rig.model_copy(update={
            "camera": bench.rig.camera.model_copy(update={"calibration": None})})
        rig_file = tmp_path / "rig.toml"
        rig_file.write_text(dump_rig(uncalibrated))
        assert main(["calibrate", "camera", "--rig", str(rig_file), "--plan", str(PLAN)]) == 0
        camera = bench.camera.renderer.camera  # the emulator's own camera model
        # floor points across the free floor (fig4-quick's walls are 50 mm thick), to pixels
        grid = np.stack(np.meshgrid(np.linspace(50, 350, 7), np.linspace(50, 350, 7)),
                        -1).reshape(-1, 2)
        pixels = camera.project(grid)
    assert "laid on its floor" in capsys.readouterr().err
    calibrated = load_rig(rig_file).camera.calibration
    error = np.hypot(*(calibrated.to_mm(pixels) - grid).T)
    assert error.max() < TOLERANCE_MM, error.max()
