"""The manual hold of any rig: setpoints an operator asks for, held on the one run engine.

A hold is a `RigProgram` like any plan's: `HoldProgram` ramps straight from where the actuators
are held now to the target setpoints (one per channel, in channel units) over `ramp_s` at the
rig's stream rate, holds them, takes a new target from any thread while holding (a new ramp from
the setpoint of the moment), and on release ramps to the rig's rest and ends. The rest is zero
for the supplies and the board; the arms' rest is where they stand, so a release ends the stream
there and the arms hold that pose. Run by `rigctl.run.engine.Run`, a hold has a record, the
e-stop, the `safe`/`unsafe` end and a summary like every run.

What differs per rig is how an operator's request becomes setpoints, with every limit checked
before anything moves: each rig kind's `hold` (`rigctl.rigs.base.RigKind`) makes a `HoldRequest`.
A hold is a run of a `HoldPlan`, which is what the record keeps as its plan.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict

from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, RigError
from rigctl.run.certificate import Check
from rigctl.run.engine import Outcome, RunContext, Step

CANNOT_PAUSE = "a manual hold cannot be paused: release it"


class HoldPlan(BaseModel):
    """What a hold runs (and its record keeps as `plan.json`): the rig kind, the operator's
    request as asked (`{"field_mT": [...]}`, `{"drive": [...]}`, `{"joints_rad": [...]}`) and the
    first ramp's duration."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["hold"] = "hold"
    name: str = "hold"
    rig: str
    target: dict[str, Any]
    ramp_s: float


@dataclass(frozen=True)
class HoldRequest:
    """An operator's request made into setpoints for one rig, its limits checked.

    `setpoints` (n_channels,) in channel units; `connect` opens the rig's actuator group; `late`
    is "slip" (field and drive programs) or "skip" (the arm servo); `check_ramp(start, ramp_s)`
    raises LimitError if the ramp from setpoints `start` breaks a limit. `pose_now`, for a rig
    whose rest is where it stands (the arms), reads the pose held now from the open actuators;
    None: the rest is zero, where the outputs start and where a release ramps to. `step`: the
    setpoints are whole multiples of it (the board's SyRen units); 0: any value."""

    target: dict[str, Any]
    setpoints: np.ndarray
    connect: Callable[[RigConfig], Any]
    rate_hz: float
    late: str
    check_ramp: Callable[[np.ndarray, float], None]
    pose_now: Callable[[Any], np.ndarray] | None = None
    step: float = 0.0

    @property
    def at_rest(self) -> bool:
        """A zero target on a rig whose rest is zero: holding it is releasing."""
        return self.pose_now is None and not np.any(self.setpoints)


def ramp_samples(ramp_s: float, rate_hz: float) -> int:
    """Cycles of a ramp of `ramp_s` at `rate_hz`: never shorter than asked, at least one."""
    return max(1, math.ceil(ramp_s * rate_hz - 1e-9))


def ramp(start: np.ndarray, target: np.ndarray, ramp_s: float, rate_hz: float) -> np.ndarray:
    """The setpoints (n, channels) of a straight ramp from `start` to `target`, one per cycle, the
    last the target itself: what `HoldProgram` streams when no cycle is late."""
    start, target = np.asarray(start, dtype=float), np.asarray(target, dtype=float)
    n = ramp_samples(ramp_s, rate_hz)
    steps: np.ndarray = start + (target - start) * (np.arange(1, n + 1) / n)[:, None]
    return steps


def target_values(target: dict[str, Any], key: str, shape: tuple[int, ...], rig_kind: str,
                  unit: str) -> np.ndarray:
    """The request's one entry `key` as finite floats of `shape`; ConfigError saying what a hold
    on this rig takes."""
    if set(target) != {key}:
        raise ConfigError(f"a {rig_kind} hold takes {{\"{key}\": ...}} ({unit}), "
                          f"got {sorted(target) or 'nothing'}")
    try:
        values = np.asarray(target[key], dtype=float)
    except (TypeError, ValueError):
        values = None
    if values is None or values.shape != shape or not np.isfinite(values).all():
        size = " x ".join(str(n) for n in shape)
        raise ConfigError(f"{key}: {size} finite values in {unit}, got {target[key]!r}")
    return values


