"""`rigctl plan ...`: the planners on the command line.

`rigctl plan rrt` grows the global-input RRT (seed 000) from the robots' starts toward their goals
and writes a `global-moves` plan whose `expected` states come from the exact workspace model;
`rigctl plan coverage` measures how much of the configuration-space grid a saved tree covers;
`rigctl plan wall-contact` places two particles on a coil board with seed 004's planner and
`rigctl plan reachable` measures how much of its Delta configuration space M moves reach.

With --raster MM the RRT plans on a raster of the workspace (a clearance query then costs the same
whatever the shapes are) and replays the moves on the exact geometry afterwards; if the replay ends
outside the tolerance, a short final approach on the exact geometry closes the gap. By default it
plans on the exact geometry, which the model currently handles as fast and more precisely.

Exit status: 0 solved within tolerance, 1 not solved (the plan with the best path found is still
written, and says so in its name), 2 bad input (the message names the argument).
`register(subparsers)` adds the `plan` command to the top-level parser; `main()` runs it alone.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rigctl.apps.cli.paths import coordinates_are_values, input_file, output_file
from rigctl.core.config import load_rig
from rigctl.core.errors import EXIT_NOT_REACHED, EXIT_OK, ConfigError, PlanError
from rigctl.core.registry import default_kind, entry_point_names, kinds, rig_kind

if TYPE_CHECKING:  # numba compiles nothing for the commands that do not plan
    from rigctl.plans.checks import WorkspaceSource

log = logging.getLogger(__name__)

DEFAULT_ROBOSTEP_MM = 5.0
DEFAULT_RADIUS_MM = 5.0
DEFAULT_RASTER_MM = 0.0
DEFAULT_PARTICLE_RADIUS_MM = 0.5
DEFAULT_EPSILON_MM = 0.01


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `plan rrt`, `plan coverage`, `plan wall-contact` and `plan reachable` to the top-level
    subparsers; each sets func(args)->int."""
    plan = subparsers.add_parser(
        "plan", help="write plans with a planner (rrt) or measure a tree (coverage)",
        description="Planners that write plans, and tools to inspect what they built.",
    )
    planners = plan.add_subparsers(dest="planner", required=True, metavar="PLANNER")

    p = planners.add_parser(
        "rrt", help="global-input RRT (seed 000): one move for all robots, walls break symmetry",
        description="Grow a global-input RRT from the starts toward the goals and write a "
        "global-moves plan. Defaults follow the paper (uniform samples, nearest node, k directions "
        "of length robostep); --goal-bias, --formation-bias, --greedy and --final-approach (or "
        "--tuned for all four) make it solve much faster. Exit 0 solved, 1 not solved (plan "
        "still written), 2 bad input.",
    )
    _add_problem_arguments(p, "(shapes or an image)", "a robot's", "once per robot")
    p.add_argument("--radius", action="append", type=float, metavar="R",
                   help=f"robot radius in mm: once for all robots or once per robot "
                   f"(default {DEFAULT_RADIUS_MM:g})")
    p.add_argument("--robostep", type=float, metavar="S",
                   help=f"length of each tree move in mm (default {DEFAULT_ROBOSTEP_MM:g}; "
                   "one magnet turn on a six-coil rig)")
    p.add_argument("--k", type=int, metavar="K", help="number of candidate directions (default 16)")
    p.add_argument("--axis-only", action="store_true", default=None,
                   help="only move along +-x and +-y (the paper's hardware run)")
    p.add_argument("--max-nodes", type=int, default=40_000, metavar="N",
                   help="stop when the tree has this many nodes (default 40000)")
    p.add_argument("--time", type=float, metavar="T", help="stop after T seconds")
    p.add_argument("--tolerance", type=float, default=1.0, metavar="E",
                   help="solved when the distance to the goal in R^2n is at most E mm (default 1)")
    p.add_argument("--goal-bias", type=float, default=None, metavar="P",
                   help="probability that a sample is the goal (default 0)")
    p.add_argument("--formation-bias", type=float, default=None, metavar="P",
                   help="probability that a sample is the goal formation moved to a random free "
                   "place (default 0)")
    p.add_argument("--greedy", action="store_true",
                   help="from every new best node, step toward the goal while that helps")
    p.add_argument("--final-approach", action="store_true",
                   help="in that descent also try shorter moves and the best-fitting translation")
    p.add_argument("--tuned", action="store_true",
                   help="shorthand for --goal-bias 0.05 --formation-bias 0.1 --greedy "
                   "--final-approach")
    p.add_argument("--nn-eps", type=float, default=0.0, metavar="EPS",
                   help="accept a node up to (1 + EPS) times farther than the nearest (default 0: "
                   "exact; 0.1 is several times faster on large trees)")
    p.add_argument("--min-separation", type=float, default=0.0, metavar="D",
                   help="keep robot centres at least r1 + r2 + D mm apart")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="random seed (default 0)")
    # the installed kinds; one the planner has no wall contact for is refused by name
    # (`RigKind.wall_contact`, asked by rigctl.plans.checks when the plan is checked)
    p.add_argument("--rig", choices=entry_point_names(), default=default_kind(),
                   help="rig kind: six-coil (robots slide along walls, moves are whole magnet "
                   "turns) or coil-board (robots stick to walls)")
    p.add_argument("--rig-file", metavar="RIG.toml", type=input_file("rig file"),
                   help="rig file whose magnets.radius_mm sets the turn length (default 10 mm)")
    p.add_argument("--raster", type=float, default=DEFAULT_RASTER_MM, metavar="MM",
                   help="plan on a raster of this pitch in mm (default 0: the exact geometry); the "
                   "written plan is always replayed on the exact geometry")
    p.add_argument("--save-tree", metavar="FILE", type=output_file("tree"),
                   help="write the tree (.npz) for later reuse")
    p.add_argument("--tree", metavar="FILE", type=input_file("tree", text=False),
                   help="reuse a saved tree: answer the goal from it, grow it if not solved")
    p.add_argument("-o", "--output", required=True, metavar="PLAN.json", type=output_file("plan"),
                   help="plan file to write")
    p.add_argument("--json", action="store_true", help="end the output with one JSON line")
    p.set_defaults(func=run_rrt)

    p = planners.add_parser(
        "coverage", help="fraction of configuration-space grid cells a saved tree reaches",
        description="Cut the configuration space (the free-space bounding box, once per robot) "
        "into hypercubes of edge G mm and report the fraction that hold a tree node (seed 000 "
        "Sec. II-d).",
    )
    p.add_argument("--workspace", required=True, metavar="WS.json", type=input_file("workspace"),
                   help="the workspace the tree was grown in")
    p.add_argument("--tree", required=True, metavar="FILE", type=input_file("tree", text=False),
                   help="tree saved by `plan rrt --save-tree`")
    p.add_argument("--grid", required=True, type=float, metavar="G", help="hypercube edge in mm")
    p.add_argument("--json", action="store_true", help="end the output with one JSON line")
    p.set_defaults(func=run_coverage)

    p = planners.add_parser(
        "wall-contact",
        help="two particles, one shared input, non-slip walls (seed 004 Alg. 1-3)",
        description="Place two particles with the same pulling input by pinning one against a "
        "non-slip wall while the other moves (seed 004). The workspace boundary must be a convex "
        "polygon, a rect or a disk, without obstacles. Writes a coil-board global-moves plan whose "
        "expected states come from the non-slip model. Exit 0 solved, 1 not solved (plan still "
        "written), 2 bad input.",
    )
    _add_problem_arguments(p, "with a convex boundary", "a particle's", "twice")
    p.add_argument("--radius", type=float, default=DEFAULT_PARTICLE_RADIUS_MM, metavar="R",
                   help=f"particle radius in mm (default {DEFAULT_PARTICLE_RADIUS_MM:g}: the paper's "
                   "1 mm spheres)")
    p.add_argument("--epsilon", type=float, default=DEFAULT_EPSILON_MM, metavar="E",
                   help=f"both particles must end within E mm of their goals (default "
                   f"{DEFAULT_EPSILON_MM:g})")
    p.add_argument("--interchangeable", action="store_true",
                   help="the particles are alike: also try the swapped goals, keep the shorter path")
    p.add_argument("--height", type=float, metavar="H",
                   help="3D (Sec. IV-G): a right prism / cylinder of height H mm over the boundary; "
                   "--start/--goal then are X,Y,Z; writes a rigctl.plan3d/1 document (no 3D rig runs it)")
    p.add_argument("-o", "--output", required=True, metavar="PLAN.json", type=output_file("plan"),
                   help="plan file to write")
    p.add_argument("--json", action="store_true",
                   help='end the output with {"solved", "moves", "length", "seconds"}')
    p.set_defaults(func=run_wall_contact)

    p = planners.add_parser(
        "reachable",
        help="fraction of the Delta configuration space reachable in M moves (seed 004 Fig. 8-9)",
        description="Point particles a distance D apart (D in units of the workspace diameter, "
        "as in the paper): the share of all relative positions reachable within M moves (even), "
        "on a grid of the Delta configuration space (the paper's numeric method likewise "
        "underestimates). Exit 0, 2 bad input.",
    )
    shape = p.add_mutually_exclusive_group(required=True)
    shape.add_argument("--disk", action="store_true", help="a disk workspace")
    shape.add_argument("--polygon", metavar="X,Y;X,Y;...",
                       help="a convex polygon workspace given by its vertices")
    shape.add_argument("--workspace", metavar="WS.json", type=input_file("workspace"),
                       help="a workspace document (convex)")
    p.add_argument("--d12", type=float, required=True, metavar="D",
                   help="initial particle distance in units of the workspace diameter")
    p.add_argument("--angle", type=float, default=0.0, metavar="DEG",
                   help="direction of p2 - p1 in degrees (default 0; a disk does not care)")
    p.add_argument("--moves", type=int, required=True, metavar="M", help="number of moves (even)")
    p.add_argument("--cells", type=int, default=121, metavar="N",
                   help="grid points per axis of the Delta space (default 121)")
    p.add_argument("--json", action="store_true", help='end the output with {"fraction": f}')
    p.set_defaults(func=run_reachable)

    # plan depm: the dual-EPM hybrid planner (seed 003); the command lives in rigctl.plans.depm.
    p = planners.add_parser(
        "depm", help="dual-EPM field/gradient sequence: hybrid planner (seed 003) or baseline",
        description="Plan the two arms' joint trajectories that produce a sequence of field and "
        "gradient 8-vectors U at the workspace centre (hybrid planner of seed 003), or the "
        "magnetic-agnostic baseline. Every trajectory is checked against the safety constraints. "
        "Exit 0 planned, 1 planned but refused by the safety check (plan still written), 2 bad "
        "input.",
    )
    p.add_argument("--sequence", required=True, metavar="FILE", type=input_file("sequence"),
                   help='JSON list of {"name", "U": [Bx, By, Bz mT, 5 gradient terms mT/m], '
                   '"hold_s"}')
    p.add_argument("--waypoints", type=int, default=20, metavar="N",
                   help="waypoints per transition (default 20)")
    p.add_argument("--k", type=int, default=4, metavar="K",
                   help="radial path alternatives per waypoint (default 4)")
    p.add_argument("--agnostic", action="store_true",
                   help="the baseline: straight joint-space moves to the same end poses")
    p.add_argument("--rig", metavar="RIG.toml", type=input_file("rig file"),
                   help="plan for this depm rig file's arm bases, magnets and limits (default: "
                   "the emulated rig's, docs/depm.md)")
    p.add_argument("-o", "--output", required=True, metavar="PLAN.json", type=output_file("plan"),
                   help="plan file to write")
    p.add_argument("--json", action="store_true", help="end the output with one JSON line")
    p.set_defaults(func=_run_depm)

    from rigctl.plans.pair import (
        add_cli as add_pair_planner,  # seed 002's two-agent planner
    )

    add_pair_planner(planners)
    paths = {"workspace": input_file("workspace"), "rig": input_file("rig file"),
             "output": output_file("plan")}
    for action in planners.choices["pair"]._actions:  # its parser lives with the pair planner
        action.type = paths.get(action.dest, action.type)
    for planner in planners.choices.values():  # --start -8,-6 is a point, not an option
        coordinates_are_values(planner)


