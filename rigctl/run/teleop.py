"""Steering by hand (teleoperation): the operator's live input as a run of the one engine.

A teleoperation session is a `RigProgram` like a plan's: `TeleopProgram` turns the operator's
latest input into the rig's setpoints every stream cycle, so the session has a record, the
certificate, the live winding model, the e-stop and the safe end of every run. What an input is
and how it becomes setpoints is the rig kind's (`RigKind.teleop` makes a `TeleopDrive`): the
rolling field's heading and speed on the six coils, the board's pull, ...

It is a dead-man control, enforced here, in the stream's own loop (the daemon's stream process),
not in the page that sends the input: the input counts only while it is fresh. `steer` stamps
each input with the stream process's clock when it arrives; a cycle that finds the latest input
older than `SILENCE_S`, or released (`steer(None)`: the key or button let go, the page lost its
focus), drives the rig's stop input instead (`TeleopDrive.step(None)`: the field ramped to zero,
the coils stopped), whatever the page or its connection does.

Every input as the stream took it (clipped to the rig's limits) and every dead-man stop is in the
record's `teleop` series (`t_s`, `live`, then the rig's input components), so that
`rigctl.run.teleop_save` can write the session back out as a plan of the rig's own kind.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, RigError
from rigctl.run.certificate import Check
from rigctl.run.engine import Outcome, RunContext, Step

SILENCE_S = 0.2
"""An input older than this (s, on the stream process's clock) is no input: the dead-man."""

NO_TELEOP = "this rig kind has no teleoperation"
CANNOT_PAUSE = "a teleoperation session cannot be paused: let go of the input, or end it"


class TeleopPlan(BaseModel):
    """What a session runs (and its record keeps as `plan.json`): the rig kind and the mode (the
    kind of input: "rolling", "drive", ...; None: the rig's first)."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["teleop"] = "teleop"
    name: str = "teleop"
    rig: str
    mode: str | None = None


@dataclass(frozen=True)
class InputComponent:
    """One component of an operator's input: its name, its unit, the range it is clipped to, and
    what it is."""

    name: str
    unit: str
    low: float
    high: float
    description: str


class TeleopDrive:
    """How one rig kind turns an operator's input into setpoints, with its own state (the
    rolling angle, the field's magnitude). Made per session by the kind's `teleop(rig, mode)`;
    `step` is called once per stream cycle, on the stream thread."""

    mode: str
    components: tuple[InputComponent, ...]
    rate_hz: float
    late: str
    connect: Callable[[RigConfig], Any]
    blocked: str | None = None  # the limit the input is stopped at now (the arms' constraints)

    def connected(self, actuators: Any) -> None:
        """The actuators are open, outputs off: where the session starts (the arms' joints)."""

    def step(self, values: np.ndarray | None) -> np.ndarray:
        """The next cycle's setpoints (n_channels,) for the input `values` (components,),
        clipped already; None: no input (the dead-man): towards the rig's rest."""
        raise NotImplementedError

    def at_rest(self) -> bool:
        """The last setpoints were the rig's rest (zero)."""
        raise NotImplementedError

    def checks(self) -> list[Check]:
        """The pre-flight of any input within the components' ranges on this rig."""
        raise NotImplementedError

    def moves_mm(self, inputs: dict[str, Any], events: list[dict[str, Any]]) -> tuple[np.ndarray, list[str]]:
        """The moves (m, 2) mm of a global-moves plan that replays a session from its record (the
        `teleop` series as `read_series` gives it, the events), and what the plan differs in,
        one line each (`rigctl.apps.teleop_save`). ConfigError where the mode has none."""
        raise ConfigError(f"teleop-save: a {self.mode} session cannot be written as a plan")

    # -- shared -------------------------------------------------------------------------------
    def clip(self, values: dict[str, Any]) -> tuple[np.ndarray, list[str]]:
        """An input {component: value} as an array in the components' order, each clipped to its
        range; the names of those clipped. ConfigError for missing, unknown or non-finite ones."""
        names = [c.name for c in self.components]
        if not isinstance(values, dict) or set(values) != set(names):
            raise ConfigError(f"a {self.mode} input takes {{{', '.join(names)}}}, got "
                              f"{sorted(values) if isinstance(values, dict) else values!r}")
        out, clipped = np.empty(len(names)), []
        for i, c in enumerate(self.components):
            value = values[c.name]
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value):
                raise ConfigError(f"{c.name}: a finite number, got {value!r}")
            out[i] = min(c.high, max(c.low, float(value)))
            if out[i] != value:
                clipped.append(c.name)
        return out, clipped

    def describe(self) -> dict[str, Any]:
        return {"mode": self.mode, "inputs": {
            c.name: {"unit": c.unit, "range": [c.low, c.high], "description": c.description}
            for c in self.components}}


class TeleopProgram:
    """The session (see the module docstring). `steer` and `end` may be called from any thread;
    pause and resume are refused (letting go of the input is the pause)."""

    n_moves = 0
    duration_s = 0.0  # until ended
    paused = False
    suspended: str | None = None

    def __init__(self, plan: TeleopPlan, rig: RigConfig, drive: TeleopDrive,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.plan, self.rig, self.drive = plan, rig, drive
        self.rate_hz, self.late = drive.rate_hz, drive.late
        self.info = {"name": plan.name, **drive.describe(), "silence_s": SILENCE_S}
        self.clock = clock
        self._lock = threading.Lock()
        self._input: np.ndarray | None = None  # the latest input, clipped
        self._at = -math.inf  # when it came (the stream process's clock, s)
        self._seq = 0  # inputs taken, to tell a new one from the same one held
        self._ending = self._aborted = self._cooling = False
        self._ctx: RunContext | None = None
        self._series: Any = None
        # the stream thread's
        self._seen = -1
        self._live = False
        self._blocked: str | None = None
        self.inputs = 0
        self.deadman_stops = 0

    # -- control, from any thread ---------------------------------------------------------------
    def steer(self, values: Sequence[float] | None) -> None:
        """The operator's input now (components, clipped by `TeleopDrive.clip`); None: let go."""
        with self._lock:
            self._input = None if values is None else np.asarray(values, dtype=float)
            self._at = self.clock()
            self._seq += 1

    def end(self) -> None:
        """Let go, bring the rig to its rest and end the session (done, not aborted)."""
        with self._lock:
            self._input, self._ending = None, True

    def pause(self, immediate: bool = False) -> None:
        raise RigError(CANNOT_PAUSE)

    def resume(self) -> None:
        raise RigError(CANNOT_PAUSE)

    def pause_to_cool(self) -> None:
        """A winding reached its warning: the input is ignored from now on (the session must be
        ended and the coils left to cool); at its limit the engine aborts the run."""
        with self._lock:
            self._cooling = True

    def abort(self) -> None:
        with self._lock:
            self._aborted, self._input = True, None

    @property
    def aborted(self) -> bool:
        return self._aborted

    # -- the run --------------------------------------------------------------------------------
    def checks(self) -> list[Check]:
        return self.drive.checks()

    def start(self, ctx: RunContext) -> None:
        self._ctx = ctx
        names = [c.name for c in self.drive.components]
        self._series = ctx.record.open_series(
            "teleop", ["t_s", "live", *names],
            {"t_s": "s", "live": "1", **{c.name: c.unit for c in self.drive.components}})

    def connected(self, actuators: Any) -> None:
        self.drive.connected(actuators)

    def next(self, k: int, measured: np.ndarray | None) -> Step | None:
        now = self.clock()
        with self._lock:
            values, at, seq = self._input, self._at, self._seq
            ending, aborted, cooling = self._ending, self._aborted, self._cooling
        if aborted:
            return None
        fresh = values is not None and not cooling and now - at <= SILENCE_S
        if seq != self._seen or fresh != self._live:
            assert self._ctx is not None
            if self._live and not fresh and values is not None:  # silent, not let go
                self.deadman_stops += 1
                self._ctx.record.event("teleop_silence", silent_s=round(now - at, 4))
            if seq != self._seen and values is not None:
                self.inputs += 1
            self._seen, self._live = seq, fresh
            row = values if fresh and values is not None else np.full(len(self.drive.components), np.nan)
            self._series.row([now - self._ctx.record.t0, 1.0 if fresh else 0.0, *row])
        setpoints = self.drive.step(values if fresh else None)
        if self.drive.blocked != self._blocked:  # a limit the input is stopped at, or no more
            self._blocked = self.drive.blocked
            assert self._ctx is not None
            self._ctx.record.event("teleop_limit", constraint=self._blocked)
        if ending and self.drive.at_rest():
            return None
        stage = "steering" if fresh else ("ending" if ending else "idle")
        return Step(setpoints, k, -1, stage=stage)

    def finish(self, ctx: RunContext) -> Outcome:
        return Outcome(reached=self._ending and not self._aborted,
                       positions_from="no agents (teleoperation)",
                       metrics={"mode": self.drive.mode, "inputs": self.inputs,
                                "silence_stops": self.deadman_stops},
                       details=[f"teleoperation ({self.drive.mode}): {self.inputs} inputs, "
                                f"{self.deadman_stops} stopped by the dead-man"])

    def close(self) -> None:
        pass
