"""`rigctl execute` of a coil-board plan on the emulated board: the real driver, the Python firmware
on a pty, the SyRen wire, the non-uniform coils and the camera loop all in the chain."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import load_plan

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "coilboard-disk.json"


def test_execute_delivers_both_particles_within_the_tolerance(tmp_path):
    plan = load_plan(PLAN)
    with EmulatedBenchProcess("coil-board", tmp_path / "bench.toml") as rig_file:
        from rigctl.core.config import load_rig

        rig = load_rig(rig_file)
        with BackdoorClient(rig.emulation.backdoor) as backdoor:
            backdoor.request("speed", factor=2.5)  # simulated seconds per real second
            # The world's default physics, the non-uniform field of issue 6: coils 200 mm out,
            # the pull varying 2.5x across the disk and leaning up to ~7 degrees.
            placed = backdoor.request("place", workspace=plan.workspace.model_dump(), agents=[
                {"position": a.start, "radius": a.radius} for a in plan.agents])
            assert placed["physics"]["pole_distance_mm"] == 200.0
            assert placed["physics"]["exponent"] == 4.0
        done = subprocess.run(
            [sys.executable, "-m", "rigctl", "execute", str(PLAN), "--rig", str(rig_file),
             "--runs", str(tmp_path / "runs"), "--json"],
            capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["reached"] and summary["faults"] == []
    goals = np.array([a.goal for a in plan.agents])
    for agent, goal in zip(summary["agents"], goals):
        # The camera's verdict and the emulator's ground truth both within the plan's tolerance.
        assert agent["error_mm"] <= plan.tolerance_mm
        assert agent["truth_error_mm"] <= plan.tolerance_mm
        assert abs(np.hypot(*(np.array(agent["final"]) - goal)) - agent["error_mm"]) < 1e-3
    assert summary["state"] == "done" and summary["safe"]  # the board's STOP ACK: all zero
    moves = summary["metrics"]["moves"]
    assert moves >= len(plan.moves)
    events = [json.loads(line) for line in
              (Path(summary["run"]) / "events.jsonl").read_text().splitlines()]
    names = [e["event"] for e in events]
    assert names[0] == "prepared"
    # The particles are found before the board is energised, and it is safe before the end.
    assert names.index("found") < names.index("energised") < names.index("safe")
    assert events[-1] == {**events[-1], "event": "state", "state": "done"}
    assert sum(name == "move" for name in names) == moves
    # Every command in the record is within the board's drive, in the board's own channels.
    channels = json.loads((Path(summary["run"]) / "channels.json").read_text())
    assert [(c["name"], c["unit"], c["high"]) for c in channels] == [
        (name, "drive", 127) for name in ("+x", "-x", "+y", "-y")]


def test_execute_refuses_open_loop_before_anything_starts(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "rigctl", "execute", str(PLAN), "--open-loop",
         "--runs", str(tmp_path / "runs")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "--open-loop: not an option" in done.stderr and "coil-board" in done.stderr
    assert not (tmp_path / "runs").exists()
