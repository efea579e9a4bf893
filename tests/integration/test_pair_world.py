"""The two-agent world (seed 002) alone and on the emulated six-coil bench.

The world is a different model from the planner's: full 3-D dipole forces, moments along the local
field (coils + the other agent), the coils' field and gradient at each agent's own position. Near
the coils' centre both must agree; the reference values are the closed form r^5 = r0^5 + 5 K t
(side by side, psi = 90 deg) and the pull's definition f = F / (sigma D).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.emulators.world.pair import PairWorld
from rigctl.physics.coils import u_actuation_matrix
from rigctl.plans.pair import (
    PairPhysics,
    agent_positions,
    default_rig,
    state_from_positions,
)
from rigctl.plans.workspace import ShapeWorkspace
from rigctl.rigs.six_coil.allocate import currents_for_u, field_and_pull_u
from rigctl.rigs.six_coil.supplies import CoilSupplies

ROOT_EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
PHYSICS = PairPhysics()
RIG = default_rig()
A8 = u_actuation_matrix(RIG)
OPEN = ShapeWorkspace(("rect", (0, 0, 20, 14)), [])


def currents(psi_g, pull_bl_s=(0.0, 0.0), b0_T=2e-3):
    force = np.asarray(pull_bl_s) * PHYSICS.drag_N_s_per_m * PHYSICS.diameter_m
    return currents_for_u(A8, field_and_pull_u(psi_g, force, PHYSICS.moment_Am2, b0_T), RIG)


def run_world(q0, amps, seconds, workspace=OPEN, mismatch=None):
    world = PairWorld(workspace, agent_positions(np.asarray(q0)) * PHYSICS.body_diameter_mm,
                      PHYSICS, RIG, (10.0, 7.0), mismatch)
    for _ in range(int(round(seconds / 1e-3))):
        world.step(1e-3, amps)
    return world, state_from_positions(world.positions_mm / PHYSICS.body_diameter_mm)


def test_side_by_side_agents_repel_as_the_closed_form_says():
    world, q = run_world([10.0, 7.0, 2.0, 0.0], currents(math.pi / 2), 0.5)
    want = (2.0**5 + 5 * PHYSICS.rate_per_s * 0.5) ** 0.2
    assert q[2] == pytest.approx(want, rel=0.01)
    assert q[3] == pytest.approx(0.0, abs=1e-6)
    assert q[:2] == pytest.approx([10.0, 7.0], abs=1e-6)


def test_head_to_tail_agents_attract_until_they_touch():
    world, q = run_world([10.0, 7.0, 2.0, 0.0], currents(0.0), 1.0)
    assert q[2] == pytest.approx(1.0, abs=1e-3)  # in contact, not overlapping
    assert world.min_separation_mm >= 1.0 - 1e-3


@pytest.mark.parametrize("slip", [1.0, 0.6])
def test_the_gradient_pulls_the_centroid_at_the_planned_speed(slip):
    """slip: the agents' mobility against the plan's Stokes drag (a liquid 1/slip as viscous)."""
    from rigctl.emulators.world.rolling import Mismatch

    psi = math.radians(30)
    pull = (0.4, 0.2)  # BL/s, inside the box at 30 deg: 0.4 <= p cos 30, 0.2 <= p sin 30
    world, q = run_world([10.0, 7.0, 3.0, math.pi / 2], currents(psi, pull), 0.5,
                         mismatch=Mismatch(slip=slip))
    # far apart (r = 3) the pair barely moves relative to itself; the centroid moves slip f t
    assert q[:2] == pytest.approx([10.0 + 0.2 * slip, 7.0 + 0.1 * slip], abs=0.01)


def test_walls_stop_the_agents():
    wall = ShapeWorkspace(("rect", (0, 0, 20, 14)), [("rect", (11.0, 0, 1, 14))])
    world, q = run_world([10.0, 7.0, 2.5, math.pi / 2], currents(0.0, (0.6, 0.0)), 1.5, wall)
    assert world.positions_mm[:, 0].max() <= 10.5 + 1e-9
    assert world.contacts > 0


@pytest.fixture
def bench():
    with SixCoilBench(world="pair") as b:
        yield b


def test_bench_moves_the_agents_with_the_currents_the_supplies_make(bench):
    """Through the real driver stack: SCPI over TCP to the emulated supplies, R-L coils, world."""
    backdoor = BackdoorClient(bench.rig.emulation.backdoor)
    start = agent_positions(np.array([10.0, 7.0, 2.0, 0.0]))
    workspace = {"boundary": {"rect": [0, 0, 20, 14]}, "obstacles": []}
    backdoor.request("place", workspace=workspace,
                     agents=[{"position": p.tolist(), "radius": 0.5} for p in start],
                     pair={"body_diameter_mm": 1.0, "moment_Am2": PHYSICS.moment_Am2,
                           "viscosity_Pa_s": PHYSICS.viscosity_Pa_s})
    supplies = CoilSupplies.connect(bench.rig)
    try:
        supplies.energise()
        amps = currents(math.pi / 2)
        supplies.cycle(amps)
        t0 = backdoor.request("truth")["sim_time_s"]
        wait_for(lambda: backdoor.request("truth")["sim_time_s"] > t0 + 0.6, timeout_s=20,
                 what="0.6 s of simulated time")
        truth = backdoor.request("truth")
        supplies.cycle(np.zeros(6))
    finally:
        supplies.stop(ramp_s=0.0)
        backdoor.close()
    measured = np.array([truth["currents_A"][c.name] for c in bench.rig.coils])
    np.testing.assert_allclose(measured, amps, atol=0.05)
    p = np.array(truth["agents"])
    q = state_from_positions(p)
    # side by side they repel; the coils take ~0.1 s (5 L/R) to reach the field, so r is
    # between the 0.5 s and 0.6 s closed-form values
    lo = (2.0**5 + 5 * PHYSICS.rate_per_s * 0.4) ** 0.2
    hi = (2.0**5 + 5 * PHYSICS.rate_per_s * (truth["sim_time_s"] - t0 + 0.05)) ** 0.2
    assert lo - 0.02 <= q[2] <= hi + 0.02
    assert abs(math.remainder(q[3], math.pi)) < 0.02
    moments = np.array(truth["moments_Am2"])
    np.testing.assert_allclose(np.linalg.norm(moments, axis=1), PHYSICS.moment_Am2, rtol=1e-9)
    assert abs(moments[0, 0]) < 0.02 * PHYSICS.moment_Am2  # along the field: +y


def run_closed_loop(plan_name, *, offset_bl=(0.0, 0.0), noise_bl=0.01, max_s=60.0, seed=1,
                    mismatch=None, identify=None):
    """The tracking controller on the world in this process (no camera): frames every 16 ms,
    measured with Gaussian noise and 30 ms late, currents through the allocation; `identify`, a
    `PullIdentification`, is given every frame and every pull sent, and the pursuit pursues with
    its estimate."""
    from rigctl.plans.pair import (
        physics_of,
        plan_arrays,
        problem_of,
        rig_max_pull,
        state_of,
    )
    from rigctl.plans.schema import load_plan
    from rigctl.rigs.six_coil.pursuit import (
        PairPursuit,
        PursuitSettings,
        distance_to_path,
    )

    plan = load_plan(Path(__file__).resolve().parents[2] / "plans" / "examples" / plan_name)
    physics = physics_of(plan)
    d = physics.body_diameter_mm
    start = plan_arrays(plan)[0]
    expected = [state_of(e, d) for e in plan.expected]
    nodes = np.vstack([start[None], expected, state_of(plan.goal, d)[None]])
    problem = problem_of(plan)
    pursuit = PairPursuit(problem, nodes, PursuitSettings(
        max_pull=0.95 * rig_max_pull(RIG, physics, plan.field_mT)))
    bounds = np.array(problem.workspace.bounds)
    begin = agent_positions(start) + np.array([[offset_bl[0], offset_bl[1]], [0.0, 0.0]])
    world = PairWorld(problem.workspace, begin * d, physics, RIG, 0.5 * (bounds[:2] + bounds[2:]),
                      mismatch)
    rng = np.random.default_rng(seed)
    amps, frames, errors, modes, held = np.zeros(6), [], [], [], 0.0
    for step in range(int(max_s / 1e-3)):
        t = step * 1e-3
        if step % 16 == 0:
            frames.append((t, world.positions_mm / d + rng.normal(0.0, noise_bl, (2, 2))))
            seen = [f for f in frames if f[0] <= t - 0.03]
            if seen:
                t_seen, p = seen[-1]
                if identify is not None and identify.frame(t_seen, p * d):
                    pursuit.set_pull_response(*identify.response())
                q = pursuit.carry_forward(state_from_positions(p), t - t_seen)
                u = pursuit.decide(q)
                if identify is not None:
                    identify.send(t, u[1:])
                modes.append(pursuit.mode)
                force = u[1:] * physics.drag_N_s_per_m * physics.diameter_m
                amps = currents_for_u(A8, field_and_pull_u(
                    u[0], force, physics.moment_Am2, plan.field_mT * 1e-3), RIG)
                truth = world.positions_mm / d
                errors.append(distance_to_path(truth, pursuit.paths))
                if pursuit.mode == "hold":
                    held += 0.016
                    if held > 2.0:
                        break
        world.step(1e-3, amps)
    final = state_from_positions(world.positions_mm / d)
    return plan, nodes, np.array(errors), modes, world, final


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_pursuit_tracks_the_formation_change_and_holds_the_goal(seed):
    """The issue's goals, for several draws of the camera noise: RMS distance of the true agents
    to the path <= 0.1 BL, the goal held within its tolerance, no separation violation."""
    from rigctl.plans.pair import goal_error

    plan, nodes, errors, modes, world, final = run_closed_loop("pair-formation-change.json",
                                                               seed=seed)
    assert modes[-1] == "hold"
    assert float(np.sqrt(np.mean(errors**2))) <= 0.1  # ground truth's distance to the path, BL
    assert goal_error(final, nodes[-1]) <= plan.tolerance_bl
    assert world.min_separation_mm / plan.agents.body_diameter_mm > plan.r_min_bl - 0.1


def test_the_pull_gain_is_identified_from_tracking_and_pursued_with():
    """Agents 0.6 times as mobile as the plan's drag says (a liquid 1/0.6 as viscous): the
    centroid's motion against the pull commanded gives 0.6, and the run still reaches the goal."""
    from rigctl.emulators.world.rolling import Mismatch
    from rigctl.plans.pair import goal_error, problem_of
    from rigctl.plans.schema import load_plan
    from rigctl.rigs.six_coil.pair import PullIdentification

    plan = load_plan(ROOT_EXAMPLES / "pair-formation-change.json")
    identify = PullIdentification(plan.agents.body_diameter_mm, problem_of(plan).workspace, 0.5)
    plan, nodes, errors, modes, world, final = run_closed_loop(
        "pair-formation-change.json", mismatch=Mismatch(slip=0.6), identify=identify)
    estimate = identify.identifier.summary()
    assert estimate["moves_used"][0] >= 8
    assert estimate["gain"][0] == pytest.approx(0.6, abs=max(0.05, 3 * estimate["gain_std"][0]))
    assert abs(estimate["heading_deg"][0]) < 5.0
    assert modes[-1] == "hold" and goal_error(final, nodes[-1]) <= plan.tolerance_bl


