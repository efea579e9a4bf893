"""Steering the coil board's particles by hand (teleoperation, `rigctl.run.teleop`).

The operator gives a heading (the direction to pull in, degrees from +x) and a drive (a fraction of
the board's `max_command`). The pull is the one a coil-board run makes for a move
(`rigctl.rigs.coil_board.run`): the direction scaled so that its larger component is 1, each
positive part on the coil of that side (+x, -x, +y, -y), times the drive, in whole SyRen units.
With no input (let go, or the dead-man) every coil is stopped in the very cycle: an iron-core
coil's SyRen puts a voltage on it, nothing needs a ramp (the board's own 200 ms link watchdog
zeroes the outputs too, should the stream stop talking to it).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from rigctl.run.certificate import Check, ceiling
from rigctl.run.teleop import InputComponent, TeleopDrive

if TYPE_CHECKING:
    from rigctl.rigs.coil_board.settings import CoilBoardRig


def pulls(heading_deg: float, drive: float, max_command: int) -> np.ndarray:
    """The four coils' drive units (+x, -x, +y, -y) pulling towards `heading_deg` at `drive`
    (0..1 of `max_command`), whole units."""
    angle = math.radians(heading_deg)
    direction = np.array([math.cos(angle), math.sin(angle)])
    direction = np.round(direction / np.abs(direction).max(), 12)  # 45 deg: both exactly 1
    parts = np.array([max(direction[0], 0.0), max(-direction[0], 0.0), max(direction[1], 0.0),
                      max(-direction[1], 0.0)])
    return np.round(drive * max_command * parts)


class BoardDrive(TeleopDrive):
    """Heading and drive of the board's pull (see the module docstring)."""

    mode = "drive"
    late = "slip"
    components = (
        InputComponent("heading_deg", "deg", -360.0, 360.0, "the direction to pull in, from +x"),
        InputComponent("drive", "1", 0.0, 1.0, "the pull as a fraction of the board's max_command"),
    )

    def __init__(self, rig: CoilBoardRig) -> None:
        from rigctl.core.errors import ConfigError
        from rigctl.rigs.coil_board.actuators import BoardActuators

        if rig.board is None:
            raise ConfigError("the rig has no [board] table: it is not a coil board")
        self.board = rig.board
        self.connect = BoardActuators.connect
        self.rate_hz = rig.board.rate_hz
        self._last = np.zeros(4)

    def step(self, values: np.ndarray | None) -> np.ndarray:
        if values is None:
            self._last = np.zeros(4)
        else:
            self._last = pulls(values[0], values[1], self.board.max_command)
        return self._last

    def at_rest(self) -> bool:
        return not self._last.any()

    def moves_mm(self, inputs: dict, events: list[dict]) -> tuple[np.ndarray, list[str]]:
        """The session's moves (m, 2) mm: for each run of inputs at one heading, the particles'
        mean displacement between the positions tracked just before it began and just after
        it ended (the record's `agents` events); with what the plan differs in."""
        tracked = [(e["t"], np.asarray(e["tracked"], dtype=float)) for e in events
                   if e["event"] == "agents" and e.get("tracked")]
        if not tracked:
            return np.zeros((0, 2)), []
        times = np.array([t for t, _ in tracked])
        t, live = inputs["t_s"], inputs["live"] == 1.0
        moves, i = [], 0
        while i < len(t):
            if not live[i]:
                i += 1
                continue
            j = i
            while j + 1 < len(t) and live[j + 1] and inputs["heading_deg"][j + 1] == \
                    inputs["heading_deg"][i]:
                j += 1
            end = t[j + 1] if j + 1 < len(t) else t[j]
            before = tracked[max(0, int(np.searchsorted(times, t[i])) - 1)][1]
            after = tracked[min(len(tracked) - 1, int(np.searchsorted(times, end)))][1]
            moves.append((after - before).mean(axis=0))
            i = j + 1
        return np.array(moves).reshape(-1, 2), [
            "each move is the particles' mean tracked displacement while one heading was held; "
            "the plan's run pulls along it until the camera sees them there"]

    def checks(self) -> list[Check]:
        """The largest drive any input asks of a coil, against the board's limit (the windings'
        heating is watched live, as in every run)."""
        return [ceiling("drive", f"coil {name}", self.board.max_command, self.board.max_command,
                        "SyRen units", "the largest any input asks (drive 1)")
                for name in self.board.coil_names]


def teleop_drive(rig: CoilBoardRig, mode: str | None) -> TeleopDrive:
    """The coil board's teleoperation: "drive" (the pull of global moves)."""
    from rigctl.core.errors import ConfigError

    if mode in (None, "drive"):
        return BoardDrive(rig)
    raise ConfigError(f"teleop: a coil-board rig steers in mode drive, not {mode!r}")
