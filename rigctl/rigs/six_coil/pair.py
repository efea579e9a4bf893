"""Run a pair-formation plan (seed 002) on the six-coil rig: field angle + pull streamed as currents,
the loop closed through the camera with pure pursuit and the proximity controller.

`PairProgram` is the pair's `RigProgram` for the one run engine (`rigctl.run.engine.Run`), which
owns the record, the start-up order, the stream loop, the states, e-stop and the summary; `PairRun`
builds that run. Before anything is opened: the plan is checked (its own model, every constraint),
its pull bound is compared with what this rig's coils make, and the open-loop program (every
segment as the 8-vector U -> six currents at the stream rate, then the hold) is allocated with
every current and voltage limit checked. Then the agents are placed (emulated bench), found by the
camera, and the supplies switched on.

Closed loop (default whenever the rig has a camera): on every fresh frame the measured formation is
carried forward over the camera's latency and `PairPursuit` picks the control; its currents go out
on the next stream cycle, rate-limited so no supply needs more than 90 % of its compliance
voltage. The pull gain is identified from the frames as the run goes (`PullIdentification`) and
the pursuit pursues with it (`settings.identify_pull`; `metrics.pull_identified`, the record's
`identification` series). While tracking is lost the run is suspended and the agents are held
unseen (no pull, the field flipped about the zero-radial angle of their last heading); lost for
`lost_after_s` is a fault of the camera. When the agents stay off the path (proximity mode)
longer than `replan_after_s`, the path is re-planned from the measured state onto the rest of the path in a
worker thread and spliced in. At the last node the goal formation is held for the plan's `hold_s`.
`--open-loop` plays the plan's controls back (the paper's open-loop mode); the camera, if any,
still measures.

The summary is the runs' one shape (`RunSummary`), errors in body lengths (`unit="bl"`); its
`metrics` add `rms_tracking_error_bl` (each measured agent's distance to its planned path, RMS
over frames and agents), `max_tracking_error_bl`, `min_separation_bl` (smallest measured centre
distance; `truth_min_separation_bl` the emulator's), `hold_max_error_bl` (largest agent distance
from its goal while holding), `held_s`, `replan_ms`, `mode` and, closed loop, `pull_identified`
(gain, gain_std, heading_deg, windows_used).
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from rigctl.core.errors import ConfigError, LimitError, PlanError
from rigctl.core.record import RunRecord
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.physics.coils import u_actuation_matrix
from rigctl.physics.identify import CommandedVelocity, RollingIdentifier
from rigctl.plans.pair import (
    ZERO_RADIAL_ANGLE_RAD,
    PairPlannerOptions,
    agent_positions,
    check,
    goal_error,
    physics_of,
    plan_arrays,
    problem_of,
    replan_pair,
    rig_max_pull,
    simulate,
    state_from_positions,
    state_of,
)
from rigctl.plans.schema import MAX_PROGRAM_SAMPLES, PairFormationPlan
from rigctl.rigs.six_coil.allocate import check_current_limits, field_and_pull_u
from rigctl.rigs.six_coil.pursuit import PairPursuit, PursuitSettings, distance_to_path
from rigctl.rigs.six_coil.supplies import CoilSupplies
from rigctl.run.agents import agent_results, place_agents, read_truth
from rigctl.run.engine import Outcome, RunContext, Step
from rigctl.run.engine import Run as EngineRun
from rigctl.run.interruptions import RequestedControl, Requests, Suspension

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

log = logging.getLogger(__name__)

CONTROLLER_PULL_SHARE = 0.95  # of the rig's largest pull: the plan used PULL_MARGIN (0.8) of it
VOLTAGE_SHARE = 0.9  # closed-loop current steps are limited to keep R I + L dI/dt below this
HOLD_START_SHARE = 0.75  # the hold's clock starts when both agents are this share of the tolerance in
LOOPBACK_REPLY_TIMEOUT_S = 1.0  # supplies' watchdog when execute started the emulated bench
HOLD_DITHER_S = 0.1  # a hold's field switches between 54.74 and 125.26 deg this often
RAMP, HOLD = -1, -2  # stages of the open-loop program that are not segments
PULL_GAIN_LIMITS = (0.3, 3.0)  # an identified pull gain outside these is not believed


@dataclass(frozen=True)
class PairRunSettings:
    closed_loop: bool = True
    pursuit: PursuitSettings = PursuitSettings()
    ramp_s: float = 0.1
    timeout_factor: float = 3.0  # give up after this times the plan's duration ...
    timeout_extra_s: float = 30.0  # ... plus this
    replan_after_s: float = 2.0
    lost_after_s: float = 2.0  # tracking lost this long: a fault
    stale_s: float = 0.25  # no fresh frame this long: hold the agents unseen (a frozen camera)
    identify_pull: bool = True  # identify the pull gain from tracking and pursue with it
    identify_window_s: float = 0.5  # the camera's frames this far apart make one measurement


@dataclass
class PreparedPair:
    plan: PairFormationPlan
    problem: object
    nodes: np.ndarray  # (k + 1, 4) start and expected states, BL
    program_A: np.ndarray  # (T, n) open-loop currents, ramps and hold included
    stage_of: np.ndarray  # (T,) int per program sample: segment index, HOLD for the hold, RAMP
    u_to_currents: np.ndarray  # (n, 8) pinv of the U actuation matrix
    controller_pull: float  # BL/s


def u_of(plan: PairFormationPlan, u: np.ndarray) -> np.ndarray:
    """The 8-vector U (..., 8) for controls u = (psi_g, f_x, f_y) (..., 3) of this plan's agents."""
    physics = physics_of(plan)
    u = np.asarray(u, dtype=float)
    force = u[..., 1:] * physics.drag_N_s_per_m * physics.diameter_m
    return field_and_pull_u(u[..., 0], force, physics.moment_Am2, plan.field_mT * 1e-3)


