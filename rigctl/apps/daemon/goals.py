"""The daemon's `plan_goals` (docs/click-a-goal.md): an operator clicks where agents should go, the
rig kind's own planner plans from where the daemon last saw them, and the plan is loaded like any
other, so the ordinary `execute` runs it and its run record keeps it.

Where the agents are: the daemon's latest tracking, which is where its last plan run left them
(the run's summary: the camera's last look in closed loop, else the emulator's ground truth), with
that plan's workspace, radii and separation (`Tracked`); after a pair formation, the two agents
and that plan's physics, which the pair planner plans with. An agent the request gives no goal keeps
its place as its goal (one input moves every agent: it must come back there).

Planning is CPU work of seconds: it runs in a process of its own (`PlannerProcess`, spawned at the
first request and kept, niced, so numba's compiled kernels are loaded once), waited on by a
thread of its own, so neither the command thread nor the stream waits for it; one request at a
time; past its deadline (the budget plus `START_GRACE_S`) the process is killed and the request
answered `deadline`. A goal that cannot be planned to is answered `unreachable` with the
planner's one line: outside the workspace, in an obstacle, too close to a wall or another goal,
or no path within the budget.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.apps.daemon.messages import ErrorCode, LoadArgs, Reply, error_reply
from rigctl.apps.daemon.states import Refusal, S
from rigctl.core.config import RigConfig
from rigctl.core.errors import PlanError

log = logging.getLogger(__name__)

START_GRACE_S = 30.0
"""Beyond its budget, how long a planning request may take before it is answered `deadline`: the
planning process's start and numba's first compile of the planner's kernels (5 s with a warm
disk cache on the 2-core CI machine; tens of seconds cold), the plan's replay and check."""

PLANNER_NICE = 5
"""The planning process's niceness: the stream and the daemon's own threads come first."""

CANNOT_PLAN = "this rig kind cannot plan to a clicked goal"


@dataclass(frozen=True)
class Tracked:
    """Where the daemon last saw the agents, and the floor they were on (a plan's)."""

    positions_mm: list[list[float]]
    source: str  # the run summary's positions_from
    run: str | None
    rig: str
    workspace: dict[str, Any]
    radii_mm: list[float]
    min_separation_mm: float
    tolerance_mm: float

    positions_px: list[list[float]] | None = None  # in the camera's pixels (a calibration's)
    plan_kind: str = "global-moves"
    template: dict[str, Any] | None = None  # a pair formation's plan document: its physics and bounds

    def as_dict(self) -> dict[str, Any]:
        """What `status` says of it (`tracked`): where the agents are, mm and px, and whence."""
        return {"positions_mm": self.positions_mm, "positions_px": self.positions_px,
                "radii_mm": self.radii_mm, "source": self.source, "run": self.run}


def tracked_after(plan: Any, summary: Any, calibration: Any = None) -> Tracked | None:
    """What a finished run says of where its agents are (in px too with the camera's
    `calibration`): None for a plan without agents on a floor (the arms' field sequences) or a
    summary without every position."""
    kind = getattr(plan, "kind", None)
    if kind not in ("global-moves", "pair-formation") or summary is None:
        return None
    finals = [a.final for a in summary.agents]
    count = 2 if kind == "pair-formation" else len(plan.agents)
    if len(finals) != count or any(f is None for f in finals):
        return None
    from rigctl.run.agents import portable_workspace

    positions = [[float(v) for v in f[:2]] for f in finals]
    px = None if calibration is None else _px(calibration, positions)
    if kind == "pair-formation":  # positions in mm; the plan's lengths in body diameters
        import json

        from rigctl.plans.schema import dump_plan

        d = float(plan.agents.body_diameter_mm)
        return Tracked(positions, summary.positions_from, summary.run, plan.rig,
                       portable_workspace(plan), [d / 2, d / 2], 0.0, float(plan.tolerance_bl) * d,
                       px, kind, json.loads(dump_plan(plan)))
    return Tracked(positions, summary.positions_from, summary.run, plan.rig,
                   portable_workspace(plan), [float(a.radius) for a in plan.agents],
                   float(plan.min_separation_mm), float(plan.tolerance_mm), px)


