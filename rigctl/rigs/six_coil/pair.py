"""Run a pair-formation plan (seed 002) on the six-coil rig: field angle + pull streamed as currents,
the loop closed through the camera with pure pursuit and the proximity controller.

Before anything is opened: the plan is checked (its own model, every constraint), its pull bound is
compared with what this rig's coils make, and the open-loop program (every segment as the 8-vector
U -> six currents at the stream rate, then the hold) is allocated with every current and voltage
limit checked. Then the agents are placed (emulated bench), found by the camera, and the supplies
switched on.

Closed loop (default whenever the rig has a camera): on every fresh frame the measured formation is
carried forward over the camera's latency and `PairPursuit` picks the control; its currents go out
on the next stream cycle, rate-limited so no supply needs more than 90 % of its compliance
voltage. While tracking is lost the agents are held unseen (no pull, the field flipped about the
zero-radial angle of their last heading); lost for `lost_after_s` is a fault. When the agents stay
off the path (proximity mode) longer than `replan_after_s`, the path
is re-planned from the measured state onto the rest of the path in a worker thread and spliced in.
At the last node the goal formation is held for the plan's `hold_s`. `--open-loop` plays the plan's
controls back (the paper's open-loop mode); the camera, if any, still measures.

The summary adds `rms_tracking_error_bl` (each measured agent's distance to its planned path, RMS
over frames and agents, in body lengths), `min_separation_bl` (smallest measured centre distance)
and `hold_max_error_bl` (largest agent distance from its goal while holding).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TextIO

import numpy as np

from rigctl.coils import u_actuation_matrix
from rigctl.config import RigConfig, dump_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.errors import ConfigError, DeviceTimeout, LimitError, PlanError, RigError
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
from rigctl.plans.schema import PairFormationPlan, dump_plan
from rigctl.record import RunRecord
from rigctl.rigs.six_coil.allocate import check_current_limits, field_and_pull_u
from rigctl.rigs.six_coil.pursuit import PairPursuit, PursuitSettings, distance_to_path
from rigctl.rigs.six_coil.supplies import CoilSupplies
from rigctl.run.control import EStopped, RunControl, RunState
from rigctl.run.emulated import portable_workspace
from rigctl.run.progress import Progress
from rigctl.stream import StreamLoop

log = logging.getLogger(__name__)

CONTROLLER_PULL_SHARE = 0.95  # of the rig's largest pull: the plan used PULL_MARGIN (0.8) of it
VOLTAGE_SHARE = 0.9  # closed-loop current steps are limited to keep R I + L dI/dt below this
HOLD_START_SHARE = 0.75  # the hold's clock starts when both agents are this share of the tolerance in
LOOPBACK_REPLY_TIMEOUT_S = 1.0  # supplies' watchdog when execute started the emulated bench
HOLD_DITHER_S = 0.1  # a hold's field switches between 54.74 and 125.26 deg this often
RAMP, HOLD = -1, -2  # stages of the open-loop program that are not segments


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


@dataclass
class PairSummary:
    reached: bool
    agents: list[dict]
    run: str
    duration_s: float
    positions_from: str
    tolerance_bl: float
    mode: str
    faults: list[dict] = field(default_factory=list)
    stream: dict | None = None
    rms_tracking_error_bl: float | None = None
    max_tracking_error_bl: float | None = None
    min_separation_bl: float | None = None
    truth_min_separation_bl: float | None = None
    hold_max_error_bl: float | None = None
    held_s: float = 0.0
    frames: int = 0
    lost_frames: int = 0
    replans: int = 0
    replan_ms: list[float] = field(default_factory=list)

    def as_dict(self) -> dict:
        out = dict(self.__dict__)
        out["duration_s"] = round(self.duration_s, 3)
        for key in ("rms_tracking_error_bl", "max_tracking_error_bl", "min_separation_bl",
                    "truth_min_separation_bl", "hold_max_error_bl"):
            if out[key] is not None:
                out[key] = round(float(out[key]), 4)
        out["held_s"] = round(self.held_s, 3)
        out["replan_ms"] = [round(v, 2) for v in self.replan_ms]
        return out


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
    for k in range(max(0, round(plan.hold_s * rate_hz))):
        rows.append([hold_field_angle(goal_phi, (k // per) % 2 == 1), 0.0, 0.0])
        scale.append(1.0)
        stage.append(HOLD)
    last = rows[-1]
    for k in range(ramp):
        rows.append([last[0], 0.0, 0.0])
        scale.append(1.0 - (k + 1) / ramp)
    stage += [RAMP] * ramp
    return np.array(rows), np.array(scale), np.array(stage)


def prepare_pair(plan: PairFormationPlan, rig: RigConfig, settings: PairRunSettings) -> PreparedPair:
    """Every refusal, no I/O: plan checks, the rig's pull, the open-loop program's limits."""
    if rig.rig.kind != "six-coil":
        raise PlanError(f"a pair-formation plan runs on a six-coil rig, not a {rig.rig.kind} rig")
    if plan.expected is None:
        plan = simulate(plan)
    check(plan)
    physics = physics_of(plan)
    rig_pull = rig_max_pull(rig, physics, plan.field_mT)
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

    def __init__(self, rig: RigConfig) -> None:
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


def slew_limited(program: np.ndarray, rig: RigConfig) -> np.ndarray:
    """A current program (T, n) with every step limited by `CoilSlew` (starting from 0 A)."""
    slew = CoilSlew(rig)
    out = np.empty_like(program)
    last = np.zeros(program.shape[1])
    for k, target in enumerate(program):
        last = out[k] = slew.step(last, target)
    return out


class _PauseRequests:
    """Pause and resume as asked from any thread. The stream thread decides when a pause takes
    effect (`hold`) and when it ends (`release`), and counts the time spent paused: it counts
    towards neither the run's timeout nor the goal hold."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._wanted = False
        self._immediate = False
        self.paused = False  # the stream thread's: holding now
        self._since: float | None = None
        self._paused_s = 0.0

    def request(self, immediate: bool) -> None:
        with self._lock:
            self._wanted = True
            self._immediate = self._immediate or immediate

    def cancel(self) -> None:
        with self._lock:
            self._wanted = self._immediate = False

    def wanted(self) -> tuple[bool, bool]:
        """(a pause is wanted, at once)."""
        with self._lock:
            return self._wanted, self._immediate

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


