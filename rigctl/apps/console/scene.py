"""What the console draws of a rig, as plain geometry: one of two scenes, as its rig kind says
(`RigKind.scene`).

"camera": the browser draws pixels; `CameraScene` turns the plan's millimetres into the camera's
pixels with the rig's own calibration (`Calibration.to_px`, lens distortion included), so an
overlay lands where the tracker measures. Every shape becomes a polygon first (a disk:
`DISK_VERTICES` corners), because a rectangle on the floor is a quadrilateral, not a rectangle, in
a tilted camera's picture.

"arms": a rig of arms and no camera; `ArmsSketch` gives every arm's joint origins, its magnet and
the keep-out sphere in mm, from the arms' measured joints and the arms' kinematics at the bases
the kind's `scene_of` names, for a top and a side view.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rigctl.core.config import RigConfig

DISK_VERTICES = 32


def shape_polygon_mm(shape: dict) -> list[list[float]]:
    """A plan shape (`{"rect": [x, y, w, h]}`, `{"polygon": [[x, y], ...]}`, `{"disk": [cx, cy,
    r]}`, mm) as its polygon's vertices, mm."""
    if "rect" in shape:
        x, y, w, h = shape["rect"]
        return [[x, y], [x + w, y], [x + w, y + h], [x, y + h]]
    if "polygon" in shape:
        return [list(map(float, p)) for p in shape["polygon"]]
    if "disk" in shape:
        cx, cy, r = shape["disk"]
        return [[cx + r * math.cos(a), cy + r * math.sin(a)]
                for a in np.linspace(0.0, 2 * math.pi, DISK_VERTICES, endpoint=False).tolist()]
    raise ValueError(f"not a plan shape: {sorted(shape)}")


def plan_paths_mm(plan: dict) -> list[list[list[float]]] | None:
    """Each agent's planned path (n_agents, n_moves + 1, 2) mm: its start, then where the plan
    expects it after each move; None for a plan without positions per move."""
    agents = plan.get("agents")
    expected = plan.get("expected")
    if not isinstance(agents, list) or not expected:
        return None
    try:
        starts = [list(map(float, a["start"][:2])) for a in agents]
        return [[starts[i]] + [list(map(float, step[i][:2])) for step in expected]
                for i in range(len(starts))]
    except (KeyError, IndexError, TypeError, ValueError):
        return None


class CameraScene:
    """The plan's geometry in the camera's pixels (the rig's calibration), for the overlays."""

    def __init__(self, rig: RigConfig) -> None:
        camera = rig.camera
        self.calibration = camera.calibration if camera is not None else None

    @property
    def available(self) -> bool:
        return self.calibration is not None

    def to_px(self, points_mm: Any) -> list[list[float]]:
        """Floor points (n, 2) mm -> pixels (n, 2), rounded to 0.1 px."""
        points = np.asarray(points_mm, dtype=float).reshape(-1, 2)
        if self.calibration is None or len(points) == 0:
            return []
        return np.round(self.calibration.to_px(points), 1).tolist()

    def of_plan(self, plan: dict) -> dict:
        """{"boundary", "obstacles", "paths", "goals", "radii_px"} in px for a plan document (keys
        without geometry left empty: an image workspace draws its bounds only)."""
        out: dict = {"boundary": [], "obstacles": [], "paths": [], "goals": [], "radii_px": []}
        if self.calibration is None:
            return out
        workspace = plan.get("workspace") or {}
        if "boundary" in workspace:
            out["boundary"] = self.to_px(shape_polygon_mm(workspace["boundary"]))
            out["obstacles"] = [self.to_px(shape_polygon_mm(s))
                                for s in workspace.get("obstacles", [])]
        paths = plan_paths_mm(plan)
        if paths:
            out["paths"] = [self.to_px(p) for p in paths]
        agents = plan.get("agents")
        agents = agents if isinstance(agents, list) else []
        goals = [a["goal"][:2] for a in agents if isinstance(a, dict) and a.get("goal")]
        out["goals"] = self.to_px(goals)
        for agent in agents:
            if isinstance(agent, dict) and "start" in agent and "radius" in agent:
                x, y = agent["start"][:2]
                a, b = self.to_px([[x, y], [x + float(agent["radius"]), y]])
                out["radii_px"].append(round(math.dist(a, b), 1))
        return out


class ArmsSketch:
    """Arms from their joints: joint origins, magnet centres, keep-out sphere. `scene`: what the
    rig kind's `scene_of` says of its arms ({"arms": [{"name", "position_mm", "rpy_deg"}],
    "keep_out_mm", "epm_radius_mm"}); None (a camera rig): nothing to sketch."""

    def __init__(self, scene: dict | None) -> None:
        from rigctl.physics.kinematics import ArmKinematics, base_transform

        arms = (scene or {}).get("arms") or []
        self.available = bool(arms)
        self.names = [str(a["name"]) for a in arms]
        self.arms = [ArmKinematics(base=base_transform(np.asarray(a["position_mm"]) * 1e-3,
                                                       a["rpy_deg"]), name=str(a["name"]))
                     for a in arms]
        self.keep_out_mm = float((scene or {}).get("keep_out_mm", 0.0))
        self.epm_radius_mm = float((scene or {}).get("epm_radius_mm", 0.0))

    def of_joints(self, joints_rad: list[float]) -> dict:
        """`joints_rad` (7 n_arms,): the first arm's seven, then the next's -> {"arms": [{"name",
        "points_mm" (9, 3): base, frames 1-7, EPM}], "keep_out_mm", "epm_radius_mm"}."""
        q = np.asarray(joints_rad, dtype=float).reshape(len(self.arms), 7)
        arms = []
        for arm, qi in zip(self.arms, q):
            origins = arm.frames(qi)[:, :3, 3] * 1e3
            arms.append({"name": arm.name, "points_mm": np.round(origins, 1).tolist()})
        return {"arms": arms, "keep_out_mm": self.keep_out_mm, "epm_radius_mm": self.epm_radius_mm}
