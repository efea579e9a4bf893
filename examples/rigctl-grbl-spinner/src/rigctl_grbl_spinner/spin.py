"""The `spin-sequence` plan and its program on the run engine: rotation rates held for durations.

    {"schema": "rigctl.plan/1", "kind": "spin-sequence", "rig": "grbl-spinner", "name": "swim",
     "segments": [{"rate_hz": 2.0, "duration_s": 3.0}, {"rate_hz": -1.0, "duration_s": 2.0}],
     "tolerance_hz": 0.05}

A helical swimmer follows the rotating magnet's field: its speed goes with the rotation rate (up
to its step-out rate), its direction with the sense. The program streams the plan's rate at the
rig's `[grbl] rate_hz`, changed from one segment's rate to the next at the rig's
`max_acceleration_hz_per_s` (GRBL's `$120` would hold it to that anyway; commanding it keeps the
recorded setpoint what the rotor can do), then back to rest.

Pre-flight (no I/O): every segment's rate within `max_rate_hz`, and every segment long enough to
reach its rate and have GRBL's planner settle on it (the change at the acceleration limit, the
planner's queue of `v / 2a`, three stream cycles) with `MIN_JUDGED_S` left to judge it.

A pause holds the rotor at rest (zero: the actuators cancel the jog, the rotor decelerates at
`$120`); `pause` waits for the end of the segment, `pause now` stops it at once, and the segment
goes on for what was left of it after `resume`. Abort ends the stream: the actuators bring the
rotor to rest. The outcome judges each segment by the rate the controller reported over its
settled part (mean within `tolerance_hz`), and counts the turns (measured; the bench's truth
beside it on an emulated bench).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from rigctl.core.errors import PlanError
from rigctl.run.certificate import Check, ceiling, floor
from rigctl.run.engine import Outcome, RunContext, Step
from rigctl_grbl_spinner.settings import SpinnerConfig

PLAN_KIND = "spin-sequence"
MIN_JUDGED_S = 0.2  # of each segment, at its rate, to judge it by
SETTLE_CYCLES = 3


class SpinSegment(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    rate_hz: Annotated[float, Field(allow_inf_nan=False, description="turns/s, signed: the sense")]
    duration_s: Annotated[float, Field(gt=0, le=3600, allow_inf_nan=False)]


class SpinSequencePlan(BaseModel):
    """A spin-sequence plan (`rigctl.plan/1`)."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    schema_: Literal["rigctl.plan/1"] = Field(alias="schema")
    kind: Literal["spin-sequence"]
    rig: Literal["grbl-spinner"]
    name: str = "spin sequence"
    segments: Annotated[list[SpinSegment], Field(min_length=1, max_length=1000)]
    tolerance_hz: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 0.05

    @property
    def duration_s(self) -> float:
        return sum(s.duration_s for s in self.segments)

    @property
    def size(self) -> str:
        return f"{len(self.segments)} segments, {self.duration_s:g} s"


def parse_spin_plan(data: dict, source: str = "plan") -> SpinSequencePlan:
    """Validate a decoded spin-sequence plan; PlanError naming the field."""
    try:
        return SpinSequencePlan.model_validate(data)
    except ValidationError as err:
        problem = err.errors()[0]
        where = ".".join(str(p) for p in problem["loc"])
        raise PlanError(f"{source}: {where}: {problem['msg']}") from None


def settle_s(previous_hz: float, rate_hz: float, rig: SpinnerConfig) -> float:
    """How long a segment takes to be at its rate: the change at the acceleration limit, GRBL's
    planner queue at that rate (v / 2a and the actuators' `LEAD_S`) and a few stream cycles of
    latency."""
    from rigctl_grbl_spinner.actuators import LEAD_S

    g = rig.grbl
    a = g.max_acceleration_hz_per_s
    return (abs(rate_hz - previous_hz) / a + abs(rate_hz) / (2 * a) + LEAD_S
            + SETTLE_CYCLES / g.rate_hz)


def spin_checks(plan: SpinSequencePlan, rig: SpinnerConfig) -> list[Check]:
    checks, previous = [], 0.0
    g = rig.grbl
    for i, segment in enumerate(plan.segments):
        subject = f"segment {i + 1}"
        checks.append(ceiling("rotation rate", subject, abs(segment.rate_hz), g.max_rate_hz, "Hz",
                              "the rig file's [grbl] max_rate_hz"))
        needed = settle_s(previous, segment.rate_hz, rig) + MIN_JUDGED_S
        checks.append(floor("segment duration", subject, segment.duration_s, needed, "s",
                            f"to reach {segment.rate_hz:g} Hz at {g.max_acceleration_hz_per_s:g} "
                            f"Hz/s and hold it {MIN_JUDGED_S:g} s: make it at least {needed:.2f} s"))
        previous = segment.rate_hz
    return checks


