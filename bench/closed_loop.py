"""Closed-loop benchmark: prints one JSON object.

For each of `--runs` seeds, an emulated six-coil bench (its own process) with model mismatch (slip
0.85, per-robot speed spread, contact noise, drift; `--field-at-robots` adds the non-uniform field)
runs the example plan open-loop and then closed-loop. With `--random-goals` each run has a plan of
its own: two magnets from seed 000's starts in its environment 1 to goals drawn from the seed at
least `--goal-clearance` mm off every wall, planned by `rigctl plan rrt --tuned` in whole turns.
Reported: the share of runs whose every robot ends within the plan's tolerance (1 mm) by the
emulator's ground truth, the worst open-loop miss, re-plans per run (mean and median), what the
closed loop identified (each robot's rolling gain against the emulator's true distance per turn),
the tracker's error at rest against ground truth, and the latency from the capture time of the
frame a decision used to the first command after it leaving the stream loop (p50 / p99),
separately for "go on" decisions and for re-plans (which include the RRT's time); the same from
the frame's arrival at the camera driver (`received_*`: what rigctl's own path costs, the camera's
encoding, transport and decoding excluded), next to OpenCV's floor per frame on the same camera in
the same runs (grey, threshold and contours of the whole picture: `opencv_floor`).

The bench's coils are off the rig file by `--coil-error` (0.05, the emulator's default);
`--calibrate-field` runs `rigctl calibrate field` against each bench first, so the allocator uses
the fitted coils (`--coil-error 0` takes the error away instead).
Run: `.venv/bin/python bench/closed_loop.py [--runs 20] [--plan plans/examples/fig4-quick.json]`;
the issue-17 case: `... --random-goals --speed-spread 0.1 --noise 0.2`.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rigctl.core.config import RigConfig, load_rig
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import load_plan
from rigctl.rigs.six_coil.global_moves import Run
from rigctl.rigs.six_coil.supervisor import SupervisorSettings

ROOT = Path(__file__).resolve().parents[1]


ENVIRONMENT_1 = ROOT / "plans" / "examples" / "fig4-two-magnets.json"  # seed 000's environment 1
STARTS = ((60.0, 300.0), (60.0, 250.0))  # seed 000's starts in it
RADIUS_MM = 8.0


def bench_rig(rig: RigConfig, reply_timeout_s: float = 1.0) -> RigConfig:
    """4 turns/s as in the integration tests; a watchdog that tolerates a loaded machine."""
    return rig.model_copy(update={
        "field": rig.field.model_copy(update={"rolling_turns_per_s": 4.0,
                                              "steering_deg_per_s": 360.0}),
        "stream": rig.stream.model_copy(update={"reply_timeout_s": reply_timeout_s}),
    })


def random_plan(folder: Path, seed: int, clearance_mm: float, plan_s: float) -> Path:
    """A whole-turn plan from STARTS to two goals drawn from `seed`, `clearance_mm` off the walls
    and apart, written by `rigctl plan rrt` (as a user makes one)."""
    from rigctl.plans.checks import plan_workspace

    workspace = plan_workspace(load_plan(ENVIRONMENT_1))
    rng = np.random.default_rng(seed)
    while True:
        goals = workspace.sample_free(rng, 2, RADIUS_MM + clearance_mm)
        if np.hypot(*(goals[1] - goals[0])) >= 2 * RADIUS_MM + clearance_mm:
            break
    out = folder / f"random-{seed}.json"
    args = [sys.executable, "-m", "rigctl", "plan", "rrt", "--workspace", str(ENVIRONMENT_1),
            "--radius", str(RADIUS_MM), "--tuned", "--seed", str(seed), "--time", str(plan_s),
            "--json", "-o", str(out)]
    for start in STARTS:
        args += ["--start", f"{start[0]:g},{start[1]:g}"]
    for goal in goals:
        args += ["--goal", f"{goal[0]:.3f},{goal[1]:.3f}"]
    done = subprocess.run(args, check=False, capture_output=True, text=True, timeout=120 + plan_s)
    if done.returncode not in (0, 1):  # 1: not solved within 1 mm, the closed loop finishes it
        raise SystemExit(f"rigctl plan rrt failed: {done.stderr[-2000:]}")
    return out


def one_seed(plan_path: Path | None, seed: int, mismatch: list[str], args) -> dict:
    with tempfile.TemporaryDirectory(prefix="rigctl-closed-loop-") as tmp:
        if plan_path is None:
            plan_path = random_plan(Path(tmp), seed, args.goal_clearance, args.plan_seconds)
        plan = load_plan(plan_path)
        with EmulatedBenchProcess("six-coil", Path(tmp) / "bench.toml",
                                  extra_args=[*mismatch, "--seed", str(seed), "--coil-error",
                                              str(args.coil_error)]) as rig_path:
            if args.calibrate_field:
                calibrate_field(rig_path)
            rig = bench_rig(load_rig(rig_path), args.reply_timeout)
            open_summary = None
            if args.open_loop:
                open_run = Run(plan, rig, runs_dir=Path(tmp) / "runs", progress_out=None)
                open_summary = open_run.execute()
            closed_run = Run(plan, rig, runs_dir=Path(tmp) / "runs", progress_out=None,
                             closed_loop=True, supervisor_settings=SupervisorSettings(seed=seed))
            closed = closed_run.execute()
            if args.keep_records:
                keep = Path(args.keep_records) / f"seed-{seed}"
                shutil.copytree(Path(tmp) / "runs", keep, dirs_exist_ok=True)
                shutil.copy(plan_path, keep / plan_path.name)
            supervisor = closed_run.program.supervisor
            assert supervisor is not None
            times = supervisor.sequencer.command_times
            latency = {"continue": [], "replan": [], "received_continue": [],
                       "received_replan": []}
            for d in supervisor.decisions:
                if d.number in times:
                    kind = "replan" if d.kind == "replan" else "continue"
                    latency[kind].append(times[d.number] - d.t_source)
                    if d.t_received is not None:
                        latency[f"received_{kind}"].append(times[d.number] - d.t_received)
            threshold = supervisor.tracking.tracker.threshold
            latency["opencv_floor"] = opencv_floor(rig, threshold) if threshold is not None else []
    truth = [a.truth_error_mm if a.truth_error_mm is not None else a.error_mm
             for a in closed.agents]
    worst = _worst(truth)
    return {
        "seed": seed,
        "goals": [a.goal for a in plan.agents],
        "identified": supervisor.identifier.summary(),
        "true_gain": true_gains(mismatch, seed, len(plan.agents)),
        "open_loop_miss_mm": _worst([a.error_mm for a in open_summary.agents])
        if open_summary is not None else None,
        "closed_loop_error_mm": worst,
        "closed_reached": not closed.faults and worst is not None and worst <= plan.tolerance_mm,
        "faults": [f["reason"] for f in closed.faults],
        "replans": closed.replans,
        "tracking": closed.tracking,
        "duration_s": round(closed.duration_s, 1),
        "latency_s": latency,
    }


def opencv_floor(rig: RigConfig, threshold: float, frames: int = 30) -> list[float]:
    """OpenCV's own cost (s) per frame of the bench's camera, read as the run read it (the camera
    driver, after the run, robots in view): grey, `cv2.threshold` at the run's tracker's threshold
    and `cv2.findContours` on the whole picture, on this process's tracking side. The least a
    frame costs between its arrival and a decision made from it."""
    import cv2

    from rigctl.drivers.camera import CameraDriver

    assert rig.camera is not None
    durations = []
    with CameraDriver(rig.camera.url, stamped=rig.camera.stamped) as driver:
        for _ in range(frames):
            image = driver.read().image
            started = time.perf_counter()
            grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            _, mask = cv2.threshold(grey, threshold, 255, cv2.THRESH_BINARY_INV)
            cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            durations.append(time.perf_counter() - started)
    return durations


def calibrate_field(rig_path: Path) -> None:
    """`rigctl calibrate field --rig RIG --model loops` against the emulated bench, as a lab
    calibrates: the rig file then names the fitted coils and the allocator uses them. Loops: the
    emulated coils are loops, which the loop fit matches best (docs/field-calibration.md), and
    the MPEM's order-3 fit would add seconds to every run of this bench."""
    done = subprocess.run([sys.executable, "-m", "rigctl", "calibrate", "field", "--rig",
                           str(rig_path), "--model", "loops", "--json"], check=False, capture_output=True,
                          text=True, timeout=600)
    if done.returncode != 0:
        raise SystemExit(f"rigctl calibrate field failed: {done.stderr[-2000:]}")


