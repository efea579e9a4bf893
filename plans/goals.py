"""Plans to clicked goals: the agents where the camera last saw them, a goal for each (an agent the
operator gave no goal keeps its place as its goal), planned by a rig kind's own planner into an
ordinary plan document that `load` checks and `execute` runs.

`GoalProblem` is what the daemon hands a rig kind's `RigKind.plan_goals` hook (plain data: it
crosses to the planning process); `GoalPlan` is the answer, a plan document or one line saying
why there is none: a goal outside the workspace, in an obstacle, too close to a wall or to another
agent's goal, or no path found within the time budget. `plan_rrt_goals` (the global-input RRT of
seed 000, rolling magnets or any kind with global moves), `plan_wall_contact_goals` (seed 004's
two particles on non-slip walls) and `plan_pair_goals` (seed 002's two interacting agents: the
formation the two clicked goals make) are the planners the kinds plug in.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rigctl.core.errors import PlanError

DEFAULT_BUDGET_S = 5.0
"""The planner's time budget (s) when the request names none."""

DEFAULT_TOLERANCE_MM = 1.0
"""How close (mm, Euclidean in R^2n for the RRT, per particle for the wall-contact planner) the
plan must end to the goals, when the request names no tolerance."""


@dataclass(frozen=True)
class GoalProblem:
    """Where the agents are and where they should go, in the workspace's frame (mm).

    rig: the rig kind's name (the plan's `rig`); workspace: a plan's workspace document (an image
    path absolute); starts_mm, goals_mm: (n, 2) per agent; radii_mm: (n,); tolerance_mm; the
    plan's min_separation_mm; seed: the planner's random seed; budget_s: its time budget."""

    rig: str
    workspace: dict[str, Any]
    starts_mm: list[list[float]]
    goals_mm: list[list[float]]
    radii_mm: list[float]
    tolerance_mm: float = DEFAULT_TOLERANCE_MM
    min_separation_mm: float = 0.0
    seed: int = 0
    budget_s: float = DEFAULT_BUDGET_S
    turn_mm: float | None = None  # moves are whole turns of this (rolling magnets); None: any
    plan_kind: str = "global-moves"  # the kind of plan the agents were last run with
    template: dict[str, Any] | None = None  # that plan's document (a pair's physics and bounds)


@dataclass(frozen=True)
class GoalPlan:
    """A planner's answer: `plan` (a plan document) when it reached the goals within the
    tolerance, else `reason` (one line); `distance_mm`: where the best path ends from the goals."""

    plan: dict[str, Any] | None = None
    reason: str | None = None
    distance_mm: float | None = None
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)


def check_goals(problem: GoalProblem, workspace) -> str | None:
    """Why the goals cannot be planned to, in one line, or None: each goal inside the workspace's
    boundary, not in an obstacle, at least its radius from every wall, and no two goals closer
    than r_i + r_j + the plan's separation."""
    goals = np.asarray(problem.goals_mm, dtype=float).reshape(-1, 2)
    radii = np.asarray(problem.radii_mm, dtype=float)
    xmin, ymin, xmax, ymax = workspace.bounds
    clearance = workspace.clearance(goals)
    for i, (goal, room, radius) in enumerate(zip(goals, clearance, radii)):
        at = f"goal of agent #{i} ({goal[0]:.1f}, {goal[1]:.1f}) mm"
        if room < 0:
            outside = not (xmin <= goal[0] <= xmax and ymin <= goal[1] <= ymax) or _outside_boundary(
                problem.workspace, goal)
            return f"{at} is {'outside the workspace' if outside else 'in an obstacle'}"
        if room < radius - 1e-9:
            return (f"{at} is too close to a wall: {room:.1f} mm of room for an agent of radius "
                    f"{radius:g} mm")
    try:
        from rigctl.plans.checks import check_placement

        check_placement(workspace, goals, radii, problem.min_separation_mm,
                        lambda i: f"goal of agent #{i}", lambda i: f"agent #{i}'s goal")
    except PlanError as err:
        return str(err)
    return None


def _outside_boundary(document: dict, point: np.ndarray) -> bool:
    """True when `point` is outside the workspace's boundary shape (not merely in an obstacle)."""
    boundary = document.get("boundary")
    if not isinstance(boundary, dict):
        return False  # an image workspace: walls and obstacles are one mask
    from rigctl.plans.schema import parse_workspace
    from rigctl.plans.workspace import Workspace

    bare = Workspace.from_spec(parse_workspace({"boundary": boundary}, "boundary"))
    return bool(bare.clearance(point[None])[0] < 0)


