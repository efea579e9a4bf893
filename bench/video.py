"""Video recording benchmark: does writing the record's video make the stream late? Prints one
JSON object.

One emulated six-coil bench (its own process, the camera over MJPEG at 60 frames/s) runs the same
closed-loop plan `--pairs` times with the record's video off and on, alternating (off, on, off,
on, ...) so that the machine's load drifts over both alike. For each side, pooled over its runs
from the records' per-cycle period errors (`stream/*.parquet`): the late share (cycles that
started more than half a period late, as the stream loop counts them) and the period error p50 /
p99; then the ratios on / off, which the issue wants within 10 % (1.10), pooled and as the median
of each pair's own ratio (the two runs of a pair ran next to each other, under much the same
load). Also: the video's frames written and dropped, its rate over the run, and its disk use per
minute (bytes of `video.avi` over the span of its frame times), the figure docs/video.md states.

Run: `.venv/bin/python bench/video.py [--pairs 5] [--rate 100] [--plan plans/examples/fig4-quick.json]`;
`--smoke`: one pair of a three-turn plan.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np

from rigctl.core.config import load_rig
from rigctl.core.record import read_events, read_series, read_stream
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import load_plan, parse_plan
from rigctl.rigs.six_coil.global_moves import execute_plan

ROOT = Path(__file__).resolve().parents[1]
LATE_FRACTION = 0.5  # the stream loop's own threshold (StreamLoop's late_fraction)


def three_turns(plan_path: Path):
    """The plan's workspace and agents, one roll of three turns (30 mm) towards -y."""
    plan = json.loads(plan_path.read_text())
    goals = [[a["start"][0], a["start"][1] - 30.0] for a in plan["agents"]]
    for agent, goal in zip(plan["agents"], goals):
        agent["goal"] = goal
    plan.update(name="three turns down", moves=[[0.0, -30.0]], expected=[goals])
    return parse_plan(plan)


def bench_rig(rig, rate_hz: float, record_video: bool):
    """4 turns/s as the integration tests; a watchdog for a loaded machine; video on or off."""
    return rig.model_copy(update={
        "field": rig.field.model_copy(update={"rolling_turns_per_s": 4.0,
                                              "steering_deg_per_s": 360.0}),
        "stream": rig.stream.model_copy(update={"reply_timeout_s": 1.0, "rate_hz": rate_hz}),
        "camera": rig.camera.model_copy(update={"record_video": record_video}),
    })


def one_run(plan, rig, runs_dir: Path) -> dict:
    summary = execute_plan(plan, rig, runs_dir=runs_dir, progress_out=None, closed_loop=True)
    run = Path(summary.run)
    stream = read_stream(run)
    errors = np.asarray(stream["period_error_s"], dtype=float)
    out = {"errors_s": errors[np.isfinite(errors)], "faults": [f["reason"] for f in summary.faults],
           "reached": summary.reached}
    video = next((e for e in read_events(run) if e["event"] == "video"), None)
    if video is not None:
        times = read_series(run, "video")["t_s"]
        span = float(times[-1] - times[0]) if len(times) > 1 else float("nan")
        size = (run / video["file"]).stat().st_size
        out["video"] = {"written": video["written"], "dropped": video["dropped"],
                        "fps_over_run": round((len(times) - 1) / span, 2),
                        "MB_per_min": round(size / span * 60 / 1e6, 2)}
    return out


def pooled(runs: list[dict], rate_hz: float) -> dict:
    errors = np.concatenate([r["errors_s"] for r in runs])
    late = errors > LATE_FRACTION / rate_hz
    return {"cycles": int(errors.size), "late_share": round(float(late.mean()), 5),
            "period_error_us": {"p50": round(float(np.percentile(errors, 50)) * 1e6, 1),
                                "p99": round(float(np.percentile(errors, 99)) * 1e6, 1)},
            "faults": [f for r in runs for f in r["faults"]],
            "reached": sum(bool(r["reached"]) for r in runs)}


def _ratio(on: float, off: float) -> float | None:
    return round(on / off, 3) if off > 0 else None


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 3) if values else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=5, help="runs off and on, alternating")
    parser.add_argument("--rate", type=float, default=100.0, help="stream rate (Hz)")
    parser.add_argument("--plan", default=str(ROOT / "plans" / "examples" / "fig4-quick.json"))
    parser.add_argument("--smoke", action="store_true", help="one pair of a three-turn plan")
    args = parser.parse_args()
    pairs = 1 if args.smoke else args.pairs
    plan = three_turns(Path(args.plan)) if args.smoke else load_plan(args.plan)
    results: dict[bool, list[dict]] = {False: [], True: []}
    with tempfile.TemporaryDirectory(prefix="rigctl-video-bench-") as tmp:
        with EmulatedBenchProcess("six-coil", Path(tmp) / "bench.toml") as rig_path:
            rig = load_rig(rig_path)
            for k in range(pairs):
                for video in (False, True):
                    results[video].append(one_run(plan, bench_rig(rig, args.rate, video),
                                                  Path(tmp) / "runs"))
    off, on = pooled(results[False], args.rate), pooled(results[True], args.rate)
    videos = [r["video"] for r in results[True] if "video" in r]
    on["video"] = {
        "written": sum(v["written"] for v in videos), "dropped": sum(v["dropped"] for v in videos),
        "fps_over_run_min": min(v["fps_over_run"] for v in videos) if videos else None,
        "MB_per_min": round(float(np.median([v["MB_per_min"] for v in videos])), 2)
        if videos else None}
    per_pair = []
    for off_run, on_run in zip(results[False], results[True]):
        a, b = pooled([off_run], args.rate), pooled([on_run], args.rate)
        per_pair.append({"late_share": _ratio(b["late_share"], a["late_share"]),
                         "period_error_p99": _ratio(b["period_error_us"]["p99"],
                                                    a["period_error_us"]["p99"])})
    print(json.dumps({
        "plan": plan.name, "pairs": pairs, "rate_hz": args.rate,
        "machine": {"cpus": os.cpu_count(), "load_1min": round(os.getloadavg()[0], 2),
                    "python": platform.python_version()},
        "off": off, "on": on,
        "ratio_on_off": {"late_share": _ratio(on["late_share"], off["late_share"]),
                         "period_error_p99": _ratio(on["period_error_us"]["p99"],
                                                    off["period_error_us"]["p99"])},
        "ratio_on_off_per_pair": per_pair,
        "ratio_on_off_median_of_pairs": {
            key: _median([p[key] for p in per_pair if p[key] is not None])
            for key in ("late_share", "period_error_p99")},
    }, indent=1))


if __name__ == "__main__":
    main()
