"""`rigctl plan pair` then `rigctl execute` end to end: the emulated six-coil bench in the pair world
(its own process), the camera over MJPEG, the supplies over SCPI; the goal formation reached and
held, closed loop; open-loop playback; a plan the coils cannot pull refused before anything starts.
"""

import json
from pathlib import Path

import pytest

from rigctl.apps.testing import plan_pair, run_rigctl

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "plans" / "examples"
WORKSPACE = EXAMPLES / "pair-formation-change-workspace.json"


@pytest.fixture(scope="module")
def short_plan(tmp_path_factory):
    """A short formation change: 2 BL side by side -> 2.6 BL at 60 degrees, 1.5 mm further on."""
    return plan_pair(tmp_path_factory.mktemp("pair"), goal="9.5,7.5,2.6,60", hold_s=1.5)


def summary_of(result):
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_closed_loop_reaches_and_holds_the_goal_formation(short_plan, tmp_path):
    result = run_rigctl("execute", str(short_plan), "--json", "--runs", str(tmp_path / "runs"),
                    cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    s = summary_of(result)
    plan = json.loads(short_plan.read_text())
    m = s["metrics"]
    assert s["reached"] and m["mode"] == "closed loop" and not s["faults"]
    assert s["tolerance_bl"] == plan["tolerance_bl"]
    assert m["held_s"] >= plan["hold_s"] - 0.05
    assert m["hold_max_error_bl"] <= plan["tolerance_bl"]
    for agent in s["agents"]:  # the emulator's ground truth agrees with the camera
        assert agent["truth_error_bl"] <= plan["tolerance_bl"]
    assert m["rms_tracking_error_bl"] <= 0.1
    # never closer than the planner's r_min by more than the camera's and the loop's error, and
    # never in contact (1 BL) in the ground truth
    assert m["min_separation_bl"] >= plan["r_min_bl"] - 0.15
    assert m["truth_min_separation_bl"] >= plan["r_min_bl"] - 0.15
    run = Path(s["run"])
    for name in ("plan.json", "rig.toml", "events.jsonl", "stream.csv", "summary.json",
                 "series/identification.csv"):
        assert (run / name).is_file(), name
    # the pull gain identified from tracking, in the summary and over time in the record
    pull = m["pull_identified"]
    assert pull["windows_used"] >= 1 and 0.3 <= pull["gain"] <= 3.0 and pull["gain_std"] < 0.3
    rows = (run / "series" / "identification.csv").read_text().splitlines()
    assert rows[0].split(",")[:2] == ["t_s", "gain_centroid"] and len(rows) == 2 + pull["windows_used"]
    events = [json.loads(line)["event"] for line in (run / "events.jsonl").read_text().splitlines()]
    assert {"placed", "energised", "track", "holding", "safe"} <= set(events)


def test_open_loop_plays_the_plan_back(short_plan, tmp_path):
    result = run_rigctl("execute", str(short_plan), "--open-loop", "--json", "--runs",
                    str(tmp_path / "runs"), cwd=tmp_path)
    assert result.returncode in (0, 1), result.stdout + result.stderr
    s = summary_of(result)
    assert s["metrics"]["mode"] == "open loop" and not s["faults"]
    assert s["tracking"]["frames"] > 0  # the camera still measured
    assert "rms_tracking_error_bl" in s["metrics"] and "min_separation_bl" in s["metrics"]


def test_a_pull_beyond_the_coils_is_refused_before_a_bench_starts(short_plan, tmp_path):
    plan = json.loads(short_plan.read_text())
    plan["max_pull_bl_s"] = 5.0
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(plan))
    result = run_rigctl("execute", str(bad), "--runs", str(tmp_path / "runs"), cwd=tmp_path)
    assert result.returncode == 2
    assert "BL/s" in result.stderr and "re-plan" in result.stderr
    assert "starting the emulated" not in result.stderr
    assert not (tmp_path / "runs").exists()