class PairRun(RunControl):
    """One pair-formation plan on one six-coil rig, with the interface of `rigctl.rigs.six_coil.global_moves.Run`:
    construction refuses a bad plan without I/O; `execute()` energises, streams and returns the
    summary; `pause`, `resume`, `abort` and `estop` may be called from any thread meanwhile;
    `on_cycle(sample, move, commanded_A, measured_A)` is called from the stream thread after every
    cycle and `on_state(state, info)` on every change of `state`.

    `move` is the plan segment being driven (0-based; the closed loop's last approach to the goal
    itself counts as the last segment), and -1 while the field ramps, while paused, while the
    camera has lost the agents and while the goal formation is held. `sample` is the open-loop
    program's sample index (it stays put while paused), the stream cycle's index closed loop.

    A pause holds the agents where they are rather than switching the coils off: these agents
    are permanent magnets, and with no field each turns along the other's and they pull together
    (about 1.2 BL/s at 2 BL apart, seed 002 eq. 1), so zero current would end in contact. The hold
    is the paper's dynamic equilibrium: no pull, the field at the zero-radial angle to the pair's
    heading, flipped every `HOLD_DITHER_S` so the transverse force cancels too (`hold_field_angle`).
    """

    def __init__(self, plan: PairFormationPlan, rig: RigConfig, *, runs_dir: str | Path = "runs",
                 progress_out: TextIO | None = None,
                 on_cycle: Callable[[int, int, np.ndarray, np.ndarray], None] | None = None,
                 on_state: Callable[[RunState, dict], None] | None = None,
                 closed_loop: bool | None = None,
                 settings: PairRunSettings = PairRunSettings()) -> None:
        if closed_loop is not None:
            settings = replace(settings, closed_loop=closed_loop)
        if settings.closed_loop and rig.camera is None:
            raise ConfigError("closed loop needs the rig's camera; this rig has none "
                              "(use --open-loop)")
        self.prepared = prepare_pair(plan, rig, settings)
        self.plan = self.prepared.plan
        self.rig = rig
        self.settings = settings
        self.runs_dir = Path(runs_dir)
        self.out = progress_out
        self.on_cycle = on_cycle
        self._init_control(on_state)
        self.d_mm = self.plan.agents.body_diameter_mm
        self._abort = threading.Event()
        self._pause = _PauseRequests()
        self._truth_at_end: dict | None = None
        samples = len(self.prepared.program_A)  # the open-loop program; closed loop takes its time
        self.info = {"name": self.plan.name, "segments": len(self.plan.segments),
                     "samples": samples, "duration_s": round(samples / rig.stream.rate_hz, 3)}

    # -- control, from any thread ---------------------------------------------------------------
    def pause(self, immediate: bool = False) -> None:
        """Hold the agents where they are, at the end of the segment being driven (closed loop:
        when the pursuit reaches its next node, or after the segment's planned time), or at once
        with `immediate`."""
        self._pause.request(immediate)

    def resume(self) -> None:
        """Go on from where the agents are: closed loop, the pursuit from the next camera frame;
        open loop, the program from the sample where it stopped."""
        self._pause.cancel()

    def abort(self) -> None:
        """Ramp the field down and end; the summary reports the abort."""
        self._abort.set()

    # -- the run --------------------------------------------------------------------------------
    def execute(self) -> PairSummary:
        from rigctl.vision.tracking import TrackingLoop

        plan, rig, prep = self.plan, self.rig, self.prepared
        record = self.record = RunRecord(self.runs_dir, plan.name or "pair-formation")
        record.write_file("plan.json", dump_plan(plan))
        record.write_file("rig.toml", dump_rig(rig))
        record.event("prepared", samples=len(prep.program_A), rate_hz=rig.stream.rate_hz,
                     closed_loop=self.settings.closed_loop)
        started = time.monotonic()
        faults: list[dict] = []
        stats = None
        backdoor = BackdoorClient(rig.emulation.backdoor) if rig.emulation else None
        tracking = None
        supplies = None
        self.metrics = _Metrics(prep.nodes)
        try:
            start_mm = agent_positions(prep.nodes[0]) * self.d_mm
            if backdoor is not None:
                backdoor.request(
                    "place", workspace=portable_workspace(plan),
                    agents=[{"position": p.tolist(), "radius": 0.5 * self.d_mm} for p in start_mm],
                    pair=plan.agents.model_dump())
                record.event("placed", agents=start_mm.tolist())
            if rig.camera is not None:
                bounds = prep.problem.workspace.bounds
                tracking = TrackingLoop(rig.camera, np.full(2, 0.5 * self.d_mm), start_mm,
                                        roi_mm=bounds)
                first = tracking.start()
                record.event("tracking", positions_mm=first.positions_mm.tolist())
            supplies = self._supplies = CoilSupplies.connect(rig)
            for name, identity in zip(supplies.names, supplies.identities):
                record.event("connected", device=name, identity=identity)
            if self._estop.is_set():  # e-stopped while connecting: never switch on
                raise EStopped()
            supplies.energise()
            record.event("energised", devices=supplies.names)
            self._set_state(RunState.RUNNING)
            stats = self._stream(supplies, tracking, record)
        except RigError as err:
            self._stopped_by(err, record, faults)
        except EStopped:
            record.event("estop", reason="before the supplies were switched on")
        except KeyboardInterrupt:
            self._abort.set()
            record.event("abort", reason="operator interrupt")
        finally:
            if supplies is not None and self._estop.is_set():
                supplies.stop(ramp_s=0.0)  # already zero and latched; closed before anything else
                self._supplies = None
            # ground truth as the run leaves the agents, before the field goes: with no field
            # the magnets still attract each other, and that is not the run's doing
            self._truth_at_end = self._read_truth(backdoor)
            if supplies is not None:
                if self._supplies is not None:  # an e-stop during this ramp cuts it short
                    supplies.stop(ramp_s=0.0 if self._estop.is_set() else rig.stream.ramp_down_s)
                    self._supplies = None  # off and closed: nothing left for an e-stop to write to
                record.event("safe", supplies=supplies.names)
            if tracking is not None:
                tracking.stop()
        self._end_state(faults, aborted=self._abort.is_set())
        summary = self._summary(record, backdoor, tracking, faults, stats, started)
        if backdoor is not None:
            backdoor.close()
        record.finish(summary.as_dict())
        return summary

    # -- the stream ----------------------------------------------------------------------------
    def _stream(self, supplies: CoilSupplies, tracking, record: RunRecord):
        rig, prep, s = self.rig, self.prepared, self.settings
        rate = rig.stream.rate_hz
        record.open_stream(supplies.names, rate_hz=rate)
        loop = self.stream_loop = StreamLoop(rate)
        slew = CoilSlew(rig)
        ramp = max(1, round(s.ramp_s * rate))
        closed = s.closed_loop and tracking is not None
        pursuit_settings = replace(s.pursuit, max_pull=prep.controller_pull)
        pursuit = PairPursuit(prep.problem, prep.nodes, pursuit_settings)
        dts = plan_arrays(self.plan)[2]
        n_segments = len(dts)
        timeout_s = s.timeout_factor * float(np.sum(dts)) + self.plan.hold_s + s.timeout_extra_s
        stream_started = time.monotonic()
        stages = self._stages = _StageProgress(self.out, len(self.plan.segments), prep.nodes,
                                               len(prep.program_A) / rate)
        program, stage_of = prep.program_A, prep.stage_of
        final_ramp = len(program) - ramp  # open loop: the program's own ramp down starts here
        headings = None if closed else expected_headings(prep.nodes, stage_of)
        pause = self._pause
        state = {"last": np.zeros(len(supplies.names)), "target": None, "frame": -1,
                 "hold_from": None, "off_since": None, "replan": None, "ramp_down": None,
                 "lost_since": None, "phi": float(prep.nodes[0][3]), "seen_at": time.monotonic(),
                 "j": 0, "pause_asked": None, "held_from": None, "awaiting_frame": False,
                 "phi_seen": False, "pause_hold": None, "pause_target": None}
        worker: dict = {}

        def replan_async(q: np.ndarray, k: int) -> None:
            t0 = time.perf_counter()
            try:
                path, joined = replan_pair(prep.problem, q, pursuit.nodes, max(k - 1, 0),
                                           PairPlannerOptions(time_s=0.3),
                                           seed=len(self.metrics.replan_ms))
                worker["result"] = (path, joined, q)
            except PlanError as err:
                worker["result"] = err
            worker["ms"] = (time.perf_counter() - t0) * 1e3

        def held(since: float, now: float) -> np.ndarray:
            """Currents that keep the agents where they are (the class docstring): no pull, the
            field at 54.74 and 125.26 deg to their heading in turn (`hold_field_angle`)."""
            flipped = int((now - since) / HOLD_DITHER_S) % 2 == 1
            u = np.array([hold_field_angle(state["phi"], flipped), 0.0, 0.0])
            return prep.u_to_currents @ u_of(self.plan, u)

        def segment_of_node(node: int) -> int:
            """The plan segment that ends at pursuit node `node` (the goal: the last one)."""
            plan_node = stages.plan_node[min(node, len(stages.plan_node) - 1)]
            return int(min(max(plan_node - 1, 0), n_segments - 1))

        def at_segment_end(mark: int, asked_mark: int, waited_s: float) -> bool:
            """Whether a plain pause asked at `asked_mark` (pursuit node or program stage) takes
            effect now that the run is at `mark`."""
            if closed:
                return (mark != asked_mark or pursuit.mode == "hold"
                        or state["hold_from"] is not None
                        or waited_s >= dts[segment_of_node(asked_mark)])
            return mark != asked_mark or mark < 0  # a new stage, or in a ramp or the hold

        def update_pause(now: float) -> None:
            wanted, immediate = pause.wanted()
            finishing = state["ramp_down"] is not None or (not closed and state["j"] >= final_ramp)
            if wanted and not pause.paused and not finishing:
                mark = pursuit.k if closed else int(stage_of[state["j"]])
                if state["pause_asked"] is None:
                    state["pause_asked"] = (now, mark)
                asked_at, asked_mark = state["pause_asked"]
                if immediate or at_segment_end(mark, asked_mark, now - asked_at):
                    pause.hold(now)
                    state["held_from"], state["pause_asked"] = now, None
                    if not closed and not state["phi_seen"]:
                        state["phi"] = float(headings[max(state["j"] - 1, 0)])
                    record.event("pause", immediate=immediate, sample=state["j"],
                                 node=pursuit.k if closed else None)
            elif not wanted:
                state["pause_asked"] = None
                if pause.paused:
                    record.event("pause_end", paused_s=round(now - state["held_from"], 3),
                                 sample=state["j"])
                    pause.release(now)
                    state["pause_hold"] = state["pause_target"] = None
                    if closed:  # the pursuit goes on from the next frame; a goal hold restarts
                        state["awaiting_frame"] = True
                        state["hold_from"] = state["off_since"] = None
                        pursuit.last_u = np.array([hold_field_angle(state["phi"], False), 0.0, 0.0])

        def closed_loop_target(k: int, now: float) -> tuple[np.ndarray, int]:
            latest = tracking.latest()
            if latest is not None and latest.frame != state["frame"] and not latest.lost.any():
                state["frame"] = latest.frame
                state["seen_at"] = now
                if state["lost_since"] is not None:
                    record.event("resume", after_s=round(now - state["lost_since"], 3))
                    state["lost_since"] = None
                q = state_from_positions(latest.positions_mm / self.d_mm)
                state["phi"] = float(q[3])
                self.metrics.measure(q, pursuit)
                if pause.paused:  # the formation held where the first frame saw it
                    if state["pause_hold"] is None:
                        state["pause_hold"] = PairPursuit(prep.problem, np.vstack([q, q]),
                                                          pursuit_settings)
                    hold = state["pause_hold"]
                    u = hold.decide(hold.carry_forward(q, now - latest.t_source))
                    state["pause_target"] = prep.u_to_currents @ u_of(self.plan, u)
                    record.event("track", frame=latest.frame, q=np.round(q, 5).tolist(),
                                 mode="paused", node=pursuit.k, u=np.round(u, 5).tolist())
                else:
                    self._decide(pursuit, q, now, latest, state, worker, replan_async, record)
            elif not tracking.ok(now) or now - state["seen_at"] > s.stale_s:
                if state["lost_since"] is None:
                    state["lost_since"] = now
                    record.event("suspend", reason="tracking lost")
                elif now - state["lost_since"] > s.lost_after_s:
                    raise DeviceTimeout(f"tracking lost for {s.lost_after_s:g} s",
                                        device="camera")
            if state["lost_since"] is not None:
                # unseen, the agents are held where they were last seen (a held field would
                # keep moving them, and they could collide unseen)
                return held(state["lost_since"], now), -1
            if pause.paused:
                if state["pause_target"] is not None:
                    return state["pause_target"], -1
                return held(state["held_from"], now), -1  # until the first frame
            if state["awaiting_frame"]:  # resumed; the pursuit decides on the next frame
                return held(state["held_from"], now), -1
            target = state["target"]
            if target is None:  # no frame decided yet: nothing to pull with
                target = np.zeros_like(state["last"])
            if k < ramp:
                return target * (k + 1) / ramp, -1
            return target, -1 if state["hold_from"] is not None else segment_of_node(pursuit.k)

        def open_loop_target(now: float) -> tuple[np.ndarray, int] | None:
            if tracking is not None:
                latest = tracking.latest()
                if latest is not None and latest.frame != state["frame"]:
                    state["frame"] = latest.frame
                    q = state_from_positions(latest.positions_mm / self.d_mm)
                    self.metrics.measure(q, None)
                    if not latest.lost.any():
                        state["phi"], state["phi_seen"] = float(q[3]), True
            if pause.paused:
                return held(state["held_from"], now), -1
            j = state["j"]
            if j >= len(program):
                return None
            state["j"] = j + 1
            return program[j], max(int(stage_of[j]), -1)

        def cycle(k: int) -> bool:
            if self._estop.is_set():
                self._finish_estop(supplies, record)
                return False
            now = time.monotonic()
            stopping = self._abort.is_set() or \
                now - stream_started - pause.paused_s(now) > timeout_s
            if stopping and state["ramp_down"] is None:
                record.event("stop", reason="abort" if self._abort.is_set() else "timeout")
                state["ramp_down"] = 0
            update_pause(now)
            sample = k if closed else state["j"]
            if closed:
                target, move = closed_loop_target(k, now)
            elif state["ramp_down"] is None:
                planned = open_loop_target(now)
                if planned is None:
                    return False
                target, move = planned
            if state["ramp_down"] is not None:
                state["ramp_down"] += 1
                if state["ramp_down"] > ramp:
                    return False
                target, move = state["last"] * max(0.0, 1.0 - state["ramp_down"] / ramp), -1
            self._set_state(RunState.PAUSED if pause.paused else RunState.RUNNING)
            if pause.paused:
                stages.paused()
            elif closed:
                stages.closed_loop(pursuit.k, holding=state["hold_from"] is not None,
                                   ramp="ramp down" if state["ramp_down"] is not None
                                   else "ramp up" if k < ramp else None)
            else:
                stages.open_loop(int(stage_of[min(sample, len(stage_of) - 1)])
                                 if state["ramp_down"] is None else RAMP)
            setpoints = slew.step(state["last"], target)
            measured = supplies.cycle(setpoints)
            state["last"] = setpoints
            record.stream_row(sample, move, setpoints, measured, loop.last_error_s)
            if self.on_cycle is not None:
                self.on_cycle(sample, move, setpoints, measured)
            return True

        try:
            return loop.run(cycle)
        finally:
            stages.done()
            record.event("stream_stats", **loop.stats().as_dict())

    def _decide(self, pursuit: PairPursuit, q: np.ndarray, now: float, latest, state: dict,
                worker: dict, replan_async, record: RunRecord) -> None:
        """A fresh frame while running: the pursuit's control for where the agents will be once
        it acts (carried over the camera's latency), re-planning, and the goal hold's clock."""
        prep = self.prepared
        q_now = pursuit.carry_forward(q, now - latest.t_source)
        u = pursuit.decide(q_now)
        state["target"] = prep.u_to_currents @ u_of(self.plan, u)
        state["awaiting_frame"] = False
        record.event("track", frame=latest.frame, q=np.round(q, 5).tolist(),
                     mode=pursuit.mode, node=pursuit.k, u=np.round(u, 5).tolist())
        self._watch_path(pursuit, q, now, state, worker, replan_async, record)
        settled = goal_error(q, prep.nodes[-1]) <= HOLD_START_SHARE * self.plan.tolerance_bl
        if pursuit.mode == "hold" and (settled or state["hold_from"] is not None):
            if state["hold_from"] is None:
                state["hold_from"] = now
                record.event("holding", node=pursuit.k)
            self.metrics.held(q, now - state["hold_from"])
            if now - state["hold_from"] >= self.plan.hold_s and state["ramp_down"] is None:
                state["ramp_down"] = 0

    def _watch_path(self, pursuit: PairPursuit, q, now, state, worker, replan_async, record) -> None:
        """Re-plan when the proximity controller has not brought the agents back in time."""
        if "result" in worker:
            result = worker.pop("result")
            self.metrics.replan_ms.append(worker.pop("ms"))
            state["replan"] = None
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
            state["off_since"] = None
            return
        if state["off_since"] is None:
            state["off_since"] = now
        if now - state["off_since"] > self.settings.replan_after_s and state["replan"] is None:
            state["replan"] = threading.Thread(target=replan_async, args=(q.copy(), pursuit.k),
                                               name="pair-replan", daemon=True)
            state["replan"].start()
            state["off_since"] = now

    # -- the summary ---------------------------------------------------------------------------
    @staticmethod
    def _read_truth(backdoor: BackdoorClient | None) -> dict | None:
        if backdoor is None:
            return None
        try:
            return backdoor.request("truth")
        except RigError as err:
            log.error("could not read ground truth: %s", err)
            return None

    def _summary(self, record, backdoor, tracking, faults, stats, started) -> PairSummary:
        plan, d = self.plan, self.d_mm
        goal = state_of(plan.goal, d)
        goal_mm = agent_positions(goal) * d
        truth = self._truth_at_end
        m = self.metrics
        final = m.last_q
        positions_from = "camera" if final is not None else "unknown"
        if final is None and truth is not None:
            final = state_from_positions(np.array(truth["agents"]) / d)
            positions_from = "emulator ground truth"
        agents = []
        for i in range(2):
            entry = {"goal_mm": goal_mm[i].round(4).tolist(), "final_mm": None, "error_bl": None}
            if final is not None:
                p = agent_positions(final)[i] * d
                entry["final_mm"] = p.round(4).tolist()
                entry["error_bl"] = round(float(np.hypot(*(p - goal_mm[i])) / d), 4)
            if truth is not None:
                t = np.array(truth["agents"][i])
                entry["truth_error_bl"] = round(float(np.hypot(*(t - goal_mm[i])) / d), 4)
            agents.append(entry)
        tol = plan.tolerance_bl
        errors = [a.get("truth_error_bl", a["error_bl"]) if not self.settings.closed_loop
                  else a["error_bl"] for a in agents]
        reached = not faults and all(e is not None and e <= tol for e in errors)
        if self.settings.closed_loop:
            reached = reached and m.held_s >= plan.hold_s - 0.05 and (
                m.hold_max is not None and m.hold_max <= tol)
        if truth is not None and truth.get("min_separation_mm") is not None:
            truth_sep = truth["min_separation_mm"] / d
        else:
            truth_sep = None
        return PairSummary(
            reached=reached, agents=agents, run=str(record.path),
            duration_s=time.monotonic() - started, positions_from=positions_from,
            tolerance_bl=tol, mode="closed loop" if self.settings.closed_loop else "open loop",
            faults=faults, stream=None if stats is None else stats.as_dict(),
            rms_tracking_error_bl=m.rms(), max_tracking_error_bl=m.max_error(),
            min_separation_bl=m.min_sep, truth_min_separation_bl=truth_sep,
            hold_max_error_bl=m.hold_max, held_s=m.held_s, frames=m.frames,
            lost_frames=0 if tracking is None else tracking.lost_frames,
            replans=len(m.replan_ms), replan_ms=list(m.replan_ms))


