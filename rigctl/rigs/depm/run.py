"""Execute a `field-sequence` plan on a dual-EPM rig (seed 003) on the one run engine, and measure
it the way seed 003 Table 1 does.

`FieldSequenceProgram` is the rig program; the actuators are the two arms (`ArmPair`); the engine
(`rigctl.run.engine.Run`) owns the record, the stream loop, the states, control from any thread
and the safe end. What is the dual-EPM rig's own:

1. **Refusals before anything is opened** (construction, no I/O): the plan must be made for this
   rig's geometry and magnets (ConfigError), and its trajectories, sampled densely, must keep the
   *rig's* safety limits (keep-out sphere, EPM-EPM distance, joint ranges, speed and acceleration
   fractions; `rigctl.plans.depm_safety`): a breach raises `SafetyRefusal` (a LimitError, exit 2)
   naming every violation with its time, arm, part and constraint.
2. **Start**: on an emulated bench the backdoor sets the bench's speed (`--time-scale`); the Hall
   board is opened (a sensor: the program owns it, `HallWatch`) and its samples recorded as the
   side series `field` (per sample: plan time, sequence number, each sensor's field in mT, and U
   by eq. 24 in mT and mT/m).
3. **Connected** (arms open, nothing servoing): both arms' joints are read, and the approach from
   there to the plan's first pose (one arm after the other, straight in joint space, at the rig's
   speed fraction: `motion.approach_path`) is checked against every constraint before anything
   moves (a breach: `SafetyRefusal`, nothing moved, exit 2).
4. **Stream** (the engine's loop, late = "skip": a servo target in the past is worthless, so a
   late cycle passes over the stale ones and the targets jump to the present): the approach,
   then the plan's PCHIP curves, both on the same direct servo. Every reply's measured joints are
   checked against the targets (`_Tracking`: a stalled or blocked joint is a fault naming the
   arm). Hall samples are taken every few cycles and placed on the plan's clock by their arrival.
5. **Holds**: pause holds the present target; pause now holds the last measured pose (the arms
   brake at once); resume continues the plan's clock from where it stopped, rejoining the path
   first if the arms stopped off it. Lost Hall data (the reader's fault, or silence) suspends the
   run the same way (the arms hold; the state says why) until samples come back, or faults it
   after `HALL_LOST_FAULT_S`. Abort holds the measured pose and ends. Samples taken while held are
   recorded (`held` = 1) but not measured: Table 1 is about the plan's motion.
6. **Hall correction** (closed loop, the default; `--open-loop` plays the plan's poses back):
   at the start of each hold the plan's clock stops, the arms hold, and the inverse magnetics is
   iterated on the measured residual (`correction`: a few small joint moves, each checked against
   every constraint) until U is within 0.5 % of the request; the correction stays on for the rest
   of the hold and is blended out over the next transition (checked too). Samples taken while
   correcting are recorded as held, not measured.
7. **Outcome**: the Table 1 metrics per component and the Fig. 6 cross-activation matrix
   (`metrics`), the lines a person reads of them (`details`); reached = every requested
   component's steady state within 2 % (docs/depm.md, "Execution and metrics").
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque

import numpy as np

import rigctl.rigs.depm.correction as correction
from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, DeviceError, LimitError
from rigctl.physics.kinematics import ArmKinematics, base_transform
from rigctl.physics.magnetics import U_COMPONENTS
from rigctl.plans.depm import joint_trajectory, plan_violations, rig_from_settings
from rigctl.plans.depm_safety import Violation
from rigctl.rigs.depm.actuators import ArmPair
from rigctl.rigs.depm.correction import HoldOffsets
from rigctl.rigs.depm.metrics import (
    STEADY_STATE_TOLERANCE,
    cross_activation,
    steady_state_reached,
    table1,
    windows_of,
)
from rigctl.rigs.depm.motion import (
    JointPath,
    Timeline,
    approach_path,
    caps,
    joint_path,
    path_violations,
)
from rigctl.rigs.depm.sensors import HALL_NAME, HallWatch, sensor_estimator
from rigctl.run.engine import Outcome, RunContext, Step
from rigctl.run.engine import Run as EngineRun
from rigctl.run.interruptions import RequestedControl, Requests

log = logging.getLogger(__name__)

TRACKING_TARGETS = 3  # measured joints are checked against the span of the last 3 targets
STALL_TIME_S = 0.5  # behind by more than the tolerance and not catching up this long: a fault
MAX_REAL_RATE_HZ = 100.0  # stream targets per real second on a faster-than-real bench
SAMPLE_EVERY = 5  # cycles between two takes of the Hall samples
HALL_LOST_FAULT_S = 5.0  # real seconds without Hall samples before the suspension is a fault
CLOCK_WINDOW = 1024  # stream cycles kept to place samples on the plan's clock
MAX_LISTED = 10  # violations named in a refusal


class SafetyRefusal(LimitError):
    """A trajectory (the plan's, or the approach to it) breaks the rig's safety constraints:
    refused before anything moved. `violations` lists every breach."""

    def __init__(self, what_breaks: str, found: list[Violation]) -> None:
        more = f"\n  ... and {len(found) - MAX_LISTED} more" if len(found) > MAX_LISTED else ""
        self.headline = f"{what_breaks} {len(found)} safety constraint(s); refused, nothing moved"
        super().__init__(self.headline + ":\n  " + "\n  ".join(str(v) for v in found[:MAX_LISTED])
                         + more)
        self.violations = found


# -- checks before anything moves -----------------------------------------------------------------


def check_plan_against_rig(plan, rig: RigConfig, arms: list[ArmKinematics]) -> None:
    """ConfigError unless the plan was made for this rig's geometry and magnets."""
    d = rig.depm
    assert d is not None
    if len(plan.arms) != len(arms):
        raise ConfigError(f"the plan has {len(plan.arms)} arms, the rig {len(arms)}")
    for arm_plan, kin in zip(plan.arms, arms):
        base = base_transform(np.asarray(arm_plan.position_mm) * 1e-3, arm_plan.rpy_deg)
        if arm_plan.name != kin.name or not np.allclose(base, kin.base, atol=1e-6):
            raise ConfigError(f"plan arm {arm_plan.name!r} stands at {list(arm_plan.position_mm)} mm "
                              f"{list(arm_plan.rpy_deg)} deg; the rig's arm {kin.name!r} elsewhere: "
                              "re-plan for this rig")
    if not math.isclose(plan.epm_moment_Am2, d.epm_moment_Am2, rel_tol=1e-6) or \
            not math.isclose(plan.tool_offset_mm, d.tool_offset_mm, rel_tol=1e-6):
        raise ConfigError(f"the plan assumes EPM moment {plan.epm_moment_Am2} A m^2 and tool offset "
                          f"{plan.tool_offset_mm} mm; the rig has {d.epm_moment_Am2} and "
                          f"{d.tool_offset_mm}: re-plan for this rig")


REAL_ARMS_REFUSED = (
    "refused on real arms: rigctl's LBR iiwa model (rigctl.physics.kinematics) turns joint A4 the "
    "opposite way from KUKA's own chain, so the magnets would not be where the plan and its safety "
    "checks put them (docs/depm.md, 'Before a real arm'); emulated benches are not affected")
"""Until the arm model is corrected and checked against a real robot's `Eef_pos`: found by the
audit of the KST server (docs/kuka-sunrise.md), which computes `Eef_pos` with KUKA's chain."""


def stream_rates(servo_rate_hz: float, time_scale: float) -> tuple[float, float]:
    """(targets per plan second, cycles per real second). A faster-than-real emulated bench gets
    the same number of targets per real second, at most MAX_REAL_RATE_HZ: the robot interpolates
    between them as it does at the nominal rate."""
    plan_rate = servo_rate_hz
    if time_scale > 1:
        plan_rate = min(servo_rate_hz, MAX_REAL_RATE_HZ / time_scale)
    return plan_rate, plan_rate * time_scale


# -- tracking -------------------------------------------------------------------------------------


class _Tracking:
    """Notices a joint that is behind its targets by more than the tolerance and does not catch up
    for STALL_TIME_S (plan seconds). A joint that lags but gains ground (after a late stream cycle
    it races after a target that jumped) is fine; a stalled one loses ground or holds."""

    def __init__(self, tolerance_rad: float) -> None:
        self.tolerance = tolerance_rad
        self.since: np.ndarray = np.full(7, np.nan)  # plan time the joint fell behind
        self.lag_then = np.zeros(7)

    def update(self, t_plan: float, lag: np.ndarray) -> tuple[int, float, float] | None:
        behind = lag > self.tolerance
        gained = behind & (lag < self.lag_then - self.tolerance / 2)
        start = behind & (np.isnan(self.since) | gained)
        self.since[start] = t_plan
        self.lag_then[start] = lag[start]
        self.since[~behind] = np.nan
        stuck = np.flatnonzero(behind & (t_plan - self.since > STALL_TIME_S))
        if len(stuck):
            j = int(stuck[np.argmax(lag[stuck])])
            return j, float(lag[j]), float(self.since[j])
        return None


def _distance_to_span(q: np.ndarray, targets) -> np.ndarray:
    """Per joint, how far `q` is outside the range the previous targets span: the robot is
    somewhere on its way between them (it interpolates from one to the next over a stream period,
    and a period can be longer or shorter than the last one), so only beyond them is it behind."""
    span = np.array(targets)
    below = span.min(axis=0) - q
    above = q - span.max(axis=0)
    return np.maximum(np.maximum(below, above), 0.0)


# -- the program ----------------------------------------------------------------------------------


class _Correcting:
    """A hold being corrected: its window, request (mT, mT/m), the plan's pose there, the move
    under way, the samples since it settled, the steps made and the residuals measured."""

    def __init__(self, window: int, requested: np.ndarray, plan_pose: np.ndarray, *,
                 settle_until: float) -> None:
        self.window = window
        self.requested = np.asarray(requested, dtype=float)
        self.plan_pose = plan_pose
        self.settle_until = settle_until
        self.move: JointPath | None = None
        self.move_t = 0.0
        self.buffer: list[np.ndarray] = []
        self.steps = 0
        self.residuals: list[float] = []


class FieldSequenceProgram(RequestedControl):
    """A field-sequence plan streamed to the two arms' servo (see the module docstring).
    Construction refuses a plan this rig must not run (ConfigError, SafetyRefusal), with no I/O."""

    late = "skip"

    def __init__(self, plan, rig: RigConfig, *, time_scale: float = 1.0,
                 closed_loop: bool = True) -> None:
        if rig.rig.kind != "depm" or rig.depm is None:
            raise ConfigError(f"a field-sequence plan runs on a depm rig with a [depm] table; this "
                              f"rig is {rig.rig.kind!r}")
        if not time_scale > 0:
            raise ConfigError("--time-scale must be positive")
        if time_scale != 1.0 and not rig.emulated:
            raise ConfigError("--time-scale is for emulated benches only; a real rig runs at 1")
        if not rig.emulated:
            raise ConfigError(REAL_ARMS_REFUSED)
        d = rig.depm
        depm_rig = rig_from_settings(d)
        self.arms, self.limits = depm_rig.arms, depm_rig.limits
        check_plan_against_rig(plan, rig, self.arms)
        found = plan_violations(plan, self.arms, self.limits)
        if found:
            raise SafetyRefusal("the plan's trajectories break", found)
        self.plan, self.rig, self.settings, self.time_scale = plan, rig, d, float(time_scale)
        self.plan_rate_hz, self.rate_hz = stream_rates(d.servo_rate_hz, self.time_scale)
        self.t_start_s, self.t_end_s = float(plan.t_s[0]), float(plan.t_s[-1])
        self.n_moves = len(plan.segments)
        self.duration_s = self.t_end_s - self.t_start_s
        self.info = {"name": plan.name or "field-sequence", "segments": self.n_moves,
                     "duration_s": round(self.duration_s, 3)}
        self.curves = joint_trajectory(plan)
        self.windows = windows_of(plan)
        self.tolerance_rad = math.radians(d.tracking_tolerance_deg)
        self.requests = Requests()  # control, set from any thread
        # state of the stream thread
        self.paused = False
        self.suspended: str | None = None
        self.timeline: Timeline | None = None
        self.refused: SafetyRefusal | None = None
        self._ctx: RunContext | None = None
        self._hall: HallWatch | None = None
        self._field = None  # the record's `field` series
        self._estimator: np.ndarray | None = None
        self._recent: list[deque] = []
        self._trackers = [_Tracking(self.tolerance_rad) for _ in self.arms]
        self._last_k: int | None = None
        self._last_target: np.ndarray | None = None
        self._cycles = 0
        self._abort_sent = False
        self._announced = 0
        self._plan_started = False
        self._plan_started_s = math.inf
        self._clock: deque[tuple[float, float, bool]] = deque(maxlen=CLOCK_WINDOW)
        self._last_cycle_s: float | None = None
        self._hall_trouble_since: float | None = None
        # what the outcome reports
        self.times: list[float] = []
        self.estimates: list[np.ndarray] = []
        self.samples = self.held_samples = self.saturated = self.skipped = 0
        self.max_cycle_gap_s = 0.0
        self.suspended_s = 0.0
        self.approach_s = 0.0
        self.plan_time_reached_s = self.t_start_s
        # the Hall correction (closed loop): per window, the joints' offset found at its hold
        self.closed_loop = bool(closed_loop)
        self._offsets = HoldOffsets(np.array([w.reached_s for w in self.windows]),
                                    np.array([w.end_s for w in self.windows]),
                                    np.array([a.model.lower_rad for a in self.arms]),
                                    np.array([a.model.upper_rad for a in self.arms]))
        self._scales = correction.kind_scales([w.U for w in self.windows])
        self._correcting: _Correcting | None = None
        self._corrected: set[int] = set()
        self.corrections: list[dict] = []

    @property
    def aborted(self) -> bool:
        return self.requests.abort_wanted

    # -- the run's phases -----------------------------------------------------------------------
    def checks(self) -> list:
        """The pre-flight of the plan's trajectories (`rigctl.rigs.depm.certify`)."""
        from rigctl.plans.depm import DepmRig
        from rigctl.rigs.depm.certify import field_sequence_checks

        depm_rig = DepmRig(arms=self.arms, moment_Am2=self.settings.epm_moment_Am2,
                           limits=self.limits)
        return field_sequence_checks(self.plan, self.rig, depm_rig, self.rate_hz)

    def start(self, ctx: RunContext) -> None:
        self._ctx = ctx
        d = self.settings
        if ctx.backdoor is not None:
            ctx.backdoor.request("speed", factor=self.time_scale)
            ctx.record.event("time_scale", factor=self.time_scale, plan_rate_hz=self.plan_rate_hz,
                             rate_hz=self.rate_hz)
        self._hall = HallWatch(d.hall_url, timeout_s=d.reply_timeout_s + 0.1).open()
        offsets = self._hall.offsets_m
        assert offsets is not None
        self._estimator = sensor_estimator(offsets)  # once: the offsets are fixed
        sensors = [f"B{i + 1}{axis}" for i in range(len(offsets)) for axis in "xyz"]
        u_columns = [f"U_{c}" for c in U_COMPONENTS]
        units = {"t_s": "s since the run started", "t_plan_s": "s on the plan's clock",
                 "seq": "board sample number", "held": "1 while the arms were held (not measured)",
                 **{c: "mT" for c in sensors},
                 **{c: ("mT" if i < 3 else "mT/m") for i, c in enumerate(u_columns)}}
        self._field = ctx.record.open_series("field", ["t_s", "t_plan_s", "seq", "held",
                                                       *sensors, *u_columns], units)
        ctx.record.event("connected", device=HALL_NAME, url=d.hall_url,
                         offsets_mm=(offsets * 1e3).tolist())

    def connected(self, actuators: ArmPair) -> None:
        """Read where the arms stand; refuse an approach that breaks a constraint (nothing has
        moved, nothing will)."""
        assert self._ctx is not None
        record = self._ctx.record
        q_now = actuators.joint_positions()
        q_start = np.array([a.joints_rad[0] for a in self.plan.arms], dtype=float)
        approach = approach_path(q_now, q_start, self.arms, self.limits)
        found = path_violations(approach, self.arms, self.limits)
        if found:
            # the engine records the refusal (its `violations` listed) and ends the run refused
            self.refused = SafetyRefusal("the approach to the plan's first pose breaks", found)
            raise self.refused
        speed, accel = caps(self.arms, self.limits)
        self.timeline = Timeline(approach, self.curves, self.t_start_s, self.t_end_s, speed, accel)
        if self.closed_loop:
            self.timeline.correct = self._offsets.apply
        self.approach_s = approach.duration_s
        self._recent = [deque([q], maxlen=TRACKING_TARGETS + 1) for q in q_now]
        self._last_target = q_now.copy()
        record.event("approach", duration_s=round(approach.duration_s, 3), q_from=q_now.tolist(),
                     q_to=q_start.tolist())
        if self.plan.planner == "agnostic":
            self._ctx.say("the magnetic-agnostic baseline: straight joint moves to the plan's end poses")
        self._ctx.say(f"approach: the arms to the plan's first pose, one after the other, at "
                      f"{self.limits.speed_fraction:.0%} speed ({approach.duration_s:.1f} s)")

    def next(self, k: int, measured: np.ndarray | None) -> Step | None:
        tl = self.timeline
        assert tl is not None and self._last_target is not None
        dt, now = self._tick(k)
        if measured is not None:
            self._check_tracking(k / self.plan_rate_hz, measured)
        samples = []
        if self._cycles % SAMPLE_EVERY == 0 or tl.finished or self.requests.abort_wanted:
            samples = self._poll_hall(now)
        self._cycles += 1
        if self.requests.abort_wanted:
            return self._abort_step(k, measured, samples)
        if tl.finished:
            self._take(samples)
            self._ctx.record.event("plan_done", t_plan_s=self.plan_time_reached_s)
            return None
        hold = self.requests.pause_wanted or self.suspended is not None
        if self._correcting is None and self.closed_loop and not hold and tl.held is None \
                and tl.rejoin is None and not tl.in_approach:
            self._start_correction(tl)
        if self._correcting is not None:
            self.paused = self.requests.pause_wanted
            if not hold:
                self._correct(tl, dt, samples, now)
            target = (tl.held if tl.held is not None else tl.advance(0.0)).copy()
            return self._step(k, target, samples, "paused" if self.paused else "hall correction")
        return self._timeline_step(k, dt, measured, samples, hold)

    def _tick(self, k: int) -> tuple[float, float]:
        """Cycle `k` begins: the plan time since the last cycle (s) and the monotonic time now;
        the cycles skipped and the longest gap between two are counted for the summary."""
        dt = 0.0 if self._last_k is None else (k - self._last_k) / self.plan_rate_hz
        if self._last_k is not None:
            self.skipped += max(0, k - self._last_k - 1)
        self._last_k = k
        now = time.monotonic()
        if self._last_cycle_s is not None:
            self.max_cycle_gap_s = max(self.max_cycle_gap_s, now - self._last_cycle_s)
        self._last_cycle_s = now
        return dt, now

    def _abort_step(self, k: int, measured: np.ndarray | None, samples: list) -> Step | None:
        """An abort stops the arms where they are: one step holding the measured pose, then the
        end."""
        if self._abort_sent:
            return None
        self._abort_sent = True
        target = (measured if measured is not None else self._last_target).reshape(
            len(self.arms), -1)
        self.timeline.hold(target)
        return self._step(k, target, samples, stage="abort")

    def _timeline_step(self, k: int, dt: float, measured: np.ndarray | None, samples: list,
                       hold: bool) -> Step:
        """The timeline's next target, `dt` s of plan on: held where a pause (at the measured
        pose if immediate) or a suspension asks, released when neither does."""
        tl = self.timeline
        if hold and tl.held is None:
            now_pose = self.requests.immediate and self.requests.pause_wanted and measured is not None
            tl.hold(measured.reshape(len(self.arms), -1) if now_pose else self._last_target)
        elif not hold and tl.held is not None:
            tl.release()
        self.paused = tl.held is not None and self.requests.pause_wanted
        target = tl.advance(dt)
        stage = None
        if tl.held is not None:
            stage = "paused" if self.paused else "suspended"
        elif tl.rejoin is not None:
            stage = "rejoin"
        elif tl.in_approach:
            stage = "approach"
        return self._step(k, target, samples, stage)

    def _step(self, k: int, target: np.ndarray, samples: list, stage: str | None) -> Step:
        tl = self.timeline
        assert tl is not None and self._ctx is not None
        record = self._ctx.record
        held = tl.held is not None or tl.rejoin is not None
        t_plan = min(tl.plan_time_s, self.t_end_s)
        if not tl.in_approach:
            if not self._plan_started:
                self._plan_started = True
                self._plan_started_s = time.monotonic()
                record.event("at_start")
            self._clock.append((time.monotonic(), t_plan, held))
            self.plan_time_reached_s = t_plan
            segments = self.plan.segments
            while self._announced < len(segments) and segments[self._announced].start_s <= t_plan:
                record.event("segment", name=segments[self._announced].name, t_plan_s=t_plan)
                self._announced += 1
        self._take(samples)
        for a, q in enumerate(target):
            self._recent[a].append(q)
        self._last_target = target
        move = self._announced - 1 if not tl.in_approach else -1
        if stage is None and move >= 0:
            stage = self.plan.segments[move].name
        return Step(target.ravel().copy(), sample=k, move=-1 if held else move,
                    stage=stage, t_s=t_plan)

    def _check_tracking(self, t_s: float, measured: np.ndarray) -> None:
        """`measured` answers the last target sent, so it is compared with the ones before it."""
        q = measured.reshape(len(self.arms), -1)
        for a, arm in enumerate(self.arms):
            recent = list(self._recent[a])
            span = recent[:-1] if len(recent) > 1 else recent
            stuck = self._trackers[a].update(t_s, _distance_to_span(q[a], span))
            if stuck is not None:
                j, behind, since = stuck
                raise DeviceError(
                    f"joint A{j + 1} is {math.degrees(behind):.1f} deg behind its targets and "
                    f"not catching up since t = {since:.2f} s (tolerance "
                    f"{self.settings.tracking_tolerance_deg:g} deg): a stalled or blocked joint; "
                    "run stopped", device=arm.name)

    # -- the Hall correction ---------------------------------------------------------------------
    def _start_correction(self, tl: Timeline) -> None:
        """At a window's hold not yet corrected: stop the plan's clock, hold, start measuring."""
        t = tl.plan_time_s
        due = [i for i, w in enumerate(self.windows)
               if i not in self._corrected and w.reached_s <= t < w.end_s]
        if not due:
            return
        i = due[0]
        self._corrected.add(i)
        pose = tl.pose_at_clock()
        tl.hold(pose)
        plan_pose = np.array([curve(min(t, self.t_end_s)) for curve in self.curves])
        self._correcting = _Correcting(i, self.windows[i].U, plan_pose, settle_until=time.monotonic()
                                       + correction.SETTLE_S)
        self._ctx.record.event("hall_correction", window=self.windows[i].name, t_plan_s=t)

    def _correct(self, tl: Timeline, dt: float, samples: list, now: float) -> None:
        c = self._correcting
        assert c is not None and tl.held is not None and self._estimator is not None
        if c.move is not None:
            c.move_t += dt
            tl.held = c.move.at(min(c.move_t, c.move.duration_s))
            if c.move_t >= c.move.duration_s:
                tl.held = c.move.q_to.copy()
                c.move = None
                c.settle_until = now + correction.SETTLE_S
                c.buffer.clear()
            return
        for sample in samples:
            if sample.received_s >= c.settle_until:
                c.buffer.append(sample.field_T.reshape(-1) @ self._estimator.T * 1e3)
        if len(c.buffer) < correction.SAMPLES:
            return
        measured, sem = correction.mean_and_sem(c.buffer)
        c.buffer.clear()
        significant = correction.significant_residual(c.requested, measured, sem)
        residual = float(np.max(np.abs(significant) / self._scales))
        c.residuals.append(float(np.max(np.abs(c.requested - measured) / self._scales)))
        if residual <= correction.TARGET or c.steps >= correction.MAX_STEPS:
            self._finish_correction(tl, "converged" if residual <= correction.TARGET else "steps")
            return
        q = tl.held.copy()
        dq = correction.correction_step(self.arms, self.settings.epm_moment_Am2, q, c.requested,
                                        c.requested - significant, self._scales)
        speed, accel = caps(self.arms, self.limits)
        move = joint_path(q, q + dq, speed, accel, one_at_a_time=False)
        found = path_violations(move, self.arms, self.limits)
        if found:
            self._finish_correction(tl, f"a step would break a constraint: {found[0]}")
            return
        c.move, c.move_t = move, 0.0
        c.steps += 1

    def _finish_correction(self, tl: Timeline, why: str) -> None:
        c = self._correcting
        assert c is not None and tl.held is not None and self._ctx is not None
        self._correcting = None
        self._offsets.offsets[c.window] = tl.held - c.plan_pose
        tl.held = self._offsets.apply(tl.plan_time_s, c.plan_pose)  # the same pose, clipped
        found = self._offsets.blend_violations(c.window, self.curves, self.arms, self.limits)
        if found:  # the blend out would break a constraint: back to the plan's path instead
            del self._offsets.offsets[c.window]
            why += f"; dropped: its blend would break {found[0]}"
        entry = {"window": self.windows[c.window].name, "steps": c.steps, "why": why,
                 "residual_pct": [round(100 * r, 3) for r in c.residuals],
                 "max_dq_rad": round(float(np.max(np.abs(tl.held - c.plan_pose))), 5)}
        self.corrections.append(entry)
        self._ctx.record.event("hall_corrected", **entry)
        tl.release()

    # -- the Hall board -------------------------------------------------------------------------
    def _poll_hall(self, now: float) -> list:
        """Samples read so far; suspends (or faults, after HALL_LOST_FAULT_S) without them."""
        assert self._hall is not None and self._ctx is not None
        samples, reason = self._hall.poll()
        record = self._ctx.record
        if reason is not None:
            if self._hall_trouble_since is None:
                self._hall_trouble_since = now
                self.suspended = f"Hall board: {reason}; the arms hold their pose"
                record.event("hall_lost", device=HALL_NAME, reason=reason)
                log.warning("%s: %s; run suspended", HALL_NAME, reason)
            elif now - self._hall_trouble_since > HALL_LOST_FAULT_S and not self.requests.abort_wanted:
                raise DeviceError(f"no samples for {now - self._hall_trouble_since:.1f} s "
                                  f"({reason}); the run stopped", device=HALL_NAME)
        elif self._hall_trouble_since is not None:
            lost_s = now - self._hall_trouble_since
            self.suspended_s += lost_s
            self._hall_trouble_since = None
            self.suspended = None
            record.event("hall_back", device=HALL_NAME, after_s=round(lost_s, 3))
        return samples

    def _take(self, samples: list) -> None:
        """Samples on the plan's clock: a sample's arrival is placed between the stream cycles
        around it, so a stream that runs late (a loaded computer) stays aligned with the plan.
        Samples from before the plan's start (the approach) are not the run's."""
        if not samples or not self._clock:
            return
        assert self._estimator is not None and self._field is not None and self._ctx is not None
        mono = np.array([c[0] for c in self._clock])
        plan_t = np.array([c[1] for c in self._clock])
        held_at = np.array([c[2] for c in self._clock])
        fields = np.array([s.field_T for s in samples])
        U = fields.reshape(len(fields), -1) @ self._estimator.T * 1e3  # mT and mT/m
        received = np.array([s.received_s for s in samples])
        t_plans = np.interp(received, mono, plan_t)
        index = np.searchsorted(mono, received, side="right") - 1
        t0 = self._ctx.record.t0
        for sample, u, f, t_plan, i in zip(samples, U, fields, t_plans, index):
            if sample.received_s < self._plan_started_s:
                continue
            held = bool(held_at[max(i, 0)])
            self._field.row([sample.received_s - t0, float(t_plan), sample.seq, int(held),
                             *(f.ravel() * 1e3), *u])
            self.saturated += int(sample.saturated.any())
            if held:
                self.held_samples += 1
                continue
            self.times.append(float(t_plan))
            self.estimates.append(u)
            self.samples += 1

    # -- the end --------------------------------------------------------------------------------
    def finish(self, ctx: RunContext) -> Outcome:
        self.close()
        metrics = self.metrics()
        return Outcome(reached=metrics["reached"], positions_from="Hall board (eq. 24)",
                       tolerance_mm=None, metrics=metrics, details=summary_lines(metrics))

    def metrics(self) -> dict:
        """Today's figures of the run (the `metrics` of its summary)."""
        table = cross = None
        if self.times:
            t, U = np.array(self.times), np.array(self.estimates)
            table = table1(t, U, self.windows)
            cross = cross_activation(t, U, self.windows)
        completed = self.timeline is not None and self.timeline.finished and not self.requests.abort_wanted
        found = self.refused.violations if self.refused is not None else []
        reached = completed and self.refused is None and steady_state_reached(table)
        return {
            "plan": self.info["name"], "planner": self.plan.planner, "reached": reached,
            "completed": completed, "violations": len(found),
            "violation_list": [str(v) for v in found],
            "refused": None if self.refused is None else self.refused.headline,
            "table1": table, "cross_activation": cross,
            "duration_s": round(self.plan_time_reached_s - self.t_start_s, 3),
            "approach_s": round(self.approach_s, 3), "samples": self.samples,
            "held_samples": self.held_samples,
            "samples_lost": 0 if self._hall is None else self._hall.missed,
            "saturated_samples": self.saturated, "skipped_cycles": self.skipped,
            "max_cycle_gap_s": round(self.max_cycle_gap_s, 4), "time_scale": self.time_scale,
            "hall_outages": 0 if self._hall is None else self._hall.outages,
            "suspended_s": round(self.suspended_s, 3),
            "rejoins": 0 if self.timeline is None else self.timeline.rejoins,
            "hall_correction": {"on": self.closed_loop, "holds": self.corrections},
        }

    def close(self) -> None:
        if self._hall is not None:
            self._hall.close()


# -- the run --------------------------------------------------------------------------------------


def FieldSequenceRun(plan, rig: RigConfig, *, time_scale: float = 1.0, closed_loop: bool = True,
                     **run_options) -> EngineRun:
    """The run of a field-sequence plan on a dual-EPM rig (the one engine with this program);
    `closed_loop` corrects each hold on the Hall board's U (`correction`); `run_options` are the
    engine's (`runs_dir`, `progress_out`, `on_cycle`, `on_state`). Refuses (ConfigError,
    SafetyRefusal) before anything is opened."""
    return EngineRun(FieldSequenceProgram(plan, rig, time_scale=time_scale, closed_loop=closed_loop),
                     rig, ArmPair.connect, **run_options)


# -- what a person reads --------------------------------------------------------------------------


def _fmt(value, digits=2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def summary_lines(m: dict) -> list[str]:
    """The Table 1 table, the cross-activation matrix and the sampling figures of a run's
    `metrics` (the summary's `details`)."""
    lines = [f"field sequence: {m['plan']} ({m['planner']} planner); violations: {m['violations']}"]
    if m.get("refused"):
        lines.append(f"refused: {m['refused']} (each one in the fault below)")
        return lines
    table = m.get("table1")
    if table is not None:
        lines.append(f"{'':8}{'request':>9}{'steady':>9}{'err %':>7}{'peak off':>10}{'rise %':>8}"
                     f"{'fall %':>8}{'sigma off':>10}  unit")
        for label in U_COMPONENTS:
            e = table[label]
            lines.append(f"{label:8}{_fmt(e['requested']):>9}{_fmt(e['steady_state']):>9}"
                         f"{_fmt(e['steady_state_error_pct'], 1):>7}"
                         f"{_fmt(e['peak_off_activation']):>10}{_fmt(e['overshoot_rise_pct'], 1):>8}"
                         f"{_fmt(e['overshoot_fall_pct'], 1):>8}{_fmt(e['sigma_off']):>10}  {e['unit']}")
        a = table["average"]
        lines.append(f"average  fields: peak off {_fmt(a['peak_off_activation_field_mT'])} mT, sigma "
                     f"{_fmt(a['sigma_off_field_mT'])} mT; gradients: peak off "
                     f"{_fmt(a['peak_off_activation_gradient_mT_per_m'])} mT/m, sigma "
                     f"{_fmt(a['sigma_off_gradient_mT_per_m'])} mT/m; overshoot rise "
                     f"{_fmt(a['overshoot_rise_pct'], 1)} %, fall {_fmt(a['overshoot_fall_pct'], 1)} %")
        lines.append(f"steady-state error: mean {_fmt(a['steady_state_error_pct'])} %, max "
                     f"{_fmt(a['steady_state_error_max_pct'])} % "
                     f"(goal < {100 * STEADY_STATE_TOLERANCE:g} %)")
    ca = m.get("cross_activation")
    if ca is not None:
        lines.append("cross-activation during each rise (% of the requested field / gradient):")
        lines.append(f"{'':8}" + "".join(f"{c:>8}" for c in ca["columns"]))
        for name, row in zip(ca["rows"], ca["percent"]):
            lines.append(f"{name:8}" + "".join(f"{_fmt(v, 0):>8}" for v in row))
    lines.append(f"samples: {m['samples']} ({m['samples_lost']} lost, {m['saturated_samples']} "
                 f"saturated, {m['held_samples']} while held); plan streamed "
                 f"{m['duration_s']:.1f} s after a {m['approach_s']:.1f} s approach; time scale "
                 f"{m['time_scale']:g}; {m['skipped_cycles']} stream cycles skipped (late, longest "
                 f"gap {m['max_cycle_gap_s'] * 1e3:.0f} ms)")
    if m.get("hall_outages"):
        lines.append(f"Hall board lost {m['hall_outages']} time(s); suspended {m['suspended_s']:.1f} s")
    if not m.get("completed"):
        lines.append("the plan did not run to its end")
    return lines
