"""Benchmark of studies on Dask (rigctl.apps.study); prints ONE JSON object on stdout.

- planner_sweep: the 40 cases of `studies/reachable-quick.toml` (seed 004 Fig. 8 on a 61 x 61
  grid: 20 values of d12 x 2 and 4 moves), run serially in this process and on a LocalCluster of
  `--workers` (2) workers, side by side in this one run (serial first, then Dask, `--repeats`
  times alternately; each ratio is of one such pair, the median reported, and the ratio of the
  best serial to the best Dask time, `speedup_best_of`). Goal: >= 1.8x on two
  cores. Both sides start with the planners' kernels loaded and exclude the cluster's start-up
  (reported apart), and both give the same fraction for every case (checked, `same_results`).
  `overhead_ms_per_case`: per worker, the gap between the end of one case and the start of the
  next (the scheduler's round trip), mean over the cases; goal < 50 ms. `idle_ms_per_case`:
  (workers x wall - sum of the case times) / cases, which adds the wait for the last case.
  The floor, in the same run: the same cases on a plain `ProcessPoolExecutor` of as many warmed
  workers (`speedup_process_pool`: what this machine gives two processes of this work, without
  Dask), and Dask against it (`dask_over_pool`, 1.0: Dask costs nothing).
- campaign: `--campaign-runs` (20) cases of `studies/closed-loop.toml` (fig4-quick closed loop on
  the emulated six-coil bench with model mismatch, one bench per seed) on two workers: the share
  delivered (ground truth within 1 mm), wall time, and port clashes (a port two cases' benches
  served at the same time; must be 0; a port the kernel hands out again after a case ended is
  counted apart).
A machine shared with other jobs makes both ratios noisy: the load average is reported.

Usage: python bench/study.py [--quick | --smoke] [--workers N] [--repeats N] [--campaign-runs N]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import re
import statistics
import sys
import tempfile
import time
import tomllib
from collections import defaultdict
from pathlib import Path

import pyarrow.parquet as pq

from rigctl.apps.study.execution import run_study
from rigctl.apps.study.spec import spec_from_dict

STUDIES = Path(__file__).resolve().parents[1] / "studies"


def _spec(name: str, **changes):
    data = tomllib.loads((STUDIES / f"{name}.toml").read_text())
    for key, value in changes.items():
        data[key] = value
    return spec_from_dict(data, STUDIES)


def _rows(folder: Path) -> list[dict]:
    return pq.read_table(folder / "results.parquet").to_pylist()


def _gaps_ms(rows: list[dict]) -> list[float]:
    """Per worker, end of a case to the start of the next one, ms."""
    by_worker = defaultdict(list)
    for r in rows:
        by_worker[r["worker"]].append((r["started_s"], r["wall_s"]))
    gaps = []
    for cases in by_worker.values():
        cases.sort()
        gaps += [1e3 * (b[0] - (a[0] + a[1])) for a, b in itertools.pairwise(cases)]
    return gaps


def _pool_wall_s(spec, out: Path, workers: int) -> tuple[float, dict]:
    """The same cases on a plain process pool of `workers` (each warmed up as a Dask worker is):
    the machine's own parallel floor for this work, without Dask. Wall s and fraction per case."""
    from concurrent.futures import ProcessPoolExecutor

    from rigctl.apps.study.cases import run_case
    from rigctl.apps.study.execution import set_up_worker

    out.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(workers, initializer=set_up_worker, initargs=(spec.command,)) as pool:
        list(pool.map(time.sleep, [0.2] * workers))  # every worker started and warm
        started = time.perf_counter()
        rows = list(pool.map(run_case, *zip(*[(spec.command, str(spec.folder), case,
                                                str(out.resolve()), spec.success, spec.error)
                                               for case in spec.cases])))
        wall = time.perf_counter() - started
    return wall, {r["case_id"]: r["figures"].get("fraction") for r in rows}