def _add_problem_arguments(p: argparse.ArgumentParser, workspace: str, whose: str,
                           count: str) -> None:
    """--workspace, --start and --goal, shared by the planners that place agents."""
    p.add_argument("--workspace", required=True, metavar="WS.json", type=input_file("workspace"),
                   help=f"workspace document {workspace}, or a plan whose workspace to use")
    p.add_argument("--start", action="append", required=True, metavar="X,Y",
                   help=f"{whose} start in mm; {count}")
    p.add_argument("--goal", action="append", required=True, metavar="X,Y",
                   help=f"{whose} goal in mm; {count}, same order as --start")


def _run_depm(args: argparse.Namespace) -> int:
    """`rigctl plan depm` (imported on use: the planner pulls in scipy's optimisers)."""
    from rigctl.plans.depm import cli

    return cli(args)


# ---------------------------------------------------------------- workspace documents


# ---------------------------------------------------------------- plan rrt


def points_mm(values: list[str], flag: str, axes: str = "X,Y") -> np.ndarray:
    """Points given as "X,Y" (or `axes`) in mm, (n, len(axes)); PlanError naming `flag` and the
    point's number."""
    points = []
    for number, text in enumerate(values, start=1):
        try:
            point = [float(v) for v in text.replace(" ", "").split(",")]
        except ValueError:
            point = []
        if len(point) != axes.count(",") + 1:
            raise PlanError(f"{flag} #{number}: expected {axes} in mm, got {text!r}")
        if not all(math.isfinite(v) for v in point):
            raise PlanError(f"{flag} #{number}: coordinates must be finite, got {text!r}")
        points.append(point)
    return np.array(points, dtype=float)


