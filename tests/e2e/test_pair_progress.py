"""Progress of a pair-formation run through `rigctl execute`, as the operator sees it: on stderr the
plan segment out of how many, the hold, elapsed and planned time; a line per stage when stderr is
not a terminal, one line rewritten in place when it is; nothing with --quiet; stdout keeps the
summary and ends with the JSON line. Stage counts and the planned time come from the plan file.
"""

import io
import json
import os
import pty
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from rigctl.apps.testing import plan_pair, run_rigctl
from rigctl.rigs.six_coil.pair import PairStages
from rigctl.run.progress import Progress

ROOT = Path(__file__).resolve().parents[2]
WORKSPACE = ROOT / "plans" / "examples" / "pair-formation-change-workspace.json"
RAMPS_S = 2 * 0.1  # the run's field ramp up and ramp down (PairRunSettings.ramp_s each)

# "  segment 3/6     1.2 s / 4.2 s planned", "  to goal ...", "  holding goal ..."
PROGRESS = re.compile(
    r"(segment (\d+)/(\d+)|to goal|holding goal|ramp up|ramp down) +([\d.]+) s / ([\d.]+) s planned")


@pytest.fixture(scope="module")
def plan_path(tmp_path_factory):
    """A short formation change: 6 segments, a 0.5 s hold."""
    return plan_pair(tmp_path_factory.mktemp("pair-progress"), goal="8.8,7.3,2.3,40", hold_s=0.5)


def plan_figures(plan_path):
    plan = json.loads(plan_path.read_text())
    planned_s = sum(s["dt_s"] for s in plan["segments"]) + plan["hold_s"] + RAMPS_S
    return len(plan["segments"]), planned_s


def stage_rank(match, n):
    """Order of a progress line's stage: segments 1..n, then the goal, then the hold."""
    if match[2] is not None:
        return int(match[2])
    return {"to goal": n + 1, "holding goal": n + 2}[match[1]]


def check_stdout(result):
    assert not PROGRESS.search(result.stdout)  # progress never on stdout
    summary = json.loads(result.stdout)  # --json: stdout is the one JSON document, nothing else
    assert "REACHED" in result.stderr  # the summary a person reads ("REACHED", "NOT REACHED")
    return summary


def test_closed_loop_prints_a_line_per_stage_on_stderr(plan_path, tmp_path):
    result = run_rigctl("execute", str(plan_path), "--json", "--runs", str(tmp_path / "runs"),
                    cwd=tmp_path, capture_output=True)
    assert result.returncode == 0, result.stdout + result.stderr
    assert check_stdout(result)["reached"]
    n, planned_s = plan_figures(plan_path)
    lines = [PROGRESS.search(line) for line in result.stderr.splitlines()]
    lines = [m for m in lines if m]
    assert "\r" not in result.stderr  # not a terminal: plain lines
    assert not any(m[1].startswith("ramp") for m in lines)  # ramps are not stages
    assert all(int(m[3]) == n for m in lines if m[3])
    ranks = [stage_rank(m, n) for m in lines]
    # each stage at most once, in order, however often the proximity controller steps back; the
    # closed loop may pass a node between two frames, so not every segment need have a line
    assert ranks == sorted(set(ranks)) and 1 <= ranks[0] <= n
    assert len(lines) <= n + 2
    assert lines[-1][1] == "holding goal"
    elapsed = [float(m[4]) for m in lines]
    assert elapsed == sorted(elapsed)
    for m in lines:
        assert float(m[5]) == pytest.approx(planned_s, abs=0.06)


def test_open_loop_on_a_terminal_rewrites_one_line_through_every_segment(plan_path, tmp_path):
    n, _ = plan_figures(plan_path)
    master, slave = pty.openpty()
    proc = subprocess.Popen([sys.executable, "-m", "rigctl", "execute", str(plan_path),
                             "--open-loop", "--json", "--runs", str(tmp_path / "runs")],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=slave, text=True)
    os.close(slave)
    chunks: list[bytes] = []

    def read_terminal():
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # EIO: every writer closed the terminal
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=read_terminal)
    reader.start()
    stdout, _ = proc.communicate(timeout=300)
    reader.join(timeout=30)
    os.close(master)
    assert proc.returncode in (0, 1), stdout
    terminal = b"".join(chunks).decode()
    progress_lines = [line for line in terminal.split("\n") if PROGRESS.search(line)]
    assert len(progress_lines) == 1, terminal  # rewritten in place, ended once
    shown = [PROGRESS.search(part) for part in progress_lines[0].split("\r")]
    segments = {int(m[2]) for m in shown if m and m[2]}
    assert segments == set(range(1, n + 1))  # open loop plays every segment of the plan
    assert any(m and m[1] == "holding goal" for m in shown)
    assert [m[1] for m in shown if m][-1] == "ramp down"
    assert not PROGRESS.search(stdout)
    json.loads(stdout.strip().splitlines()[-1])


def test_quiet_leaves_stderr_free_of_progress(plan_path, tmp_path):
    result = run_rigctl("execute", str(plan_path), "--open-loop", "--quiet", "--json", "--runs",
                    str(tmp_path / "runs"), cwd=tmp_path, capture_output=True)
    assert result.returncode in (0, 1), result.stdout + result.stderr
    check_stdout(result)
    assert not PROGRESS.search(result.stderr), result.stderr
    assert "starting the emulated" not in result.stderr


def test_a_re_planned_path_counts_as_the_plan_segment_it_rejoins():
    """In process, no bench: a plan of 6 segments (nodes 0..7, 7 the goal); after node 4 the
    agents stray, and a 3-node re-plan rejoins plan node 3 (the end of segment 3). The line does
    not step back to segment 3, and the spliced path's nodes after the join are the plan's."""
    out = io.StringIO()
    progress = Progress(out, 6, 10.0)  # the run engine shows each step's (stage_key, stage) so
    stages = PairStages(6, n_nodes=8)

    def show(key_stage, t_s):
        progress.update(key_stage[0], t_s, key_stage[1])

    for node in (1, 2, 3, 4, 5):
        show(stages.closed_loop(node, holding=False, ramp=None), 1.0)
    stages.spliced(3, joined=3)  # nodes now: 3 re-planned ones, then plan nodes 4..7
    for node in (1, 2, 3, 4, 5, 6):  # pursuit node 3 is plan node 4, node 6 the goal
        show(stages.closed_loop(node, holding=False, ramp=None), 2.0)
    show(stages.closed_loop(6, holding=True, ramp=None), 3.0)
    shown = [m[1] for m in map(PROGRESS.search, out.getvalue().splitlines())]
    assert shown == [f"segment {k}/6" for k in (1, 2, 3, 4, 5, 6)] + ["to goal", "holding goal"]
