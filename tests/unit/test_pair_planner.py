"""The pair RRT (Alg. 1-3) and the plan documents it writes: every constraint respected.

The constraints are checked here by an independent replay: each segment is integrated with a plain
Euler scheme at 1 ms (not the planner's RK4), and the agents' positions are tested against the
workspace's clearance, the separation against (r_min, r_max) and the pull against the rig's box.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.cli.main import main
from rigctl.core.errors import PlanError
from rigctl.plans.pair import (
    PairPhysics,
    PairPlannerOptions,
    PairProblem,
    agent_positions,
    check,
    default_rig,
    goal_error,
    plan_pair,
    replan_pair,
    rig_max_pull,
)
from rigctl.plans.schema import load_plan
from rigctl.plans.workspace import ShapeWorkspace

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
WS = ShapeWorkspace(("rect", (0, 0, 20, 14)), [("rect", (6, 0, 1, 8)), ("disk", (11, 5, 1.2))])


def independent_replay(start, controls, dts, k):
    """States every 5 ms along the segments, integrated by scipy's adaptive RK45 (rtol 1e-10),
    independently of the planner's fixed-step RK4."""
    from scipy.integrate import solve_ivp

    q = np.array(start, dtype=float)
    out = [q[None]]
    for (psi_g, fx, fy), dt in zip(controls, dts):
        def rates(_t, y, psi_g=psi_g, fx=fx, fy=fy):
            psi = psi_g - y[3]
            return [fx, fy, k * (1 - 3 * math.cos(psi) ** 2) / y[2] ** 4,
                    k * math.sin(2 * psi) / y[2] ** 5]
        t_eval = np.linspace(0.0, dt, max(2, int(round(dt / 5e-3)) + 1))
        sol = solve_ivp(rates, (0.0, dt), q, t_eval=t_eval, rtol=1e-10, atol=1e-12)
        q = sol.y[:, -1]
        out.append(sol.y.T[1:])
    return np.concatenate(out)


def assert_respects_constraints(problem, start, controls, dts, expected, margin=1e-3):
    """Replay each segment from the planner's state before it (the open-loop chain is unstable:
    an attracting pair amplifies a 1e-7 difference tenfold every few segments, so a whole-path
    replay tests chaos, not the plan); it must land on the planner's next state and keep every
    constraint on the way."""
    before = np.vstack([np.asarray(start, dtype=float)[None], expected[:-1]])
    pieces = []
    for k in range(len(dts)):
        states = independent_replay(before[k], controls[k:k + 1], dts[k:k + 1], problem.rate)
        assert np.abs(states[-1] - expected[k]).max() < 1e-5
        pieces.append(states)
    states = np.concatenate(pieces)
    assert states[:, 2].min() > problem.r_min - margin
    assert states[:, 2].max() < problem.r_max + margin
    p = agent_positions(states) * problem.diameter_mm
    clearance = problem.workspace.clearance(p)
    assert clearance.min() >= 0.5 * problem.diameter_mm - margin
    bx = problem.max_pull * np.abs(np.cos(controls[:, 0]))
    by = problem.max_pull * np.abs(np.sin(controls[:, 0]))
    assert np.all(np.abs(controls[:, 1]) <= bx + 1e-9)
    assert np.all(np.abs(controls[:, 2]) <= by + 1e-9)
    return states


@pytest.fixture(scope="module")
def problem():
    return PairProblem(WS, PairPhysics(), 1.5, 3.5, 0.6, sample_workspace=WS)


def test_plan_reaches_goal_and_respects_every_constraint(problem):
    start, goal = np.array([3, 4, 2.0, math.pi / 2]), np.array([15, 10, 2.8, 0.3])
    path = plan_pair(problem, start, goal, PairPlannerOptions(time_s=20), seed=2)
    assert path.solved
    states = assert_respects_constraints(problem, start, path.controls, path.dts, path.states)
    # the independent replay ends where the planner said, within integration error
    assert goal_error(states[-1], goal) <= 0.15 + 1e-4