class SpinProgram:
    """The run engine's program of a spin-sequence plan (`rigctl.run.engine.RigProgram`)."""

    late = "slip"
    suspended: str | None = None

    def __init__(self, plan: SpinSequencePlan, rig: SpinnerConfig) -> None:
        self.plan, self.rig = plan, rig
        self.rate_hz = rig.grbl.rate_hz
        self.n_moves = len(plan.segments)
        self.step_hz = rig.grbl.max_acceleration_hz_per_s / self.rate_hz  # per cycle, at most
        last = plan.segments[-1].rate_hz
        self.duration_s = plan.duration_s + abs(last) / rig.grbl.max_acceleration_hz_per_s
        self.info = {"name": plan.name, "size": plan.size, "duration_s": self.duration_s}
        self.ends_s = np.cumsum([s.duration_s for s in plan.segments])
        self.t_s = 0.0  # the plan's time: it stands still while paused
        self.command = 0.0  # the setpoint sent last, Hz
        self.paused = False
        self._pause_at_end: int | None = None  # pause when this segment ends
        self._aborted = False
        self._samples: list[tuple[int, float, float]] = []  # (segment, plan time, measured Hz)
        self._last: tuple[int, float] | None = None
        self._ctx: RunContext | None = None

    def checks(self) -> list[Check]:
        return spin_checks(self.plan, self.rig)

    def start(self, ctx: RunContext) -> None:
        self._ctx = ctx

    def connected(self, actuators) -> None:
        pass

    # -- control, from any thread ---------------------------------------------------------------
    def pause(self, immediate: bool) -> None:
        if immediate:
            self.paused = True
        else:
            self._pause_at_end = self._segment()

    def pause_to_cool(self) -> None:
        self.pause(False)

    def resume(self) -> None:
        self._pause_at_end = None
        self.paused = False

    def abort(self) -> None:
        self._aborted = True

    @property
    def aborted(self) -> bool:
        return self._aborted

    # -- the stream -----------------------------------------------------------------------------
    def _segment(self) -> int:
        """The segment the plan's time is in (n_moves once past the last)."""
        return int(np.searchsorted(self.ends_s, self.t_s, side="right"))

    def next(self, k: int, measured: np.ndarray | None) -> Step | None:
        if measured is not None and self._last is not None and not self.paused:
            self._samples.append((*self._last, float(measured[0])))
        if self._aborted:
            return None
        segment = self._segment()
        if self._pause_at_end is not None and segment > self._pause_at_end:
            self.paused, self._pause_at_end = True, None
        done = segment >= self.n_moves
        target = 0.0 if self.paused or done else self.plan.segments[segment].rate_hz
        if done and self.command == 0.0:
            return None
        self.command += float(np.clip(target - self.command, -self.step_hz, self.step_hz))
        self._last = (segment, self.t_s)
        if not self.paused and not done:
            self.t_s += 1.0 / self.rate_hz
        stage = "paused" if self.paused else "to rest" if done else None
        return Step(np.array([self.command]), k, -1 if (self.paused or done) else segment,
                    stage=stage, t_s=self.t_s)

    def finish(self, ctx: RunContext) -> Outcome:
        from rigctl.run.agents import read_truth

        results, details, previous, start = [], [], 0.0, 0.0
        for i, segment in enumerate(self.plan.segments):
            settled = start + settle_s(previous, segment.rate_hz, self.rig)
            rates = [r for s, t, r in self._samples if s == i and t >= settled]
            mean = float(np.mean(rates)) if rates else None
            ok = mean is not None and abs(mean - segment.rate_hz) <= self.plan.tolerance_hz
            results.append({"segment": i + 1, "rate_hz": segment.rate_hz,
                            "measured_hz": None if mean is None else round(mean, 4),
                            "samples": len(rates), "within_tolerance": ok})
            shown = "not reached" if mean is None else f"{mean:.3f} Hz"
            details.append(f"segment {i + 1}: {segment.rate_hz:g} Hz for {segment.duration_s:g} s, "
                           f"measured {shown}{'' if ok else ' (outside the tolerance)'}")
            previous, start = segment.rate_hz, start + segment.duration_s
        turns = sum(r for _, _, r in self._samples) / self.rate_hz
        metrics = {"segments": results, "turns_measured": round(turns, 3)}
        truth = read_truth(ctx.backdoor)
        if truth is not None:
            metrics["truth"] = {"angle_deg": truth["angle_deg"], "rate_hz": truth["rate_hz"]}
        reached = not self._aborted and all(r["within_tolerance"] for r in results)
        return Outcome(reached=reached, positions_from="the controller's status reports",
                       tolerance_mm=self.plan.tolerance_hz, tolerance_unit="Hz", metrics=metrics,
                       details=details)

    def close(self) -> None:
        pass


def build_spin_run(plan, rig, **run):
    """The engine's `Run` of a spin-sequence plan on a grbl-spinner rig, its limits checked
    (CertificateRefused) with no I/O."""
    from rigctl.run.engine import Run
    from rigctl_grbl_spinner.actuators import SpinnerActuators

    if not isinstance(plan, SpinSequencePlan):
        raise PlanError(f"plan: a {PLAN_KIND} plan is needed, got {type(plan).__name__}")
    return Run(SpinProgram(plan, rig), rig, SpinnerActuators.connect, **run)