def _radii(values: list[float] | None, n: int) -> np.ndarray:
    values = values or [DEFAULT_RADIUS_MM]
    if len(values) == 1:
        values = values * n
    if len(values) != n:
        raise PlanError(f"--radius: give one radius or one per robot ({n}), got {len(values)}")
    radii = np.array(values, dtype=float)
    if np.any(~(radii > 0)):
        raise PlanError(f"--radius: radii must be > 0 mm, got {values}")
    return radii


def _check_configuration(ws, points: np.ndarray, radii: np.ndarray, gap: float, flag: str) -> None:
    """Every robot in free space, no two closer than r_i + r_j + gap (PlanError naming the flag)."""
    from rigctl.plans.checks import check_placement

    check_placement(ws, points, radii, gap, lambda i: f"{flag} #{i + 1}", lambda i: f"#{i + 1}")


def _turn_mm(args: argparse.Namespace) -> float | None:
    """One whole roll of the kind's agents (its `RigKind.turn_mm`), None for moves of any length."""
    turn = rig_kind(args.rig).turn_mm
    if turn is None:
        return None
    rig = None
    if args.rig_file:
        try:
            rig = load_rig(args.rig_file)
        except ConfigError as err:
            raise PlanError(f"--rig-file: {err}") from None
    return turn(rig)


