"""A teleoperation session written back out as a plan that replays it (`rigctl teleop-save`).

The record of a session (`rigctl.run.teleop`) holds every input as the stream took it (its
`teleop` series) and, on an emulated bench, the agents' positions as it went (`agents` events).
The rig kind's drive turns the inputs into the moves of a global-moves plan of its own rig kind
(`TeleopDrive.moves_mm`: the six coils step the inputs through the rolling field anew, the board
takes the particles' tracked displacement); the agents start where they were first tracked, their
goals are where they were last, and the expected states come from the global-input model
(`rigctl.plans.checks.simulate`). A plan cannot say everything a live session did (its moves are
realized by the rig's own rules: steering, whole turns, holds); what differs is returned with the
plan, one line each, and written into its name's tail.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.config import load_rig
from rigctl.core.errors import ConfigError
from rigctl.core.record import read_events, read_series

MARGIN_MM = 50.0  # the default workspace: the tracked positions' box grown by this


def teleop_plan(run_dir: str | Path, *, workspace: dict | None = None,
                radius_mm: float | None = None) -> tuple[Any, list[str]]:
    """The global-moves plan (`GlobalMovesPlan`, expected states filled) that replays the session
    recorded in `run_dir`, and what it differs in. `workspace`: the plan's (a plan document's
    `workspace`; None: the box of the tracked positions grown by MARGIN_MM, no obstacles);
    `radius_mm`: the agents' (None: the rig's magnets' radius). ConfigError, one line, for a record
    that is no session or has no tracked positions."""
    from rigctl.plans.checks import simulate
    from rigctl.plans.schema import parse_plan
    from rigctl.rigs import rig_kind
    from rigctl.run.teleop import TeleopPlan

    run_dir = Path(run_dir)
    try:
        session = TeleopPlan.model_validate(json.loads((run_dir / "plan.json").read_text()))
    except (OSError, ValueError) as err:
        raise ConfigError(f"{run_dir}: not a teleoperation session's record ({err.__class__.__name__}"
                          " reading its plan.json)") from None
    rig = load_rig(run_dir / "rig.toml")
    inputs = read_series(run_dir, "teleop")
    if inputs is None or not len(inputs["t_s"]):
        raise ConfigError(f"{run_dir}: the session has no inputs to replay")
    events = read_events(run_dir)
    drive = rig_kind(rig.rig.kind).teleop(rig, session.mode)
    moves, notes = drive.moves_mm(inputs, events)  # first: a mode with no plan says so
    tracked = [np.asarray(e["tracked"], dtype=float) for e in events
               if e["event"] == "agents" and e.get("tracked")]
    if not tracked:
        raise ConfigError(f"{run_dir}: no tracked positions in the record (a plan starts from its "
                          "agents: steer on the emulated bench, or with the agents tracked)")
    start, end = tracked[0], tracked[-1]
    radius = float(radius_mm if radius_mm is not None else
                   getattr(getattr(rig, "magnets", None), "radius_mm", 1.0))
    if workspace is None:
        everything = np.vstack(tracked)
        low, high = everything.min(axis=0) - MARGIN_MM, everything.max(axis=0) + MARGIN_MM
        workspace = {"boundary": {"rect": [*low.round(3).tolist(),
                                           *(high - low).round(3).tolist()]}, "obstacles": []}
    kind = rig_kind(rig.rig.kind)
    tolerance_mm = 1.0
    if kind.turn_mm is not None and getattr(getattr(rig, "field", None), "whole_turns", False):
        # each whole-turn move may end up to half a turn from the session's roll: the plan's
        # goal (where the session ended) is as far as they add up, and no re-plan should chase it
        tolerance_mm = max(tolerance_mm, 0.5 * kind.turn_mm(rig) * len(moves) + 0.5)
        notes.append(f"its tolerance is {tolerance_mm:.3f} mm: each whole-turn move ends within "
                     "half a turn of the session's")
    document = {
        "schema": "rigctl.plan/1", "kind": "global-moves", "rig": rig.rig.kind,
        "name": f"teleoperation {run_dir.name} replayed ({len(moves)} moves)",
        "workspace": workspace,
        "agents": [{"start": s.round(4).tolist(), "goal": g.round(4).tolist(), "radius": radius}
                   for s, g in zip(start, end)],
        "moves": moves.round(6).tolist(),
        "tolerance_mm": round(tolerance_mm, 3),
    }
    return simulate(parse_plan(document, str(run_dir / "plan.json"))), notes