def _worst(errors: list[float | None]) -> float | None:
    """The largest error, None when none was measured (a run stopped before the camera or
    ground truth said where the robots were)."""
    known = [e for e in errors if e is not None]
    return max(known) if known else None


def true_gains(mismatch: list[str], seed: int, n: int) -> list[float]:
    """The emulated world's distance per turn over 2 pi R, per robot, drawn as the world draws it
    (`Mismatch`: slip x (1 + s_i), s_i ~ N(0, speed_spread) from the seed)."""
    from rigctl.emulators.world.rolling import Mismatch

    def value(flag: str) -> float:
        return float(mismatch[mismatch.index(flag) + 1])

    world = Mismatch(slip=value("--slip"), speed_spread=value("--speed-spread"), seed=seed)
    rng = np.random.default_rng(world.seed)
    spread = rng.normal(0.0, world.speed_spread, n) if world.speed_spread else np.zeros(n)
    return np.round(world.slip * (1.0 + spread), 4).tolist()


def percentiles_ms(values: list[float], digits: int = 1) -> dict:
    if not values:
        return {"n": 0}
    v = np.array(values) * 1e3
    return {"n": len(v), "p50": round(float(np.percentile(v, 50)), digits),
            "p99": round(float(np.percentile(v, 99)), digits), "max": round(float(v.max()), digits)}