@pytest.fixture(scope="module")
def microfactory():
    """The Fig. 6 maze: both agents from the left bay into the two narrow chambers (1.8 mm wide,
    a 0.4 mm wall between them), side by side at 2.2 BL."""
    plan = load_plan(EXAMPLES / "pair-microfactory.json")
    from rigctl.plans.pair import problem_of

    return problem_of(plan), np.array([3, 4, 2.0, math.pi / 2]), np.array([16.4, 12.5, 2.2, 0.0])


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_goal_tree_planner_solves_the_microfactory_for_any_seed(microfactory, seed):
    """The default planner (goal tree + connect steps) within a node budget, not a clock; the
    joined path, followed forward from the start, respects every constraint and ends in both
    chambers (each agent between its chamber's walls, checked against the workspace by hand)."""
    problem, start, goal = microfactory
    path = plan_pair(problem, start, goal, PairPlannerOptions.fast(time_s=120, max_nodes=3000),
                     seed=seed)
    assert path.solved
    states = assert_respects_constraints(problem, start, path.controls, path.dts, path.states)
    assert goal_error(states[-1], goal) <= 0.15 + 1e-4
    (x1, y1), (x2, y2) = agent_positions(states[-1])
    assert 14.4 + 0.5 <= x1 <= 16.2 - 0.5 and 16.6 + 0.5 <= x2 <= 18.4 - 0.5
    assert y1 > 9.5 + 1.5 and y2 > 9.5 + 1.5  # well inside, past the chambers' mouths


def test_paper_variant_is_one_tree_and_the_default_adds_the_goal_tree():
    paper, fast = PairPlannerOptions.paper(), PairPlannerOptions.fast()
    assert not paper.bidirectional and paper.connect_steps == 0
    assert fast.bidirectional and fast.connect_steps > 0
    assert (paper.n_psi, paper.dts, paper.goal_bias) == (fast.n_psi, fast.dts, fast.goal_bias)


def test_same_seed_same_plan(problem):
    start, goal = np.array([3, 10, 2.0, 0.0]), np.array([4, 11, 2.5, 1.0])
    for options in (PairPlannerOptions.paper(), PairPlannerOptions.fast()):
        a = plan_pair(problem, start, goal, options, seed=5)
        b = plan_pair(problem, start, goal, options, seed=5)
        np.testing.assert_array_equal(a.controls, b.controls)


def test_bad_start_is_refused(problem):
    with pytest.raises(PlanError, match="separation"):
        plan_pair(problem, [3, 4, 1.2, 0.0], [15, 10, 2.0, 0.0])
    with pytest.raises(PlanError, match="wall"):
        plan_pair(problem, [6.5, 4, 2.0, math.pi / 2], [15, 10, 2.0, 0.0])


def test_replan_from_a_disturbed_state_is_fast_and_joins_the_path(problem):
    start, goal = np.array([2.5, 11, 2.0, 0.0]), np.array([15, 11, 2.0, 0.0])
    path = plan_pair(problem, start, goal, PairPlannerOptions(time_s=20), seed=3)
    assert path.solved
    k = len(path.states) // 3
    measured = path.states[k] + np.array([0.3, -0.3, 0.2, 0.15])
    fix, joined = replan_pair(problem, measured, path.states, k,
                              PairPlannerOptions(time_s=5.0, max_nodes=400), seed=1)
    assert fix.solved and joined >= k
    assert goal_error(fix.states[-1] if len(fix.states) else measured, path.states[joined]) <= 0.15
    assert_respects_constraints(problem, measured, fix.controls, fix.dts, fix.states)
    # its time (the goal is < 100 ms) is measured by bench/pair.py, not asserted here