def _options(args: argparse.Namespace, tree_meta: dict | None):
    """RrtOptions from the arguments; move-set settings a reused tree fixes come from the tree."""
    from rigctl.plans.rrt import RrtOptions

    turn = _turn_mm(args)
    stored = tree_meta or {}
    robostep = args.robostep
    if robostep is None:
        robostep = stored.get("robostep_mm", turn if turn is not None else DEFAULT_ROBOSTEP_MM)
    k = args.k if args.k is not None else stored.get("k", 16)
    axis_only = stored.get("axis_only", False) if args.axis_only is None else bool(args.axis_only)
    goal_bias = args.goal_bias if args.goal_bias is not None else (0.05 if args.tuned else 0.0)
    formation_bias = args.formation_bias
    if formation_bias is None:
        formation_bias = 0.1 if args.tuned else 0.0
    if not robostep > 0:
        raise PlanError(f"--robostep: must be > 0 mm, got {robostep:g}")
    if turn is not None:
        turns = robostep / turn
        if abs(turns - round(turns)) > 1e-6 or round(turns) < 1:
            raise PlanError(
                f"--robostep {robostep:g}: on a six-coil rig every move is a whole number of "
                f"magnet turns ({turn:g} mm each); use a multiple of it or --rig coil-board"
            )
        robostep = round(turns) * turn
    for flag, value, ok in [
        ("--k", k, k >= 1),
        ("--max-nodes", args.max_nodes, args.max_nodes >= 1),
        ("--tolerance", args.tolerance, args.tolerance >= 0),
        ("--goal-bias", goal_bias, 0.0 <= goal_bias <= 1.0),
        ("--formation-bias", formation_bias, 0.0 <= formation_bias <= 1.0 - goal_bias),
        ("--min-separation", args.min_separation, args.min_separation >= 0),
        ("--nn-eps", args.nn_eps, args.nn_eps >= 0),
        ("--raster", args.raster, args.raster >= 0),
    ]:
        if not ok:
            raise PlanError(f"{flag}: value {value:g} is out of range")
    if args.time is not None and not args.time > 0:
        raise PlanError(f"--time: must be > 0 s, got {args.time:g}")
    return RrtOptions(
        robostep_mm=robostep,
        k=k,
        axis_only=axis_only,
        turn_mm=turn,
        max_nodes=args.max_nodes,
        tolerance_mm=args.tolerance,
        goal_bias=goal_bias,
        formation_bias=formation_bias,
        greedy=args.greedy or args.tuned,
        final_approach=args.final_approach or args.tuned,
        nn_eps=args.nn_eps,
    )