def _workspace(problem: GoalProblem):
    from rigctl.plans.schema import parse_workspace
    from rigctl.plans.workspace import Workspace

    return Workspace.from_spec(parse_workspace(problem.workspace, "workspace"))


def _document(problem: GoalProblem, goals: np.ndarray, moves: np.ndarray, states: np.ndarray,
              name: str) -> dict[str, Any]:
    """The plan document of a plan to the goals, checked as `rigctl validate` checks it (the
    replay through the plan's model reproduces `expected`)."""
    from rigctl.plans.checks import check_plan
    from rigctl.plans.schema import dump_plan, parse_plan

    data = {
        "schema": "rigctl.plan/1", "kind": "global-moves", "rig": problem.rig, "name": name,
        "workspace": problem.workspace,
        "agents": [{"start": [float(v) for v in s], "goal": [float(v) for v in g],
                    "radius": float(r)}
                   for s, g, r in zip(problem.starts_mm, goals, problem.radii_mm)],
        "moves": np.asarray(moves, dtype=float).reshape(-1, 2).tolist(),
        "expected": np.asarray(states, dtype=float).tolist(),
        "tolerance_mm": max(float(problem.tolerance_mm), 1e-3),
        "min_separation_mm": float(problem.min_separation_mm),
    }
    plan = parse_plan(data, "the clicked goals' plan")
    check_plan(plan)
    import json

    return json.loads(dump_plan(plan))


def _not_found(kind: str, problem: GoalProblem, distance: float, seconds: float) -> GoalPlan:
    return GoalPlan(reason=f"no path found within the budget ({problem.budget_s:g} s, {kind}): "
                    f"the best ends {distance:.2f} mm from the goals (tolerance "
                    f"{problem.tolerance_mm:g} mm)", distance_mm=distance, seconds=seconds)


def plan_rrt_goals(problem: GoalProblem, contact: str) -> GoalPlan:
    """The global-input RRT (seed 000, `rigctl plan rrt --tuned`) from the starts to the goals
    within `problem.budget_s`, moves whole turns of `problem.turn_mm` when set; `contact`: how
    agents meet walls ("slide", "non-slip")."""
    from rigctl.plans.model import GlobalInputModel
    from rigctl.plans.rrt import RrtOptions, plan_rrt, polish

    started = time.perf_counter()
    workspace = _workspace(problem)
    why = check_goals(problem, workspace)
    if why is not None:
        return GoalPlan(reason=why)
    starts = np.asarray(problem.starts_mm, dtype=float).reshape(-1, 2)
    goals = np.asarray(problem.goals_mm, dtype=float).reshape(-1, 2)
    radii = np.asarray(problem.radii_mm, dtype=float)
    turn = problem.turn_mm
    options = RrtOptions(robostep_mm=turn if turn else 5.0, turn_mm=turn,
                         tolerance_mm=problem.tolerance_mm, goal_bias=0.05, formation_bias=0.1,
                         greedy=True, final_approach=True)
    model = GlobalInputModel(workspace, radii, contact, min_separation_mm=problem.min_separation_mm)
    if float(np.linalg.norm(starts - goals)) <= problem.tolerance_mm:
        return GoalPlan(reason="every agent is at its goal already (within the tolerance)")
    # the straight way first (the RRT's final-approach descent from the starts, deterministic):
    # a clicked goal in open floor is usually a translation, which an operator expects drawn as
    # one; the tree only when that does not reach the goals
    moves, states, distance = polish(model, starts, goals, np.empty((0, 2)), options)
    nodes = 0
    if distance > problem.tolerance_mm:
        result = plan_rrt(model, starts, goals, options=options,
                          rng=np.random.default_rng(problem.seed), time_budget_s=problem.budget_s)
        moves, states, distance = polish(model, starts, goals, result.moves, options)
        nodes = result.nodes
    seconds = time.perf_counter() - started
    if distance > problem.tolerance_mm or not len(moves):
        return _not_found("global-input RRT", problem, distance, seconds)
    how = f"rrt seed {problem.seed}" if nodes else "direct"
    name = f"clicked goals: {how}, {len(moves)} moves, {distance:.3f} mm from the goals"
    return GoalPlan(plan=_document(problem, goals, moves, states, name), distance_mm=distance,
                    seconds=seconds, extra={"nodes": nodes})