def frame_to_command(results: list[dict]) -> dict:
    """The latency figures of the runs: from a frame's capture (the camera's stamp) and from its
    arrival at the camera driver (decoded) to the first command after the decision made from it,
    for go-on decisions and for re-plans, and OpenCV's floor per frame measured in the same runs."""
    def pooled(key: str) -> list[float]:
        return [t for r in results for t in r["latency_s"][key]]

    return {"continue": percentiles_ms(pooled("continue")),
            "replan": percentiles_ms(pooled("replan")),
            "received_continue": percentiles_ms(pooled("received_continue"), 2),
            "received_replan": percentiles_ms(pooled("received_replan")),
            "opencv_floor": percentiles_ms(pooled("opencv_floor"), 2)}


def parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=100)
    parser.add_argument("--plan", default=str(ROOT / "plans" / "examples" / "fig4-quick.json"))
    parser.add_argument("--slip", default="0.85")
    parser.add_argument("--speed-spread", default="0.01")
    parser.add_argument("--noise", default="0.05")
    parser.add_argument("--drift", default="0.005")
    parser.add_argument("--field-at-robots", action="store_true")
    parser.add_argument("--random-goals", action="store_true",
                        help="a plan per run: seed 000's environment 1, random goals off the walls")
    parser.add_argument("--goal-clearance", type=float, default=10.0,
                        help="mm between a random goal's magnet and any wall (default 10)")
    parser.add_argument("--plan-seconds", type=float, default=8.0,
                        help="RRT time for each random plan (default 8 s)")
    parser.add_argument("--no-open-loop", dest="open_loop", action="store_false",
                        help="run the closed loop only (the open-loop figures are then null)")
    parser.add_argument("--coil-error", type=float, default=0.05, metavar="F",
                        help="how far the emulated coils are off the rig file (gain, centre, "
                        "axis; default 0.05, the emulator's own default)")
    parser.add_argument("--calibrate-field", action="store_true",
                        help="calibrate the field (`rigctl calibrate field`) before each run: "
                        "the allocator then uses the fitted coils")
    parser.add_argument("--reply-timeout", type=float, default=1.0,
                        help="the supplies' watchdog, s (default 1; raise it on a loaded machine)")
    parser.add_argument("--keep-records", metavar="DIR",
                        help="keep each seed's run records and plan in DIR/seed-N (read a failure "
                        "event by event with `rigctl report`)")
    return parser


def main() -> None:
    args = parser().parse_args()
    mismatch = ["--slip", args.slip, "--speed-spread", args.speed_spread, "--noise", args.noise,
                "--drift", args.drift] + (["--field-at-robots"] if args.field_at_robots else [])
    plan = None if args.random_goals else Path(args.plan)
    results = []
    for i in range(args.runs):
        results.append(one_seed(plan, args.first_seed + i, mismatch, args))
        r = results[-1]
        print(f"run {i + 1}/{args.runs} seed {r['seed']}: closed loop "
              f"{r['closed_loop_error_mm']} mm, reached {r['closed_reached']}, {r['replans']} "
              f"re-plans{', FAULT ' + r['faults'][0] if r['faults'] else ''}; identified "
              f"{r['identified']['gain']} (true {r['true_gain']})", file=sys.stderr, flush=True)
    gain_errors = [abs(g - t) for r in results
                   for g, t, used in zip(r["identified"]["gain"], r["true_gain"],
                                         r["identified"]["moves_used"]) if used]
    tracking_max = [r["tracking"]["max_error_mm"] for r in results
                    if r["tracking"] and r["tracking"]["max_error_mm"] is not None]
    print(json.dumps({
        "plan": "random goals in environment 1" if plan is None else plan.name,
        "mismatch": " ".join(mismatch),
        "coil_error": args.coil_error,
        "field_calibrated": args.calibrate_field,
        "runs": args.runs,
        "closed_loop_success_share": sum(r["closed_reached"] for r in results) / args.runs,
        "open_loop_success_share": sum(r["open_loop_miss_mm"] is not None and
                                       r["open_loop_miss_mm"] <= 1.0 for r in results) / args.runs,
        "open_loop_missed_by_more_than_5_mm": sum(r["open_loop_miss_mm"] is not None and
                                                  r["open_loop_miss_mm"] > 5.0 for r in results),
        "replans_mean": round(float(np.mean([r["replans"] for r in results])), 2),
        "replans_median": float(np.median([r["replans"] for r in results])),
        "identified_gain_error_max": round(max(gain_errors), 4) if gain_errors else None,
        "tracker_error_at_rest_max_mm": max(tracking_max) if tracking_max else None,
        "frame_to_command_latency_ms": frame_to_command(results),
        "per_run": [{k: v for k, v in r.items() if k != "latency_s"} for r in results],
    }, indent=1))


if __name__ == "__main__":
    main()