def cube_pull_bound_bl_s(rig, field_T, moment_Am2, viscosity_Pa_s, diameter_m):
    """The largest centroid speed (BL/s) a cube of six equal loops can give both agents at any
    field angle, in closed form from the loops' on-axis field.

    A loop of N turns, radius a, fed I, at distance d from the centre on its axis makes there
    B = b I along the axis, b = mu0 N a^2 / (2 (a^2 + d^2)^(3/2)), and the axial gradient
    c I, c = 3 d b / (a^2 + d^2) (sign: towards the loop), with -c I / 2 on each transverse
    diagonal term (div B = 0, axial symmetry) and no off-diagonal terms. So a pair's sum of
    currents makes the field and its difference D the gradient, and for the in-plane terms
    G_x = c (D_x - (D_y + D_z) / 2), G_y = c (D_y - (D_x + D_z) / 2). The least-norm currents have
    D_x + D_y + D_z = 0, hence D_x = 2 G_x / (3c), D_y = 2 G_y / (3c), D_z = -2 (G_x + G_y) / (3c):
    an x coil carries B_x / (2b) + G_x / (3c) at worst, a z coil (G_x + G_y) / (3c). With
    |B| = field_T at any angle and |G_x|, |G_y| <= g, the x and y coils allow
    g = 3c (I_max - field_T / (2b)), the z coils g = 3c I_max / 2.
    The pull on a moment m aligned with the field is m g along the axis it points on (seed 002:
    a weak gradient pulls the centroid), against the Stokes drag sigma = 6 pi eta R of each agent:
    v = m g / (3 pi eta D), or v / D body lengths per second.
    """
    coils = rig.coils
    a_m = coils[0].loop_radius_mm * 1e-3
    d_m = abs(max(coils[0].centre_mm, key=abs)) * 1e-3
    turns, i_max = coils[0].turns, coils[0].current_limit_A
    for coil in coils:  # the closed form holds for a cube of equal coils facing the centre
        assert (coil.loop_radius_mm * 1e-3, coil.turns, coil.current_limit_A) == (a_m, turns, i_max)
        assert np.allclose(np.abs(np.asarray(coil.centre_mm) * 1e-3), d_m * np.abs(coil.axis))
    assert sorted(tuple(np.sign(c.centre_mm).astype(int)) for c in coils) == sorted(
        tuple(s * e) for e in np.eye(3, dtype=int) for s in (1, -1))
    mu0 = 4e-7 * math.pi
    b = mu0 * turns * a_m**2 / (2.0 * (a_m**2 + d_m**2) ** 1.5)
    c = 3.0 * d_m * b / (a_m**2 + d_m**2)
    g = 3.0 * c * min(i_max - field_T / (2.0 * b), i_max / 2.0)
    return moment_Am2 * g / (3.0 * math.pi * viscosity_Pa_s * diameter_m) / diameter_m


@pytest.mark.parametrize("field_mT", [2.0, 4.0, 5.5])
def test_rig_pull_bound_is_what_the_coils_make(field_mT):
    """The planner's pull bound equals the closed form: larger would ask the coils for more than
    their 20 A, smaller would throw away pull. 2 mT: the z coils (gradients only) bind; 4 and
    5.5 mT (above 3.07 mT): the field's share of the x and y coils' current does."""
    physics = PairPhysics()
    rig = default_rig()
    expected = cube_pull_bound_bl_s(rig, field_mT * 1e-3, physics.moment_Am2,
                                    physics.viscosity_Pa_s, physics.body_diameter_mm * 1e-3)
    # (the code takes the gradients by central differences of the loop field: 1e-7 apart)
    assert rig_max_pull(rig, physics, field_mT) == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("name", ["pair-microfactory.json", "pair-formation-change.json"])
def test_example_plans_are_valid_and_end_at_their_goal(name):
    plan = load_plan(EXAMPLES / name)
    check(plan)
    d = plan.agents.body_diameter_mm
    from rigctl.plans.pair import plan_arrays, problem_of, state_of

    start, controls, dts = plan_arrays(plan)
    problem = problem_of(plan)
    expected = np.array([state_of(e, d) for e in plan.expected])
    states = assert_respects_constraints(problem, start, controls, dts, expected)
    assert goal_error(states[-1], state_of(plan.goal, d)) < plan.tolerance_bl


def test_check_refuses_an_expected_state_the_model_does_not_reach():
    """Each expected state is compared with one segment from the expected state before it, so a
    long plan is not refused for the open-loop chain's chaos, but a wrong entry is, by name."""
    plan = load_plan(EXAMPLES / "pair-microfactory.json")
    k = len(plan.expected) // 2
    wrong = plan.expected[k].model_copy(update={"r_bl": plan.expected[k].r_bl + 1e-3})
    bad = plan.model_copy(update={"expected": [*plan.expected[:k], wrong, *plan.expected[k + 1:]]})
    bad._source, bad._base_dir = plan._source, plan._base_dir
    with pytest.raises(PlanError, match=rf"expected\.{k}: "):
        check(bad)


