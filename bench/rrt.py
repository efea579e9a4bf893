"""Benchmark of the global-input RRT (plans/rrt.py); prints ONE JSON object on stdout.

Environment 1 of seed 000 in mm: 400 x 400 with 50 mm border walls and the L of rects
[175, 150, 100, 25] and [150, 150, 25, 100]; robots of radius 5 mm from (60, 300), (60, 250) to
(330, 300), (330, 200); robostep 5 mm, k = 16; slide contact (the paper's model).

Figures:
- growth: nodes per second of the paper's algorithm (no goal test: tolerance 0) while one tree
  grows to 40,000, 200,000 and 400,000 nodes; `average` = N / time to grow N nodes (what the
  paper's 26,000 / 11,000 nodes/s compare with), `segment` = the rate between two sizes.
  Reported for the exact nearest node and for --nn-eps (default 0.1). Default batches: up to
  4,096 samples per model call (tree / 8 early on).
- solve: the study `studies/rrt-solve.toml` (`rigctl plan rrt` per seed, run serially here so
  that the time budgets do not compete): over --seeds seeds, the share solved within 2 mm and the
  median seconds to solve, with the tuned options (goal bias 0.05, formation bias 0.1, greedy
  descent, final approach), 5 s budget each. As `rigctl plan rrt` plans for a six-coil rig, every
  move is a whole number of 5 mm magnet turns (`studies/five-mm-turns.toml`; the final approach
  makes the fitted translation of whole turns that add up to it, `RrtOptions.turn_legs`), and
  the seconds include the replay on the exact geometry that writes the plan.
- four_robots: seconds to grow a 340,000-node tree for four robots (seed 000 Sec. IV).
- image_maps: time per clearance query and per model move (1 mm, robots in a free square) on two
  800 x 800 px image maps with few and with many obstacle pixels, best of five (the grid
  backend's cost must not depend on the obstacle pixels).
Planning uses the exact geometry (the model is as fast there as on a 0.5 mm raster, and more
precise); the raster's construction time is reported for reference.
- peer (with --peer CHECKOUT): seed 000's published C++/OMPL planner (bench/peers/README.md),
  built with -O2 from a checkout with bench/peers/swarm-robots-ompl.patch, and ours grow a
  40,000-node tree each (no goal test, same start and goal, 5 mm moves, k = 16), interleaved
  over --peer-rounds rounds (peer then ours, seeds 1, 2, ...); nodes/s of each (N / the
  planner's own timing of its growth) and the ratio of the medians, and the same per CPU second
  (the peer's whole run, user + system; ours the growth), which a shared machine's load moves
  less. Without --peer, or without
  g++ and libompl-dev, `peer` says why it was skipped. The peer's robots are points (it ignores
  the radius) and each of its moves stops short of an obstacle by whole millimetres: it is the
  same workspace and moves, not the same model.
- geometry_kernel: the exact-geometry kernels are compiled with numba and cached on disk;
  `compile_s` is what compiling them costs (in a child process with an empty cache),
  `warm_up_s` what loading them cost this run. Both happen before any timing above starts.

Usage: python bench/rrt.py [--quick | --smoke] [--seeds N] [--sizes 40000,200000,400000] [--four N]
       [--peer CHECKOUT [--peer-rounds 5]]
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

from rigctl.plans.model import GlobalInputModel
from rigctl.plans.rrt import RrtOptions, plan_rrt
from rigctl.plans.workspace import ShapeWorkspace, Workspace, warm_up

RADIUS_MM = 5.0
ROBOSTEP_MM = 5.0
START = np.array([[60.0, 300.0], [60.0, 250.0]])
GOAL = np.array([[330.0, 300.0], [330.0, 200.0]])
FOUR_START = np.array([[60.0, 300.0], [60.0, 250.0], [60.0, 200.0], [60.0, 100.0]])
FOUR_GOAL = np.array([[330.0, 300.0], [330.0, 200.0], [300.0, 100.0], [200.0, 300.0]])


def environment_1() -> ShapeWorkspace:
    walls = [(0, 0, 400, 50), (0, 350, 400, 50), (0, 0, 50, 400), (350, 0, 50, 400)]
    ell = [(175, 150, 100, 25), (150, 150, 25, 100)]
    return ShapeWorkspace(("rect", (0, 0, 400, 400)), [("rect", r) for r in walls + ell])


def growth(model: GlobalInputModel, sizes: list[int], nn_eps: float, seed: int) -> dict:
    """Grow one tree through the sizes (no goal test) and time each stretch."""
    rng = np.random.default_rng(seed)
    tree = None
    elapsed = 0.0
    previous = 1
    rates = {}
    for size in sizes:
        options = RrtOptions(robostep_mm=ROBOSTEP_MM, k=16, max_nodes=size, tolerance_mm=0.0,
                             stop_when_solved=False, nn_eps=nn_eps)
        result = plan_rrt(model, START, GOAL, options=options, rng=rng, tree=tree)
        tree = result.tree
        elapsed += result.seconds
        rates[str(size)] = {
            "seconds": round(elapsed, 3),
            "average_nodes_per_s": round(size / elapsed),
            "segment_nodes_per_s": round((size - previous) / result.seconds),
        }
        previous = size
    first, last = str(sizes[0]), str(sizes[-1])
    rates["fall_first_to_last"] = round(
        rates[first]["average_nodes_per_s"] / rates[last]["average_nodes_per_s"], 2
    )
    return rates


def solve_rate(seeds: int, budget_s: float) -> dict:
    """The rrt-solve study over `seeds` seeds with `budget_s` per seed, serially in this process."""
    import tomllib

    import pyarrow.parquet as pq

    from rigctl.apps.study.execution import run_study
    from rigctl.apps.study.spec import spec_from_dict

    studies = Path(__file__).resolve().parents[1] / "studies"
    data = tomllib.loads((studies / "rrt-solve.toml").read_text())
    data["run"]["args"]["time"] = budget_s
    data["seeds"] = {"count": seeds}
    spec = spec_from_dict(data, studies)
    with tempfile.TemporaryDirectory(prefix="bench-rrt-solve-") as out:
        run_study(spec, out, serial=True, progress_out=None)
        rows = sorted(pq.read_table(Path(out) / "results.parquet").to_pylist(), key=lambda r: r["seed"])
    times, solved, runs = [], 0, []
    for r in rows:
        runs.append({"seed": r["seed"], "solved": bool(r["fig_solved"]),
                     "seconds": round(r["fig_seconds"], 3), "nodes": r["fig_nodes"],
                     "distance": round(r["fig_distance"], 3), "moves": r["fig_moves"]})
        if r["fig_solved"]:
            solved += 1
            times.append(r["fig_seconds"])
    return {
        "tolerance_mm": 2.0,
        "budget_s": budget_s,
        "solved": solved,
        "seeds": seeds,
        "share_solved": solved / seeds,
        "median_seconds_when_solved": round(statistics.median(times), 3) if times else None,
        "max_seconds_when_solved": round(max(times), 3) if times else None,
        "runs": runs,
    }


def four_robots(workspace: Workspace, nodes: int, nn_eps: float) -> dict:
    model = GlobalInputModel(workspace, [RADIUS_MM] * 4)
    options = RrtOptions(robostep_mm=ROBOSTEP_MM, k=16, max_nodes=nodes, tolerance_mm=0.0,
                         stop_when_solved=False, nn_eps=nn_eps)
    result = plan_rrt(model, FOUR_START, FOUR_GOAL, options=options, rng=np.random.default_rng(0))
    return {"nodes": result.nodes, "nn_eps": nn_eps, "seconds": round(result.seconds, 2),
            "nodes_per_s": round(result.nodes / result.seconds)}


def image_maps(queries: int) -> dict:
    """Clearance queries and model moves on a map with few and one with many obstacle pixels."""
    rng = np.random.default_rng(0)
    size = 800
    few = np.ones((size, size), dtype=bool)
    few[:8], few[-8:], few[:, :8], few[:, -8:] = False, False, False, False
    many = few.copy()
    # a dense field of 2-px specks away from a central free square where the robots are put
    specks = rng.random((size // 4, size // 4)) < 0.5
    many &= ~np.kron(specks, np.ones((4, 4), dtype=bool))
    many[300:500, 300:500] = True
    result = {}
    for name, mask in [("few", few), ("many", many)]:
        workspace = Workspace.from_mask(mask, mm_per_px=0.5)
        points = rng.uniform(150.0, 250.0, size=(queries, 2))  # the free square, in mm
        workspace.clearance(points[:1000])
        query_s = math.inf
        for _ in range(5):  # best of five: the machine is shared
            started = time.perf_counter()
            workspace.clearance(points)
            query_s = min(query_s, time.perf_counter() - started)
        model = GlobalInputModel(workspace, [2.0, 2.0])
        configs = rng.uniform(160.0, 240.0, size=(8192, 2, 2))
        configs[:, 1] = configs[:, 0] + [6.0, 0.0]
        moves = rng.normal(size=(8192, 2))
        moves *= 1.0 / np.linalg.norm(moves, axis=1, keepdims=True)
        apply_s = math.inf
        for _ in range(5):
            started = time.perf_counter()
            model.apply(configs, moves)
            apply_s = min(apply_s, time.perf_counter() - started)
        result[name] = {
            "obstacle_pixels": int((~mask).sum()),
            "clearance_ns_per_point": round(query_s / queries * 1e9, 1),
            "apply_us_per_config": round(apply_s / len(configs) * 1e6, 2),
        }
    return result


PEER_PATCH = Path(__file__).resolve().parent / "peers" / "swarm-robots-ompl.patch"
PEER_NODES = 40_000


def build_peer(checkout: Path, into: Path) -> Path:
    """Build seed 000's planner from `checkout` (its repository, holding Swarmrobots_ompl.zip, or
    the unzipped folder) in `into` with the patch applied; returns the program's path.
    Raises RuntimeError with the reason when it cannot be built."""
    if not (shutil.which("g++") and shutil.which("patch") and shutil.which("pkg-config")):
        raise RuntimeError("needs g++, patch and pkg-config")
    archive = checkout / "Swarmrobots_ompl.zip"
    unpacked = into / "unpacked"
    if archive.is_file():
        with zipfile.ZipFile(archive) as source:
            source.extractall(unpacked)
        root = unpacked
    elif checkout.is_dir():
        root = checkout
    else:
        raise RuntimeError(f"{checkout} is not a checkout of pjparthjoshi/Swarm-Robots-OMPL")
    sources = sorted(root.glob("**/3 robots/src"))
    if not sources:
        raise RuntimeError(f"{checkout} has no '3 robots/src' folder")
    work = into / "peer"
    (work / "src").mkdir(parents=True)
    for path in sources[0].iterdir():  # the program's sources only (the zip also holds .o files)
        if path.suffix in (".cpp", ".h"):
            shutil.copy2(path, work / "src" / path.name)
    patched = subprocess.run(["patch", "-p1", "--quiet", "-i", str(PEER_PATCH)], cwd=work,
                             capture_output=True, text=True)
    if patched.returncode:
        raise RuntimeError(f"the patch does not apply: {patched.stdout.strip()}")
    flags = subprocess.run(["pkg-config", "--cflags", "ompl"], capture_output=True, text=True)
    if flags.returncode:
        raise RuntimeError("OMPL not found (apt-get install libompl-dev)")
    program = work / "peer"
    command = ["g++", "-O2", *flags.stdout.split(), *map(str, sorted((work / "src").glob("*.cpp"))),
               "-o", str(program), "-lompl"]
    built = subprocess.run(command, capture_output=True, text=True)
    if built.returncode:
        raise RuntimeError("the build failed: " + built.stderr.strip().splitlines()[-1])
    return program


def run_peer(program: Path, seed: int, nodes: int) -> tuple[float, float]:
    """Nodes per second of one peer run growing a `nodes`-node tree (no goal test): by its own
    wall-clock timing of the growth, and by the CPU seconds (user + system) of the whole run."""
    env = dict(os.environ, PEER_SEED=str(seed), PEER_MAX_NODES=str(nodes), PEER_TOLERANCE="0",
               PEER_SECONDS="3600")
    used = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryDirectory(prefix="bench-rrt-peer-") as cwd:  # it writes its tree there
        out = subprocess.run([str(program)], input="1\n1\n2\n", env=env, cwd=cwd, check=True,
                             capture_output=True, text=True).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (after.ru_utime - used.ru_utime) + (after.ru_stime - used.ru_stime)
    for line in out.splitlines():
        if line.startswith("PEER nodes"):
            _, _, grown, _, seconds = line.split()
            return int(grown) / float(seconds), int(grown) / cpu_s
    raise RuntimeError("the peer printed no 'PEER nodes' line")


def peer_comparison(checkout: str | None, model: GlobalInputModel, rounds: int) -> dict:
    """Peer and ours interleaved, `rounds` times each, at PEER_NODES nodes."""
    if checkout is None:
        return {"skipped": "no --peer CHECKOUT given (bench/peers/README.md)"}
    with tempfile.TemporaryDirectory(prefix="bench-rrt-build-") as scratch:
        try:
            program = build_peer(Path(checkout), Path(scratch))
        except RuntimeError as err:
            return {"skipped": str(err)}
        peer, ours, peer_cpu, ours_cpu = [], [], [], []
        for seed in range(1, rounds + 1):
            wall, cpu = run_peer(program, seed, PEER_NODES)
            peer.append(wall)
            peer_cpu.append(cpu)
            options = RrtOptions(robostep_mm=ROBOSTEP_MM, k=16, max_nodes=PEER_NODES,
                                 tolerance_mm=0.0, stop_when_solved=False)
            cpu_started = time.process_time()
            result = plan_rrt(model, START, GOAL, options=options, rng=np.random.default_rng(seed))
            ours_cpu.append(result.nodes / (time.process_time() - cpu_started))
            ours.append(result.nodes / result.seconds)
    return {
        "nodes": PEER_NODES,
        "rounds": rounds,
        "peer_nodes_per_s": [round(v) for v in peer],
        "ours_nodes_per_s": [round(v) for v in ours],
        "ratio_of_medians": round(statistics.median(ours) / statistics.median(peer), 2),
        # per CPU second: on a loaded machine the wall-clock figures swing with the load
        "peer_nodes_per_cpu_s": [round(v) for v in peer_cpu],
        "ours_nodes_per_cpu_s": [round(v) for v in ours_cpu],
        "cpu_ratio_of_medians": round(statistics.median(ours_cpu) / statistics.median(peer_cpu), 2),
    }


def compile_seconds() -> float:
    """Seconds to compile the geometry kernels from scratch (a child process, empty numba cache)."""
    code = "from rigctl.plans.workspace import warm_up; print(warm_up())"
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        out = subprocess.run([sys.executable, "-c", code], env=env, check=True,
                             capture_output=True, text=True)
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke run in ~20 s")
    parser.add_argument("--seeds", type=int, help="seeds for the solve rate (default 20)")
    parser.add_argument("--sizes", help="comma-separated tree sizes (default 40000,200000,400000)")
    parser.add_argument("--four", type=int, help="four-robot tree size (default 340000)")
    parser.add_argument("--nn-eps", type=float, default=0.1, help="approximate nearest node run")
    parser.add_argument("--budget", type=float, default=5.0, help="seconds per solve attempt")
    parser.add_argument("--peer", metavar="CHECKOUT",
                        help="a checkout of pjparthjoshi/Swarm-Robots-OMPL: build and run it")
    parser.add_argument("--peer-rounds", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument("--smoke", action="store_true",
                        help="the smallest run of every stage, for the test suite: its figures "
                             "mean nothing")
    args = parser.parse_args()
    if args.smoke:  # two tiny trees, one seed with a short budget, 1,000 map queries
        args.sizes, args.seeds, args.four, args.budget = "2000,4000", 1, 2_000, 0.5
    logging.basicConfig(level=logging.WARNING)
    sizes = [int(v) for v in (args.sizes or ("40000,80000" if args.quick else
                                             "40000,200000,400000")).split(",")]
    seeds = args.seeds if args.seeds is not None else (3 if args.quick else 20)
    four = args.four if args.four is not None else (20_000 if args.quick else 340_000)

    started = time.perf_counter()
    kernel = {"compile_s": round(compile_seconds(), 2), "warm_up_s": round(warm_up(), 3)}
    exact = environment_1()
    raster_started = time.perf_counter()
    raster = exact.rasterize(0.5)
    raster_s = time.perf_counter() - raster_started
    del raster
    model = GlobalInputModel(exact, [RADIUS_MM, RADIUS_MM])
    report = {
        "benchmark": "rrt",
        "python": platform.python_version(),
        "machine": platform.machine(),
        "environment": "seed 000 environment 1, radius 5 mm, robostep 5 mm, k 16, slide",
        "geometry_kernel": kernel,
        "raster_0_5mm_build_s": round(raster_s, 3),
        "growth_exact_nn": growth(model, sizes, 0.0, seed=1),
        f"growth_nn_eps_{args.nn_eps:g}": growth(model, sizes, args.nn_eps, seed=1),
        "paper_cpp_ompl_nodes_per_s": {"40000": 26000, "200000": 11000},
        "peer": peer_comparison(args.peer, model, 1 if args.smoke else args.peer_rounds),
        "solve": solve_rate(seeds, args.budget),
        "four_robots": four_robots(exact, four, args.nn_eps),
        "image_maps": image_maps(1_000 if args.smoke else 200_000 if args.quick else 1_000_000),
    }
    report["total_seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