def run_rrt(args: argparse.Namespace) -> int:
    """`rigctl plan rrt`: plan, write the plan, report. Returns the exit status."""
    from rigctl.plans.checks import WorkspaceSource, contact_for_rig
    from rigctl.plans.model import GlobalInputModel
    from rigctl.plans.rrt import RrtTree, check_tree_meta, plan_rrt, polish, tree_meta

    source = WorkspaceSource(args.workspace)
    starts = points_mm(args.start, "--start")
    goals = points_mm(args.goal, "--goal")
    if len(starts) != len(goals):
        raise PlanError(f"--goal: {len(goals)} goals for {len(starts)} starts; give one per robot")
    radii = _radii(args.radius, len(starts))
    output = Path(args.output)

    tree = None
    if args.tree:
        try:
            tree = RrtTree.load(args.tree)
        except PlanError as err:
            raise PlanError(f"--tree: {err}") from None
    contact = contact_for_rig(args.rig)
    options = _options(args, tree.meta if tree is not None else None)

    exact = source.workspace()
    _check_configuration(exact, starts, radii, args.min_separation, "--start")
    _check_configuration(exact, goals, radii, args.min_separation, "--goal")
    raster = None if source.image_path is not None or args.raster == 0 else args.raster
    started = time.perf_counter()
    planning_ws = exact.rasterize(raster) if raster is not None else exact
    planning = GlobalInputModel(planning_ws, radii, contact, min_separation_mm=args.min_separation)
    meta = tree_meta(
        workspace_hash=source.hash, radii=radii, contact=contact,
        min_separation_mm=args.min_separation, raster_mm=raster, options=options,
    )
    if tree is not None:
        check_tree_meta(tree, meta, source=f"--tree {args.tree}")
        if not np.allclose(tree.root, starts, rtol=0, atol=1e-9):
            raise PlanError(
                f"--tree {args.tree}: grown from start {tree.root.tolist()}, "
                f"not {starts.tolist()}; "
                "a tree answers new goals from its own start only"
            )

    def progress(nodes: int, distance: float, seconds: float) -> None:
        print(f"rrt: {nodes} nodes, best distance {distance:.2f} mm, {seconds:.1f} s",
              file=sys.stderr, flush=True)

    result = plan_rrt(
        planning, starts, goals, options=options, rng=np.random.default_rng(args.seed),
        time_budget_s=args.time, tree=tree, progress=None if args.json else progress,
    )
    result.tree.meta = meta
    if args.save_tree:
        result.tree.save(args.save_tree)
    exact_model = GlobalInputModel(exact, radii, contact, min_separation_mm=args.min_separation)
    moves, states, distance = polish(exact_model, starts, goals, result.moves, options)
    seconds = time.perf_counter() - started
    solved = distance <= options.tolerance_mm

    name = (f"rrt seed {args.seed}: solved, {distance:.3f} mm from the goal" if solved else
            f"rrt seed {args.seed}: NOT SOLVED, best path ends {distance:.3f} mm from the goal")
    _write_plan(output, source, args.rig, name, starts, goals, radii, moves, states,
                options.tolerance_mm, args.min_separation)
    verdict = "solved" if solved else "NOT solved (best path written)"
    print(f"rrt: {verdict}: {len(moves)} moves, {distance:.3f} mm from the goal, "
          f"{result.nodes} nodes, {seconds:.2f} s -> {output}", file=sys.stderr)
    if args.json:
        print(json.dumps({"solved": solved, "nodes": result.nodes, "seconds": round(seconds, 4),
                          "distance": distance, "moves": len(moves)}))
    return EXIT_OK if solved else EXIT_NOT_REACHED