def test_steer_along_follows_a_path_from_a_disturbed_start():
    """What joins the goal tree: new segments, each simulated from where the last really ended,
    through another path's states; from a start 0.1 BL off that path it still ends at the goal,
    every constraint kept (independent replay)."""
    from rigctl.plans.pair import steer_along

    plan = load_plan(EXAMPLES / "pair-formation-change.json")
    from rigctl.plans.pair import plan_arrays, problem_of, state_of

    problem = problem_of(plan)
    start, goal = plan_arrays(plan)[0], state_of(plan.goal, plan.agents.body_diameter_mm)
    path = plan_pair(problem, start, goal, PairPlannerOptions.paper(time_s=120, max_nodes=3000),
                     seed=4)
    begin = start + np.array([0.07, -0.07, 0.05, 0.03])
    steered = steer_along(problem, begin, path.states, PairPlannerOptions.fast(), final=goal)
    assert steered is not None
    states, controls, dts = steered
    replay = assert_respects_constraints(problem, begin, controls, dts, states)
    assert goal_error(replay[-1], goal) <= 0.15 + 1e-4
    assert dts.max() <= 0.6 + 1e-12


def test_check_refuses_a_pull_the_coils_cannot_make():
    plan = load_plan(EXAMPLES / "pair-formation-change.json")
    seg = plan.segments[0].model_copy(update={"psi_deg": 0.0, "f_x": 0.0, "f_y": 0.1})
    bad = plan.model_copy(update={"segments": [seg], "expected": None})
    with pytest.raises(PlanError, match=r"segments\.0: pull"):
        check(bad)


def test_cli_plans_and_checks(tmp_path, capsys):
    out = tmp_path / "p.json"
    code = main(["plan", "pair", "--workspace", str(EXAMPLES / "pair-formation-change-workspace.json"),
                 "--start", "7,6,2,0", "--goal", "9,7,2.5,40", "--seed", "1", "-o", str(out), "--json"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and summary["solved"]
    check(load_plan(out))
    assert main(["plan", "pair", "--check", '{"r": 2, "phi": 0, "psi_deg": 90}', "--json"]) == 1
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == {
        "rank": 2, "zero_radial_angle_deg": 54.7356}
    assert main(["plan", "pair", "--check", '{"r": 2, "phi": 0, "psi_deg": 30}', "--json"]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["rank"] == 3
    assert main(["plan", "pair", "--workspace", str(EXAMPLES / "pair-formation-change-workspace.json"),
                 "--start", "7,6,1.0,0", "--goal", "9,7,2.5,40", "-o", str(out)]) == 2


def test_samples_inside_an_obstacles_convex_hull_are_rejected():
    """A U-shaped obstacle: its notch is free space, but inside the hull, so no sample lands there."""
    from rigctl.plans.pair import PairRRT, hull_workspace
    from rigctl.plans.schema import parse_workspace
    from rigctl.plans.workspace import Workspace

    spec = parse_workspace({"boundary": {"rect": [0, 0, 20, 14]}, "obstacles": [
        {"polygon": [[5, 3], [15, 3], [15, 11], [13, 11], [13, 5], [7, 5], [7, 11], [5, 11]]}]})
    ws = Workspace.from_spec(spec)
    prob = PairProblem(ws, PairPhysics(), 1.5, 3.5, 0.6, sample_workspace=hull_workspace(spec))
    rrt = PairRRT(prob, PairPlannerOptions(goal_bias=0.0), np.random.default_rng(0))
    drawn = (rrt._sample(np.zeros(4), 1.0) for _ in range(400))
    samples = np.array([s for s in drawn if s is not None])
    p = agent_positions(samples) * prob.diameter_mm
    hull = ShapeWorkspace(("rect", (0, 0, 20, 14)), [("rect", (5, 3, 10, 8))])  # by hand
    assert len(samples) > 300 and hull.clearance(p).min() >= 0.5 - 1e-9
    assert ws.clearance(np.array([[10.0, 8.0]]))[0] > 0.5  # the notch itself is free
