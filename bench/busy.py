"""Benchmark: a busy computer loses no run. Prints ONE JSON object on stdout.

Runs a plan with `rigctl execute PLAN --json` on its emulated bench while CPU-bound hogs (plain
Python busy loops at the caller's priority, as a build or a study would be) keep the cores busy,
alternating two conditions run by run so that both see the same machine:

- `favoured`: as rigctl runs by default: where the machine permits it (root, CAP_SYS_NICE, an
  RLIMIT_NICE that reaches it), the stream and tracking threads at niceness -10 and the emulated
  bench at -5 (`rigctl.core.stream.FAVOURED_NICE`, `emulators/base.py`);
- `plain`: the same with both left at the caller's niceness (RIGCTL_STREAM_NICE=0,
  RIGCTL_EMULATOR_NICE=0): what the run got before.

Per condition: runs, runs lost (not `done`, or any fault), of which ended by a supply's reply
watchdog (`no reply within`), goals reached, and the stream's late share and period error p99
(median and worst over the runs). `permitted` says whether this machine lets a process raise its
priority at all; where it does not, both conditions are the same run.

    python bench/busy.py                      # 20 runs per condition, two hogs (the issue's figure)
    python bench/busy.py --runs 3 --hogs 2    # a quick look
    python bench/busy.py --smoke              # one open-loop run, favoured only, one hog
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PLAN = ROOT / "plans" / "examples" / "fig4-quick.json"
CONDITIONS = {
    "favoured": {},
    "plain": {"RIGCTL_STREAM_NICE": "0", "RIGCTL_EMULATOR_NICE": "0"},
}


def _hog() -> None:
    while True:
        pass


def one_run(plan: Path, extra_env: dict, runs_dir: Path, timeout_s: float,
            flags: list[str]) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("RIGCTL_STREAM_NICE",
                                                             "RIGCTL_EMULATOR_NICE")}
    env.update(extra_env)
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "rigctl", "execute", str(plan), "--json", "-q",
                           "--runs", str(runs_dir), *flags],
                          capture_output=True, text=True, env=env, timeout=timeout_s)
    wall = time.monotonic() - started
    try:
        summary = json.loads(done.stdout)
    except json.JSONDecodeError:
        return {"exit": done.returncode, "wall_s": round(wall, 1), "lost": True, "watchdog": False,
                "error": done.stderr.strip().splitlines()[-1:] or ["no output"]}
    faults = [str(f) for f in summary.get("faults") or []]
    stream = summary.get("stream") or {}
    return {
        "exit": done.returncode,
        "wall_s": round(wall, 1),
        "state": summary.get("state"),
        "reached": bool(summary.get("reached")),
        "lost": summary.get("state") != "done" or bool(faults),
        "watchdog": any("no reply within" in f for f in faults),
        "faults": faults,
        "late_share": stream.get("late_share"),
        "period_error_p99_us": (stream.get("period_error_us") or {}).get("p99"),
    }


def summarise(runs: list[dict]) -> dict:
    def figure(key: str) -> dict | None:
        values = [r[key] for r in runs if r.get(key) is not None]
        if not values:
            return None
        return {"median": round(statistics.median(values), 4), "max": round(max(values), 4)}

    return {
        "runs": len(runs),
        "lost": sum(r["lost"] for r in runs),
        "watchdog_trips": sum(r["watchdog"] for r in runs),
        "reached": sum(bool(r.get("reached")) for r in runs),
        "late_share": figure("late_share"),
        "period_error_p99_us": figure("period_error_p99_us"),
        "faults": sorted({f for r in runs for f in r.get("faults", [])})[:10],
    }


def raising_permitted(nice: int = -10) -> bool:
    """Whether this process may take niceness `nice` (root, or RLIMIT_NICE reaching 20 - nice)."""
    return os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_NICE)[0] >= 20 - nice


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=20, help="runs per condition (default 20)")
    parser.add_argument("--hogs", type=int, default=2, help="CPU-bound hog processes (default 2)")
    parser.add_argument("--plan", type=Path, default=PLAN, help="the plan (default fig4-quick)")
    parser.add_argument("--open-loop", action="store_true", help="runs without the camera")
    parser.add_argument("--smoke", action="store_true",
                        help="one open-loop run, favoured only, one hog (the suite's smoke run)")
    args = parser.parse_args()
    conditions = dict(CONDITIONS)
    if args.smoke:
        args.runs, args.hogs, args.open_loop = 1, 1, True
        del conditions["plain"]
    flags = ["--open-loop"] if args.open_loop else []
    load_before = os.getloadavg()
    hogs = [multiprocessing.Process(target=_hog, daemon=True) for _ in range(args.hogs)]
    for hog in hogs:
        hog.start()
    per: dict[str, list[dict]] = {name: [] for name in conditions}
    try:
        with tempfile.TemporaryDirectory(prefix="rigctl-busy-") as tmp:
            for i in range(args.runs):
                for name, extra in conditions.items():  # alternated: both see the same machine
                    run = one_run(args.plan, extra, Path(tmp), 600, flags)
                    per[name].append(run)
                    print(f"run {i + 1}/{args.runs} {name}: {run.get('state')} "
                          f"{'LOST ' + '; '.join(run.get('faults', [])) if run['lost'] else 'ok'}",
                          file=sys.stderr, flush=True)
    finally:
        for hog in hogs:
            hog.terminate()
        for hog in hogs:
            hog.join()
    out = {
        "plan": args.plan.name,
        "hogs": args.hogs,
        "closed_loop": not args.open_loop,
        "permitted": raising_permitted(),
        "conditions": {name: summarise(runs) for name, runs in per.items()},
        "per_run": per,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_before": [round(x, 2) for x in load_before]},
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