class _StageProgress:
    """What the operator sees of a pair run, through the runs' one `Progress` line: the plan
    segment the agents are on out of how many, the approach to the goal, the hold, elapsed time.
    Closed loop, the furthest segment reached is shown (the proximity controller may head back a
    node, and a line per step back off a terminal would flood the log); re-planned nodes count as
    the plan node their path rejoins."""

    def __init__(self, out: TextIO | None, n_segments: int, nodes: np.ndarray,
                 planned_s: float) -> None:
        self.n = n_segments
        self.progress = Progress(out, n_segments, planned_s)
        # pursuit node -> plan node (0 start, k the end of segment k, n + 1 the goal itself)
        self.plan_node = np.arange(len(nodes))
        self.reached = 0
        self.started = time.monotonic()

    def spliced(self, n_new: int, joined: int) -> None:
        """The pursuit's path re-planned: `n_new` nodes that rejoin its node `joined`."""
        self.plan_node = np.concatenate([np.full(n_new, self.plan_node[joined]),
                                         self.plan_node[joined + 1:]])

    def closed_loop(self, node: int, *, holding: bool, ramp: str | None) -> None:
        """Heading for pursuit node `node`; `ramp` names a field ramp going on."""
        if ramp is not None:
            self._show(-1, ramp)
        elif holding:
            self._show(self.n + 1, "holding goal")
        else:
            node = min(node, len(self.plan_node) - 1)  # a display never stops a run
            self.reached = max(self.reached, int(self.plan_node[node]))
            self._segment(self.reached - 1)

    def open_loop(self, stage: int) -> None:
        if stage == HOLD:
            self._show(self.n + 1, "holding goal")
        elif stage == RAMP:
            self._show(-1, "ramp up" if self.reached == 0 else "ramp down")
        else:
            self._segment(stage)

    def _segment(self, index: int) -> None:
        """On segment `index` (0-based; n: heading for the goal itself)."""
        index = max(index, 0)
        self.reached = max(self.reached, index + 1)
        self._show(index, f"segment {index + 1}/{self.n}" if index < self.n else "to goal")

    def paused(self) -> None:
        self._show(-1, "paused")

    def _show(self, key: int, what: str) -> None:
        self.progress.update(key, time.monotonic() - self.started, what)

    def done(self) -> None:
        self.progress.done()


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