def test_the_pursuit_commands_the_inverse_of_the_identified_response():
    from rigctl.plans.pair import problem_of
    from rigctl.plans.schema import load_plan
    from rigctl.rigs.six_coil.pursuit import PairPursuit, PursuitSettings

    plan = load_plan(ROOT_EXAMPLES / "pair-formation-change.json")
    pursuit = PairPursuit(problem_of(plan), np.zeros((2, 4)), PursuitSettings(max_pull=1.0))
    psi = math.radians(40)
    pursuit.set_pull_response(0.5, 0.0)  # the agents do half what they are told: ask twice
    assert pursuit.commanded(np.array([psi, 0.2, 0.1])) == pytest.approx([psi, 0.4, 0.2])
    pursuit.set_pull_response(1.0, math.pi / 2)  # they move 90 deg to the left of the pull
    assert pursuit.commanded(np.array([psi, 0.2, 0.1])) == pytest.approx([psi, 0.1, -0.2])
    pursuit.set_pull_response(0.25, 0.0)  # beyond the coils' box at psi: clipped to it
    assert pursuit.commanded(np.array([psi, 0.4, 0.4])) == pytest.approx(
        [psi, math.cos(psi), math.sin(psi)])


def test_proximity_controller_brings_strayed_agents_back_to_the_path():
    plan, nodes, errors, modes, world, final = run_closed_loop(
        "pair-formation-change.json", offset_bl=(-0.8, 0.5), max_s=6.0)
    assert modes[0] == "proximity" and errors[0].max() > 0.6
    back = modes.index("pursuit")
    assert errors[back:].max() < 0.45  # never strays that far again once back


