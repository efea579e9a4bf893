"""The daemon's planning process for clicked goals (rigctl/apps/daemon/goals.py): a request not
answered within its deadline is refused `deadline` and the process is killed, not left planning
on a shared machine; the next request starts a fresh one."""

from __future__ import annotations

import json
import multiprocessing
from pathlib import Path

import pytest

from rigctl.apps.daemon.goals import PlannerProcess
from rigctl.apps.daemon.messages import ErrorCode
from rigctl.apps.daemon.states import Refusal
from rigctl.core.registry import rig_kind
from rigctl.plans.goals import GoalProblem

FIG4 = json.loads((Path(__file__).resolve().parents[2] / "plans" / "examples"
                   / "fig4-quick.json").read_text())


def test_a_missed_deadline_kills_the_planning_process_and_says_so():
    rig = rig_kind("six-coil").bench_rig()
    problem = GoalProblem(rig="six-coil", workspace=FIG4["workspace"],
                          starts_mm=[[220.0, 230.0], [100.0, 230.0]],
                          goals_mm=[[220.0, 250.0], [100.0, 250.0]], radii_mm=[8.0, 8.0])
    planner = PlannerProcess()
    try:
        # a process that has not even imported the planner by then cannot answer
        with pytest.raises(Refusal) as refused:
            planner.plan(rig, problem, 0.05)
        assert refused.value.code is ErrorCode.DEADLINE
        assert "nothing was loaded" in str(refused.value)
        assert not [p for p in multiprocessing.active_children() if p.name == "rigctl-goals"]
    finally:
        planner.close()