def _write_plan(output: Path, source: WorkspaceSource, rig: str, name: str, starts, goals, radii,
                moves, states, tolerance: float, min_separation: float) -> None:
    from rigctl.plans.checks import check_plan
    from rigctl.plans.schema import dump_plan, parse_plan

    data = {
        "schema": "rigctl.plan/1",
        "kind": "global-moves",
        "rig": rig,
        "name": name,
        "workspace": source.document_for(output),
        "agents": [
            {"start": s.tolist(), "goal": g.tolist(), "radius": float(r)}
            for s, g, r in zip(starts, goals, radii)
        ],
        "moves": np.asarray(moves).tolist(),
        "expected": np.asarray(states).tolist(),
        "tolerance_mm": max(float(tolerance), 1e-3),
        "min_separation_mm": float(min_separation),
    }
    plan = parse_plan(data, str(output))
    check_plan(plan)  # the replay through the plan's own model reproduces `expected`
    output.write_text(dump_plan(plan))


# ---------------------------------------------------------------- plan coverage


def run_coverage(args: argparse.Namespace) -> int:
    """`rigctl plan coverage`: coverage of a saved tree. Returns the exit status."""
    from rigctl.plans.checks import WorkspaceSource
    from rigctl.plans.coverage import coverage, free_bounding_box
    from rigctl.plans.rrt import RrtTree

    source = WorkspaceSource(args.workspace)
    if not args.grid > 0:
        raise PlanError(f"--grid: must be > 0 mm, got {args.grid:g}")
    try:
        tree = RrtTree.load(args.tree)
    except PlanError as err:
        raise PlanError(f"--tree: {err}") from None
    if tree.meta.get("workspace_hash") != source.hash:
        raise PlanError(f"--tree {args.tree} was grown in another workspace than {args.workspace}")
    box = free_bounding_box(source.workspace(), resolution_mm=min(1.0, args.grid / 4.0))
    result = coverage(tree.nodes, box, args.grid)
    print(f"coverage: {result.occupied} of {result.total} hypercubes of {args.grid:g} mm "
          f"({100.0 * result.fraction:.4g} %), {len(tree)} nodes, {tree.n_agents} robots, "
          f"box {tuple(round(v, 3) for v in result.box)} per robot", file=sys.stderr)
    if args.json:
        print(json.dumps({"coverage": result.fraction, "occupied": result.occupied,
                          "total": result.total, "nodes": len(tree), "grid_mm": args.grid,
                          "box": list(result.box),
                          "cells_per_robot": list(result.cells_per_robot)}))
    return EXIT_OK


