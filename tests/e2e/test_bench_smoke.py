"""Every bench script still runs: a quick run of each prints one JSON object and exits 0. The
figures themselves are measured by running the scripts in full (see the README), not here."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"

QUICK = {
    "stream.py": ["--seconds", "0.5", "--rates", "100"],
    "rrt.py": ["--quick"],
    "tracker.py": ["--seconds", "0.5", "--closed-loop-runs", "0"],
    "closed_loop.py": ["--runs", "1"],  # with --random-goals: 2 min of re-plans
    "daemon.py": ["--seconds", "0.3"],
    "coilboard_link.py": ["--round-trips", "50", "--seconds", "0.5", "--trials", "1"],
    "coilboard.py": ["--pairs", "2", "--runs", "1", "--mobility-spread", "0.1"],
    "depm.py": ["--time-scale", "8", "--no-random"],
    "pair.py": ["--quick"],
    "preflight.py": ["--rig", "six-coil", "--repeat", "1"],
    "certificate.py": ["--quick"],
    "fuzz_daemon.py": ["--requests", "200", "--plans", "20"],
    "faults.py": ["--rig", "six-coil", "--cell", "daemon/x+:drop_link/moving"],
    "soak.py": ["--minutes", "0.3", "--interval", "2"],
    "calibrate_field.py": ["--seeds", "0"],
    "study.py": ["--quick"],
    "console.py": ["--quick"],
}


def test_every_bench_script_has_a_quick_run() -> None:
    assert {p.name for p in BENCH.glob("*.py")} == set(QUICK)


@pytest.mark.parametrize("script", sorted(QUICK))
def test_the_bench_runs_and_prints_one_json_object(script: str, tmp_path) -> None:
    done = subprocess.run([sys.executable, str(BENCH / script), *QUICK[script]],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    figures = json.loads(done.stdout)
    assert isinstance(figures, dict) and figures
