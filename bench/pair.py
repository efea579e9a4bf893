"""Benchmark of the two-agent planner and tracker (seed 002, issue 8); prints ONE JSON object.

Figures:
- solve: `rigctl plan pair`'s RRT on the two demonstration problems (plans/examples/pair-*.json:
  the Fig. 6 micro-factory maze and a formation change) over --seeds seeds with a --budget time
  limit, for the default planner ("fast": goal tree + connect steps) and Alg. 1-3 as printed
  ("paper"): share solved within the budget, median / p95 / max seconds per solve, median nodes,
  median planned duration and segments.
- replan: re-planning from a measured state onto the rest of a path (what a run does when the
  proximity controller cannot bring the agents back): the micro-factory path, a node chosen at
  random, the formation disturbed by 0.1-0.4 BL in each agent's position; per re-plan seconds
  (median, p95, max) and the share that joined the path (goal < 100 ms).
- decide: milliseconds per tracking decision (`PairPursuit.decide`) along the micro-factory path.
- runs: `rigctl execute` of each demonstration plan on the emulated bench (pair world, its own
  process; camera sensor noise always on, plus --noise MM of agent jitter per sqrt(s)):
  rms_tracking_error_bl (goal <= 0.1), hold_max_error_bl (goal <= 0.2), min_separation_bl against
  the plan's r_min (no violation), reached.
- mobility: the formation change on a bench whose agents move --slip times as fast under a force
  as the plan's Stokes drag says (a liquid 1/slip as viscous; default 0.6), closed loop with the
  pull gain identified from tracking (`PullIdentification`) and without (the pursuit believes the
  plan's drag): each run's tracking RMS, hold error, duration and reached, and the identified gain
  (+- its standard deviation) against the true pull gain (the slip times the coils' own gradient
  error, which --coil-error 0 removes: the bench is started with it, so the truth is the slip).

Usage: python bench/pair.py [--quick] [--seeds N] [--budget S] [--replans N] [--noise MM]
                            [--slip F] [--mobility-seeds N]
(--quick: the default planner only, 3 seeds, and only the formation change is run; about 1 minute.)
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "plans" / "examples"
PROBLEMS = {
    "microfactory": ("pair-microfactory.json", [3, 4, 2, 90], [16.4, 12.5, 2.2, 0]),
    "formation_change": ("pair-formation-change.json", [7, 6, 2, 0], [11, 7, 3, 90]),
}


def _q(doc, d):
    return np.array([doc[0] / d, doc[1] / d, doc[2], math.radians(doc[3])])


def _spread(seconds: list[float], unit: str, scale: float, digits: int) -> dict:
    """Median, p95 (nearest rank: never below the median) and max of `seconds` times `scale`."""
    v = sorted(seconds)
    return {f"median_{unit}": round(scale * statistics.median(v), digits),
            f"p95_{unit}": round(scale * v[math.ceil(0.95 * len(v)) - 1], digits),
            f"max_{unit}": round(scale * v[-1], digits)}


def bench_solve(names, seeds, variants, budget_s):
    """Each variant of the planner (`PairPlannerOptions.paper` = Alg. 1-3 as printed, `fast` =
    plus the goal tree and connect steps) on each problem, seeds 0..seeds-1, `budget_s` each."""
    from rigctl.plans.pair import PairPlannerOptions, plan_pair, problem_of
    from rigctl.plans.schema import load_plan

    out = {}
    for variant in variants:
        for name in names:
            file, start, goal = PROBLEMS[name]
            plan = load_plan(EXAMPLES / file)
            problem = problem_of(plan)
            d = plan.agents.body_diameter_mm
            times, nodes, plan_s, segments, solved = [], [], [], [], 0
            for seed in range(seeds):
                options = getattr(PairPlannerOptions, variant)(time_s=budget_s)
                path = plan_pair(problem, _q(start, d), _q(goal, d), options, seed)
                times.append(path.seconds)
                nodes.append(path.nodes)
                if path.solved:
                    solved += 1
                    plan_s.append(float(path.dts.sum()))
                    segments.append(len(path.dts))
            out[f"{name}/{variant}"] = {
                "seeds": seeds, "budget_s": budget_s, "solved_share": solved / seeds,
                **_spread(times, "s", 1.0, 4),
                "median_nodes": int(statistics.median(nodes)),
                "median_plan_duration_s": round(statistics.median(plan_s), 2) if plan_s else None,
                "median_segments": int(statistics.median(segments)) if segments else None}
    return out


def bench_replan(count):
    from rigctl.plans.pair import PairPlannerOptions, problem_of, replan_pair, state_of
    from rigctl.plans.schema import load_plan

    plan = load_plan(EXAMPLES / PROBLEMS["microfactory"][0])
    problem = problem_of(plan)
    d = plan.agents.body_diameter_mm
    nodes = np.array([state_of(plan.start, d)] + [state_of(e, d) for e in plan.expected])
    rng = np.random.default_rng(7)
    times, joined = [], 0
    from rigctl.plans.pair import agent_positions, state_from_positions

    for i in range(count):
        k = int(rng.integers(1, len(nodes) - 5))
        for _ in range(50):  # a disturbed formation the agents can physically be in
            p = agent_positions(nodes[k]) + rng.uniform(0.1, 0.4, (2, 1)) * _unit2(rng)
            q = state_from_positions(p)
            if problem.separation_ok(q[2]) and problem.agents_free(q[None])[0]:
                break
        t0 = time.perf_counter()
        path, _ = replan_pair(problem, q, nodes, k, PairPlannerOptions(time_s=0.5), seed=i)
        times.append(time.perf_counter() - t0)
        joined += path.solved
    return {"count": count, "joined_share": joined / count, **_spread(times, "ms", 1e3, 2)}


def _unit2(rng):
    a = rng.uniform(0, 2 * math.pi, 2)
    return np.stack([np.cos(a), np.sin(a)], axis=1)


def bench_decide():
    from rigctl.plans.pair import (
        default_rig,
        physics_of,
        problem_of,
        rig_max_pull,
        state_of,
    )
    from rigctl.plans.schema import load_plan
    from rigctl.rigs.six_coil.pursuit import PairPursuit, PursuitSettings

    plan = load_plan(EXAMPLES / PROBLEMS["microfactory"][0])
    d = plan.agents.body_diameter_mm
    nodes = np.array([state_of(plan.start, d)] + [state_of(e, d) for e in plan.expected])
    pull = 0.95 * rig_max_pull(default_rig(), physics_of(plan), plan.field_mT)
    ctl = PairPursuit(problem_of(plan), nodes, PursuitSettings(max_pull=pull))
    times = []
    for q in nodes:
        t0 = time.perf_counter()
        ctl.decide(q + 0.02)
        times.append(time.perf_counter() - t0)
    spread = _spread(times, "ms", 1e3, 3)
    return {"median_ms": spread["median_ms"], "p95_ms": spread["p95_ms"]}


def bench_runs(names, noise):
    out = {}
    for name in names:
        file = PROBLEMS[name][0]
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [sys.executable, "-m", "rigctl", "execute", str(EXAMPLES / file), "--json",
                   "--quiet", "--runs", tmp]
            if noise:
                cmd += ["--noise", str(noise), "--seed", "3"]
            result = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp)
        try:
            s = json.loads(result.stdout.strip().splitlines()[-1])
        except (IndexError, json.JSONDecodeError):
            out[name] = {"error": (result.stderr or result.stdout)[-500:]}
            continue
        plan = json.loads((EXAMPLES / file).read_text())
        metrics, tracking = s.get("metrics") or {}, s.get("tracking") or {}
        out[name] = {k: s.get(k) for k in ("reached", "replans", "duration_s")}
        out[name].update({k: metrics.get(k) for k in (
            "rms_tracking_error_bl", "max_tracking_error_bl", "hold_max_error_bl",
            "min_separation_bl", "truth_min_separation_bl")})
        out[name].update({k: tracking.get(k) for k in ("frames", "lost_frames")})
        out[name]["r_min_bl"] = plan["r_min_bl"]
        out[name]["faults"] = [f["reason"] for f in s.get("faults", [])]
        out[name]["stream_late_share"] = (s.get("stream") or {}).get("late_share")
    return out


def bench_mobility(slip: float, seeds: int) -> dict:
    """The formation change with agents `slip` times as mobile as planned, with and without the
    pull gain identified (module docstring)."""
    from dataclasses import replace

    from rigctl.core.config import load_rig
    from rigctl.emulators.process import EmulatedBenchProcess
    from rigctl.plans.schema import load_plan
    from rigctl.rigs.six_coil.pair import PairRun, PairRunSettings, loopback_rig

    plan = load_plan(EXAMPLES / PROBLEMS["formation_change"][0])
    runs: dict[str, list] = {"identified": [], "not_identified": []}
    for seed in range(seeds):
        for name, identify in (("identified", True), ("not_identified", False)):
            with tempfile.TemporaryDirectory() as tmp, EmulatedBenchProcess(
                    "six-coil", Path(tmp) / "bench.toml",
                    extra_args=["--world", "pair", "--slip", str(slip), "--coil-error", "0",
                                "--seed", str(seed)]) as rig_path:
                settings = replace(PairRunSettings(), identify_pull=identify)
                run = PairRun(plan, loopback_rig(load_rig(rig_path)), settings=settings,
                              runs_dir=Path(tmp) / "runs", progress_out=None)
                s = run.execute()
            m = s.metrics
            row = {"seed": seed, "reached": s.reached, "duration_s": round(s.duration_s, 2),
                   "rms_tracking_error_bl": m.get("rms_tracking_error_bl"),
                   "hold_max_error_bl": m.get("hold_max_error_bl"),
                   "faults": [f["reason"] for f in s.faults]}
            if identify:
                row["pull_identified"] = m.get("pull_identified")
            runs[name].append(row)

    def median(name: str, key: str):
        values = [r[key] for r in runs[name] if r[key] is not None]
        return round(statistics.median(values), 4) if values else None

    return {"slip": slip, "true_pull_gain": slip, "seeds": seeds,
            **{f"{name}_{key}_median": median(name, key) for name in runs
               for key in ("rms_tracking_error_bl", "duration_s")},
            **{f"{name}_reached": sum(r["reached"] for r in runs[name]) for name in runs},
            "runs": runs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per solve figure "
                        "(default 10, --quick 3)")
    parser.add_argument("--budget", type=float, default=10.0, metavar="S",
                        help="time limit per solve (default 10 s: the goal is 95 %% within it)")
    parser.add_argument("--replans", type=int, default=30)
    parser.add_argument("--noise", type=float, default=0.0, metavar="MM")
    parser.add_argument("--slip", type=float, default=0.6, metavar="F",
                        help="the mobility figure's agents move F times as fast as planned")
    parser.add_argument("--mobility-seeds", type=int, default=None, metavar="N",
                        help="runs each way of the mobility figure (default 3, --quick 1)")
    args = parser.parse_args()
    names = ["formation_change"] if args.quick else list(PROBLEMS)
    seeds = args.seeds or (3 if args.quick else 10)
    variants = ["fast"] if args.quick else ["fast", "paper"]
    t0 = time.perf_counter()
    result = {
        "solve": bench_solve(list(PROBLEMS), seeds, variants, args.budget),
        "replan": bench_replan(args.replans),
        "decide": bench_decide(),
        "runs": bench_runs(names, args.noise),
        "mobility": bench_mobility(args.slip, args.mobility_seeds or (1 if args.quick else 3)),
    }
    result["bench_seconds"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
