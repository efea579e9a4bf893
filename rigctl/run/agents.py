"""The agents of a run on a plane (magnets, particles, a pair): placing them on an emulated bench
(the workspace sent to another process), reading the bench's ground truth, and each agent's result
against its goal as the summary shows it."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rigctl.core.errors import RigError
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.plans.schema import FieldSequencePlan, Plan
from rigctl.run.summary import AgentResult

if TYPE_CHECKING:
    from rigctl.run.engine import RunContext

log = logging.getLogger(__name__)


def portable_workspace(plan: Plan) -> dict[str, Any]:
    """The plan's workspace as JSON for another process: an image path made absolute."""
    if isinstance(plan, FieldSequencePlan):  # the arms' plans: a field at one point, no floor
        raise ValueError(f"a {plan.kind} plan has no workspace to lay down")
    workspace = plan.workspace.model_dump(mode="json", exclude_none=True)
    if "image" in workspace and plan.base_dir is not None:
        workspace["image"] = str((Path(plan.base_dir) / workspace["image"]).resolve())
    return workspace


def place_agents(ctx: RunContext, plan: Plan, agents: list[dict[str, Any]],
                 **extra: object) -> None:
    """On an emulated bench (`ctx.backdoor`, a `RunContext`'s): put `agents` ({"position": [x, y]
    mm, "radius": mm}) in the plan's workspace and record where; nothing without a bench."""
    if ctx.backdoor is None:
        return
    ctx.backdoor.request("place", workspace=portable_workspace(plan), agents=agents, **extra)
    ctx.record.event("placed", agents=[list(a["position"]) for a in agents])


def truth_of(backdoor: BackdoorClient | None) -> np.ndarray:
    """The bench's true agent positions (n, 2) mm; RigError without a bench or an answer."""
    if backdoor is None:
        raise RigError("no emulator backdoor", device="bench backdoor")
    return np.array(backdoor.request("truth")["agents"], dtype=float)


def read_truth(backdoor: BackdoorClient | None) -> dict[str, Any] | None:
    """The bench's whole `truth` answer, None without a bench or if it failed (logged): a run
    that ends must not fail for want of it."""
    if backdoor is None:
        return None
    try:
        return backdoor.request("truth")
    except RigError as err:
        log.error("could not read ground truth: %s", err)
        return None


def agent_results(goals_mm: np.ndarray, camera_mm: np.ndarray | None,
                  truth: dict[str, Any] | None, *,
                  scale_mm: float = 1.0, unit: str = "mm") -> tuple[list[AgentResult], str]:
    """Each agent's final position and error against its goal (goals, camera: (n, 2) mm; truth:
    the bench's answer, `read_truth`; errors in `unit`, `scale_mm` mm each), and where the
    positions came from: the camera's last look, with ground truth's error beside it on an
    emulated bench; else ground truth itself."""
    truth_mm = None if truth is None else np.array(truth["agents"], dtype=float)
    final = camera_mm if camera_mm is not None else truth_mm
    beside = truth_mm if camera_mm is not None else None
    goals = np.asarray(goals_mm, dtype=float)

    def errors(p: np.ndarray | None) -> list[float | None]:
        return [None] * len(goals) if p is None else [
            round(float(e) / scale_mm, 4) for e in np.hypot(*(np.asarray(p) - goals).T)]

    results = [AgentResult(None if final is None else [round(float(v), 4) for v in final[i]],
                           goals[i].round(4).tolist(), error, truth_error, unit)
               for i, (error, truth_error) in enumerate(zip(errors(final), errors(beside)))]
    if camera_mm is None:
        return results, "unknown" if truth_mm is None else "emulator ground truth"
    return results, "camera (closed loop)" + (
        "" if truth_mm is None else f"; emulator ground truth in truth_error_{unit}")
