"""Click a goal (issue 39 item 2) through `rigctl daemon` on the emulated six-coil bench, both as
processes: after a short run the daemon knows where the magnets are; `plan_goals` plans from there
to goals given in mm (the RRT in the daemon's planning process), the plan is loaded and the
ordinary `execute` runs it in closed loop; the run record keeps the plan, and the bench's ground
truth (its backdoor, not the daemon) puts every magnet within the plan's tolerance of the goal
asked for. Goals in an obstacle or outside the workspace are refused `unreachable` with the
reason, nothing loaded."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from rigctl.apps.client import CommandRefused, Rig
from rigctl.apps.testing import plan_pair, wait_for
from rigctl.core.config import dump_rig, load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from tests.browser.pages import PATIENT_REPLY_S
from tests.e2e.test_daemon_cli import DaemonProcess

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"


def first_plan() -> dict:
    """fig4-quick's workspace and magnets, one roll of one turn towards -y (a second of rolling):
    the run that tells the daemon where the magnets are."""
    plan = json.loads((EXAMPLES / "fig4-quick.json").read_text())
    plan["name"] = "one turn down"
    plan["moves"] = [[0.0, -10.0]]
    ends = [[a["start"][0], a["start"][1] - 10.0] for a in plan["agents"]]
    plan["expected"] = [ends]
    for agent, end in zip(plan["agents"], ends):
        agent["goal"] = end
    return plan


@pytest.fixture(scope="module")
def bench_and_daemon(tmp_path_factory):
    folder = tmp_path_factory.mktemp("click-goal")
    with EmulatedBenchProcess("six-coil", folder / "bench.toml") as bench_path:
        # the devices' reply watchdog as the browser tests have it (a loaded machine is not what
        # this test is about)
        rig = load_rig(bench_path)
        rig_path = folder / "patient-bench.toml"
        rig_path.write_text(dump_rig(rig.model_copy(update={"stream": rig.stream.model_copy(
            update={"reply_timeout_s": max(rig.stream.reply_timeout_s, PATIENT_REPLY_S)})})))
        daemon = DaemonProcess(rig_path, folder / "runs", folder / "daemon.log")
        try:
            with Rig(daemon.endpoints["command"], timeout_s=30.0) as rig, \
                    BackdoorClient(load_rig(rig_path).emulation.backdoor) as backdoor:
                yield rig, backdoor, daemon
        finally:
            daemon.close()


def run_to_end(rig: Rig, plan_id: str) -> dict:
    rig.execute(plan_id)
    rig.wait_state("running", "idle", timeout_s=60.0)
    rig.wait_state("idle", timeout_s=120.0)
    # the run thread keeps the summary (and where the agents are) as the run ends
    wait_for(lambda: rig.status()["run"] is None, 30.0, "the run ended")
    return rig.status()


def test_before_any_run_the_daemon_says_it_does_not_know_where_the_agents_are(bench_and_daemon):
    rig, _, _ = bench_and_daemon
    with pytest.raises(CommandRefused) as refused:
        rig.plan_goals({0: [220.0, 250.0]})
    assert refused.value.code == "wrong_state"
    assert "no tracked positions yet" in refused.value.reason


def test_a_clicked_goal_is_planned_loaded_executed_recorded_and_reached(bench_and_daemon):
    rig, backdoor, _ = bench_and_daemon
    first = run_to_end(rig, rig.load(first_plan()))
    assert first["last_run"]["reached"], first["last_run"]
    truth = backdoor.request("truth")["agents"]
    # both magnets two turns up from where the first run left them (the plan's own ends, not
    # what the daemon saw): one clicked goal each
    goals = {i: [x, y + 20.0] for i, (x, y) in enumerate(first_plan()["expected"][-1])}
    planned = rig.plan_goals(goals, seed=0, budget_s=5.0)
    plan = planned["plan"]
    assert plan["kind"] == "global-moves" and plan["rig"] == "six-coil"
    assert [a["goal"] for a in plan["agents"]] == [goals[0], goals[1]]
    # the plan starts where the daemon last saw the magnets: the camera's last look, which the
    # bench's truth confirms to a fifth of a radius (the tracker's accuracy at rest)
    for start, real in zip(planned["starts_mm"], truth):
        assert math.dist(start, real) < 0.2 * 8.0, (planned["starts_mm"], truth)
    # the paths to draw: from each start through every planned state to the goal's neighbourhood
    for i, path in enumerate(planned["paths_mm"]):
        assert path[0] == planned["starts_mm"][i]
        assert len(path) == len(plan["moves"]) + 1
        assert math.dist(path[-1], goals[i]) <= plan["tolerance_mm"]
    assert len(planned["paths_px"]) == 2  # the bench's camera is calibrated: pixels too
    assert planned["plan_id"] in rig.status()["plans"]

    status = run_to_end(rig, planned["plan_id"])
    last = status["last_run"]
    assert last["plan_id"] == planned["plan_id"] and last["reached"], last
    record = Path(last["run"])
    kept = json.loads((record / "plan.json").read_text())
    assert kept["moves"] == plan["moves"]
    assert [a["goal"] for a in kept["agents"]] == [goals[0], goals[1]]
    # ground truth, from the bench: every magnet within the plan's tolerance of its clicked goal
    truth = backdoor.request("truth")["agents"]
    for i, real in enumerate(truth):
        assert math.dist(real, goals[i]) <= plan["tolerance_mm"], (truth, goals)


@pytest.mark.parametrize("goal, reason", [
    ([200.0, 160.0], "in an obstacle"),
    ([500.0, 200.0], "outside the workspace"),
    ([220.0, 55.0], "too close to a wall"),
])
def test_an_unreachable_goal_says_why_and_loads_nothing(bench_and_daemon, goal, reason):
    rig, _, _ = bench_and_daemon
    if rig.status()["last_run"] is None:
        run_to_end(rig, rig.load(first_plan()))
    plans = rig.status()["plans"]
    with pytest.raises(CommandRefused) as refused:
        rig.plan_goals({0: goal}, budget_s=1.0)
    assert refused.value.code == "unreachable"
    assert reason in refused.value.reason and "goal of agent #0" in refused.value.reason
    assert rig.status()["plans"] == plans


def test_after_a_pair_formation_the_clicked_goals_are_a_formation_the_pair_planner_reaches(
        tmp_path):
    """The six-coil bench's pair world: a short formation change, then both agents clicked a
    millimetre further on (the same formation moved): planned by the pair planner with the first
    plan's physics, executed in closed loop, reached by the bench's ground truth."""
    first = json.loads(plan_pair(tmp_path, goal="9.5,7.5,2.6,60", hold_s=0.5).read_text())
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml",
                              extra_args=["--world", "pair"]) as rig_path:
        daemon = DaemonProcess(rig_path, tmp_path / "runs", tmp_path / "daemon.log")
        try:
            with Rig(daemon.endpoints["command"], timeout_s=30.0) as rig, \
                    BackdoorClient(load_rig(rig_path).emulation.backdoor) as backdoor:
                status = run_to_end(rig, rig.load(first))
                assert status["last_run"]["reached"], status["last_run"]
                here = status["tracked"]["positions_mm"]
                goals = {i: [x + 1.0, y] for i, (x, y) in enumerate(here)}
                planned = rig.plan_goals(goals, budget_s=10.0)
                plan = planned["plan"]
                assert plan["kind"] == "pair-formation" and plan["segments"]
                assert plan["agents"] == first["agents"] and plan["r_min_bl"] == first["r_min_bl"]
                status = run_to_end(rig, planned["plan_id"])
                assert status["last_run"]["plan_id"] == planned["plan_id"]
                assert status["last_run"]["reached"], status["last_run"]
                tolerance_mm = plan["tolerance_bl"] * plan["agents"]["body_diameter_mm"]
                truth = backdoor.request("truth")["agents"]
                for i, real in enumerate(truth):
                    assert math.dist(real, goals[i]) <= tolerance_mm, (truth, goals)
        finally:
            daemon.close()