def planner_sweep(tmp: Path, workers: int, repeats: int, study: str, quick: bool,
                  smoke: bool = False) -> dict:
    spec = _spec(study, **({"parameters": {"d12": [0.2, 0.4], "moves": [2]}} if smoke else
                           {"parameters": {"d12": [0.2, 0.4, 0.6, 0.8, 1.0],
                                           "moves": [2, 4]}} if quick else {}))
    pairs = []
    for k in range(repeats):
        serial = run_study(spec, tmp / f"serial-{k}", serial=True, progress_out=None)
        started = time.perf_counter()
        dask = run_study(spec, tmp / f"dask-{k}", workers=workers, progress_out=None)
        total = time.perf_counter() - started
        pool_s, pooled = _pool_wall_s(spec, tmp / f"pool-{k}", workers)
        a, b = _rows(tmp / f"serial-{k}"), _rows(tmp / f"dask-{k}")
        fractions = {r["case_id"]: r["fig_fraction"] for r in a}
        same = fractions == {r["case_id"]: r["fig_fraction"] for r in b} == pooled
        gaps = _gaps_ms(b)
        pairs.append({
            "serial_s": round(serial.wall_s, 3), "dask_s": round(dask.wall_s, 3),
            "speedup": round(serial.wall_s / dask.wall_s, 3),
            "pool_s": round(pool_s, 3), "speedup_process_pool": round(serial.wall_s / pool_s, 3),
            "cluster_start_and_warm_up_s": round(total - dask.wall_s, 2),
            "overhead_ms_per_case": round(statistics.mean(gaps), 2) if gaps else None,
            "overhead_ms_max": round(max(gaps), 2) if gaps else None,
            "idle_ms_per_case": round(1e3 * (workers * dask.wall_s - dask.case_wall_s) / dask.ran, 1),
            "case_s_sum_serial": round(serial.case_wall_s, 3),
            "case_s_sum_dask": round(dask.case_wall_s, 3),
            "same_results": same,
        })
    ratios = [p["speedup"] for p in pairs]
    overheads = [p["overhead_ms_per_case"] for p in pairs if p["overhead_ms_per_case"] is not None]
    return {
        "study": f"studies/{study}.toml", "cases": len(spec.cases), "workers": workers,
        "speedup_median": statistics.median(ratios), "speedup_goal": 1.8,
        # the floor: the same cases on a plain process pool, this machine's own parallel speed-up
        "speedup_process_pool_median": statistics.median(p["speedup_process_pool"] for p in pairs),
        "dask_over_pool_median": statistics.median(p["pool_s"] / p["dask_s"] for p in pairs),
        "speedup_best_of": round(min(p["serial_s"] for p in pairs) / min(p["dask_s"] for p in pairs), 3),
        "overhead_ms_per_case_median": statistics.median(overheads) if overheads else None,
        "overhead_goal_ms": 50, "same_results": all(p["same_results"] for p in pairs),
        "runs": pairs,
    }


def campaign(tmp: Path, runs: int, workers: int) -> dict:
    spec = _spec("closed-loop", seeds={"first": 100, "count": runs})
    started = time.perf_counter()
    outcome = run_study(spec, tmp / "campaign", workers=workers, progress_out=sys.stderr)
    wall = time.perf_counter() - started
    rows = _rows(tmp / "campaign")
    owners: dict[int, list[tuple[float, float]]] = defaultdict(list)
    for r in rows:
        bench = tmp / "campaign" / "cases" / r["case_id"] / "bench.toml"
        for port in set(re.findall(r"127\.0\.0\.1:(\d+)", bench.read_text())):
            owners[int(port)].append((r["started_s"], r["started_s"] + r["wall_s"]))

    def clash(spans: list[tuple[float, float]]) -> bool:
        """Two cases' benches served the port at the same time (the kernel hands a port out
        again once a finished case's bench let it go: that is no clash)."""
        spans = sorted(spans)
        return any(b[0] < a[1] for a, b in itertools.pairwise(spans))
    delivered = [r for r in rows if r["success"]]
    errors = [r["error"] for r in rows if r["error"] is not None]
    return {
        "study": "studies/closed-loop.toml", "runs": runs, "workers": outcome.workers,
        "ran_ok": outcome.ran - outcome.not_ok, "delivered": len(delivered),
        "delivered_share": len(delivered) / runs, "port_clashes": sum(clash(c) for c in owners.values()),
        "ports_reused_after_a_case_ended": sum(len(c) > 1 and not clash(c) for c in owners.values()),
        "ports_served": len(owners), "wall_s": round(wall, 1),
        "case_s_median": round(statistics.median(r["wall_s"] for r in rows), 1),
        "worst_error_mm": max(errors) if errors else None,
        "not_delivered": [{"seed": r["seed"], "state": r["fig_state"], "error_mm": r["error"],
                           "message": r["message"]} for r in rows if not r["success"]],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="10 planner cases, 2 emulated runs")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--study", default="reachable", choices=("reachable", "reachable-quick"),
                        help="the planner sweep (default: reachable, seed 004's Fig. 8-9, 112 "
                             "cases; reachable-quick: 40 cases on a 61 x 61 grid; --quick: 10 of "
                             "those); the bench compares the cases' reachable fractions")
    parser.add_argument("--repeats", type=int, help="serial/Dask pairs of the sweep (default 5)")
    parser.add_argument("--campaign-runs", type=int, help="emulated closed-loop runs (default 20)")
    parser.add_argument("--smoke", action="store_true",
                        help="the smallest run of every stage, for the test suite: its figures "
                             "mean nothing (2 planner cases, 1 emulated run)")
    args = parser.parse_args()
    args.quick = args.quick or args.smoke
    repeats = args.repeats or (1 if args.quick else 5)
    runs = args.campaign_runs if args.campaign_runs is not None else (
        1 if args.smoke else 2 if args.quick else 20)
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-study-") as tmp:
        os.environ.setdefault("RIGCTL_LOCK_DIR", str(Path(tmp) / "locks"))
        load_before = os.getloadavg()[0]
        report = {
            "benchmark": "study", "python": platform.python_version(), "cores": os.cpu_count(),
            "planner_sweep": planner_sweep(Path(tmp), args.workers, repeats,
                                           "reachable-quick" if args.quick else args.study, args.quick,
                                           args.smoke),
            "campaign": campaign(Path(tmp), runs, args.workers) if runs else None,
            "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