def planned_paths_mm(plan: dict[str, Any], starts_mm: list[Any]) -> list[list[list[float]]]:
    """Each agent's planned path (mm): its start, then where the plan expects it after every move
    (a pair formation: after every segment, from the formation's centroid, separation and
    heading)."""
    if plan["kind"] == "pair-formation":
        from rigctl.plans.pair import agent_positions

        d = float(plan["agents"]["body_diameter_mm"])
        states = [[s["x_mm"] / d, s["y_mm"] / d, s["r_bl"], np.radians(s["phi_deg"])]
                  for s in plan["expected"]]
        each = [(agent_positions(q) * d).round(4).tolist() for q in states]
    else:
        each = plan["expected"]
    return [[list(start)] + [state[i] for state in each] for i, start in enumerate(starts_mm)]


def _px(calibration: Any, points_mm: Any) -> list[list[float]]:
    points = np.asarray(points_mm, dtype=float).reshape(-1, 2)
    return np.round(calibration.to_px(points), 1).tolist() if len(points) else []


def _serve(conn: Any) -> None:
    """The planning process: (rig, problem) in, ("ok", GoalPlan) or ("refused"/"error", text)
    out, until None or the pipe closes."""
    try:
        os.nice(PLANNER_NICE)
    except OSError:
        pass
    from rigctl.core.registry import rig_kind

    while True:
        try:
            message = conn.recv()
        except EOFError:
            return
        if message is None:
            return
        rig, problem = message
        try:
            conn.send(("ok", rig_kind(rig.rig.kind).plan_goals(rig, problem)))
        except PlanError as err:
            conn.send(("refused", str(err)))
        except Exception as err:  # a bug in a planner: said, and the process serves on
            log.exception("planning to clicked goals failed")
            conn.send(("error", f"{type(err).__name__}: {err}"))


class PlannerProcess:
    """One planning process, spawned when first asked and kept; killed at a missed deadline."""

    def __init__(self) -> None:
        self._process: Any = None
        self._conn: Any = None

    def plan(self, rig: RigConfig, problem: Any, deadline_s: float) -> Any:
        """The rig kind's `plan_goals(rig, problem)` in the planning process: a `GoalPlan`;
        PlanError for a problem it refused, Refusal(DEADLINE) past `deadline_s`."""
        if self._process is None or not self._process.is_alive():
            context = multiprocessing.get_context("spawn")
            self._conn, child = context.Pipe()
            self._process = context.Process(target=_serve, args=(child,), name="rigctl-goals",
                                            daemon=True)
            self._process.start()
            child.close()
        conn = self._conn  # close() (a missed deadline, the daemon's shutdown) drops it
        try:
            conn.send((rig, problem))
            answered = conn.poll(deadline_s)
            if answered:
                kind, value = conn.recv()
        except (EOFError, OSError):
            self.close()
            raise Refusal(ErrorCode.INTERNAL, "plan_goals: the planning process died or the "
                          "daemon is stopping: nothing was loaded") from None
        if not answered:
            self.close()
            raise Refusal(ErrorCode.DEADLINE, f"plan_goals: no answer within {deadline_s:g} s "
                          "(the budget and the planner's start): nothing was loaded")
        if kind == "refused":
            raise PlanError(value)
        if kind == "error":
            raise Refusal(ErrorCode.INTERNAL, f"plan_goals: {value}")
        return value

    def close(self) -> None:
        process, self._process = self._process, None
        if process is not None and process.is_alive():
            process.kill()
            process.join(5)
        if self._conn is not None:
            self._conn.close()
            self._conn = None


