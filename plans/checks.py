"""What a plan means beyond its schema: the geometry and model it runs under, the states the model
expects (`simulate`), and the checks that refuse it (`check_plan`), each naming the field."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rigctl.core.errors import PlanError
from rigctl.plans.model import Contact, GlobalInputModel
from rigctl.plans.schema import REPLAY_TOLERANCE_MM, GlobalMovesPlan, load_workspace
from rigctl.plans.workspace import Workspace


def contact_for_rig(rig: str) -> Contact:
    """How agents meet walls on a rig kind: its `RigKind.wall_contact` (rolling magnets slide,
    particles stick), asked of the registry."""
    from rigctl.core.registry import kinds

    found = kinds().get(rig)
    if found is None or found.wall_contact is None:
        runs = sorted(n for n, k in kinds().items() if k.wall_contact is not None)
        raise PlanError(f"rig {rig!r} runs no global-moves plans (expected one of {', '.join(runs)})")
    return found.wall_contact


def plan_workspace(plan: GlobalMovesPlan):
    """The plan's workspace geometry (`rigctl.plans.workspace.Workspace`)."""
    return Workspace.from_spec(plan.workspace, base_dir=plan.base_dir)


def plan_model(plan: GlobalMovesPlan, workspace=None):
    """The global-input model a plan runs under: its workspace, radii, rig contact and separation."""
    return GlobalInputModel(
        workspace if workspace is not None else plan_workspace(plan),
        [agent.radius for agent in plan.agents],
        contact=contact_for_rig(plan.rig),
        min_separation_mm=plan.min_separation_mm,
    )


def simulate(plan: GlobalMovesPlan) -> GlobalMovesPlan:
    """A copy of the plan with `expected` filled in by the global-input model (other kinds: by
    their own planner's model)."""
    if plan.kind != "global-moves":
        module = _kind_module(plan)
        if module is None:
            raise PlanError(f"{plan.kind}: no model here fills a {plan.kind} plan's states "
                            "(--simulate is for the planners' kinds)")
        return module.simulate(plan)
    model = plan_model(plan)
    start = np.array([agent.start for agent in plan.agents], dtype=float)
    states = model.rollout(start, np.array(plan.moves, dtype=float).reshape(-1, 2))
    expected = [[(float(x), float(y)) for x, y in state] for state in states]
    copy = plan.model_copy(update={"expected": expected})
    copy._source, copy._base_dir = plan._source, plan._base_dir
    return copy


def check_placement(workspace, points: np.ndarray, radii: np.ndarray, gap_mm: float,
                    field: Callable[[int], str], agent: Callable[[int], str]) -> None:
    """PlanError unless every agent (points (n, 2) mm, radii (n,) mm) lies in free space, at least
    its radius from every surface, and no two centres are closer than r_i + r_j + gap_mm;
    `field(i)` names where agent i was given, `agent(i)` the agent."""
    clearance = workspace.clearance(points)
    for index, (point, room, radius) in enumerate(zip(points, clearance, radii)):
        if room < radius - 1e-9:
            where = "inside a wall or outside the boundary" if room < 0 else "too close to a wall"
            raise PlanError(f"{field(index)}: ({point[0]:g}, {point[1]:g}) is {where} "
                            f"(clearance {room:.3f} mm, radius {radius:g} mm)")
    for i in range(len(points)):
        for j in range(i + 1, len(points)):
            distance = float(np.hypot(*(points[j] - points[i])))
            need = radii[i] + radii[j] + gap_mm
            if distance < need - 1e-9:
                raise PlanError(f"{field(j)}: overlaps {agent(i)} (centres {distance:.3f} mm "
                                f"apart, need {need:g} mm)")


def check_plan(plan: GlobalMovesPlan) -> None:
    """Geometric checks beyond the schema; raises PlanError naming the field.

    Starts and goals lie in free space (at least the agent's radius from every surface), agents do
    not overlap at start or at goal, `expected` has one entry per move with one position per agent,
    and replaying the moves through the model reproduces `expected` within 1e-6 mm. Other kinds
    are checked by their own planner's module (`_kind_module(plan).check`).
    """
    if plan.kind != "global-moves":
        module = _kind_module(plan)
        # an installed rig kind's own plan kind (`RigKind.plan_models`): its builder and the
        # pre-flight certificate check it, as they do every plan
        return None if module is None else module.check(plan)
    source = plan.source
    if not plan.moves:
        raise PlanError(f"{source}: moves: empty; a plan makes at least one move")
    workspace = plan_workspace(plan)
    model = plan_model(plan, workspace)
    radii = model.radii
    for field in ("start", "goal"):
        points = np.array([getattr(agent, field) for agent in plan.agents], dtype=float)
        check_placement(workspace, points, radii, plan.min_separation_mm,
                        lambda i, f=field: f"{source}: agents.{i}.{f}", lambda i: f"agent {i}")
    if plan.expected is None:
        return
    if len(plan.expected) != len(plan.moves):
        raise PlanError(
            f"{source}: expected: has {len(plan.expected)} entries for {len(plan.moves)} moves "
            "(one per move)"
        )
    for index, state in enumerate(plan.expected):
        if len(state) != len(plan.agents):
            raise PlanError(
                f"{source}: expected.{index}: has {len(state)} positions for "
                f"{len(plan.agents)} agents"
            )
    start = np.array([agent.start for agent in plan.agents], dtype=float)
    replay = model.rollout(start, np.array(plan.moves, dtype=float).reshape(-1, 2))
    expected = np.array(plan.expected, dtype=float)
    error = np.hypot(*(replay - expected).transpose(2, 0, 1))  # (moves, agents)
    bad = np.argwhere(error > REPLAY_TOLERANCE_MM)
    if len(bad):
        move, agent = bad[0]
        got = replay[move, agent]
        raise PlanError(
            f"{source}: expected.{move}.{agent}: the model puts agent {agent} at "
            f"({got[0]:.6f}, {got[1]:.6f}) after move {move}, {error[move, agent]:.3g} mm from "
            "expected"
        )


def _kind_module(plan):
    """The planner module that owns a plan kind's semantics (`check`, `simulate`)."""
    import importlib

    modules = {"field-sequence": "rigctl.plans.depm", "pair-formation": "rigctl.plans.pair"}
    return importlib.import_module(modules[plan.kind]) if plan.kind in modules else None


class WorkspaceSource:
    """A workspace document read from disk: its spec, folder (for image paths) and hash."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)
        try:
            self.spec = load_workspace(self.path)  # a whole plan: its workspace
        except PlanError as err:
            raise PlanError(f"--workspace: {err}") from None
        self.base_dir = self.path.resolve().parent
        self.document = self.spec.model_dump(mode="json", exclude_none=True)
        self.image_path = None
        if "image" in self.document:
            self.image_path = (self.base_dir / self.document["image"]).resolve()
        self.hash = self._hash()

    def _hash(self) -> str:
        content = dict(self.document)
        if self.image_path is not None:
            try:
                content["image"] = hashlib.sha256(self.image_path.read_bytes()).hexdigest()
            except OSError as err:
                raise PlanError(f"--workspace: image {self.image_path}: {err.strerror}") from None
        canonical = json.dumps(content, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()

    def workspace(self):
        return Workspace.from_spec(self.spec, base_dir=self.base_dir)

    def document_for(self, plan_path: Path) -> dict:
        """The workspace document as a plan written at `plan_path` must spell it (image path
        relative to the plan's folder)."""
        document = dict(self.document)
        if self.image_path is not None:
            document["image"] = os.path.relpath(self.image_path, plan_path.resolve().parent)
        return document
