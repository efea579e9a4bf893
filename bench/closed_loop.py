"""Closed-loop benchmark: prints one JSON object.

For each of `--runs` seeds, an emulated six-coil bench (its own process) with model mismatch (slip
0.85, per-robot speed spread, contact noise, drift; `--field-at-robots` adds the non-uniform field)
runs the example plan open-loop and then closed-loop. Reported: the share of runs whose every robot
ends within the plan's tolerance (1 mm) by the emulator's ground truth, the worst open-loop miss,
re-plans per run, the tracker's error at rest against ground truth, and the latency from the
capture time of the frame a decision used to the first command after it leaving the stream loop
(p50 / p99), separately for "go on" decisions and for re-plans (which include the RRT's time).

Run: `.venv/bin/python bench/closed_loop.py [--runs 20] [--plan plans/examples/fig4-quick.json]`.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import load_plan

from rigctl.config import RigConfig, load_rig
from rigctl.rigs.six_coil.global_moves import Run
from rigctl.rigs.six_coil.supervisor import SupervisorSettings

ROOT = Path(__file__).resolve().parents[1]


def bench_rig(rig: RigConfig) -> RigConfig:
    """4 turns/s as in the integration tests; a watchdog that tolerates a loaded machine."""
    return rig.model_copy(update={
        "field": rig.field.model_copy(update={"rolling_turns_per_s": 4.0,
                                              "steering_deg_per_s": 360.0}),
        "stream": rig.stream.model_copy(update={"reply_timeout_s": 1.0}),
    })


def one_seed(plan_path: Path, seed: int, mismatch: list[str]) -> dict:
    plan = load_plan(plan_path)
    with tempfile.TemporaryDirectory(prefix="rigctl-closed-loop-") as tmp:
        with EmulatedBenchProcess("six-coil", Path(tmp) / "bench.toml",
                                  extra_args=[*mismatch, "--seed", str(seed)]) as rig_path:
            rig = bench_rig(load_rig(rig_path))
            open_run = Run(plan, rig, runs_dir=Path(tmp) / "runs", progress_out=None)
            open_summary = open_run.execute()
            closed_run = Run(plan, rig, runs_dir=Path(tmp) / "runs", progress_out=None,
                             closed_loop=True, supervisor_settings=SupervisorSettings(seed=seed))
            closed = closed_run.execute()
            supervisor = closed_run.program.supervisor
            assert supervisor is not None
            times = supervisor.sequencer.command_times
            latency = {"continue": [], "replan": []}
            for d in supervisor.decisions:
                if d.number in times:
                    kind = "replan" if d.kind == "replan" else "continue"
                    latency[kind].append(times[d.number] - d.t_source)
    truth = [a.truth_error_mm if a.truth_error_mm is not None else a.error_mm
             for a in closed.agents]
    return {
        "seed": seed,
        "open_loop_miss_mm": max(a.error_mm for a in open_summary.agents),
        "closed_loop_error_mm": max(truth),
        "closed_reached": not closed.faults and max(truth) <= plan.tolerance_mm,
        "faults": [f["reason"] for f in closed.faults],
        "replans": closed.replans,
        "tracking": closed.tracking,
        "duration_s": round(closed.duration_s, 1),
        "latency_s": latency,
    }


def percentiles_ms(values: list[float]) -> dict:
    if not values:
        return {"n": 0}
    v = np.array(values) * 1e3
    return {"n": len(v), "p50": round(float(np.percentile(v, 50)), 1),
            "p99": round(float(np.percentile(v, 99)), 1), "max": round(float(v.max()), 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=100)
    parser.add_argument("--plan", default=str(ROOT / "plans" / "examples" / "fig4-quick.json"))
    parser.add_argument("--slip", default="0.85")
    parser.add_argument("--speed-spread", default="0.01")
    parser.add_argument("--noise", default="0.05")
    parser.add_argument("--drift", default="0.005")
    parser.add_argument("--field-at-robots", action="store_true")
    args = parser.parse_args()
    mismatch = ["--slip", args.slip, "--speed-spread", args.speed_spread, "--noise", args.noise,
                "--drift", args.drift] + (["--field-at-robots"] if args.field_at_robots else [])
    results = [one_seed(Path(args.plan), args.first_seed + i, mismatch) for i in range(args.runs)]
    continue_latency = [t for r in results for t in r["latency_s"]["continue"]]
    replan_latency = [t for r in results for t in r["latency_s"]["replan"]]
    tracking_max = [r["tracking"]["max_error_mm"] for r in results
                    if r["tracking"] and r["tracking"]["max_error_mm"] is not None]
    print(json.dumps({
        "plan": Path(args.plan).name,
        "mismatch": " ".join(mismatch),
        "runs": args.runs,
        "closed_loop_success_share": sum(r["closed_reached"] for r in results) / args.runs,
        "open_loop_success_share": sum(r["open_loop_miss_mm"] <= 1.0 for r in results) / args.runs,
        "open_loop_missed_by_more_than_5_mm": sum(r["open_loop_miss_mm"] > 5.0 for r in results),
        "replans_mean": round(float(np.mean([r["replans"] for r in results])), 2),
        "tracker_error_at_rest_max_mm": max(tracking_max) if tracking_max else None,
        "frame_to_command_latency_ms": {"continue": percentiles_ms(continue_latency),
                                        "replan": percentiles_ms(replan_latency)},
        "per_run": [{k: v for k, v in r.items() if k != "latency_s"} for r in results],
    }, indent=1))


if __name__ == "__main__":
    main()