class HoldProgram:
    """Hold `request`'s setpoints until released (see the module docstring). `retarget` and
    `release` may be called from any thread; pause and resume are refused."""

    n_moves = 0
    duration_s = 0.0  # until released
    paused = False
    suspended: str | None = None

    def __init__(self, plan: HoldPlan, rig: RigConfig, request: HoldRequest) -> None:
        self.plan, self.rig, self.request = plan, rig, request
        self.rate_hz, self.late = request.rate_hz, request.late
        self.info = {"name": "hold", "target": request.target, "ramp_s": plan.ramp_s}
        self._lock = threading.Lock()
        # the next target, taken by the stream thread: (target, setpoints or None to release, ramp)
        self._asked: tuple[dict[str, Any] | None, np.ndarray | None, float] | None = (
            request.target, request.setpoints, plan.ramp_s)
        self._aborted = False
        self._ctx: RunContext | None = None
        # the stream thread's
        self._last = np.zeros(len(request.setpoints))  # the setpoints sent last
        self._from = self._to = self._last
        self._k0, self._n = -1, 1
        self._releasing = self._reached = False
        self.retargets = -1  # the first target is not a retarget

    # -- control, from any thread ---------------------------------------------------------------
    def retarget(self, target: dict[str, Any], setpoints: Any, ramp_s: float) -> None:
        """Ramp from the setpoints of the moment to `setpoints` over `ramp_s`, then hold them."""
        with self._lock:
            self._asked = (target, np.asarray(setpoints, dtype=float), ramp_s)

    def release(self, ramp_s: float) -> None:
        """Ramp to the rest over `ramp_s` (the arms: stop where they are) and end."""
        with self._lock:
            self._asked = (None, None, ramp_s)

    def pause(self, immediate: bool = False) -> None:
        raise RigError(CANNOT_PAUSE)

    def resume(self) -> None:
        raise RigError(CANNOT_PAUSE)

    def pause_to_cool(self) -> None:
        pass  # a hold cannot pause: the warning is logged, and at the limit it is released

    def abort(self) -> None:
        self._aborted = True
        self.release(self.rig.stream.ramp_down_s)

    @property
    def aborted(self) -> bool:
        return self._aborted

    # -- the run --------------------------------------------------------------------------------
    def checks(self) -> list[Check]:
        """None of its own: the rig's hold request checked its limits, and the run's live winding
        model watches the coils' heating while it holds."""
        return []

    def start(self, ctx: RunContext) -> None:
        self._ctx = ctx

    def connected(self, actuators: Any) -> None:
        """Where the hold starts (zero, or the arms' pose), and the first ramp checked from it
        (nothing has moved)."""
        if self.request.pose_now is not None:
            self._last = np.asarray(self.request.pose_now(actuators), dtype=float).ravel()
        self._from = self._to = self._last
        self.request.check_ramp(self._last, self.plan.ramp_s)

    def next(self, k: int, measured: np.ndarray | None) -> Step | None:
        with self._lock:
            asked, self._asked = self._asked, None
        if asked is not None:
            target, setpoints, ramp_s = asked
            self._releasing = setpoints is None
            if self._releasing and self.request.pose_now is not None:
                return None  # the arms' rest: where they stand now
            self._from = self._last
            self._to = np.zeros_like(self._last) if setpoints is None else setpoints
            self._k0, self._n = k - 1, ramp_samples(ramp_s, self.rate_hz)
            if not self._releasing:
                self.retargets += 1
                self.info["target"] = target
            assert self._ctx is not None
            self._ctx.record.event("release" if self._releasing else "hold", target=target,
                                   setpoints=self._to.tolist(), ramp_s=ramp_s)
        elif self._releasing and self._reached:
            return None
        f = min(1.0, (k - self._k0) / self._n)
        setpoints = self._from + (self._to - self._from) * f
        if self.request.step:
            setpoints = np.round(setpoints / self.request.step) * self.request.step
        self._last, self._reached = setpoints, f >= 1.0
        stage = "releasing" if self._releasing else "holding" if self._reached else "ramping"
        return Step(setpoints, k, -1, stage=stage)

    def finish(self, ctx: RunContext) -> Outcome:
        retargets = max(self.retargets, 0)
        return Outcome(reached=self._releasing and not self._aborted,
                       positions_from="no agents (a manual hold)",
                       metrics={"target": self.info["target"], "retargets": retargets},
                       details=[f"hold: {self.info['target']}, retargeted {retargets} times"])

    def close(self) -> None:
        pass