def hold_field_angle(phi: float, flipped: bool) -> float:
    """The field angle (rad) that holds a pair of heading `phi` (rad) where it is: the zero-radial
    angle, 54.74 deg to the line of centres, or with `flipped` its mirror 125.26 deg (no radial
    force either, the transverse force reversed; seed 002's sign flip of psi, as the forces do not
    change when the field turns by 180 deg). Flipping between these two turns the field through
    90 deg, where the agents repel, instead of through 0 deg, where they attract most: the coils
    take tens of ms to turn the field, and a flip through 0 deg pulled a held pair into contact."""
    return phi + (math.pi - ZERO_RADIAL_ANGLE_RAD if flipped else ZERO_RADIAL_ANGLE_RAD)


def open_loop_controls(plan: PairFormationPlan, rate_hz: float,
                       ramp_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per stream sample: the control (T, 3), the field scale (T,) and the stage (T,) int (ramp
    up, segments, the hold at the goal heading's `hold_field_angle`s, ramp down): the segment's
    index, `HOLD` while holding, `RAMP` while ramping."""
    start, controls, dts = plan_arrays(plan)
    ramp = max(1, round(ramp_s * rate_hz))
    rows, scale, stage = [], [], []
    first = controls[0] if len(controls) else np.array([start[3] + ZERO_RADIAL_ANGLE_RAD, 0, 0])
    for k in range(ramp):
        rows.append([first[0], 0.0, 0.0])
        scale.append((k + 1) / ramp)
    stage += [RAMP] * ramp
    for i, (u, dt) in enumerate(zip(controls, dts)):
        n = max(1, round(dt * rate_hz))
        rows += [u.tolist()] * n
        scale += [1.0] * n
        stage += [i] * n
    goal_phi = math.radians(plan.goal.phi_deg)
    per = max(1, round(HOLD_DITHER_S * rate_hz))
    held = max(0, round(plan.hold_s * rate_hz))
    flipped = (np.arange(held) // per) % 2 == 1  # the hold as arrays: it may be 10^5 samples
    hold = np.zeros((held, 3))
    hold[:, 0] = np.where(flipped, hold_field_angle(goal_phi, True),
                          hold_field_angle(goal_phi, False))
    last = hold[-1, 0] if held else rows[-1][0]
    down = np.zeros((ramp, 3))
    down[:, 0] = last
    return (np.vstack([np.array(rows).reshape(-1, 3), hold, down]),
            np.concatenate([scale, np.ones(held), 1.0 - (np.arange(ramp) + 1) / ramp]),
            np.concatenate([stage, np.full(held, HOLD), np.full(ramp, RAMP)]).astype(int))


def prepare_pair(plan: PairFormationPlan, rig: SixCoilRig, settings: PairRunSettings) -> PreparedPair:
    """Every refusal, no I/O: plan checks, the rig's pull, the open-loop program's limits."""
    if rig.rig.kind != "six-coil":
        raise PlanError(f"a pair-formation plan runs on a six-coil rig, not a {rig.rig.kind} rig")
    samples = (sum(s.dt_s for s in plan.segments) + plan.hold_s + 2 * settings.ramp_s) * rig.stream.rate_hz
    if samples > MAX_PROGRAM_SAMPLES:  # before the program is built, a list per sample
        raise PlanError(f"segments: {samples:.3g} samples of program at {rig.stream.rate_hz:g} Hz; "
                        f"at most {MAX_PROGRAM_SAMPLES} (fewer or shorter segments)")
    if plan.expected is None:
        plan = simulate(plan)
    check(plan)
    physics = physics_of(plan)
    rig_pull = rig_max_pull(rig, physics, plan.field_mT)
    if rig_pull == 0.0 and plan.max_pull_bl_s > 0.0:
        raise LimitError(f"the plan pulls up to {plan.max_pull_bl_s:.3f} BL/s but this rig's coils "
                         "make no field gradient at the workspace centre (a uniform-field rig, such "
                         "as a Helmholtz triad, cannot pull): a pair-formation plan needs a rig "
                         "whose coils make gradients")
    if plan.max_pull_bl_s > rig_pull * (1 + 1e-6):
        raise LimitError(f"the plan pulls up to {plan.max_pull_bl_s:.3f} BL/s but this rig's coils "
                         f"make at most {rig_pull:.3f} BL/s with a {plan.field_mT:g} mT field; "
                         "re-plan with --rig for this rig")
    A8 = u_actuation_matrix(rig)
    pinv = np.linalg.pinv(A8)
    controls, scale, stage_of = open_loop_controls(plan, rig.stream.rate_hz, settings.ramp_s)
    U = u_of(plan, controls)
    U[:, :3] *= scale[:, None]

    def describe(k: int) -> str:
        return (f"segment {int(stage_of[k])}" if stage_of[k] >= 0
                else f"sample {k} (ramp or hold)")

    # the current limits on the program as asked: `slew_limited` clips to them, which would hide it
    raw = U @ pinv.T
    check_current_limits(
        raw, rig, None, describe,
        current_advice="lower field_mT or re-plan with a smaller pull (--rig for this rig)")
    program = slew_limited(raw, rig)
    check_current_limits(
        program, rig, rig.stream.rate_hz, describe, current_advice="",
        voltage_advice="re-plan: consecutive segments turn the field too far for the coils' "
        "inductance, or raise the coil's compliance_V")
    start = state_of(plan.start, physics.body_diameter_mm)
    expected = [state_of(e, physics.body_diameter_mm) for e in plan.expected or []]
    goal = state_of(plan.goal, physics.body_diameter_mm)
    # the path ends at the goal itself: the planner stops within its tolerance of it, the closed
    # loop closes the rest
    nodes = np.vstack([start[None], *([np.array(expected)] if expected else []), goal[None]])
    return PreparedPair(plan, problem_of(plan), nodes, program, stage_of, pinv,
                        CONTROLLER_PULL_SHARE * rig_pull)


class CoilSlew:
    """Per-sample current steps that keep every supply's R I + L dI/dt within VOLTAGE_SHARE of its
    compliance: a jump between two segments' currents is spread over the samples it needs (the
    coils' L/R = 20 ms lags them about as much anyway)."""

    def __init__(self, rig: SixCoilRig) -> None:
        self.rate = rig.stream.rate_hz
        self.resistance = np.array([c.resistance_ohm for c in rig.coils])
        self.inductance = np.array([c.inductance_H for c in rig.coils])
        self.compliance = np.array([c.compliance_V for c in rig.coils])
        self.limits = np.array([c.current_limit_A for c in rig.coils])

    def step(self, last: np.ndarray, target: np.ndarray) -> np.ndarray:
        target = np.clip(target, -self.limits, self.limits)
        room = np.maximum(VOLTAGE_SHARE * self.compliance - self.resistance * np.abs(target), 0.0) \
            / (self.inductance * self.rate)
        return last + np.clip(target - last, -room, room)


def slew_limited(program: np.ndarray, rig: SixCoilRig) -> np.ndarray:
    """A current program (T, n) with every step limited by `CoilSlew` (starting from 0 A).

    Between two rows where the program changes its target is constant, and once a step there
    changes nothing the rest of that stretch is the same value: it is filled, not stepped; and a
    stretch that starts where an earlier one did, towards the same target, repeats its steps (the
    hold's dither flips between two angles: one transition each way). Sample by sample, a
    32-minute hold at 100 Hz took 2.5 s and a `load` waited for it."""
    slew = CoilSlew(rig)
    out = np.empty_like(program)
    last = np.zeros(program.shape[1])
    settled: dict[tuple[bytes, bytes], np.ndarray] = {}  # (from, target): its steps, then still
    if not len(program):
        return out
    changes = np.flatnonzero(np.any(program[1:] != program[:-1], axis=1)) + 1
    for a, b in itertools.pairwise([0, *changes.tolist(), len(program)]):
        target = program[a]
        key = (last.tobytes(), target.tobytes())
        steps = settled.get(key)
        if steps is None:
            steps, still = _transition(slew, last, target, b - a)
            if still:
                settled[key] = steps
        m = min(len(steps), b - a)
        out[a:a + m] = steps[:m]
        out[a + m:b] = steps[m - 1] if m else last
        last = out[b - 1]
    return out


def _transition(slew: CoilSlew, last: np.ndarray, target: np.ndarray,
                n: int) -> tuple[np.ndarray, bool]:
    """Up to `n` steps from `last` towards `target`, and whether they ended because a step
    changed nothing (from then on the output stays where it is)."""
    steps = []
    for _ in range(n):
        step = slew.step(last, target)
        if np.array_equal(step, last):
            return np.array(steps).reshape(-1, len(last)), True
        steps.append(step)
        last = step
    return np.array(steps).reshape(-1, len(last)), False


class _PauseRequests(Requests):
    """The operator's requests, and the time spent paused: the stream thread decides when a
    pause takes effect (`hold`) and when it ends (`release`); paused time counts towards neither
    the run's timeout nor the goal hold."""

    def __init__(self) -> None:
        super().__init__()
        self.paused = False  # the stream thread's: holding now
        self._since: float | None = None
        self._paused_s = 0.0

    def hold(self, now: float) -> None:
        self.paused, self._since = True, now

    def release(self, now: float) -> None:
        self._paused_s += now - (self._since or now)
        self.paused, self._since = False, None

    def paused_s(self, now: float) -> float:
        """Seconds spent paused so far, the pause going on included."""
        return self._paused_s + (now - self._since if self._since is not None else 0.0)


def expected_headings(nodes: np.ndarray, stage_of: np.ndarray) -> np.ndarray:
    """Per open-loop program sample (T,): the pair heading (rad) the plan expects once that
    sample has been sent, interpolated along each segment (the start's heading before the first
    segment, the goal's after the last). `nodes` (n + 2, 4): start, segment ends, goal."""
    phi = np.full(len(stage_of), float(nodes[-1][3]))
    segments = np.flatnonzero(stage_of >= 0)
    phi[: segments[0] if len(segments) else 0] = float(nodes[0][3])
    for seg in np.unique(stage_of[segments]):
        idx = np.flatnonzero(stage_of == seg)
        a = float(nodes[seg][3])
        turn = math.remainder(float(nodes[seg + 1][3]) - a, 2.0 * math.pi)
        phi[idx] = a + turn * (np.arange(1, len(idx) + 1) / len(idx))
    return phi


class PullIdentification:
    """The pair's pull gain from tracking (`rigctl.physics.identify`): how far the agents' centroid moves
    for the pull commanded. The dipole forces between the agents are equal and opposite, so only
    the coils' pull and a drift move the centroid, c(t1) - c(t0) = g R(theta) int f dt + v (t1 - t0):
    the rolling robots' linear model with the centroid as the one agent and the integral of the
    commanded pull (`CommandedVelocity`) as its move, in mm. A measurement spans `window_s` between
    two frames in which both agents kept `WALL_MARGIN_BL` from every wall (a wall pushes back);
    a hold, a pause, a lost camera or a ramp starts the window again. g lumps the liquid's
    viscosity, the agents' moments and the coils' gradient as built."""

    WALL_MARGIN_BL = 0.3
    MIN_PULL_BL = 0.2  # a window commanded less than this far says nothing of the gain

    def __init__(self, d_mm: float, workspace, window_s: float) -> None:
        self.d_mm, self.workspace, self.window_s = float(d_mm), workspace, float(window_s)
        self.identifier = RollingIdentifier(1, gain_std=0.3, heading_std_rad=0.1,
                                            drift_std_mm_s=0.01 * d_mm, noise_mm=0.03 * d_mm,
                                            noise_per_mm=0.03, names=["centroid"])
        self.commands = CommandedVelocity()
        self._start: tuple[float, np.ndarray] | None = None  # (capture time, centroid mm)
        self._pulling = False

    def send(self, t: float, pull_bl_s: np.ndarray) -> None:
        """The pull (f_x, f_y) BL/s commanded from monotonic time t on."""
        self.commands.send(t, np.asarray(pull_bl_s, dtype=float) * self.d_mm)
        self._pulling = True

    def interrupt(self, t: float) -> None:
        """Something other than the pursuit commands the coils from t on (no pull assumed)."""
        if self._pulling or self._start is not None:
            self.commands.send(t, np.zeros(2))
            self._pulling, self._start = False, None

    def frame(self, t: float, positions_mm: np.ndarray) -> bool:
        """A fresh frame captured at t (both agents seen); True when it closed a measurement the
        estimate took."""
        clear = self.workspace.clearance(positions_mm) >= (0.5 + self.WALL_MARGIN_BL) * self.d_mm
        if not bool(np.all(clear)):
            self._start = None
            return False
        centroid = positions_mm.mean(axis=0)
        if self._start is None or t - self._start[0] < self.window_s:
            if self._start is None:
                self._start = (t, centroid)
            return False
        t0, c0 = self._start
        self._start = (t, centroid)
        pulled = self.commands.integral(t0, t)
        if float(np.hypot(*pulled)) < self.MIN_PULL_BL * self.d_mm:
            return False
        return bool(self.identifier.observe(pulled, (centroid - c0)[None], [True], t - t0)[0])

    def response(self) -> tuple[float, float]:
        """(gain, heading rad) to pursue with."""
        gains, headings = self.identifier.response()
        return float(np.clip(gains[0], *PULL_GAIN_LIMITS)), float(headings[0])


class PairProgram(RequestedControl):
    """One pair-formation plan on one six-coil rig, as the run engine's `RigProgram`:
    construction refuses a bad plan without I/O (`prepare_pair`); `start` places the agents on
    the emulated bench and finds them with the camera; `next` is one stream cycle's currents;
    `finish` the outcome in body lengths. `pause`, `resume` and `abort` may be called from any
    thread.

    A step's `move` is the plan segment being driven (0-based; the closed loop's last approach to
    the goal itself counts as the last segment), and -1 while the field ramps, while paused, while
    the camera has lost the agents and while the goal formation is held. Its `sample` is the
    open-loop program's sample index (it stays put while paused), the stream cycle's index closed
    loop. Its `stage` and `stage_key` are what the progress line shows (`PairStages`).

    A pause holds the agents where they are rather than switching the coils off: these agents
    are permanent magnets, and with no field each turns along the other's and they pull together
    (about 1.2 BL/s at 2 BL apart, seed 002 eq. 1), so zero current would end in contact. The hold
    is the paper's dynamic equilibrium: no pull, the field at the zero-radial angle to the pair's
    heading, flipped every `HOLD_DITHER_S` so the transverse force cancels too (`hold_field_angle`).
    """

    late = "slip"  # a field program: a late cycle shifts the rest, it must not bunch the path

    def __init__(self, plan: PairFormationPlan, rig: SixCoilRig,
                 settings: PairRunSettings = PairRunSettings()) -> None:
        if settings.closed_loop and rig.camera is None:
            raise ConfigError("closed loop needs the rig's camera; this rig has none "
                              "(use --open-loop)")
        prep = self.prepared = prepare_pair(plan, rig, settings)
        self.plan = prep.plan
        self.rig = rig
        self.settings = settings
        self.rate_hz = rig.stream.rate_hz
        self.n_moves = len(self.plan.segments)
        samples = len(prep.program_A)  # the open-loop program; closed loop takes its time
        self.duration_s = samples / self.rate_hz
        self.info = {"name": self.plan.name, "segments": len(self.plan.segments),
                     "samples": samples, "duration_s": round(samples / rig.stream.rate_hz, 3)}
        self.d_mm = self.plan.agents.body_diameter_mm
        self.metrics = _Metrics(prep.nodes)
        self.requests = self._pause = _PauseRequests()
        self._record: RunRecord | None = None
        self._backdoor: BackdoorClient | None = None
        self._tracking = None  # TrackingLoop, once started
        self._truth_at_end: dict | None = None
        # the stream thread's from here on
        self._ramp = max(1, round(settings.ramp_s * self.rate_hz))
        self._slew = CoilSlew(rig)
        self._pursuit_settings = replace(settings.pursuit, max_pull=prep.controller_pull)
        self._pursuit = PairPursuit(prep.problem, prep.nodes, self._pursuit_settings)
        self._dts = plan_arrays(self.plan)[2]
        self._timeout_s = (settings.timeout_factor * float(np.sum(self._dts)) + self.plan.hold_s
                           + settings.timeout_extra_s)
        self._stages = PairStages(len(self.plan.segments), len(prep.nodes))
        self._final_ramp = samples - self._ramp  # open loop: the program's own ramp down
        self._headings = expected_headings(prep.nodes, prep.stage_of)
        self._closed = False  # closed loop with a camera: decided in `start`
        self._last = np.zeros(prep.program_A.shape[1])  # the currents sent last cycle
        self._target: np.ndarray | None = None  # the pursuit's currents from the last frame
        self._frame = -1
        self._started_at: float | None = None
        self._seen_at = 0.0
        self._suspension = Suspension(settings.lost_after_s)
        self._phi = float(prep.nodes[0][3])  # the pair's heading, last seen (or expected)
        self._phi_seen = False
        self._j = 0  # open loop: the next program sample
        self._ramp_down: int | None = None  # cycles into the final ramp down
        self._hold_from: float | None = None  # the goal hold's clock
        self._off_since: float | None = None  # in proximity mode since
        self._replan: threading.Thread | None = None
        self._worker: dict = {}  # the re-plan thread's result
        self._pause_asked: tuple[float, int] | None = None  # (when, node or stage)
        self._held_from: float | None = None  # paused since
        self._awaiting_frame = False  # resumed: the pursuit decides on the next frame
        self._pause_hold: PairPursuit | None = None  # the pause's own hold of the formation
        self._pause_target: np.ndarray | None = None
        self._pull = (PullIdentification(self.d_mm, prep.problem.workspace,
                                         settings.identify_window_s)
                      if settings.identify_pull else None)
        self._series = None  # the record's `identification` series, closed loop

    # -- control: `pause` holds the agents where they are, at the end of the segment being
    # driven (closed loop: when the pursuit reaches its next node, or after the segment's planned
    # time), or at once; `resume` goes on from where they are (closed loop, the pursuit from the
    # next camera frame; open loop, the program from the sample where it stopped); `abort` ramps
    # the field down and ends.
    @property
    def aborted(self) -> bool:
        return self._pause.abort_wanted

    @property
    def paused(self) -> bool:
        return self._pause.paused

    @property
    def suspended(self) -> str | None:
        return self._suspension.reason

    # -- the run's phases -----------------------------------------------------------------------
    def checks(self) -> list:
        """The pre-flight of the open-loop current program (`rigctl.rigs.six_coil.certify`)."""
        from rigctl.rigs.six_coil.certify import current_program_checks

        stage_of = self.prepared.stage_of
        return current_program_checks(
            self.rig, self.prepared.program_A, self.rate_hz, move_ends=[],
            describe=lambda k: f"segment {int(stage_of[k])}" if stage_of[k] >= 0 else "a ramp or hold")

    def start(self, ctx: RunContext) -> None:
        from rigctl.vision.tracking import TrackingLoop

        plan, prep, d = self.plan, self.prepared, self.d_mm
        self._record, self._backdoor = ctx.record, ctx.backdoor
        self._suspension.record = ctx.record
        ctx.record.event("pair", closed_loop=self.settings.closed_loop,
                         timeout_s=round(self._timeout_s, 3))
        start_mm = agent_positions(prep.nodes[0]) * d
        place_agents(ctx, plan, [{"position": p.tolist(), "radius": 0.5 * d} for p in start_mm],
                     pair=plan.agents.model_dump())
        if self.rig.camera is not None:  # the agents are found before anything is energised
            self._tracking = TrackingLoop(self.rig.camera, np.full(2, 0.5 * d), start_mm,
                                          roi_mm=prep.problem.workspace.bounds,
                                          on_floor=prep.problem.workspace.contains)
            self._tracking.record_to(ctx.record)  # the camera's positions, in the run record
            self._tracking.tap(ctx.on_frame)  # the console's camera view, if any
            first = self._tracking.start()
            ctx.record.event("tracking", positions_mm=first.positions_mm.tolist())
        self._closed = self.settings.closed_loop and self._tracking is not None
        if self._closed and self._pull is not None:
            identifier = self._pull.identifier
            self._series = ctx.record.open_series("identification", identifier.series_columns(),
                                                  identifier.series_units())
            self._series.row(identifier.series_row(0.0))

    def next(self, k: int, measured: np.ndarray | None) -> Step | None:
        now = time.monotonic()
        if self._started_at is None:
            self._started_at = self._seen_at = now
        record = self._record
        assert record is not None
        stopping = self._pause.abort_wanted or \
            now - self._started_at - self._pause.paused_s(now) > self._timeout_s
        if stopping and self._ramp_down is None:
            record.event("stop", reason="abort" if self._pause.abort_wanted else "timeout")
            self._ramp_down = 0
        self._update_pause(now)
        sample = k if self._closed else self._j
        if self._closed:  # the camera is read on every cycle, the ramp down included
            target, move = self._closed_loop_target(k, now)
        elif self._ramp_down is None:
            planned = self._open_loop_target(now)
            if planned is None:
                return self._end()
            target, move = planned
        if self._ramp_down is not None:
            if self._pull is not None:
                self._pull.interrupt(now)
            self._ramp_down += 1
            if self._ramp_down > self._ramp:
                return self._end()
            target, move = self._last * max(0.0, 1.0 - self._ramp_down / self._ramp), -1
        key, stage = self._stage(k, sample)
        self._last = self._slew.step(self._last, target)
        return Step(self._last, sample, move, stage=stage, t_s=now - self._started_at,
                    stage_key=key)

    def _end(self) -> None:
        """The program is over: ground truth as it leaves the agents, before the supplies are
        stopped (with no field the magnets still attract each other, and that is not the run's
        doing)."""
        self._truth_at_end = read_truth(self._backdoor)

    def _stage(self, k: int, sample: int) -> tuple[int, str]:
        if self._pause.paused:
            return self._stages.paused()
        if self._closed:
            ramp = ("ramp down" if self._ramp_down is not None
                    else "ramp up" if k < self._ramp else None)
            return self._stages.closed_loop(self._pursuit.k, holding=self._hold_from is not None,
                                            ramp=ramp)
        stage_of = self.prepared.stage_of
        return self._stages.open_loop(int(stage_of[min(sample, len(stage_of) - 1)])
                                      if self._ramp_down is None else RAMP)

    # -- holding still --------------------------------------------------------------------------
    def _held(self, since: float, now: float) -> np.ndarray:
        """Currents that keep the agents where they are (the class docstring): no pull, the field
        at 54.74 and 125.26 deg to their heading in turn (`hold_field_angle`)."""
        flipped = int((now - since) / HOLD_DITHER_S) % 2 == 1
        u = np.array([hold_field_angle(self._phi, flipped), 0.0, 0.0])
        return self.prepared.u_to_currents @ u_of(self.plan, u)

    def _segment_of_node(self, node: int) -> int:
        """The plan segment that ends at pursuit node `node` (the goal: the last one)."""
        plan_node = self._stages.plan_node[min(node, len(self._stages.plan_node) - 1)]
        return int(min(max(plan_node - 1, 0), len(self._dts) - 1))

    def _at_segment_end(self, mark: int, asked_mark: int, waited_s: float) -> bool:
        """Whether a plain pause asked at `asked_mark` (pursuit node or program stage) takes
        effect now that the run is at `mark`."""
        if self._closed:
            return (mark != asked_mark or self._pursuit.mode == "hold"
                    or self._hold_from is not None
                    or waited_s >= self._dts[self._segment_of_node(asked_mark)])
        return mark != asked_mark or mark < 0  # a new stage, or in a ramp or the hold

    def _update_pause(self, now: float) -> None:
        """Pause and resume take effect here, on the stream thread (`_PauseRequests`)."""
        pause, record, closed = self._pause, self._record, self._closed
        wanted, immediate = pause.pause_wanted, pause.immediate
        finishing = self._ramp_down is not None or (not closed and self._j >= self._final_ramp)
        if wanted and not pause.paused and not finishing:
            mark = self._pursuit.k if closed else int(self.prepared.stage_of[self._j])
            if self._pause_asked is None:
                self._pause_asked = (now, mark)
            asked_at, asked_mark = self._pause_asked
            if immediate or self._at_segment_end(mark, asked_mark, now - asked_at):
                pause.hold(now)
                self._held_from, self._pause_asked = now, None
                if not closed and not self._phi_seen:
                    self._phi = float(self._headings[max(self._j - 1, 0)])
                record.event("pause", immediate=immediate, sample=self._j,
                             node=self._pursuit.k if closed else None)
        elif not wanted:
            self._pause_asked = None
            if pause.paused:
                record.event("pause_end", paused_s=round(now - self._held_from, 3),
                             sample=self._j)
                pause.release(now)
                self._pause_hold = self._pause_target = None
                if closed:  # the pursuit goes on from the next frame; a goal hold restarts
                    self._awaiting_frame = True
                    self._hold_from = self._off_since = None
                    self._pursuit.last_u = np.array([hold_field_angle(self._phi, False), 0.0, 0.0])

    # -- the closed loop ------------------------------------------------------------------------
    def _closed_loop_target(self, k: int, now: float) -> tuple[np.ndarray, int]:
        prep, s, record = self.prepared, self.settings, self._record
        latest = self._tracking.latest()
        if latest is not None and latest.frame != self._frame and not latest.lost.any():
            self._frame = latest.frame
            self._seen_at = now
            self._suspension.regained(now)
            q = state_from_positions(latest.positions_mm / self.d_mm)
            self._phi = float(q[3])
            self.metrics.measure(q, self._pursuit)
            if self._pull is not None and self._pull.frame(latest.t_source, latest.positions_mm):
                self._identified(latest.t_source)
            if self._pause.paused:  # the formation held where the first frame saw it
                if self._pause_hold is None:
                    self._pause_hold = PairPursuit(prep.problem, np.vstack([q, q]),
                                                   self._pursuit_settings)
                    self._pause_hold.set_pull_response(self._pursuit.pull_gain,
                                                       self._pursuit.pull_heading_rad)
                hold = self._pause_hold
                u = hold.decide(hold.carry_forward(q, now - latest.t_source))
                self._pause_target = prep.u_to_currents @ u_of(self.plan, u)
                record.event("track", frame=latest.frame, q=np.round(q, 5).tolist(),
                             mode="paused", node=self._pursuit.k, u=np.round(u, 5).tolist())
            else:
                self._decide(q, now, latest)
        elif not self._tracking.ok(now) or now - self._seen_at > s.stale_s:
            why = (self._tracking.why_lost(now, "agent") if not self._tracking.ok(now)
                   else f"camera: no fresh frame for {s.stale_s:g} s")
            self._suspension.lost(now, f"tracking lost ({why})")
        if self._pull is not None and (self._suspension.since is not None or self._pause.paused
                                       or self._awaiting_frame or k < self._ramp):
            self._pull.interrupt(now)  # no pursuit's pull to measure the agents against
        if self._suspension.since is not None:
            # unseen, the agents are held where they were last seen (a held field would keep
            # moving them, and they could collide unseen)
            return self._held(self._suspension.since, now), -1
        if self._pause.paused:
            if self._pause_target is not None:
                return self._pause_target, -1
            return self._held(self._held_from, now), -1  # until the first frame
        if self._awaiting_frame:  # resumed; the pursuit decides on the next frame
            return self._held(self._held_from, now), -1
        target = self._target
        if target is None:  # no frame decided yet: nothing to pull with
            target = np.zeros_like(self._last)
        if k < self._ramp:
            return target * (k + 1) / self._ramp, -1
        return target, -1 if self._hold_from is not None else self._segment_of_node(self._pursuit.k)

    def _open_loop_target(self, now: float) -> tuple[np.ndarray, int] | None:
        """The program's next sample (or the pause's hold); the camera, if any, only measures."""
        if self._tracking is not None:
            latest = self._tracking.latest()
            if latest is not None and latest.frame != self._frame:
                self._frame = latest.frame
                q = state_from_positions(latest.positions_mm / self.d_mm)
                self.metrics.measure(q, None)
                if not latest.lost.any():
                    self._phi, self._phi_seen = float(q[3]), True
        if self._pause.paused:
            return self._held(self._held_from, now), -1
        j, program = self._j, self.prepared.program_A
        if j >= len(program):
            return None
        self._j = j + 1
        return program[j], max(int(self.prepared.stage_of[j]), -1)

    def _decide(self, q: np.ndarray, now: float, latest) -> None:
        """A fresh frame while running: the pursuit's control for where the agents will be once
        it acts (carried over the camera's latency), re-planning, and the goal hold's clock."""
        prep, pursuit, record = self.prepared, self._pursuit, self._record
        q_now = pursuit.carry_forward(q, now - latest.t_source)
        u = pursuit.decide(q_now)
        self._target = prep.u_to_currents @ u_of(self.plan, u)
        if self._pull is not None:
            self._pull.send(now, u[1:])
        self._awaiting_frame = False
        record.event("track", frame=latest.frame, q=np.round(q, 5).tolist(),
                     mode=pursuit.mode, node=pursuit.k, u=np.round(u, 5).tolist())
        self._watch_path(q, now)
        settled = goal_error(q, prep.nodes[-1]) <= HOLD_START_SHARE * self.plan.tolerance_bl
        if pursuit.mode == "hold" and (settled or self._hold_from is not None):
            if self._hold_from is None:
                self._hold_from = now
                record.event("holding", node=pursuit.k)
            self.metrics.held(q, now - self._hold_from)
            if now - self._hold_from >= self.plan.hold_s and self._ramp_down is None:
                self._ramp_down = 0

    def _identified(self, t_source: float) -> None:
        """A new pull measurement was taken: pursue with the estimate, record it."""
        gain, heading = self._pull.response()
        self._pursuit.set_pull_response(gain, heading)
        identifier = self._pull.identifier
        estimate = identifier.summary()
        self._record.event("identify", gain=estimate["gain"][0],
                           gain_std=estimate["gain_std"][0],
                           heading_deg=estimate["heading_deg"][0])
        if self._series is not None:
            self._series.row(identifier.series_row(t_source - self._record.t0))

    def _watch_path(self, q: np.ndarray, now: float) -> None:
        """Re-plan when the proximity controller has not brought the agents back in time."""
        pursuit, worker, record = self._pursuit, self._worker, self._record
        if "result" in worker:
            result = worker.pop("result")
            self.metrics.replan_ms.append(worker.pop("ms"))
            self._replan = None
            if isinstance(result, PlanError):
                record.event("replan_failed", reason=str(result))
            else:
                path, joined, q0 = result
                if path.solved:
                    pursuit.splice(np.vstack([q0[None], path.states]), joined)
                    self._stages.spliced(len(path.states) + 1, joined)
                    self.metrics.paths = pursuit.paths
                    record.event("replan", joined=joined, segments=len(path.dts),
                                 ms=round(self.metrics.replan_ms[-1], 2))
        if pursuit.mode != "proximity":
            self._off_since = None
            return
        if self._off_since is None:
            self._off_since = now
        if now - self._off_since > self.settings.replan_after_s and self._replan is None:
            self._replan = threading.Thread(target=self._replan_async, args=(q.copy(), pursuit.k),
                                            name="pair-replan", daemon=True)
            self._replan.start()
            self._off_since = now

    def _replan_async(self, q: np.ndarray, k: int) -> None:
        """On the re-plan thread: a path from `q` onto the rest of the pursuit's, for
        `_watch_path` to splice in on a later frame."""
        t0 = time.perf_counter()
        try:
            path, joined = replan_pair(self.prepared.problem, q, self._pursuit.nodes, max(k - 1, 0),
                                       PairPlannerOptions(time_s=0.3),
                                       seed=len(self.metrics.replan_ms))
            self._worker["result"] = (path, joined, q)
        except PlanError as err:
            self._worker["result"] = err
        self._worker["ms"] = (time.perf_counter() - t0) * 1e3

    # -- the end --------------------------------------------------------------------------------
    def finish(self, ctx: RunContext) -> Outcome:
        """Each agent's final position (the camera's last frame, else ground truth) against the
        goal formation, in body lengths; reached closed loop only when the goal was also held
        for the plan's `hold_s` within its tolerance."""
        self.close()
        if self._truth_at_end is None:  # a fault or an e-stop ended the stream
            self._truth_at_end = read_truth(ctx.backdoor)
        plan, d, m = self.plan, self.d_mm, self.metrics
        goal_mm = agent_positions(state_of(plan.goal, d)) * d
        truth = self._truth_at_end
        camera = None if m.last_q is None else agent_positions(m.last_q) * d
        agents, positions_from = agent_results(goal_mm, camera, truth, scale_mm=d, unit="bl")
        tol = plan.tolerance_bl
        closed = self.settings.closed_loop
        # open loop judges by ground truth where there is one: the camera only watched
        errors = [a.error_mm if closed or a.truth_error_mm is None else a.truth_error_mm
                  for a in agents]
        reached = all(e is not None and e <= tol for e in errors)
        if closed:
            reached = reached and m.held_s >= plan.hold_s - 0.05 and (
                m.hold_max is not None and m.hold_max <= tol)
        truth_sep = None
        if truth is not None and truth.get("min_separation_mm") is not None:
            truth_sep = truth["min_separation_mm"] / d
        mode = "closed loop" if closed else "open loop"
        metrics = {
            "mode": mode, "rms_tracking_error_bl": _round(m.rms()),
            "max_tracking_error_bl": _round(m.max_error()), "min_separation_bl": _round(m.min_sep),
            "truth_min_separation_bl": _round(truth_sep), "hold_max_error_bl": _round(m.hold_max),
            "held_s": round(m.held_s, 3), "replan_ms": [round(v, 2) for v in m.replan_ms]}
        if self._closed and self._pull is not None:
            e = self._pull.identifier.summary()
            metrics["pull_identified"] = {"gain": e["gain"][0], "gain_std": e["gain_std"][0],
                                          "heading_deg": e["heading_deg"][0],
                                          "windows_used": e["moves_used"][0]}
        tracking = None
        if self._tracking is not None:
            tracking = {"frames": m.frames, "lost_frames": self._tracking.lost_frames}
        return Outcome(agents=agents, reached=reached, positions_from=positions_from,
                       tolerance_mm=tol, tolerance_unit="bl", metrics=metrics,
                       replans=len(m.replan_ms), tracking=tracking,
                       details=_details(metrics))

    def close(self) -> None:
        if self._tracking is not None:
            self._tracking.stop()


def _round(value: float | None) -> float | None:
    return None if value is None else round(float(value), 4)


def _details(metrics: dict) -> list[str]:
    """The summary's lines about the pair's own figures (frames and re-plans have their own)."""
    lines = [f"mode: {metrics['mode']}"]
    if metrics["rms_tracking_error_bl"] is not None:
        lines.append(f"tracking: RMS {metrics['rms_tracking_error_bl']:.3f} BL, max "
                     f"{metrics['max_tracking_error_bl']:.3f} BL from the planned path")
    if metrics["min_separation_bl"] is not None:
        truth = metrics["truth_min_separation_bl"]
        extra = "" if truth is None else f" (ground truth {truth:.3f} BL)"
        lines.append(f"closest approach: {metrics['min_separation_bl']:.3f} BL{extra}")
    pull = metrics.get("pull_identified")
    if pull is not None and pull["windows_used"]:
        lines.append(f"pull identified: gain {pull['gain']:.3f} +- {pull['gain_std']:.3f}, heading "
                     f"{pull['heading_deg']:+.1f} deg ({pull['windows_used']} windows)")
    if metrics["hold_max_error_bl"] is not None:
        lines.append(f"hold: {metrics['held_s']:.1f} s, worst agent error "
                     f"{metrics['hold_max_error_bl']:.3f} BL")
    return lines


def PairRun(plan: PairFormationPlan, rig: SixCoilRig, *, closed_loop: bool | None = None,
            settings: PairRunSettings = PairRunSettings(), **run_options) -> EngineRun:
    """The run of a pair-formation plan on a six-coil rig (the one engine with `PairProgram`);
    `closed_loop`, if given, overrides the settings'; `run_options` are the engine's (`runs_dir`,
    `progress_out`, `on_cycle`, `on_state`). Refuses a bad plan
    without I/O."""
    if closed_loop is not None:
        settings = replace(settings, closed_loop=closed_loop)
    return EngineRun(PairProgram(plan, rig, settings), rig, CoilSupplies.connect, **run_options)


class PairStages:
    """What the operator sees of a pair run on the runs' one progress line, as a step's
    (`stage_key`, `stage`): the plan segment the agents are on out of how many, the approach to
    the goal, the hold. Off a terminal a line is printed per new key, ramps and pauses (key -1)
    not. Closed loop, the furthest segment reached is shown (the proximity controller may head
    back a node, and a line per step back off a terminal would flood the log); re-planned nodes
    count as the plan node their path rejoins."""

    def __init__(self, n_segments: int, n_nodes: int) -> None:
        self.n = n_segments
        # pursuit node -> plan node (0 start, k the end of segment k, n + 1 the goal itself)
        self.plan_node = np.arange(n_nodes)
        self.reached = 0

    def spliced(self, n_new: int, joined: int) -> None:
        """The pursuit's path re-planned: `n_new` nodes that rejoin its node `joined`."""
        self.plan_node = np.concatenate([np.full(n_new, self.plan_node[joined]),
                                         self.plan_node[joined + 1:]])

    def closed_loop(self, node: int, *, holding: bool, ramp: str | None) -> tuple[int, str]:
        """Heading for pursuit node `node`; `ramp` names a field ramp going on."""
        if ramp is not None:
            return -1, ramp
        if holding:
            return self.n + 1, "holding goal"
        node = min(node, len(self.plan_node) - 1)  # a display never stops a run
        self.reached = max(self.reached, int(self.plan_node[node]))
        return self._segment(self.reached - 1)

    def open_loop(self, stage: int) -> tuple[int, str]:
        if stage == HOLD:
            return self.n + 1, "holding goal"
        if stage == RAMP:
            return -1, "ramp up" if self.reached == 0 else "ramp down"
        return self._segment(stage)

    def paused(self) -> tuple[int, str]:
        return -1, "paused"

    def _segment(self, index: int) -> tuple[int, str]:
        """On segment `index` (0-based; n: heading for the goal itself)."""
        index = max(index, 0)
        self.reached = max(self.reached, index + 1)
        return index, f"segment {index + 1}/{self.n}" if index < self.n else "to goal"


class _Metrics:
    """Tracking figures from the camera's measurements (body lengths)."""

    def __init__(self, nodes: np.ndarray) -> None:
        self.paths = agent_positions(nodes)
        self.goal = nodes[-1]
        self.sq: list[float] = []
        self.errors: list[float] = []
        self.min_sep: float | None = None
        self.hold_max: float | None = None
        self.held_s = 0.0
        self.frames = 0
        self.last_q: np.ndarray | None = None
        self.replan_ms: list[float] = []

    def measure(self, q: np.ndarray, pursuit: PairPursuit | None) -> None:
        p = agent_positions(q)
        d = distance_to_path(p, self.paths if pursuit is None else pursuit.paths)
        self.sq += (d**2).tolist()
        self.errors.append(float(d.max()))
        self.min_sep = float(q[2]) if self.min_sep is None else min(self.min_sep, float(q[2]))
        self.frames += 1
        self.last_q = q

    def held(self, q: np.ndarray, held_s: float) -> None:
        err = float(goal_error(q, self.goal))
        self.hold_max = err if self.hold_max is None else max(self.hold_max, err)
        self.held_s = held_s

    def rms(self) -> float | None:
        return float(np.sqrt(np.mean(self.sq))) if self.sq else None

    def max_error(self) -> float | None:
        return max(self.errors) if self.errors else None




def loopback_rig(rig: SixCoilRig) -> SixCoilRig:
    """The rig of the emulated bench `execute` starts itself, with the supplies' reply watchdog
    at least `LOOPBACK_REPLY_TIMEOUT_S`: the bench is a process on the same (perhaps busy)
    machine, nothing real is energised, and a scheduler stall of a few hundred ms is not a
    silent supply. A rig file given with --rig keeps its own watchdog."""
    timeout = max(rig.stream.reply_timeout_s, LOOPBACK_REPLY_TIMEOUT_S)
    return rig.model_copy(update={"stream": rig.stream.model_copy(
        update={"reply_timeout_s": timeout})})


