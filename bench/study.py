"""Benchmark of studies on Dask (rigctl.apps.study); prints ONE JSON object on stdout.

- studies: every shipped study (`studies/*.toml`), each on a reduced but representative case set
  (`REDUCED`: the same command and arguments, fewer parameter values or seeds), run serially in
  this process and then on a LocalCluster of `--workers` (2) workers, in this one run: `speedup`
  = serial wall / Dask wall (both from the first case to the last, the cluster's start and the
  workers' warm-up reported apart, `cluster_start_s`); goal >= 1.8 on two workers. Where the
  time goes: `case_slowdown` (the cases' summed wall time on the workers over the serial one:
  cases slowed by sharing the cores, e.g. the emulated benches' own processes), `idle_share` (the
  workers' time not in a case: the scheduler's round trips and the wait for the last case, the
  tail), and `cpu_busy` (the machine's busy share of its cores during each side, from
  /proc/stat, other users' work included: near 1.0 on the Dask side, the cores are the limit, not
  the scheduler). `same_results`: every case's success and error figure equal on both sides (for
  the studies whose cases are deterministic: not a time budget, not a real-time emulated run).
  The planner studies also run on a plain `ProcessPoolExecutor` of as many warmed workers
  (`speedup_process_pool`: what this machine gives two processes of this work, without Dask).
- tiny_cases: `--tiny-cases` (1,000) cases of `rigctl plan reachable` on an 11 x 11 grid (its smallest), 2 moves (a
  few ms each, mostly the command's own parsing and files), serially (the plain loop) and on the
  workers: `overhead_ms_per_case` = (workers x wall - the cases' own summed time) / cases, and
  `overhead_share` = that / the mean case time of the plain loop; goal <= 0.05.
  `over_plain_loop_ms_per_case` = (workers x wall - the plain loop's wall) / cases, which adds
  what the cores' sharing costs the cases.
- campaign (`--campaign-runs N`, default 0): N cases of `studies/closed-loop.toml` on the workers:
  the share delivered, and port clashes (a port two cases' benches served at the same time; must
  be 0; a port the kernel hands out again after a case ended is counted apart).
A machine shared with other jobs makes the ratios noisy: the load average is reported.

Usage: python bench/study.py [--smoke] [--workers N] [--study NAME ...] [--tiny-cases N]
                             [--campaign-runs N]
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

REDUCED = {
    # seed 004 Fig. 8-9: the four d12 rows of docs/studies.md's table, every move count (28 cases)
    "reachable": {"parameters": {"d12": [0.001, 0.2, 0.6, 1.0],
                                 "moves": [2, 4, 6, 8, 10, 12, 14]}},
    "reachable-quick": {},  # all 40
    "rrt-solve": {"seeds": {"count": 4}},  # 4 seeds of its 5 s budget
    "closed-loop": {"seeds": {"first": 100, "count": 4}},
    "closed-loop-mismatch": {"parameters": {"slip": [1.0, 0.7], "noise": [0.05]},
                             "seeds": {"count": 2}},
    "faults": {"seeds": {"count": 1}},  # its 4 faults, one seed
    # its one plan, 4 times on benches of their own (the coil-board bench takes no seed: the
    # world's time factor, 3 in the study, differs a little instead)
    "coilboard-delivery": {"cases": [{"plan": "../plans/examples/coilboard-disk.json", "speed": v}
                                     for v in (3.0, 2.9, 2.8, 2.7)]},
}
SMOKE = {"reachable-quick": {"parameters": {"d12": [0.2, 0.4], "moves": [2]}}}  # + 1 campaign run
DETERMINISTIC = {"reachable", "reachable-quick"}  # the others: a time budget or a real-time run


def _study_names() -> list[str]:
    """The shipped studies: the TOML files of studies/ with a [run] table (not the rig file)."""
    return sorted(p.stem for p in STUDIES.glob("*.toml") if "run" in tomllib.loads(p.read_text()))


def _spec(name: str, changes: dict):
    data = tomllib.loads((STUDIES / f"{name}.toml").read_text())
    for key, value in changes.items():
        if key == "time":
            data["run"]["args"]["time"] = value
        else:
            data[key] = value
    return spec_from_dict(data, STUDIES)


def _rows(folder: Path) -> list[dict]:
    return pq.read_table(folder / "results.parquet").to_pylist()


def _cpu_ticks() -> tuple[int, int]:
    """(busy, total) jiffies of all cores since boot, from /proc/stat."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle + iowait
    return sum(fields) - idle, sum(fields)


def _timed(run):
    """run()'s value and the machine's busy share of its cores meanwhile."""
    busy0, total0 = _cpu_ticks()
    value = run()
    busy1, total1 = _cpu_ticks()
    return value, round((busy1 - busy0) / max(1, total1 - total0), 3)


def _pool_wall_s(spec, out: Path, workers: int) -> float:
    """The same cases on a plain process pool of `workers` (each warmed up as a Dask worker is):
    the machine's own parallel floor for this work, without Dask. Wall s."""
    from concurrent.futures import ProcessPoolExecutor

    from rigctl.apps.study.cases import run_case
    from rigctl.apps.study.execution import set_up_worker

    out.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(workers, initializer=set_up_worker, initargs=(spec.command,)) as pool:
        list(pool.map(time.sleep, [0.2] * workers))  # every worker started and warm
        started = time.perf_counter()
        list(pool.map(run_case, *zip(*[(spec.command, str(spec.folder), case, str(out.resolve()),
                                         spec.success, spec.error) for case in spec.cases])))
        return time.perf_counter() - started