class GoalPlanning:
    """The daemon's `plan_goals`: `daemon` is the `Daemon` (its rig, kind, state, lock, `load`)."""

    def __init__(self, daemon: Any) -> None:
        self.daemon = daemon
        self.tracked: Tracked | None = None
        self.planner = PlannerProcess()
        self._busy = threading.Lock()

    def saw_run(self, job: Any, summary: Any) -> None:
        """A run ended (the run thread): where it left the agents is the latest tracking."""
        try:
            camera = self.daemon.rig.camera
            tracked = tracked_after(getattr(job, "plan", None), summary,
                                    camera.calibration if camera is not None else None)
        except Exception:  # never let this fail a run's end
            log.exception("could not keep where the run left the agents")
            return
        if tracked is not None:
            self.tracked = tracked

    def status(self) -> dict[str, Any] | None:
        """`status`'s `tracked`: where the daemon last saw the agents (None: nowhere yet)."""
        tracked = self.tracked
        return None if tracked is None else tracked.as_dict()

    def answer_on_thread(self, answer: Callable[[], Reply], deliver: Callable[[Reply], None],
                         request_id: Any) -> None:
        """`plan_goals` answered from a thread of its own (the command thread sends the reply);
        a second request while one plans is answered `busy`."""
        if not self._busy.acquire(blocking=False):
            deliver(error_reply(request_id, ErrorCode.BUSY,
                                "plan_goals: another request is planning; retry when it is answered"))
            return
        daemon = self.daemon

        def work() -> None:
            try:
                reply = answer()
            finally:
                self._busy.release()
            daemon._deliveries.append(lambda: deliver(reply))
            daemon._wakeup.wake()

        threading.Thread(target=work, name="daemon-goals", daemon=True).start()

    def command(self, args: Any) -> dict[str, Any]:
        """Plan from the tracked positions to the goals, load the plan; its id, document, the
        planned paths (mm and, with a camera calibration, px) and where the agents start."""
        from rigctl.plans.goals import GoalProblem

        daemon = self.daemon
        with daemon._lock:
            daemon._require(S.IDLE, doing="plan to clicked goals")
            if daemon._active is not None:
                raise Refusal(ErrorCode.BUSY, "the last run is still stopping")
        if daemon.kind.plan_goals is None:
            raise Refusal(ErrorCode.UNREACHABLE, f"{CANNOT_PLAN} ({daemon.rig.rig.kind})")
        tracked = self.tracked
        if tracked is None:
            raise Refusal(ErrorCode.WRONG_STATE, "no tracked positions yet: the daemon knows where "
                          "the agents are once a plan has run on this rig")
        calibration = daemon.rig.camera.calibration if daemon.rig.camera is not None else None
        goals = [list(p) for p in tracked.positions_mm]
        for goal in args.goals:
            if goal.agent >= len(goals):
                raise Refusal(ErrorCode.BAD_ARGS, f"plan_goals: no agent #{goal.agent} (the "
                              f"daemon tracks {len(goals)}: #0-#{len(goals) - 1})")
            if goal.px is not None:
                if calibration is None:
                    raise Refusal(ErrorCode.BAD_ARGS, "plan_goals: a goal in px needs the rig's "
                                  "camera calibration (rigctl calibrate camera); give it in mm")
                goal_mm = calibration.to_mm(np.asarray([goal.px], dtype=float))[0]
            else:
                goal_mm = goal.mm
            if not np.all(np.isfinite(goal_mm)):  # a pixel far beyond the picture's horizon
                raise Refusal(ErrorCode.UNREACHABLE, f"plan_goals: the goal of agent "
                              f"#{goal.agent} at {goal.px} px is not on the floor")
            goals[goal.agent] = [round(float(v), 4) for v in goal_mm]
        problem = GoalProblem(
            rig=tracked.rig, workspace=tracked.workspace, starts_mm=tracked.positions_mm,
            goals_mm=goals, radii_mm=tracked.radii_mm,
            tolerance_mm=args.tolerance_mm if args.tolerance_mm is not None else tracked.tolerance_mm,
            min_separation_mm=tracked.min_separation_mm, seed=args.seed, budget_s=args.budget_s,
            plan_kind=tracked.plan_kind, template=tracked.template)
        started = time.monotonic()
        try:
            result = self.planner.plan(daemon.rig, problem, args.budget_s + START_GRACE_S)
        except PlanError as err:
            raise Refusal(ErrorCode.UNREACHABLE, f"plan_goals: {err}") from None
        if result.plan is None:
            raise Refusal(ErrorCode.UNREACHABLE, f"plan_goals: {result.reason}")
        loaded = daemon._cmd_load(LoadArgs(plan=result.plan))  # checked as any plan: kept loaded
        paths = planned_paths_mm(result.plan, tracked.positions_mm)
        log.info("plan_goals: plan %s (%s), %.3f mm from the goals, %.2f s", loaded["plan_id"],
                 result.plan["name"], result.distance_mm, time.monotonic() - started)
        reply = {**loaded, "plan": result.plan, "starts_mm": tracked.positions_mm,
                 "goals_mm": goals, "paths_mm": paths, "distance_mm": result.distance_mm,
                 "planner_s": round(result.seconds, 3), "tracked": tracked.as_dict()}
        if calibration is not None:
            reply["paths_px"] = [_px(calibration, p) for p in paths]
            reply["goals_px"] = _px(calibration, goals)
            reply["starts_px"] = _px(calibration, tracked.positions_mm)
        return reply
