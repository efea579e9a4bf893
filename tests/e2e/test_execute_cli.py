"""`rigctl` end to end, as a user runs it: subprocesses, the emulated bench in its own process."""

import json
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.testing import run_rigctl
from rigctl.emulators.process import EmulatedBenchProcess

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "plans" / "examples"


# These checks need an ideal bench: `--coil-error 0` makes its coils exactly the rig file's (the
# default bench's coils are off by up to 5 %, and the closed loop corrects what that costs:
# `test_the_default_bench_has_coil_errors_that_the_closed_loop_corrects`).
IDEAL_COILS = ["--coil-error", "0"]

# How far the emulated world may end from the plan's model on a bench without model mismatch.
# At the realizer's speeds the two differ only by the coils' L/R lag (a few hundredths of a mm);
# half the plans' 1 mm tolerance leaves room for the tracker and still fails when the field's
# path changes (samples bunched after stalls once moved a robot past it under load).
WORLD_FOLLOWS_MODEL_MM = 0.5


def check_reached_expected(result, plan_path):
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    plan = json.loads(plan_path.read_text())
    assert summary["reached"] is True
    expected_final = np.array(plan["expected"][-1])
    goals = np.array([a["goal"] for a in plan["agents"]])
    np.testing.assert_array_equal(expected_final, goals)  # so the goal errors below are the model's
    # the emulated world, moved only by the field the supplies made, followed the model without
    # the closed loop having to correct it ...
    assert summary.get("replans", 0) == 0, summary
    # ... and ends where the model said: in the camera's view ...
    finals = np.array([a["final"] for a in summary["agents"]])
    np.testing.assert_allclose(finals, expected_final, atol=WORLD_FOLLOWS_MODEL_MM)
    # ... and in the emulator's ground truth (the final positions themselves when open loop)
    truth = [a.get("truth_error_mm", a["error_mm"]) for a in summary["agents"]]
    assert max(truth) <= WORLD_FOLLOWS_MODEL_MM, summary["agents"]
    assert Path(summary["run"]).is_dir()
    return summary


@pytest.mark.parametrize("name", ["fig4-quick.json", "fig4-two-magnets.json"])
def test_execute_example_on_the_emulated_bench(name, tmp_path):
    plan = EXAMPLES / name
    result = run_rigctl("execute", str(plan), *IDEAL_COILS, "--json", "--runs", str(tmp_path / "runs"),
                        cwd=tmp_path)
    summary = check_reached_expected(result, plan)
    assert "emulator ground truth" in result.stdout
    run = Path(summary["run"])
    for name in ("plan.json", "rig.toml", "events.jsonl", "stream.csv", "summary.json"):
        assert (run / name).is_file(), name


def test_emulate_then_execute_with_the_rig_file_behaves_the_same(tmp_path):
    plan = EXAMPLES / "fig4-quick.json"
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml", extra_args=IDEAL_COILS) as rig_path:
        assert "[emulation]" in rig_path.read_text()
        result = run_rigctl("execute", str(plan), "--rig", str(rig_path), "--json", "--runs",
                        str(tmp_path / "runs"), cwd=tmp_path)
    check_reached_expected(result, plan)


def test_the_default_bench_has_coil_errors_that_the_closed_loop_corrects(tmp_path):
    """The README's bench as a new user gets it (coils up to 5 % off the rig file): the example
    still reaches its goals, the closed loop correcting what the coils' errors cost."""
    plan = EXAMPLES / "fig4-quick.json"
    result = run_rigctl("execute", str(plan), "--json", "--runs", str(tmp_path / "runs"), cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["reached"] is True and not summary["faults"]
    assert max(a["truth_error_mm"] for a in summary["agents"]) <= 1.0, summary["agents"]


def test_validate_names_the_broken_field(tmp_path):
    result = run_rigctl("validate", str(EXAMPLES / "broken-plan.json"), cwd=tmp_path)
    assert result.returncode == 2
    assert "radius" in result.stderr


def test_validate_accepts_the_examples(tmp_path):
    for plan in ("fig4-quick.json", "fig4-two-magnets.json"):
        result = run_rigctl("validate", str(EXAMPLES / plan), cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        assert result.stdout.startswith("OK")


def test_schema_plan_is_json_schema(tmp_path):
    result = run_rigctl("schema", "plan", cwd=tmp_path)
    assert result.returncode == 0
    schema = json.loads(result.stdout)
    assert "global-moves" in json.dumps(schema)


def test_version_is_the_installed_package_version(tmp_path):
    from importlib.metadata import version

    done = run_rigctl("--version", cwd=tmp_path)
    assert done.returncode == 0
    assert done.stdout.strip() == f"rigctl {version('rigctl')}"


def test_json_puts_exactly_one_document_on_stdout_errors_included(tmp_path):
    plan = Path(__file__).resolve().parents[2] / "plans" / "examples" / "fig4-quick.json"
    done = run_rigctl("execute", str(plan), "--json", "--runs", str(tmp_path / "runs"),
                      cwd=tmp_path)
    summary = json.loads(done.stdout)  # the whole of stdout
    assert done.returncode == (0 if summary["reached"] else 1)
    assert "run record:" in done.stderr and "run record:" not in done.stdout
    bad = run_rigctl("execute", str(tmp_path / "missing.json"), "--json", cwd=tmp_path)
    assert bad.returncode == 2
    assert json.loads(bad.stdout)["error"]["code"] == "bad_input"
    assert "missing.json" in bad.stderr


def test_every_command_has_its_own_action_and_help(tmp_path):
    from rigctl.apps.cli.main import build_parser

    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices
    for name, sub in commands.items():
        if sub._subparsers is None:  # a group (plan, keys) has commands of its own
            assert sub.get_default("func") is not None, f"rigctl {name} does nothing"
        assert run_rigctl(name, "--help", cwd=tmp_path).returncode == 0, name
    # each verb is carried out by its own function (a verb wired to another's would pass --help)
    assert commands["reset"].get_default("verb") == "reset"
    assert commands["estop"].get_default("func").__name__ == "_cmd_estop"