def format_pair_summary(summary: PairSummary) -> str:
    lines = [f"run record: {summary.run}", f"duration: {summary.duration_s:.1f} s ({summary.mode})"]
    if summary.stream:
        st = summary.stream
        lines.append(f"stream: {st['cycles']} cycles at {st['rate_hz']:g} Hz; late {st['late_cycles']}")
    if summary.rms_tracking_error_bl is not None:
        lines.append(f"tracking: RMS {summary.rms_tracking_error_bl:.3f} BL, max "
                     f"{summary.max_tracking_error_bl:.3f} BL over {summary.frames} frames "
                     f"({summary.lost_frames} lost); re-plans {summary.replans}")
    if summary.min_separation_bl is not None:
        extra = "" if summary.truth_min_separation_bl is None else \
            f" (ground truth {summary.truth_min_separation_bl:.3f} BL)"
        lines.append(f"closest approach: {summary.min_separation_bl:.3f} BL{extra}")
    if summary.hold_max_error_bl is not None:
        lines.append(f"hold: {summary.held_s:.1f} s, worst agent error "
                     f"{summary.hold_max_error_bl:.3f} BL")
    lines.append(f"positions from: {summary.positions_from}")
    for i, a in enumerate(summary.agents):
        err = "?" if a["error_bl"] is None else f"{a['error_bl']:.3f} BL"
        lines.append(f"  agent {i}: final {a['final_mm']} mm, goal {a['goal_mm']} mm, error {err}")
    for f in summary.faults:
        lines.append(f"FAULT: {f['reason']}")
    lines.append(f"REACHED and held: both agents within {summary.tolerance_bl:g} BL"
                 if summary.reached else f"NOT REACHED (tolerance {summary.tolerance_bl:g} BL)")
    return "\n".join(lines)


def loopback_rig(rig: RigConfig) -> RigConfig:
    """The rig of the emulated bench `execute` starts itself, with the supplies' reply watchdog
    at least `LOOPBACK_REPLY_TIMEOUT_S`: the bench is a process on the same (perhaps busy)
    machine, nothing real is energised, and a scheduler stall of a few hundred ms is not a
    silent supply. A rig file given with --rig keeps its own watchdog."""
    timeout = max(rig.stream.reply_timeout_s, LOOPBACK_REPLY_TIMEOUT_S)
    return rig.model_copy(update={"stream": rig.stream.model_copy(
        update={"reply_timeout_s": timeout})})