def plan_wall_contact_goals(problem: GoalProblem) -> GoalPlan:
    """Seed 004's wall-contact planner (two particles, one pulling input, non-slip walls of a
    convex workspace without obstacles), replayed through the non-slip model."""
    from rigctl.plans.model import GlobalInputModel
    from rigctl.plans.wall_contact import centre_region, plan_with_model

    started = time.perf_counter()
    document = problem.workspace
    if "boundary" not in document or document.get("obstacles"):
        return GoalPlan(reason="the wall-contact planner needs a convex boundary without "
                        "obstacles (this workspace has " + ("obstacles" if document.get(
                            "obstacles") else "no shape boundary") + ")")
    if len(problem.starts_mm) != 2:
        return GoalPlan(reason=f"the wall-contact planner places exactly two particles, not "
                        f"{len(problem.starts_mm)}")
    workspace = _workspace(problem)
    why = check_goals(problem, workspace)
    if why is not None:
        return GoalPlan(reason=why)
    starts = np.asarray(problem.starts_mm, dtype=float).reshape(2, 2)
    goals = np.asarray(problem.goals_mm, dtype=float).reshape(2, 2)
    radii = np.asarray(problem.radii_mm, dtype=float)
    if float(np.max(np.hypot(*(starts - goals).T))) <= problem.tolerance_mm:
        return GoalPlan(reason="every agent is at its goal already (within the tolerance)")
    model = GlobalInputModel(workspace, radii, "non-slip")
    result, chosen, _ = plan_with_model(model, centre_region(document["boundary"],
                                                             float(radii.max())),
                                        starts, goals, problem.tolerance_mm)
    seconds = time.perf_counter() - started
    if not result.solved or not len(result.moves):
        return _not_found("wall-contact planner", problem, float(result.error), seconds)
    name = f"clicked goals: wall contact, {len(result.moves)} moves"
    return GoalPlan(plan=_document(problem, chosen, result.moves, result.states, name),
                    distance_mm=float(result.error), seconds=seconds)


def plan_pair_goals(problem: GoalProblem) -> GoalPlan:
    """Seed 002's pair planner (`rigctl plan pair`): from the formation the two agents make now to
    the one their goals make (centroid, separation, heading), with the physics, bounds, field and
    hold of the pair-formation plan they last ran (`problem.template`). The tolerance is in mm
    here and the plan's in body lengths."""
    import math

    from rigctl.plans.pair import (
        PairPlannerOptions,
        check,
        plan_pair,
        problem_of,
        simulate,
        state_from_positions,
        state_to_doc,
        wrap_angle,
    )
    from rigctl.plans.schema import dump_plan, parse_plan

    started = time.perf_counter()
    template = problem.template
    if template is None or len(problem.starts_mm) != 2:
        return GoalPlan(reason="the pair planner plans two agents from a pair-formation plan's "
                        "physics: run one first")
    workspace = _workspace(problem)
    why = check_goals(problem, workspace)
    if why is not None:
        return GoalPlan(reason=why)
    d = float(template["agents"]["body_diameter_mm"])
    start = state_from_positions(np.asarray(problem.starts_mm, dtype=float) / d)
    goal = state_from_positions(np.asarray(problem.goals_mm, dtype=float) / d)
    tolerance_bl = problem.tolerance_mm / d
    base = {key: value for key, value in template.items()
            if key not in ("segments", "expected", "name", "start", "goal", "tolerance_bl")}
    base.update(workspace=problem.workspace, start=state_to_doc(start, d),
                goal=state_to_doc(goal, d), segments=[], tolerance_bl=tolerance_bl,
                name="clicked goals: pair formation")
    try:
        skeleton = parse_plan(base, "the clicked goals' plan")
        options = PairPlannerOptions.fast(time_s=problem.budget_s,
                                          goal_tol=min(PairPlannerOptions.goal_tol, tolerance_bl))
        path = plan_pair(problem_of(skeleton), start, goal, options, seed=problem.seed)
    except PlanError as err:
        return GoalPlan(reason=str(err))
    seconds = time.perf_counter() - started
    if not path.solved:
        return _not_found("pair planner", problem, path.goal_distance * d, seconds)
    base["segments"] = [
        {"psi_deg": float(math.degrees(wrap_angle(u[0]))), "f_x": float(u[1]), "f_y": float(u[2]),
         "dt_s": float(dt)} for u, dt in zip(path.controls, path.dts)]
    base["name"] = (f"clicked goals: pair formation, {len(path.dts)} segments, "
                    f"{float(path.dts.sum()):.1f} s")
    plan = simulate(parse_plan(base, "the clicked goals' plan"))
    check(plan)
    import json

    return GoalPlan(plan=json.loads(dump_plan(plan)), distance_mm=path.goal_distance * d,
                    seconds=seconds)
