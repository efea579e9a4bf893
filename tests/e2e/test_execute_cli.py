"""`rigctl` end to end, as a user runs it: subprocesses, the emulated bench in its own process."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rigctl.emulators.process import EmulatedBenchProcess

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "plans" / "examples"


def rigctl(*args, cwd):
    return subprocess.run([sys.executable, "-m", "rigctl", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=600)


def check_reached_expected(result, plan_path):
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    plan = json.loads(plan_path.read_text())
    assert summary["reached"] is True
    expected_final = np.array(plan["expected"][-1])
    finals = np.array([a["final"] for a in summary["agents"]])
    # the emulated world, moved only by the field the supplies made, ends where the model said
    np.testing.assert_allclose(finals, expected_final, atol=0.5)
    assert Path(summary["run"]).is_dir()
    return summary


@pytest.mark.parametrize("name", ["fig4-quick.json", "fig4-two-magnets.json"])
def test_execute_example_on_the_emulated_bench(name, tmp_path):
    plan = EXAMPLES / name
    result = rigctl("execute", str(plan), "--json", "--runs", str(tmp_path / "runs"), cwd=tmp_path)
    summary = check_reached_expected(result, plan)
    assert "emulator ground truth" in result.stdout
    run = Path(summary["run"])
    for name in ("plan.json", "rig.toml", "events.jsonl", "stream.csv", "summary.json"):
        assert (run / name).is_file(), name


def test_emulate_then_execute_with_the_rig_file_behaves_the_same(tmp_path):
    plan = EXAMPLES / "fig4-quick.json"
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml") as rig_path:
        assert "[emulation]" in rig_path.read_text()
        result = rigctl("execute", str(plan), "--rig", str(rig_path), "--json", "--runs",
                        str(tmp_path / "runs"), cwd=tmp_path)
    check_reached_expected(result, plan)


def test_validate_names_the_broken_field(tmp_path):
    result = rigctl("validate", str(EXAMPLES / "broken-plan.json"), cwd=tmp_path)
    assert result.returncode == 2
    assert "radius" in result.stderr


def test_validate_accepts_the_examples(tmp_path):
    for plan in ("fig4-quick.json", "fig4-two-magnets.json"):
        result = rigctl("validate", str(EXAMPLES / plan), cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        assert result.stdout.startswith("OK")


def test_schema_plan_is_json_schema(tmp_path):
    result = rigctl("schema", "plan", cwd=tmp_path)
    assert result.returncode == 0
    schema = json.loads(result.stdout)
    assert "global-moves" in json.dumps(schema)
