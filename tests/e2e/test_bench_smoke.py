"""Every bench script still runs: the smallest run of each prints one JSON object, exits 0, and has
the figures that show its whole path ran (every stage once, tiny). The figures themselves are
measured by running the scripts in full (see the README), not here: in these runs they mean
nothing.

Each script's smallest run, wall and CPU (user + sys, the script's children included), one script
at a time on the shared two-core machine (`/usr/bin/time -f "%e %U %S"`); "before" is the run this
test made until now:

    script             before: args                           wall s  cpu s   after (QUICK below)  wall s  cpu s
    stream.py          --seconds 0.5 --rates 100                2.2    2.1                          2.7    1.7
    rrt.py             --quick                                   22*    14*   --smoke                 7.7    7.6
    tracker.py         --seconds 0.5 --closed-loop-runs 0       24.4   23.0   --smoke ...             7.9    5.7
    closed_loop.py     --runs 1                                 20.3   12.1   (unchanged)            21.6   13.5
    daemon.py          --seconds 0.3 (all three rigs)            48*    25*   --rig six-coil          15.7   12.6
    coilboard_link.py  --round-trips 50 --seconds 0.5 ...        5.4    2.2   (10 round trips)        4.0    1.2
    coilboard.py       --pairs 2 --runs 1 ...                   29.5   16.4   --smoke --seed 5 ...   11.3    7.6
    depm.py            --time-scale 8 --no-random                45*    21*   --smoke ...            17.6    9.0
    pair.py            --quick                                   75*    38*   (1 seed, --slip 1 ...) 50.7   34.6
    preflight.py       --rig six-coil --repeat 1                13.3    8.5   --rig coil-board        6.7    6.3
    certificate.py     --quick                                   3.2    2.7   (unchanged)             3.7    2.5
    fuzz_daemon.py     --requests 200 --plans 20                 6.5    6.1   (20 and 3)              4.9    4.7
    faults.py          one daemon cell, hold 1.5                 9.8    8.8   + the execute cell     19.0   14.7
    soak.py            --minutes 0.3 --interval 2               25.3   20.2   --minutes 0.05          8.8    7.5
    calibrate_field.py --seeds 0                                11.2    4.5   (unchanged)            11.2    4.5
    study.py           --quick                                   34*    30*   --smoke --workers 1    23.2   16.5
    console.py         --quick                                   41*    23*   --smoke                28.7   23.7
    together                                                   ~416   ~258                          245    174
    This module as a whole (pytest, the 17 runs one after another): 262 s wall, 173 s CPU, at
    load 3.6-5.2.
    (* from the issue: user CPU only, not measured here again. Load average 3 to 6 during the
    runs, 10 to 12 during coilboard.py's and console.py's first "after" runs; the two-core machine
    shared with four other engineers' test runs. The CPU figures include the scripts' children.)
    cli.py --smoke (added later: one start of each command timed): 0.9 s wall, 1.1 s CPU.
    viewer.py --smoke (added later: a 20 s and a 5 s synthetic record, each served by `rigctl
    view` and opened with 3 seeks in one headless Chromium): 18.3 s wall, 8.3 s CPU.
    What is left is mostly real-time closed-loop runs on emulated benches, which no size shortens:
    pair.py's three formation-change runs (~15-21 s each), the one of closed_loop.py, of the study
    campaign and of coilboard.py's delivery, and console.py's two Chromium starts.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"

QUICK = {
    "stream.py": ["--seconds", "0.2", "--rates", "100"],
    "rrt.py": ["--smoke"],
    # the closed-loop latency stage is closed_loop.py's one_seed, which closed_loop.py runs below
    "tracker.py": ["--smoke", "--closed-loop-runs", "0"],
    "closed_loop.py": ["--runs", "1"],  # with --random-goals: 2 min of re-plans
    # six-coil: the one rig with every stage (the status flood runs on it alone)
    "daemon.py": ["--rig", "six-coil", "--seconds", "0.2"],
    "coilboard_link.py": ["--round-trips", "10", "--seconds", "0.1", "--trials", "1"],
    # seed 5: the shortest delivery pair of seeds 0-11 (3 planned moves, 31 mm against seed 0's 5
    # and 94 mm); the delivery run is in real time (x3) and its re-plans grow with the load
    "coilboard.py": ["--smoke", "--seed", "5", "--mobility-spread", "0.1"],
    "depm.py": ["--smoke", "--time-scale", "8"],
    # --slip 1: the mobility runs last the plan's ~15 s instead of ~21 s (the pull gain is still
    # identified); the three formation-change runs are in real time, the floor of this smoke run
    "pair.py": ["--quick", "--seeds", "1", "--replans", "1", "--budget", "2", "--slip", "1"],
    # coil-board: the cheapest bench here (the rigs share the refusals' and the doctor's path)
    "preflight.py": ["--rig", "coil-board", "--repeat", "1"],
    "certificate.py": ["--quick"],
    "fuzz_daemon.py": ["--requests", "20", "--plans", "3"],
    # one cell through the daemon, one through a local `rigctl execute`: both paths
    "faults.py": ["--rig", "six-coil", "--cell", "daemon/x+:drop_link/moving",
                  "--cell", "execute/x+:drop_link/moving", "--hold", "0.3"],
    "soak.py": ["--minutes", "0.05", "--interval", "1", "--moves", "1"],
    "calibrate_field.py": ["--seeds", "0"],
    "study.py": ["--smoke", "--workers", "1"],
    "console.py": ["--smoke"],
    "fields.py": ["--smoke"],  # with mag_manip's side venv present, its comparison runs too
    "busy.py": ["--smoke"],  # one open-loop run beside one hog
    "cli.py": ["--smoke"],
    "video.py": ["--smoke"],  # one pair (video off, on) of a three-turn closed-loop run
    "viewer.py": ["--smoke"],  # a 20 s and a 5 s synthetic record, 3 seeks in each
}

# per script, figures (key paths) only its last stages write: present and not empty means the
# whole path ran
FIGURES = {
    "stream.py": [("rates", "100", "cycles")],
    "rrt.py": [("growth_nn_eps_0.1",), ("peer",), ("solve", "runs"), ("four_robots", "nodes"),
               ("image_maps", "many")],
    "tracker.py": [("tracker", "1280x1024", "8"), ("stream", "frames")],
    "closed_loop.py": [("per_run",), ("closed_loop_success_share",)],
    "daemon.py": [("rigs", "six-coil", "telemetry_10_subscribers"),
                  ("rigs", "six-coil", "estop", "no_owner_direct"),
                  ("rigs", "six-coil", "status_flood", "with_flood")],
    "coilboard_link.py": [("python", "watchdog_ms"), ("simavr",)],
    "coilboard.py": [("planner", "hexagon"), ("link", "python", "watchdog_ms"),
                     ("delivery", "mobility_diff_error")],
    "depm.py": [("model", "baseline"), ("measured", "planned"),
                ("measured_without_correction", "planned"), ("goals_met",)],
    "pair.py": [("solve",), ("replan", "joined_share"), ("decide", "median_ms"),
                ("runs", "formation_change", "reached"), ("mobility", "runs", "not_identified")],
    "preflight.py": [("rigs", "coil-board", "bad_url"), ("rigs", "coil-board", "doctor")],
    "certificate.py": [("rigs", "coil-board"), ("winding_model",), ("model_vs_emulator",)],
    "fuzz_daemon.py": [("plans",), ("ping_after",)],
    "faults.py": [("cells",), ("figures",)],
    "soak.py": [("daemon", "samples"), ("stream", "rss_MB")],
    "calibrate_field.py": [("worst", "after"), ("runs",)],
    "study.py": [("studies",), ("tiny_cases", "overhead_ms_per_case"), ("campaign", "ran_ok")],
    "console.py": [("frames", "frames_drawn"), ("estop", "ok"), ("pages", "runs"),
                   ("websocket_watchers", "runs")],
    "fields.py": [("eval", "best_us"), ("allocate_8dof", "best_us"), ("fit", "held_out_pct"),
                  ("mag_manip", "available")],
    "busy.py": [("conditions", "favoured", "runs"), ("per_run",)],
    "cli.py": [("floor", "median_s"), ("version", "median_s"), ("help", "median_s"),
               ("command_help", "median_s")],
    "video.py": [("on", "video", "MB_per_min"), ("ratio_on_off", "period_error_p99")],
    "viewer.py": [("long", "seek_ms", "max"), ("floor", "open_s"), ("ratio_long_floor", "open")],
}


def test_every_bench_script_has_a_quick_run() -> None:
    assert {p.name for p in BENCH.glob("*.py")} == set(QUICK) == set(FIGURES)


@pytest.mark.parametrize("script", sorted(QUICK))
def test_the_bench_runs_and_prints_one_json_object(script: str, tmp_path) -> None:
    done = subprocess.run([sys.executable, str(BENCH / script), *QUICK[script]],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    figures = json.loads(done.stdout)
    assert isinstance(figures, dict) and figures
    for path in FIGURES[script]:
        value = figures
        for key in path:
            assert isinstance(value, dict) and key in value, (path, json.dumps(figures)[:3000])
            value = value[key]
        assert value is not None and value != [] and value != {}, (path, value)