def one_study(tmp: Path, name: str, changes: dict, workers: int) -> dict:
    """A study's reduced cases serially, then on `workers` Dask workers (see the docstring)."""
    spec = _spec(name, changes)
    serial, serial_busy = _timed(lambda: run_study(spec, tmp / f"{name}-serial", serial=True,
                                                   progress_out=None))
    started = time.perf_counter()
    dask, dask_busy = _timed(lambda: run_study(spec, tmp / f"{name}-dask", workers=workers,
                                               progress_out=None))
    total = time.perf_counter() - started
    a, b = _rows(tmp / f"{name}-serial"), _rows(tmp / f"{name}-dask")
    outcome = {
        "study": f"studies/{name}.toml", "command": spec.command, "cases": len(spec.cases),
        "serial_s": round(serial.wall_s, 3), "dask_s": round(dask.wall_s, 3),
        "speedup": round(serial.wall_s / dask.wall_s, 3),
        "cluster_start_s": round(total - dask.wall_s, 2),
        "case_s_sum_serial": round(serial.case_wall_s, 3),
        "case_s_sum_dask": round(dask.case_wall_s, 3),
        "case_slowdown": round(dask.case_wall_s / serial.case_wall_s, 3),
        "idle_share": round(1 - dask.case_wall_s / (dask.workers * dask.wall_s), 3),
        "cpu_busy": {"serial": serial_busy, "dask": dask_busy},
        "not_ok": [serial.not_ok, dask.not_ok],
        "same_results": None,
    }
    if name in DETERMINISTIC:
        figures = [{r["case_id"]: (r["success"], r["error"]) for r in rows} for rows in (a, b)]
        outcome["same_results"] = figures[0] == figures[1]
    if not spec.command == "execute":
        pool_s = _pool_wall_s(spec, tmp / f"{name}-pool", workers)
        outcome["speedup_process_pool"] = round(serial.wall_s / pool_s, 3)
    return outcome


def tiny_cases(tmp: Path, count: int, workers: int) -> dict:
    """`count` cases of a few ms (see the docstring): the scheduling overhead per case."""
    step = 1.0 / count
    spec = spec_from_dict({"name": "tiny", "run": {"command": "plan reachable", "args": {
        "disk": True, "cells": 11, "moves": 2}},
        "parameters": {"d12": [round(step * (k + 1), 9) for k in range(count)]}}, tmp)
    serial = run_study(spec, tmp / "tiny-serial", serial=True, progress_out=None)
    started = time.perf_counter()
    dask = run_study(spec, tmp / "tiny-dask", workers=workers, progress_out=None)
    total = time.perf_counter() - started
    own_ms = 1e3 * serial.wall_s / count
    overhead_ms = 1e3 * (dask.workers * dask.wall_s - dask.case_wall_s) / count
    return {
        "cases": count, "workers": dask.workers, "plain_loop_s": round(serial.wall_s, 3),
        "case_ms_plain_loop": round(own_ms, 3), "dask_s": round(dask.wall_s, 3),
        "cluster_start_s": round(total - dask.wall_s, 2),
        "overhead_ms_per_case": round(overhead_ms, 3),
        "overhead_share": round(overhead_ms / own_ms, 3), "overhead_goal_share": 0.05,
        "over_plain_loop_ms_per_case": round(
            1e3 * (dask.workers * dask.wall_s - serial.wall_s) / count, 3),
        "speedup": round(serial.wall_s / dask.wall_s, 3),
        "not_ok": [serial.not_ok, dask.not_ok],
    }


def campaign(tmp: Path, runs: int, workers: int) -> dict:
    spec = _spec("closed-loop", {"seeds": {"first": 100, "count": runs}})
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
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--study", action="append", choices=_study_names(),
                        help="only this shipped study (repeatable; default: every one)")
    parser.add_argument("--tiny-cases", type=int, help="cases of the overhead stage (default "
                                                        "1000; 0: none)")
    parser.add_argument("--campaign-runs", type=int,
                        help="emulated closed-loop runs of the port-clash campaign (default 0)")
    parser.add_argument("--smoke", action="store_true",
                        help="the smallest run of every stage, for the test suite: its figures "
                             "mean nothing (2 cases of one planner study, 20 tiny cases, 1 "
                             "campaign run)")
    args = parser.parse_args()
    reduced = SMOKE if args.smoke else REDUCED
    names = [n for n in (args.study or _study_names()) if n in reduced]
    tiny = args.tiny_cases if args.tiny_cases is not None else 20 if args.smoke else 1000
    runs = args.campaign_runs if args.campaign_runs is not None else 1 if args.smoke else 0
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-study-") as tmp:
        os.environ.setdefault("RIGCTL_LOCK_DIR", str(Path(tmp) / "locks"))
        load_before = os.getloadavg()[0]
        studies = []
        for name in names:
            print(f"bench study: {name}", file=sys.stderr, flush=True)
            studies.append(one_study(Path(tmp), name, reduced[name], args.workers))
        report = {
            "benchmark": "study", "python": platform.python_version(), "cores": os.cpu_count(),
            "workers": args.workers, "speedup_goal": 1.8,
            "studies": studies,
            "speedup_min": min((s["speedup"] for s in studies), default=None),
            "tiny_cases": tiny_cases(Path(tmp), tiny, args.workers) if tiny else None,
            "campaign": campaign(Path(tmp), runs, args.workers) if runs else None,
            "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