# ---------------------------------------------------------------- plan wall-contact


def _non_slip_kind() -> str:
    """The rig kind whose particles stick to walls (`RigKind.wall_contact`): what seed 004's
    planner plans for."""
    sticky = sorted(n for n, k in kinds().items() if k.wall_contact == "non-slip")
    if len(sticky) != 1:
        raise PlanError(f"wall-contact: plans for the one installed rig kind whose particles stick "
                        f"to walls; found {', '.join(sticky) or 'none'}")
    return sticky[0]


def run_wall_contact(args: argparse.Namespace) -> int:
    """`rigctl plan wall-contact`: Alg. 1 of seed 004, the plan written. Returns the exit status."""
    from rigctl.plans.checks import WorkspaceSource
    from rigctl.plans.model import GlobalInputModel
    from rigctl.plans.wall_contact import centre_region, plan_with_model

    source = WorkspaceSource(args.workspace)
    document = source.document
    if "boundary" not in document:
        raise PlanError("--workspace: the wall-contact planner needs a shape boundary, not an image")
    if document.get("obstacles"):
        raise PlanError("--workspace: the wall-contact planner works in convex workspaces without "
                        "obstacles")
    if args.height is not None:
        return _run_wall_contact_3d(args, document)
    starts = points_mm(args.start, "--start")
    goals = points_mm(args.goal, "--goal")
    if len(starts) != 2 or len(goals) != 2:
        raise PlanError(f"--start/--goal: the planner places exactly two particles, got "
                        f"{len(starts)} starts and {len(goals)} goals")
    if not args.radius > 0:
        raise PlanError(f"--radius: must be > 0 mm, got {args.radius:g}")
    if not args.epsilon > 0:
        raise PlanError(f"--epsilon: must be > 0 mm, got {args.epsilon:g}")
    output = Path(args.output)
    radii = np.full(2, args.radius)
    region = centre_region(document["boundary"], args.radius)
    exact = source.workspace()
    _check_configuration(exact, starts, radii, 0.0, "--start")
    _check_configuration(exact, goals, radii, 0.0, "--goal")

    started = time.perf_counter()
    model = GlobalInputModel(exact, radii, "non-slip")
    result, chosen, _ = plan_with_model(
        model, region, starts, goals, args.epsilon, interchangeable=args.interchangeable
    )
    seconds = time.perf_counter() - started
    swapped = args.interchangeable and not np.array_equal(chosen, goals)
    verdict = "solved" if result.solved else "NOT SOLVED"
    name = (f"wall-contact: {verdict}, {len(result.moves)} moves, {result.length:.3f} mm, "
            f"ends {result.error:.3g} mm from the goal" + (", goals swapped" if swapped else ""))
    _write_plan(output, source, _non_slip_kind(), name, starts, chosen, radii, result.moves,
                result.states, args.epsilon, 0.0)
    print(f"wall-contact: {verdict}: {len(result.moves)} moves, path {result.length:.3f} mm, "
          f"{result.error:.3g} mm from the goal, {seconds * 1e3:.1f} ms -> {output}",
          file=sys.stderr)
    if args.json:
        print(json.dumps({"solved": result.solved, "moves": len(result.moves),
                          "length": round(result.length, 6), "seconds": round(seconds, 6)}))
    return EXIT_OK if result.solved else EXIT_NOT_REACHED


