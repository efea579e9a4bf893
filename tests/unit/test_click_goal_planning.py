"""Planning to clicked goals (`rigctl.plans.goals`, the daemon's `plan_goals` in
rigctl/apps/daemon/goals.py) without a daemon process: each reason a goal cannot be planned to,
in one line; a plan that reaches the goals replays (through the plan's own model, as `rigctl
validate` checks it) to within the tolerance, in whole magnet turns on the six-coil rig; the
wall-contact planner on the coil board; a rig kind without the hook and a daemon that has seen no
run say so."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from rigctl.apps.daemon.goals import CANNOT_PLAN, GoalPlanning
from rigctl.apps.daemon.messages import ErrorCode, PlanGoalsArgs
from rigctl.apps.daemon.states import Refusal, S
from rigctl.core.registry import rig_kind
from rigctl.plans.goals import GoalProblem, plan_rrt_goals, plan_wall_contact_goals
from rigctl.plans.schema import parse_plan

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
FIG4 = json.loads((EXAMPLES / "fig4-quick.json").read_text())
COIL_BOARD = json.loads((EXAMPLES / "coilboard-disk.json").read_text())
STARTS = [[220.0, 230.0], [100.0, 230.0]]  # fig4-quick's magnets after one turn down


def problem(goals, **changes) -> GoalProblem:
    return GoalProblem(**{"rig": "six-coil", "workspace": FIG4["workspace"], "starts_mm": STARTS,
                          "goals_mm": goals, "radii_mm": [8.0, 8.0], "turn_mm": 10.0,
                          "budget_s": 2.0, **changes})


@pytest.mark.parametrize("goal, reason", [
    ([200.0, 160.0], "goal of agent #0 (200.0, 160.0) mm is in an obstacle"),  # fig4's wall
    ([500.0, 230.0], "goal of agent #0 (500.0, 230.0) mm is outside the workspace"),
    ([220.0, 55.0], "too close to a wall: 5.0 mm of room for an agent of radius 8 mm"),
    ([100.0, 240.0], "overlaps"),  # on top of agent #1, which keeps its place
])
def test_a_goal_that_cannot_be_planned_to_says_why_in_one_line(goal, reason):
    answer = plan_rrt_goals(problem([goal, STARTS[1]]), "slide")
    assert answer.plan is None and reason in answer.reason and "\n" not in answer.reason


def test_no_path_within_the_budget_says_so_and_how_close_it_came():
    # two magnets in a corridor 20 mm wide (radius 8) cannot pass each other: no input swaps them
    corridor = {"boundary": {"rect": [0.0, 0.0, 200.0, 20.0]}}
    answer = plan_rrt_goals(problem([[150.0, 10.0], [50.0, 10.0]], workspace=corridor,
                                    starts_mm=[[50.0, 10.0], [150.0, 10.0]], budget_s=0.5),
                            "slide")
    assert answer.plan is None
    assert answer.reason.startswith("no path found within the budget (0.5 s, global-input RRT)")
    # they never pass: x0 <= x1 - 16, so the nearest configuration to the goals (x0 = 150,
    # x1 = 50) is x0 = 150 - t, x1 = 50 + t with 2 t - 100 = 16: t = 58, sqrt(2) * 58 mm away
    assert answer.distance_mm >= math.sqrt(2) * 58.0 - 1e-6


def test_a_reachable_goal_gives_a_plan_of_whole_turns_that_replays_to_it():
    goals = [[220.0, 250.0], [100.0, 250.0]]
    answer = plan_rrt_goals(problem(goals), "slide")
    assert answer.reason is None
    plan = parse_plan(answer.plan, "clicked")  # the schema's own checks, whole turns included
    moves = np.array(plan.moves)
    turns = np.hypot(*moves.T) / 10.0
    np.testing.assert_allclose(turns, np.round(turns), atol=1e-6)
    # the magnets move together and nothing is in their way here: the sum of the moves is the
    # displacement, computed by hand (20 mm up for both)
    np.testing.assert_allclose(moves.sum(axis=0), [0.0, 20.0], atol=plan.tolerance_mm)
    ends = np.array(plan.expected[-1])
    assert all(math.dist(e, g) <= plan.tolerance_mm for e, g in zip(ends, goals))
    assert [a.start for a in plan.agents] == [tuple(s) for s in STARTS]


def test_a_translation_is_planned_straight_and_the_tree_is_seeded():
    # both magnets the same way, nothing in between: straight, in whole turns (42.4 mm is not
    # one: two moves or more)
    straight = plan_rrt_goals(problem([[250.0, 260.0], [130.0, 260.0]]), "slide").plan
    np.testing.assert_allclose(np.sum(straight["moves"], axis=0), [30.0, 30.0], atol=1.0)
    assert straight["name"].startswith("clicked goals: direct")
    # one magnet alone (the other back where it was) needs the walls: the seeded tree, the same
    # plan for the same seed (a budget it does not reach: the tree stops when solved)
    starts = [[250.0, 183.0], [130.0, 160.0]]
    alone = [[262.0, 205.0], [130.0, 160.0]]
    first = plan_rrt_goals(problem(alone, starts_mm=starts, seed=0, budget_s=30.0), "slide").plan
    again = plan_rrt_goals(problem(alone, starts_mm=starts, seed=0, budget_s=30.0), "slide").plan
    assert first is not None and first["name"].startswith("clicked goals: rrt seed 0")
    assert first["moves"] == again["moves"]


def test_the_coil_board_plans_two_particles_with_wall_contact():
    agents = COIL_BOARD["agents"]
    starts = [a["start"] for a in agents]
    goals = [a["goal"] for a in agents]
    answer = rig_kind("coil-board").plan_goals(None, GoalProblem(
        rig="coil-board", workspace=COIL_BOARD["workspace"], starts_mm=starts, goals_mm=goals,
        radii_mm=[0.5, 0.5], tolerance_mm=0.5))
    assert answer.reason is None, answer.reason
    plan = parse_plan(answer.plan, "clicked")
    assert all(math.dist(e, g) <= 0.5 for e, g in zip(plan.expected[-1], goals))
    assert plan_wall_contact_goals(GoalProblem(
        rig="coil-board", workspace=FIG4["workspace"], starts_mm=starts, goals_mm=goals,
        radii_mm=[0.5, 0.5])).reason.startswith("the wall-contact planner needs a convex boundary")


class _Daemon(SimpleNamespace):
    """What `GoalPlanning.command` asks of the daemon, standing idle."""

    def _require(self, *states, doing):
        assert S.IDLE in states


def daemon_of(kind: str) -> _Daemon:
    import threading

    return _Daemon(kind=rig_kind(kind), rig=SimpleNamespace(rig=SimpleNamespace(kind=kind),
                                                            camera=None),
                   _lock=threading.RLock(), _active=None)


def test_a_kind_without_the_hook_and_a_daemon_that_saw_no_run_say_so():
    args = PlanGoalsArgs(goals=[{"agent": 0, "mm": [1.0, 2.0]}])
    with pytest.raises(Refusal) as refused:
        GoalPlanning(daemon_of("depm")).command(args)
    assert refused.value.code is ErrorCode.UNREACHABLE and CANNOT_PLAN in str(refused.value)
    with pytest.raises(Refusal) as refused:
        GoalPlanning(daemon_of("six-coil")).command(args)
    assert refused.value.code is ErrorCode.WRONG_STATE
    assert "no tracked positions yet" in str(refused.value)


def test_a_goal_is_given_in_mm_or_px_not_both():
    with pytest.raises(ValueError, match='either "mm" or "px"'):
        PlanGoalsArgs(goals=[{"agent": 0, "mm": [1.0, 2.0], "px": [3.0, 4.0]}])


def test_two_agents_last_run_as_a_pair_are_planned_as_a_formation_by_the_pair_planner():
    from rigctl.apps.daemon.goals import planned_paths_mm, tracked_after
    from rigctl.plans.pair import agent_positions, state_of
    from rigctl.plans.schema import load_plan
    from rigctl.run.summary import AgentResult

    source = EXAMPLES / "pair-formation-change.json"
    pair = load_plan(source)
    d = pair.agents.body_diameter_mm
    # where the last pair run left them (its summary), and the formation its goal makes
    here = (agent_positions(state_of(pair.start, d)) * d).tolist()
    there = (agent_positions(state_of(pair.goal, d)) * d).tolist()
    summary = SimpleNamespace(agents=[AgentResult(p, p, 0.0) for p in here],
                              positions_from="camera (closed loop)", run="runs/x")
    tracked = tracked_after(pair, summary)
    assert tracked.plan_kind == "pair-formation" and tracked.radii_mm == [d / 2, d / 2]
    assert tracked.tolerance_mm == pytest.approx(pair.tolerance_bl * d)
    problem = GoalProblem(rig="six-coil", workspace=tracked.workspace, starts_mm=here,
                          goals_mm=there, radii_mm=tracked.radii_mm,
                          tolerance_mm=tracked.tolerance_mm, budget_s=10.0,
                          plan_kind=tracked.plan_kind, template=tracked.template)
    answer = rig_kind("six-coil").plan_goals(None, problem)
    assert answer.reason is None, answer.reason
    plan = parse_plan(answer.plan, "clicked")
    assert plan.kind == "pair-formation" and plan.segments
    paths = planned_paths_mm(answer.plan, here)
    for agent in range(2):
        assert paths[agent][0] == here[agent]
        # the model's end, each agent within the plan's tolerance of its clicked goal
        assert math.dist(paths[agent][-1], there[agent]) <= plan.tolerance_bl * d
    # a goal in the pillar of that workspace (a disk at (10, 11) mm, radius 1.5): the reason
    inside = plan_pair_goals_reason(problem, [[10.0, 11.0], there[1]])
    assert inside == "goal of agent #0 (10.0, 11.0) mm is in an obstacle"


def plan_pair_goals_reason(problem: GoalProblem, goals) -> str:
    from dataclasses import replace

    from rigctl.plans.goals import plan_pair_goals

    return plan_pair_goals(replace(problem, goals_mm=goals)).reason


def test_a_goal_for_an_agent_not_tracked_or_in_px_without_a_calibration_is_a_bad_argument():
    from rigctl.apps.daemon.goals import Tracked

    planning = GoalPlanning(daemon_of("six-coil"))
    planning.tracked = Tracked(STARTS, "camera (closed loop)", "runs/x", "six-coil",
                               FIG4["workspace"], [8.0, 8.0], 0.0, 1.0)
    for goal, says in (({"agent": 2, "mm": [220.0, 250.0]}, "no agent #2 (the daemon tracks 2"),
                       ({"agent": 0, "px": [10.0, 10.0]}, "needs the rig's camera calibration")):
        with pytest.raises(Refusal) as refused:
            planning.command(PlanGoalsArgs(goals=[goal]))
        assert refused.value.code is ErrorCode.BAD_ARGS and says in str(refused.value)
