"""Studies on Dask (rigctl.apps.study): two local workers give a serial run's planner results case for
case, short cases sent several to a task too; a stopped study resumes without running a finished
case again; emulated cases side by side each get a bench of their own; `rigctl study report` draws
what the table holds."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from rigctl.apps.study.execution import run_study
from rigctl.apps.study.spec import spec_from_dict

ROOT = Path(__file__).resolve().parents[2]
STUDIES = ROOT / "studies"


def _rows(folder: Path) -> dict[str, dict]:
    return {r["case_id"]: r for r in pq.read_table(folder / "results.parquet").to_pylist()}


def _rrt_study() -> dict:
    """The RRT of environment 1 over 3 seeds x 2 nearest-node settings, node budgets (no time
    budget: what a case computes must not depend on the machine's load)."""
    return {"name": "rrt-repro", "run": {"command": "plan rrt", "args": {
        "workspace": str(STUDIES / "environment-1.json"),
        "rig-file": str(STUDIES / "five-mm-turns.toml"),
        "start": ["60,300", "60,250"], "goal": ["330,300", "330,200"], "radius": 5,
        "robostep": 5, "max-nodes": 1500, "tolerance": 2, "tuned": True}},
        "parameters": {"nn-eps": [0.0, 0.1]}, "seeds": {"count": 3}}


def test_two_local_workers_give_the_serial_planner_results_case_for_case(tmp_path) -> None:
    spec = spec_from_dict(_rrt_study(), tmp_path)
    serial = run_study(spec, tmp_path / "serial", serial=True, progress_out=None)
    dask = run_study(spec, tmp_path / "dask", workers=2, progress_out=None)
    assert serial.ran == dask.ran == 6 and serial.not_ok == dask.not_ok == 0
    assert dask.workers == 2 and dask.dashboard and dask.dashboard.startswith("http://")
    a, b = _rows(tmp_path / "serial"), _rows(tmp_path / "dask")
    assert set(a) == set(b) == {c.id for c in spec.cases}
    assert len({r["worker"] for r in b.values()}) == 2  # both workers ran cases
    for case_id, row in a.items():
        for key in ("fig_solved", "fig_nodes", "fig_distance", "fig_moves", "seed", "nn-eps"):
            assert b[case_id][key] == row[key], (case_id, key)
        plan_a = json.loads(Path(row["record"]).read_text())
        plan_b = json.loads(Path(b[case_id]["record"]).read_text())
        assert plan_a["moves"] == plan_b["moves"] and plan_a["expected"] == plan_b["expected"]
    # and both are what `rigctl plan rrt` itself writes for a case, run on its own
    case = spec.cases[-1]
    args = _rrt_study()["run"]["args"]
    argv = [sys.executable, "-m", "rigctl", "plan", "rrt", "--workspace", args["workspace"],
            "--rig-file", args["rig-file"], "--start", "60,300", "--start", "60,250", "--goal",
            "330,300", "--goal", "330,200", "--radius", "5", "--robostep", "5", "--max-nodes",
            "1500", "--tolerance", "2", "--tuned", "--nn-eps", str(case.parameters["nn-eps"]),
            "--seed", str(case.seed), "-o", str(tmp_path / "alone.json"), "--json"]
    alone = json.loads(subprocess.run(argv, capture_output=True, text=True, check=True).stdout)
    assert (alone["nodes"], alone["distance"], alone["moves"]) == (
        a[case.id]["fig_nodes"], a[case.id]["fig_distance"], a[case.id]["fig_moves"])


def test_short_cases_sent_several_to_a_task_give_the_serial_results_seed_for_seed(tmp_path) -> None:
    """12 RRT cases of a 300-node budget (short: after the first four, Dask gets them two to a
    task, `execution.chunk_size`, unless the machine's load makes them longer than 0.25 s); each
    seed's plan is still the one the serial run made."""
    data = _rrt_study()
    data["run"]["args"]["max-nodes"] = 300
    data["seeds"] = {"count": 6}
    spec = spec_from_dict(data, tmp_path)
    serial = run_study(spec, tmp_path / "serial", serial=True, progress_out=None)
    dask = run_study(spec, tmp_path / "dask", workers=2, progress_out=None)
    assert serial.ran == dask.ran == 12 and serial.not_ok == dask.not_ok == 0
    a, b = _rows(tmp_path / "serial"), _rows(tmp_path / "dask")
    assert set(a) == set(b) == {c.id for c in spec.cases}
    for case_id, row in a.items():
        for key in ("fig_solved", "fig_nodes", "fig_distance", "fig_moves", "seed", "nn-eps"):
            assert b[case_id][key] == row[key], (case_id, key)
        plan_a = json.loads(Path(row["record"]).read_text())
        plan_b = json.loads(Path(b[case_id]["record"]).read_text())
        assert plan_a["moves"] == plan_b["moves"]


class _Stop(KeyboardInterrupt):
    pass


def test_a_stopped_study_resumes_and_runs_no_finished_case_again(tmp_path) -> None:
    spec = spec_from_dict({"name": "resume", "run": {"command": "plan reachable",
                                                     "args": {"disk": True, "cells": 21}},
                           "parameters": {"d12": [0.1, 0.3, 0.5], "moves": [2, 4]}}, tmp_path)
    seen = []

    def stop_after_two(row: dict) -> None:
        seen.append(row["case_id"])
        if len(seen) == 2:
            raise _Stop  # as Ctrl-C would, between two finished cases

    with pytest.raises(_Stop):
        run_study(spec, tmp_path / "out", workers=2, progress_out=None, on_result=stop_after_two)
    first = _rows(tmp_path / "out")
    assert set(first) == set(seen)  # every finished case was in the table before the stop
    again = []
    outcome = run_study(spec, tmp_path / "out", workers=2, progress_out=None,
                        on_result=lambda r: again.append(r["case_id"]))
    assert (outcome.skipped, outcome.ran) == (2, 4) and not set(again) & set(first)
    rows = _rows(tmp_path / "out")
    assert set(rows) == {c.id for c in spec.cases}
    for case_id, row in first.items():  # untouched: same worker, same time
        assert (rows[case_id]["worker"], rows[case_id]["finished_at"]) == (row["worker"], row["finished_at"])
    # the planner's 2-move fraction for d12 0.3 is also the first of its 4-move table
    two = {r["d12"]: r["fig_fraction"] for r in rows.values() if r["moves"] == 2}
    assert two[0.1] < two[0.3] < two[0.5]  # seed 004 Fig. 8: grows with d12 up to ~0.81

    png = tmp_path / "report.png"
    done = subprocess.run([sys.executable, "-m", "rigctl", "study", "report", str(tmp_path / "out"),
                           "-o", str(png), "--json"], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    drawn = json.loads(done.stdout)
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    by_d12 = drawn["figures"]["error"]["d12"]  # one line per moves value, one point per d12
    for point in by_d12:
        expected = [r["fig_fraction"] for r in rows.values()
                    if r["d12"] == point["value"] and r["moves"] == point["line"]["moves"]]
        assert point["n"] == 1 and point["mean"] == pytest.approx(expected[0])
    by_moves = drawn["figures"]["error"]["moves"]
    for point in by_moves:
        values = [r["fig_fraction"] for r in rows.values() if r["moves"] == point["value"]
                  and r["d12"] == point["line"]["d12"]]
        assert point["mean"] == pytest.approx(float(np.mean(values)))


def _ports(rig_toml: Path) -> set[int]:
    return {int(p) for p in re.findall(r"127\.0\.0\.1:(\d+)", rig_toml.read_text())}


def test_emulated_cases_side_by_side_each_run_on_a_bench_of_their_own(tmp_path) -> None:
    spec = spec_from_dict({"name": "campaign", "run": {"command": "execute", "args": {
        "plan": str(ROOT / "plans" / "examples" / "fig4-quick.json"), "open-loop": True,
            "coil-error": 0,  # open loop on the ideal bench: its coils are the rig file's
        "rig.field.rolling_turns_per_s": 8.0, "rig.field.steering_deg_per_s": 720.0,
        "rig.stream.reply_timeout_s": 5.0}},
        "cases": [{"slip": 1.0}, {"slip": 1.0, "fault": {"device": "x+", "kind": "drop_link",
                                                          "after_s": 0.3}}]}, tmp_path)
    outcome = run_study(spec, tmp_path / "out", workers=2, progress_out=None)
    assert outcome.not_ok == 0
    rows = {json.dumps(r["fault"]): r for r in _rows(tmp_path / "out").values()}
    clean, faulted = rows["null"], next(r for k, r in rows.items() if k != "null")
    # the clean case reached its goals by the emulator's ground truth; the other one's supply
    # dropped its link mid-run: faulted, exit 3, the fault named
    assert clean["fig_exit_code"] == 0 and clean["success"] is True and clean["error"] < 1.0
    assert faulted["fig_exit_code"] == 3 and faulted["fig_state"] == "faulted"
    assert faulted["fig_fault_injected_at_s"] is not None and "x+" in faulted["message"]
    folders = [tmp_path / "out" / "cases" / r["case_id"] for r in (clean, faulted)]
    ports = [_ports(f / "bench.toml") for f in folders]
    assert all(len(p) >= 7 for p in ports) and not ports[0] & ports[1]  # 6 supplies, camera, backdoor
    for folder, row in zip(folders, (clean, faulted)):
        assert Path(row["record"]).parent == folder / "runs"
        assert _ports(Path(row["record"]) / "rig.toml") <= _ports(folder / "bench.toml")