def test_a_frozen_camera_holds_the_agents_unseen_and_the_run_resumes(tmp_path):
    """The camera freezes mid-run: the run suspends (no pull, field flipped about the zero-radial
    angle), the agents stay apart, and when frames come again it resumes and reaches the goal."""
    import json
    import threading
    from pathlib import Path

    from rigctl.apps.cli.main import main
    from rigctl.apps.testing import wait_for
    from rigctl.core.config import StreamSettings
    from rigctl.plans.schema import load_plan
    from rigctl.rigs.six_coil.pair import PairRun

    workspace = Path(__file__).resolve().parents[2] / "plans" / "examples" / \
        "pair-formation-change-workspace.json"
    plan_file = tmp_path / "short.json"
    assert main(["plan", "pair", "--workspace", str(workspace), "--start", "8,7,2,0", "--goal",
                 "9.5,7.5,2.6,60", "--seed", "2", "--hold", "1", "-o", str(plan_file)]) == 0
    plan = load_plan(plan_file)
    with SixCoilBench(world="pair") as bench:
        # the supplies' reply watchdog is not under test: bench and run share this process
        rig = bench.rig.model_copy(update={"stream": StreamSettings(reply_timeout_s=1.0)})
        run = PairRun(plan, rig, runs_dir=tmp_path / "runs")
        result = {}
        thread = threading.Thread(target=lambda: result.setdefault("summary", run.execute()))
        thread.start()

        def events():
            files = list((tmp_path / "runs").glob("*/events.jsonl"))
            if not files:
                return []
            return [json.loads(line)["event"] for line in files[0].read_text().splitlines()
                    if line.endswith("}")]

        try:
            wait_for(lambda: events().count("track") >= 30, timeout_s=60, what="30 tracked frames")
            with BackdoorClient(bench.rig.emulation.backdoor) as backdoor:
                backdoor.request("camera", kind="freeze")
                wait_for(lambda: "suspend" in events(), timeout_s=20, what="the run to suspend")
                backdoor.request("camera", kind="restore")
        finally:
            thread.join(120)
    summary = result["summary"]
    assert not summary.faults and summary.reached
    seen = events()
    assert seen.index("suspend") < seen.index("resume")
    assert summary.metrics["truth_min_separation_bl"] >= plan.r_min_bl - 0.15