def _run_wall_contact_3d(args: argparse.Namespace, document: dict) -> int:
    """`rigctl plan wall-contact --height H`: Sec. IV-G in a right prism or cylinder."""
    from rigctl.plans.wall_contact import centre_region
    from rigctl.plans.wall_contact_3d import (
        plan_document_3d,
        plan_wall_contact_3d,
        prism_region,
    )

    points = {flag: points_mm(values, flag, "X,Y,Z (with --height)")
              for flag, values in (("--start", args.start), ("--goal", args.goal))}
    for flag, parsed in points.items():
        if len(parsed) != 2:
            raise PlanError(f"{flag}: the planner places exactly two particles, got {len(parsed)}")
    if not (args.height > 2 * args.radius and args.radius > 0 and args.epsilon > 0):
        raise PlanError(f"--height {args.height:g}: must exceed the particles' diameter "
                        f"{2 * args.radius:g} mm (and --radius, --epsilon > 0)")
    output = Path(args.output)
    region = prism_region(centre_region(document["boundary"], args.radius), args.height, args.radius)
    result, chosen = plan_wall_contact_3d(region, points["--start"], points["--goal"], args.epsilon,
                                          args.interchangeable)
    output.write_text(json.dumps(plan_document_3d(document, args.height, args.radius,
                                                  points["--start"], chosen, result, args.epsilon),
                                 indent=1))
    verdict = "solved" if result.solved else "NOT SOLVED"
    print(f"wall-contact 3D: {verdict}: {len(result.moves)} moves, path {result.length:.3f} mm, "
          f"{result.error:.3g} mm from the goal, {result.seconds * 1e3:.1f} ms -> {output}",
          file=sys.stderr)
    if args.json:
        print(json.dumps({"solved": result.solved, "moves": len(result.moves),
                          "length": round(result.length, 6), "seconds": round(result.seconds, 6)}))
    return EXIT_OK if result.solved else EXIT_NOT_REACHED


# ---------------------------------------------------------------- plan reachable


def run_reachable(args: argparse.Namespace) -> int:
    """`rigctl plan reachable`: reachable fractions of the Delta space. Returns the exit status."""
    from rigctl.plans.checks import WorkspaceSource
    from rigctl.plans.wall_contact import (
        DiskRegion,
        PolygonRegion,
        centre_region,
        reachable_fraction,
    )

    if args.disk:
        region = DiskRegion(np.zeros(2), 0.5)
    elif args.polygon:
        vertices = points_mm([v for v in args.polygon.split(";") if v.strip()], "--polygon")
        if len(vertices) < 3:
            raise PlanError("--polygon: give at least three vertices X,Y;X,Y;X,Y")
        region = PolygonRegion(vertices)
    else:
        source = WorkspaceSource(args.workspace)
        if "boundary" not in source.document or source.document.get("obstacles"):
            raise PlanError("--workspace: needs a convex shape boundary without obstacles")
        region = centre_region(source.document["boundary"], 0.0)
    if not 0.0 < args.d12 <= 1.0:
        raise PlanError(f"--d12: must be in (0, 1] (units of the workspace diameter), got {args.d12:g}")
    if not args.cells >= 11:
        raise PlanError(f"--cells: must be >= 11, got {args.cells}")
    angle = math.radians(args.angle)
    start = args.d12 * region.size * np.array([math.cos(angle), math.sin(angle)])
    started = time.perf_counter()
    fractions = reachable_fraction(region, start, args.moves, cells=args.cells)
    seconds = time.perf_counter() - started
    table = ", ".join(f"{2 * (i + 1)}: {100 * f:.1f} %" for i, f in enumerate(fractions))
    print(f"reachable: d12 {args.d12:g}: {table} ({args.cells} x {args.cells} grid, "
          f"{seconds:.2f} s)", file=sys.stderr)
    if args.json:
        print(json.dumps({"fraction": round(fractions[-1], 6)}))
    return EXIT_OK
