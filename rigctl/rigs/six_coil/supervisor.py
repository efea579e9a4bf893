"""The closed loop: the camera watches the robots, and after every move the supervisor compares where
they are with where the plan expected them, re-plans from the measured state when they are off, and
holds the field while it cannot see them.

Three threads cooperate:

- the tracking thread (`TrackingLoop`) reads the rig's camera (`CameraDriver`), tracks every fresh
  frame (`Tracker`, the rig file's calibration) and publishes the latest positions. Tracking is
  *lost* when no fresh frame came for `camera.timeout_s` (a frozen, dropped or stalled stream) or a
  robot was not found in `LOST_AFTER_FRAMES` frames in a row (black-out, occlusion);
- the stream thread asks the sequencer (`SupervisedSequencer`) for each cycle's currents. The
  sequencer stops at the end of every move with the field held (the magnets lie still, aligned) and
  waits there until the supervisor releases it or splices a new program in; it also holds at once,
  mid-move, while tracking is lost (the field stops turning, so the magnets stop);
- the decision thread (`Supervisor`) judges each move end from a frame captured after the move
  settled: within `threshold_mm` of the expected state, go on; otherwise re-plan from the measured
  state to the goals with the RRT (`plan_rrt`, a time budget, fractional turns allowed), realize the
  new moves from the field the coils hold now, allocate them, certify them like a plan and splice
  them in place of the rest of the program (`certified_replan`). At the end of the program the
  goals themselves are checked, with a bounded number of further re-plans before it gives up with a
  fault.

A re-plan is streamed only with a certificate of its own: every check of the plan's pre-flight
(`rigctl.rigs.six_coil.certify`: currents, voltages R(T) I + L dI/dt, field, gradient, heating,
links, size) run on the whole stream as it will then have been, the samples already sent followed
by the re-plan, at the stream's own rate. Its first sample's dI/dt is taken from the currents being
streamed when it is spliced in, not from 0 A: a re-plan starts from the field the coils hold, so
there is no step there, and a check from 0 A saw one of the whole held current in one sample, which
at 1 kHz (dI/dt = I x rate: 9.8 A x 1000/s x 30 mH = 293 V) refused every re-plan of a run that
100 Hz (29 V) let through. Where the currents being streamed are not the re-plan's first sample, a
straight lead-in ramp joins them (`lead_in`), over the plan's own `field.ramp_s` or longer when a
supply's compliance needs it. A refusal is a fault, never a clip. (The heating check counts the
samples at the stream's rate; the time the stream held the field at move ends while the supervisor
judged and re-planned is not in it, and the run's live winding model watches that.)

Each robot's own response is identified from what the camera saw (`rigctl.physics.identify`): after every
move, the robots whose measured path touched no wall and no other robot update their rolling gain,
heading bias and drift (a Kalman filter per robot, with its uncertainty); a robot that met a wall
but no other robot updates them from the one-agent model's image of the move (linearised at the
estimate: along a wall it tells the gain, not the heading). Re-plans run the RRT on the
global-input model with those per-robot responses, so the moves it chooses are the commanded ones
and the states it expects are where each robot will really go. Relative errors, which no
shared translation can fix, are fixed with a wall: a contact correction (`rigctl.plans.correction`:
push along an axis until a robot rests on a wall, then the translation that fits best) is tried
first, the RRT (which finds longer wall manoeuvres) when that does not reach the tolerance. The estimates go to
the record's `identification` series after every move. Every decision is a run-record event:
`check`, `identify`, `replan` (and `replan_wide` at the end of the program), `suspend`, `resume`,
`give_up`.
"""

from __future__ import annotations

import json
import logging
import math
import os
import pickle
import select
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from rigctl.core.errors import ConfigError, PlanError, RigError
from rigctl.core.priority import step_back
from rigctl.core.record import RunRecord, Series
from rigctl.physics.coils import actuation_matrix, field_offset
from rigctl.physics.identify import RollingIdentifier
from rigctl.plans.checks import plan_model
from rigctl.plans.correction import correct_by_contact
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.rrt import RrtOptions, plan_rrt, replay
from rigctl.plans.schema import GlobalMovesPlan, dump_plan, parse_plan
from rigctl.rigs.six_coil.allocate import CurrentProgram, allocate, currents_for_field
from rigctl.rigs.six_coil.certify import current_program_checks
from rigctl.rigs.six_coil.realize import NO_MOVE, FieldProgram, realize_global_moves
from rigctl.rigs.six_coil.sequencer import Sequencer
from rigctl.run.certificate import Certificate, certify
from rigctl.run.hold import ramp
from rigctl.run.interruptions import Suspension
from rigctl.vision.tracking import TrackingLoop

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

log = logging.getLogger(__name__)

_SHORTEST_MOVE_MM = 0.05  # re-planned moves shorter than this are left out (each costs a hold)
REPLAN_ATTEMPTS = 3  # RRT runs (other seeds, longer budgets) before a re-plan that found no move fails
_GAIN_LIMITS = (0.5, 1.5)  # plausible range of the rolled distance per commanded distance
_FREE_MARGIN_MM = 0.3  # a measured path this close to a wall or another robot may have touched it
_COMMAND_WAIT_S = 0.02  # a go-on waits at most this for its command to leave (100 Hz: 2 cycles)
LEAD_IN_VOLTAGE_SHARE = 0.9  # of a supply's compliance a lead-in may use: the winding's R rises hot


# -- sequencing ----------------------------------------------------------------------------------

class SupervisedSequencer(Sequencer):
    """A `Sequencer` that waits at the end of every move (`gates`) until released, holds the field
    at once while tracking is lost, and takes a new program spliced in place of the rest.

    currents: the program; move_ends: samples where moves end; ramp_samples: abort/pause ramps.
    """

    def __init__(self, currents: CurrentProgram, move_ends: list[int], ramp_samples: int) -> None:
        super().__init__(currents, move_ends, ramp_samples)
        self.gates = set(move_ends)  # samples where the supervisor judges the move
        self.waiting_at: int | None = None
        self.arrived = threading.Event()
        self._released: int | None = None
        self._held = False
        self._mark: int | None = None  # decision awaiting its first command
        self.command_times: dict[int, float] = {}
        self.command_left = threading.Event()  # the released decision's first command left

    def next(self) -> tuple[np.ndarray, int, int] | None:
        with self._lock:
            if not (self.requests.abort_wanted or self.aborted or self._queue):
                if self._held:
                    return self._last, self.index, -1
                if self.index in self.gates and self.index != self._released:
                    if self.waiting_at != self.index:
                        self.waiting_at = self.index
                        self.arrived.set()
                    return self._last, self.index, -1
        step = super().next()
        if step is not None and self._mark is not None and not self.paused:
            self.command_times[self._mark] = time.monotonic()
            self._mark = None
            self.command_left.set()
        return step

    def release(self, decision: int | None = None) -> None:
        """Go on from the move end it waits at; `decision` is timed to its first command."""
        with self._lock:
            self._released = self.waiting_at
            self.waiting_at = None
            self.arrived.clear()
            self._mark = decision
            if decision is not None:
                self.command_left.clear()
        self.wake()

    def streamed(self) -> np.ndarray:
        """The program's samples (k, n) A sent so far: a copy, its last row the setpoints held
        while the sequencer waits at a move end."""
        with self._lock:
            return self.program[:self.index].copy()

    def splice(self, new: CurrentProgram, new_move_ends: list[int], decision: int | None = None,
               at: int | None = None) -> int:
        """Replace everything from the current sample on by `new` (its move ends relative to its
        own start); returns the absolute sample where `new` starts. `at`: the sample `new` was
        certified to start at (`streamed`); PlanError if the stream has gone past it."""
        with self._lock:
            k = self.index
            if at is not None and k != at:
                raise PlanError(f"the re-plan was made to start at sample {at}, but the stream is "
                                f"at sample {k}: not spliced")
            first_move = int(self.segments.max(initial=-1)) + 1
            segment = np.where(new.segment >= 0, new.segment + first_move, -1)
            self.program = np.concatenate([self.program[:k], new.currents_A])
            self.segments = np.concatenate([self.segments[:k], segment])
            self.gates = {k + e for e in new_move_ends}
            self.boundaries = self.boundaries | self.gates
            self._released = None
            self.waiting_at = None
            self.arrived.clear()
            self._mark = decision
        self.wake()
        return k

    def hold(self) -> None:
        """Hold the present setpoints now, mid-move if need be (the field stops turning)."""
        with self._lock:
            self._held = True
            self.paused = True

    def unhold(self) -> None:
        with self._lock:
            self._held = False
            self.paused = False


# -- the supervisor ------------------------------------------------------------------------------

@dataclass(frozen=True)
class SupervisorSettings:
    """threshold_mm: after a move, a robot farther than this from the expected state re-plans;
    goal_threshold_mm: at the end, every robot must be this close to its goal (None: 3/4 of the
    plan's tolerance, leaving room for the tracker's error); max_replans: re-plans in a run before
    giving up, however much they gain (bounds the run's time); stalled_replans: re-plans on the way
    that found the robots no closer to their goals than at an earlier re-plan (by progress_mm in
    R^2n) before giving up, so corrections that keep gaining ground are not cut off mid-route;
    final_replans: at most this many after the program ended; replan_budget_s: RRT time budget;
    settle_s: wait after a move end before judging; rrt_tolerance_mm: what the re-plan aims for
    (distance in R^2n); seed: the RRT's randomness;
    estimate_gain: identify each robot's response from the moves seen and re-plan with it (False:
    re-plan with the planner's model as it is); contact_noise_mm: how far a robot sliding along a
    wall strays from the model per square-root turn (its moves are weighed by it);
    wide_step_turns, final_replan_budget_s, wide_replans: a re-plan at the end of the program that
    did not reach the tolerance tries again with a tree of this many turns a step, for this long,
    and takes it when it reaches the tolerance or gets less than half as far; at most
    `wide_replans` times in a run (each costs its budget, and a state one could not correct is
    seldom corrected by the next)."""

    threshold_mm: float = 1.0
    goal_threshold_mm: float | None = None
    max_replans: int = 40
    stalled_replans: int = 6
    progress_mm: float = 1.0
    final_replans: int = 6
    replan_budget_s: float = 2.0
    settle_s: float = 0.05
    rrt_tolerance_mm: float = 0.3
    seed: int = 0
    estimate_gain: bool = True
    contact_noise_mm: float = 0.25
    wide_step_turns: float = 5.0
    wide_replans: int = 2
    final_replan_budget_s: float = 4.0


class ReplanBudget:
    """How many more corrections a run may make. A re-plan on the way is charged as stalled only
    when the run made no headway since the one before: no move of that correction landed on its
    plan (`landed`, the moves judged within the threshold since), and the robots are no closer to
    their goals (distance in R^2n) than at the best earlier re-plan by `progress_mm`. (The goal
    distance alone is no measure: a route round an obstacle takes the robots away from their goals
    for a while.) Every re-plan counts against `max_replans`, those after the program ended against
    `final_replans`. `charge` returns None while the run may re-plan, else why it may not."""

    def __init__(self, settings: SupervisorSettings) -> None:
        self.settings = settings
        self.total = self.stalled = self.final = 0
        self.best_mm = math.inf

    def charge(self, goal_distance_mm: float, last: bool, landed: int = 0) -> str | None:
        s = self.settings
        if self.total >= s.max_replans:
            return f"the run's {s.max_replans} re-plans are used up"
        if last and self.final >= s.final_replans:
            return f"{s.final_replans} re-plans at the end of the program did not reach them"
        progressed = landed > 0 or goal_distance_mm <= self.best_mm - s.progress_mm
        if not last and not progressed and self.stalled >= s.stalled_replans:
            return (f"ran out of corrections on the way: {self.stalled} corrections missed at "
                    f"their first move and brought the robots no closer to their goals (best "
                    f"{self.best_mm:.2f} mm in all, now {goal_distance_mm:.2f} mm)")
        self.total += 1
        self.final += last
        self.stalled += not last and not progressed
        self.best_mm = min(self.best_mm, goal_distance_mm)
        return None


@dataclass
class Decision:
    """One judgement at a move end (for the record and the latency figures): t_source, t_received
    monotonic s its frame was taken and reached the camera driver (None: not told)."""

    number: int
    sample: int
    kind: str  # "continue", "replan", "done", "give_up"
    t_source: float
    error_mm: list[float] = field(default_factory=list)
    t_received: float | None = None


class Supervisor:
    """Runs the closed loop for one run: see the module docstring.

    plan: the plan (expected filled); rig: must have a camera with a calibration; program, currents:
    what `rigctl.rigs.six_coil.global_moves.prepare` made; ramp_samples: the sequencer's ramp; truth: optional callable
    returning the emulator's true positions (n, 2) mm, to measure the tracker against.
    """

    def __init__(self, plan: GlobalMovesPlan, rig: SixCoilRig, program: FieldProgram,
                 currents: CurrentProgram, *, ramp_samples: int,
                 settings: SupervisorSettings = SupervisorSettings(),
                 truth: Callable[[], np.ndarray] | None = None) -> None:
        if rig.camera is None:
            raise ConfigError("the closed loop needs a [camera] in the rig file")
        self.plan, self.rig, self.settings, self.truth = plan, rig, settings, truth
        self.model: GlobalInputModel = plan_model(plan)
        self.goals = np.array([a.goal for a in plan.agents], dtype=float)
        self.goal_threshold_mm = settings.goal_threshold_mm or 0.75 * plan.tolerance_mm
        starts = np.array([a.start for a in plan.agents], dtype=float)
        ends = [program.move_end_index(i) for i in range(program.n_moves)]
        self.sequencer = SupervisedSequencer(currents, ends, ramp_samples)
        expected = np.array(plan.expected, dtype=float).reshape(-1, len(starts), 2)
        self._expected = {e: expected[i] for i, e in enumerate(ends)}
        # The RRT runs in a worker process: in this one it would hold the GIL for its whole time
        # budget and starve the stream loop.
        self._planner: ReplanWorker | None = None
        self._plan_text = dump_plan(plan)
        bounds = self.model.workspace.bounds
        self.tracking = TrackingLoop(rig.camera, self.model.radii, starts, roi_mm=bounds,
                                     on_floor=self.model.workspace.contains)
        self.gain = 1.0
        self.replans = 0
        self.budget = ReplanBudget(settings)
        self._landed = 0  # moves judged on their plan since the last re-plan
        self._wide_tried = 0  # re-plans at the end that tried the wide tree
        self.decisions: list[Decision] = []
        self.tracking_errors_mm: list[float] = []
        self.fault: RigError | None = None
        self.suspension = Suspension()  # why the run is held now (tracking lost), if it is
        self.final_positions: np.ndarray | None = None
        self.record: RunRecord | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._measured_at: dict[int, np.ndarray] = {}
        self._truth_pool: ThreadPoolExecutor | None = None  # ground truth, off the decision path
        moves = np.array(plan.moves, dtype=float).reshape(-1, 2)
        self._commanded_at = {e: moves[i] for i, e in enumerate(ends)}  # each move's input, mm
        self._time_at: dict[int, float] = {}  # capture time of the frame each judgement used
        self.identifier = RollingIdentifier(len(starts))
        self._series: Series | None = None

    # -- life cycle -----------------------------------------------------------------------------
    def start(self, record: RunRecord | None) -> None:
        """Acquire the robots with the camera and start judging (before the stream starts)."""
        self.record = self.suspension.record = record
        self._planner = ReplanWorker()  # imports numpy, scipy and the planner while we go on
        if self.truth is not None:
            self._truth_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="truth")
        if record is not None:
            self.tracking.record_to(record)  # the camera's positions, in the run record
            self._series = record.open_series("identification", self.identifier.series_columns(),
                                              self.identifier.series_units())
        assert self.rig.camera is not None  # a supervisor is made for a rig with a camera only
        first = self.tracking.start(acquire_timeout_s=max(5.0, 2 * self.rig.camera.timeout_s))
        self._measured_at[0] = first.positions_mm
        self._time_at[0] = first.t_source
        self._t0 = record.t0 if record is not None else first.t_source  # the run's clock
        if self._series is not None:
            self._series.row(self.identifier.series_row(first.t_source - self._t0))
        self._event("tracking", frame=first.frame, positions=first.positions_mm.round(3).tolist())
        self._thread = threading.Thread(target=self._run, name="supervisor", daemon=True)
        self._thread.start()
        # the re-planner's imports run on the other core while the camera acquired the robots;
        # they finish before anything is energised, not during the stream's first seconds
        if not self._planner.wait_ready(timeout_s=10.0):
            log.warning("the re-planning process is still starting; streaming anyway")

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            every_attempt = REPLAN_ATTEMPTS * (REPLAN_ATTEMPTS + 1) / 2  # budgets 1x, 2x, 3x
            self._thread.join(self.settings.replan_budget_s * every_attempt + 5.0)
        if self._truth_pool is not None:
            self._truth_pool.shutdown(wait=True)
        state = self.tracking.latest()
        if state is not None:
            self.final_positions = state.positions_mm
        self._measure_tracking()
        self.tracking.stop()
        if self._planner is not None:
            self._planner.close()

    def summary(self) -> dict:
        """`replans` and `tracking` for the run summary."""
        errors = np.array(self.tracking_errors_mm)
        return {
            "replans": self.replans,
            "identified": self.identifier.summary(),
            "tracking": {
                "mean_error_mm": round(float(errors.mean()), 4) if errors.size else None,
                "max_error_mm": round(float(errors.max()), 4) if errors.size else None,
                "lost_frames": self.tracking.lost_frames,
                "frames": self.tracking.frames,
            },
        }

    # -- the decision thread --------------------------------------------------------------------
    def _event(self, name: str, **info: object) -> None:
        if self.record is not None:
            self.record.event(name, **info)
        log.info("supervisor: %s %s", name, info)

    def _run(self) -> None:
        seq, suspension = self.sequencer, self.suspension
        while not self._stop.is_set():
            if not self.tracking.ok():
                if suspension.since is None:
                    seq.hold()
                    suspension.lost(time.monotonic(), self.tracking.why_lost(),
                                    sample=seq.index)
                self.tracking.wait(0.05)
                continue
            if suspension.since is not None:
                seq.unhold()
                suspension.regained(time.monotonic(), sample=seq.index)
            if not seq.arrived.wait(0.02):
                continue
            try:
                self._judge(seq.waiting_at)
            except RigError as err:
                self._give_up(err)
                return
            except Exception as err:  # a bug must not leave the run waiting at a move end forever
                log.exception("supervisor failed")
                self._give_up(RigError(f"supervisor failed: {type(err).__name__}: {err}"))
                return

    def _give_up(self, err: RigError) -> None:
        self.fault = err
        self._event("give_up", reason=str(err), kind=type(err).__name__, device=err.device)
        self.sequencer.requests.abort()
        self.sequencer.release()

    def _judge(self, sample: int | None) -> None:
        seq = self.sequencer
        if sample is None:
            return
        arrived = time.monotonic()
        state = self.tracking.captured_after(arrived + self.settings.settle_s,
                                             timeout_s=self.tracking.timeout_s)
        if state is None:
            return  # tracking lost meanwhile: the loop suspends, and judges again after
        measured = state.positions_mm
        expected = self._expected[sample]
        last = sample == max(seq.gates)
        if self.truth is not None and self._truth_pool is not None:
            # asked now, while the robots are at rest, and answered off the decision's path: a
            # backdoor round trip to a busy emulator took milliseconds of the frame-to-command time
            self._truth_pool.submit(self._measure_tracking, measured).add_done_callback(
                _log_failure)
        error = np.hypot(*(measured - expected).T)
        goal_error = np.hypot(*(measured - self.goals).T)
        number = len(self.decisions)
        decision = Decision(number, sample, "continue", state.t_source, error.round(4).tolist(),
                            state.t_received)
        self.decisions.append(decision)
        go_on = (goal_error.max() <= self.goal_threshold_mm if last
                 else error.max() <= self.settings.threshold_mm)
        if go_on:  # release first, identify and write the record after: the command leaves sooner
            decision.kind = "done" if last else "continue"
            self._landed += 1
            seq.release(number)
            # Python here would hold the GIL each time the stream thread comes back from a
            # socket in the cycle that sends the command (up to a switch interval per read)
            seq.command_left.wait(_COMMAND_WAIT_S)
        # what the move says of the robots' response: a re-plan below uses it, a go-on does not
        # wait for it (its fit and record lines took 1-2 ms of the frame-to-command time)
        self._identify(sample, measured, state.t_source)
        self._event("check", sample=sample, error_mm=error.round(4).tolist(),
                    goal_error_mm=goal_error.round(4).tolist(), last=last, gain=round(self.gain, 4))
        if go_on:
            return
        refused = self.budget.charge(float(np.linalg.norm(goal_error)), last, self._landed)
        if refused is not None:
            raise PlanError(
                f"goals not reached after {self.replans} re-plans ({refused}): agents "
                f"{np.flatnonzero(goal_error > self.goal_threshold_mm).tolist()} are "
                f"{goal_error.max():.2f} mm from their goals at worst (threshold "
                f"{self.goal_threshold_mm:g} mm)")
        decision.kind = "replan"
        self._replan(sample, measured, error, last, number)

    def _replan(self, sample: int, measured: np.ndarray, error: np.ndarray, last: bool,
                number: int) -> None:
        s = self.settings
        start = self._free_start(measured)
        assert self._planner is not None
        gains, headings = self.identifier.response() if s.estimate_gain else (None, None)
        if gains is not None:
            gains = np.clip(gains, *_GAIN_LIMITS)
        for attempt in range(REPLAN_ATTEMPTS):
            # an RRT that found nothing in its budget (a loaded machine grows fewer nodes) tries
            # again with other random draws and a longer budget before the run gives up
            result = self._planner.replan(
                self._plan_text, str(self.plan.base_dir or "."), start, self.goals,
                2.0 * math.pi * self.rig.magnets.radius_mm, s.rrt_tolerance_mm,
                s.seed + self.replans + 1000 * attempt, s.replan_budget_s * (1 + attempt),
                gains, headings)
            if len(result.moves):
                break
            self._event("replan_empty", sample=sample, attempt=attempt + 1,
                        planned_distance_mm=round(result.distance, 4), nodes=result.nodes)
        if last and not result.solved and self._wide_tried < s.wide_replans:
            self._wide_tried += 1
            # at the end, robots a millimetre or two off need a wall manoeuvre the one-turn tree
            # rarely finds in its budget (seed 112: 20 000 nodes, 1.5 mm short, every time);
            # trees of `wide_step_turns` turns a step, given longer, find it
            wide = self._planner.replan(
                self._plan_text, str(self.plan.base_dir or "."), start, self.goals,
                2.0 * math.pi * self.rig.magnets.radius_mm * s.wide_step_turns,
                s.rrt_tolerance_mm, s.seed + self.replans + 500, s.final_replan_budget_s, gains,
                headings)
            # taken when it reaches the tolerance, or gets less than half as far: a long wide
            # manoeuvre that ends nearly as far off only adds the error of its own many moves
            chosen = bool(len(wide.moves)) and (wide.solved or wide.distance < 0.5 * result.distance)
            self._event("replan_wide", sample=sample, planned_distance_mm=round(wide.distance, 4),
                        solved=wide.solved, nodes=wide.nodes, seconds=round(wide.seconds, 3),
                        chosen=chosen)
            if chosen:
                result = wide
        if len(result.moves) == 0:
            raise PlanError(f"re-plan from the measured state found no move that brings the robots "
                            f"closer to their goals in {REPLAN_ATTEMPTS} attempts (best "
                            f"{result.distance:.2f} mm)")
        self.replans += 1
        self._landed = 0
        commanded = result.moves  # the model already maps each robot's response
        streamed = self.sequencer.streamed()
        # a LimitError here (allocation, certificate) is a fault, never a clip
        replan = certified_replan(commanded, self.rig, streamed,
                                  name=f"{self.plan.name}: re-plan {self.replans}")
        ends = replan.move_ends
        begin = self.sequencer.splice(replan.currents, ends, number, at=len(streamed))
        for i, e in enumerate(ends):
            self._commanded_at[begin + e] = commanded[i]
            self._expected[begin + e] = result.states[i]
        self._measured_at[begin] = measured
        self._time_at[begin] = self._time_at.get(sample, time.monotonic())
        self._event("replan", sample=sample, reason="end of program" if last else "off the plan",
                    error_mm=error.round(4).tolist(), moves=len(result.moves),
                    commanded_mm=np.round(commanded, 3).tolist(), planned_distance_mm=round(
                        result.distance, 4), solved=result.solved, nodes=result.nodes,
                    seconds=round(result.seconds, 3), gain=round(self.gain, 4),
                    lead_in=replan.lead, certificate=replan.certificate_line())

    def _free_start(self, measured: np.ndarray) -> np.ndarray:
        """The measured state nudged into free space (a tracked robot may sit a hair inside a wall
        or another robot), so the model and the planner accept it."""
        p = measured.astype(float).copy()
        radii = self.model.radii
        for _ in range(8):
            if bool(self.model.is_free(p)):
                break
            clearance, normal, _ = self.model.workspace.surface(p)
            inside = clearance < radii + 1e-6
            p[inside] += ((radii - clearance + 1e-5)[:, None] * normal)[inside]
            for i in range(len(p)):
                for j in range(i + 1, len(p)):
                    gap = p[j] - p[i]
                    dist = float(np.hypot(*gap))
                    need = radii[i] + radii[j] + self.model.min_separation_mm + 1e-5
                    if dist < need:
                        push = (need - dist) / 2 * gap / max(dist, 1e-9)
                        p[i] -= push
                        p[j] += push
        return p

    def _identify(self, sample: int, measured: np.ndarray, t_source: float) -> None:
        """Update each robot's identified response from the move that ended at `sample`: the
        robots whose measured straight path stayed clear of the walls and of the other robots
        (by `_FREE_MARGIN_MM`) saw the commanded input act on them alone."""
        begin = self._start_of(sample)
        before = self._measured_at.get(begin)
        self._measured_at[sample] = measured
        self._time_at[sample] = t_source
        if not self.settings.estimate_gain or before is None:
            return
        commanded = self._commanded_at.get(sample)
        if commanded is None:
            return
        displacement = measured - before
        free = self._moved_freely(before, displacement)
        dt = max(t_source - self._time_at.get(begin, t_source), 0.0)
        used = self.identifier.observe(commanded, displacement, free, dt)
        used |= self._identify_along_walls(before, commanded, displacement, free, dt)
        gains, _ = self.identifier.response()
        self.gain = float(np.clip(gains.mean(), *_GAIN_LIMITS))
        if self._series is not None:
            self._series.row(self.identifier.series_row(t_source - self._t0))
        if used.any():
            estimate = self.identifier.summary()
            self._event("identify", sample=sample, used=np.flatnonzero(used).tolist(),
                        gain=estimate["gain"], gain_std=estimate["gain_std"],
                        heading_deg=estimate["heading_deg"])

    def _identify_along_walls(self, before: np.ndarray, commanded: np.ndarray,
                              displacement: np.ndarray, free: np.ndarray, dt: float) -> np.ndarray:
        """(n,) True where a robot that moved but not freely, and kept clear of the other robots
        (their straight paths never came within reach), updated its gain from the move
        (`observe_linearised`): alone, a robot of response a, b moves as the one-agent model
        (`GlobalInputModel.alone`) moves it by [[a, -b], [b, a]] u, so that model gives the
        prediction and, by differences in a and b, its derivatives. A robot that slid along walls
        on every move is learnt too, instead of taking the others' mean."""
        used = np.zeros(len(before), dtype=bool)
        radii, after = self.model.radii, before + displacement
        turns = float(np.hypot(*commanded)) / (2.0 * math.pi * self.rig.magnets.radius_mm)
        jitter = self.settings.contact_noise_mm * math.sqrt(turns)
        for i in np.flatnonzero((np.hypot(*displacement.T) > 1.0) & ~free).tolist():
            others = np.arange(len(before)) != i
            reach = radii[i] + radii[others] + self.model.min_separation_mm + _FREE_MARGIN_MM
            gap = before[others] - before[i]  # (m, 2), and how it changed over the move
            change = (after[others] - after[i]) - gap
            t = np.clip(-np.sum(gap * change, axis=1) / np.maximum(
                np.sum(change * change, axis=1), 1e-12), 0.0, 1.0)
            if np.any(np.hypot(*(gap + t[:, None] * change).T) < reach):
                continue  # it may have met another robot: the one-agent model does not know
            single = self.model.alone(i)
            start = before[i].copy()
            clearance, normal, _ = self.model.workspace.surface(start[None])
            if clearance[0] < radii[i]:  # tracked a hair inside a wall: put it back out
                start += (radii[i] - clearance[0] + 1e-5) * normal[0]
            predicted, jacobian = one_agent_move(single, start, commanded,
                                                 self.identifier.estimates[i].mean[:2])
            used[i] = self.identifier.observe_linearised(
                i, commanded, predicted, jacobian, after[i] - start, dt, jitter)
        return used

    def _moved_freely(self, before: np.ndarray, displacement: np.ndarray) -> np.ndarray:
        """(n,) True where a robot's straight path from `before` (n, 2) by `displacement` (n, 2)
        kept `_FREE_MARGIN_MM` from every wall, and from every other robot at both ends."""
        radii = self.model.radii
        moved = np.hypot(*displacement.T) > 1.0
        clear = self.model.workspace.sweep_clear(before, displacement, radii + _FREE_MARGIN_MM)
        free = moved & np.asarray(clear, dtype=bool)
        after = before + displacement
        for i in range(len(before)):
            for j in range(i + 1, len(before)):
                reach = radii[i] + radii[j] + self.model.min_separation_mm + _FREE_MARGIN_MM
                if min(np.hypot(*(before[j] - before[i])), np.hypot(*(after[j] - after[i]))) < reach:
                    free[i] = free[j] = False
        return free

    def _start_of(self, sample: int) -> int:
        """The sample where the move ending at `sample` began (the previous gate or splice)."""
        earlier = [s for s in self._measured_at if s < sample]
        return max(earlier) if earlier else 0

    def _measure_tracking(self, measured: np.ndarray | None = None) -> None:
        """Tracked against the emulator's ground truth, robots at rest."""
        if self.truth is None:
            return
        if measured is None:
            state = self.tracking.latest()
            if state is None:
                return
            measured = state.positions_mm
        try:
            truth = np.asarray(self.truth(), dtype=float).reshape(measured.shape)
        except RigError as err:
            log.warning("could not read ground truth: %s", err)
            return
        self.tracking_errors_mm.extend(np.hypot(*(measured - truth).T).tolist())


def one_agent_move(single: GlobalInputModel, start: np.ndarray, commanded: np.ndarray,
                   ab: np.ndarray, step: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """A robot of response (a, b) (gain g, heading theta: a = g cos theta, b = g sin theta) alone
    at `start` (2,) mm, moved by the shared input `commanded` (2,) mm: it moves as the one-agent
    model `single` moves it by [[a, -b], [b, a]] u. Returns its displacement (2,) and the
    derivatives (2, 2) of it in (a, b) (forward differences of `step`)."""
    a, b = float(ab[0]), float(ab[1])
    points = np.array([[a, b], [a + step, b], [a, b + step]])
    moves = np.stack([points[:, 0] * commanded[0] - points[:, 1] * commanded[1],
                      points[:, 1] * commanded[0] + points[:, 0] * commanded[1]], axis=1)
    ends = single.apply(np.broadcast_to(start, (3, 1, 2)), moves)[:, 0]
    return ends[0] - start, np.stack([ends[1] - ends[0], ends[2] - ends[0]], axis=1) / step


def _log_failure(future) -> None:
    if future.exception() is not None:
        log.error("measuring the tracker against ground truth failed: %r", future.exception())


# -- a re-plan's program, certified ------------------------------------------------------------------

@dataclass(frozen=True)
class CertifiedReplan:
    """A re-plan ready to splice: its field program, its currents (the lead-in first, then the
    program's), the lead-in's length in samples, the program's move ends in `currents`' samples,
    and the certificate of the whole stream it makes."""

    field: FieldProgram
    currents: CurrentProgram
    lead: int
    move_ends: list[int]
    certificate: Certificate

    def certificate_line(self) -> str:
        """For the record's `replan` event: how many checks passed, the tightest one and the
        highest supply voltage."""
        c = self.certificate.checks
        tight = min(c, key=lambda x: x.margin / max(abs(x.limit), 1e-12))
        volts = max((x for x in c if x.check.startswith("voltage")), key=lambda x: x.value)
        return (f"passed {len(c)} checks; tightest: {tight}; highest voltage: {volts.value:.1f} V "
                f"of {volts.subject} (limit {volts.limit:g} V)")


def lead_in(start_A: np.ndarray, first_A: np.ndarray, rig: SixCoilRig) -> np.ndarray:
    """The setpoints (m, n) A that take the supplies from `start_A` (n,), the currents being
    streamed, to `first_A` (n,), a re-plan's first sample, without a step; `first_A` itself is
    not among them. Empty (m = 0) where they are equal, as when the re-plan starts from the field
    the coils hold. Otherwise the straight ramp of a hold (`rigctl.run.hold.ramp`) over the
    plan's own `field.ramp_s` (the start and end ramps of every program), made longer where a
    supply's L dI/dt would need more than LEAD_IN_VOLTAGE_SHARE of its compliance left above
    R I at the ramp's larger end: L |dI| / (share V - R max|I|) seconds."""
    start, first = np.asarray(start_A, dtype=float), np.asarray(first_A, dtype=float)
    step = np.abs(first - start)
    if step.max(initial=0.0) <= 1e-9:
        return np.zeros((0, len(start)))
    resistance = np.array([c.resistance_ohm for c in rig.coils])
    inductance = np.array([c.inductance_H for c in rig.coils])
    compliance = np.array([c.compliance_V for c in rig.coils])
    room = LEAD_IN_VOLTAGE_SHARE * compliance - resistance * np.maximum(np.abs(start),
                                                                        np.abs(first))
    # no room at all: the certificate refuses the program's current itself; ramp at the plan's pace
    need = np.where((room > 0) & (step > 0), inductance * step / np.maximum(room, 1e-12), 0.0)
    return ramp(start, first, max(rig.field.ramp_s, float(need.max())), rig.stream.rate_hz)[:-1]


def certified_replan(moves_mm: np.ndarray, rig: SixCoilRig, streamed_A: np.ndarray, *,
                     name: str) -> CertifiedReplan:
    """Realize, allocate and certify re-planned `moves_mm` (m, 2) on the run's `rig` to follow
    `streamed_A` (k, n) A, the samples the stream has sent (`SupervisedSequencer.streamed`): the
    moves in fractional turns (corrections; the paper's whole turns stay for the plan itself),
    from the field the last sample makes; a lead-in joins them if they differ, and the stream
    they make together is checked with the plan's own checks (`current_program_checks`) at the
    stream's rate. LimitError (a `CertificateRefused`) naming the failed check if anything breaks
    a limit; nothing is spliced then."""
    n = len(rig.coils)
    held = streamed_A[-1] if len(streamed_A) else np.zeros(n)
    A, offset_T = actuation_matrix(rig), field_offset(rig)[0:3]  # an MPEM's Offset; 0 for loops
    fractional = rig.model_copy(update={"field": rig.field.model_copy(
        update={"whole_turns": False})})
    program = realize_global_moves(moves_mm, fractional, start_field_T=A @ held + offset_T)
    lead = lead_in(held, currents_for_field(A, program.field_T[0] - offset_T), rig)
    currents = allocate(program, rig, start_A=lead[-1] if len(lead) else held)
    m, rate = len(lead), program.rate_hz
    joined = CurrentProgram(
        t_s=np.arange(m + len(currents.t_s)) / rate,
        currents_A=np.vstack([lead, currents.currents_A]),
        segment=np.concatenate([np.full(m, NO_MOVE), currents.segment]),
        coil_names=currents.coil_names)
    ends = [m + program.move_end_index(i) for i in range(program.n_moves)]
    k = len(streamed_A)

    def describe(j: int) -> str:
        if j < k:
            return "the program streamed before it"
        if j < k + m:
            return "its lead-in from the currents being streamed"
        return program.describe_sample(j - k - m)

    stream = np.vstack([streamed_A.reshape(-1, n), joined.currents_A])
    checks = current_program_checks(rig, stream, rate, describe=describe,
                                    move_ends=[k + e for e in ends[:-1]])
    certificate = certify(rig, "re-plan", name, checks).require(
        f"{name}: refused by its certificate, not streamed")
    return CertifiedReplan(program, joined, m, ends, certificate)


# -- the re-planner (a worker process) ---------------------------------------------------------------

@dataclass(frozen=True)
class Replanned:
    """moves (m, 2) mm, states (m, n, 2) mm after each, distance to the goals (mm, R^2n), solved,
    nodes grown, seconds spent."""

    moves: np.ndarray
    states: np.ndarray
    distance: float
    solved: bool
    nodes: int
    seconds: float


def replan_worker(plan_text: str, base_dir: str, start: np.ndarray, goals: np.ndarray,
                  robostep_mm: float, tolerance_mm: float, seed: int, budget_s: float,
                  gains: np.ndarray | None = None, headings_rad: np.ndarray | None = None
                  ) -> Replanned:
    """Re-plan from `start` (n, 2) mm to `goals` (n, 2) mm with the RRT under the plan's model
    with each robot's identified response (gains, headings_rad (n,); None: the shared input):
    one turn per tree move, fractional final approach, `budget_s` seconds at most. Moves shorter
    than _SHORTEST_MOVE_MM are dropped (the states replayed without them)."""
    plan = parse_plan(json.loads(plan_text), "re-plan", base_dir=base_dir)
    model = plan_model(plan).with_response(gains, headings_rad)
    began = time.perf_counter()
    # First the contact correction (push against a wall, then translate: a second or less);
    # the RRT only when that does not reach the tolerance, and the better of the two is used.
    correction = correct_by_contact(model, start, goals)
    improves = correction.distance < float(np.linalg.norm(start - goals))
    moves, nodes = (correction.moves if improves else np.zeros((0, 2))), 0
    if correction.distance > tolerance_mm:
        options = RrtOptions(robostep_mm=robostep_mm, k=16, tolerance_mm=tolerance_mm,
                             greedy=True, final_approach=True, goal_bias=0.05, max_nodes=20_000,
                             nn_eps=0.5)
        result = plan_rrt(model, start, goals, options=options, rng=np.random.default_rng(seed),
                          time_budget_s=budget_s)
        nodes = result.nodes
        if len(result.moves):
            tree_end = replay(model, start, result.moves)[-1]
            if float(np.linalg.norm(tree_end - goals)) < correction.distance:
                moves = result.moves
    moves = moves[np.hypot(*moves.T) >= _SHORTEST_MOVE_MM] if len(moves) else moves
    states = replay(model, start, moves)
    end = states[-1] if len(states) else start
    distance = float(np.linalg.norm(end - goals))
    return Replanned(moves, states, distance, distance <= tolerance_mm, nodes,
                     time.perf_counter() - began)


class ReplanWorker:
    """`replan` in a child process (`python -m rigctl.rigs.six_coil.supervisor`): pickled calls over its stdin
    and stdout, one at a time. Started ahead so its imports are done by the first re-plan."""

    def __init__(self) -> None:
        # a process group of its own: a terminal's Ctrl-C is the run's to handle (an abort), not
        # a KeyboardInterrupt here that would end the run as a re-plan fault; `close`, or its
        # stdin closing with the run's process, ends it. The run's session all the same: where
        # the kernel groups CPU time by session, its niceness then puts it behind the run
        # (`rigctl.core.priority`), where a session of its own would take as much as the run's
        self._proc = subprocess.Popen([sys.executable, "-m", "rigctl.rigs.six_coil.supervisor"],
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      process_group=0)
        self._lock = threading.Lock()
        self._ready = False  # the child's "ready" (imports done) has been read

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait until the child has imported everything (a second of CPU on its core, which
        would otherwise compete with the stream's first seconds); False if it did not say so in
        time (it is then awaited by the first `replan`)."""
        with self._lock:
            if not self._ready:
                assert self._proc.stdout is not None
                if not select.select([self._proc.stdout], [], [], timeout_s)[0]:
                    return False
                self._read_ready()
        return True

    def _read_ready(self) -> None:
        assert self._proc.stdout is not None  # started with stdout=PIPE
        try:
            pickle.load(self._proc.stdout)
        except EOFError:
            raise PlanError("the re-planning process ended unexpectedly") from None
        self._ready = True

    def replan(self, *args: object) -> Replanned:
        """`replan_worker(*args)` in the child; PlanError if the child failed."""
        with self._lock:
            assert self._proc.stdin is not None and self._proc.stdout is not None
            if not self._ready:
                self._read_ready()
            pickle.dump(args, self._proc.stdin)
            self._proc.stdin.flush()
            try:
                ok, value = pickle.load(self._proc.stdout)
            except EOFError:
                raise PlanError("the re-planning process ended unexpectedly") from None
        if not ok:
            raise PlanError(f"re-plan failed: {value}")
        return Replanned(**value)

    def close(self) -> None:
        """End the child (its stdin closed: it exits) and close both pipes: a daemon runs one
        worker per run, so a pipe left open is a descriptor leaked per run."""
        assert self._proc.stdin is not None and self._proc.stdout is not None
        self._proc.stdin.close()
        try:
            self._proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        self._proc.stdout.close()


def _serve_replans() -> None:
    """The child's loop, until its parent is gone (its stdin ends, or its stdout breaks: the run's
    process was killed, which its guardian reports; a traceback here would only add noise)."""
    try:
        _answer_replans(sys.stdin.buffer, sys.stdout.buffer)
    except BrokenPipeError:
        # Python flushes stdout again at exit: point it at nothing so that flush cannot fail too
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _answer_replans(stdin, stdout) -> None:
    """Read a pickled argument tuple, answer (ok, Replanned or message); return at end of input."""
    pickle.dump((True, "ready"), stdout)  # every import is done
    stdout.flush()
    while True:
        try:
            args = pickle.load(stdin)
        except EOFError:
            return
        try:
            answer: tuple = (True, dict(replan_worker(*args).__dict__))
        except Exception as err:  # reported to the parent, which turns it into a fault
            answer = (False, f"{type(err).__name__}: {err}")
        pickle.dump(answer, stdout)
        stdout.flush()


if __name__ == "__main__":
    step_back("re-planning process")  # it computes: the stream and the bench go first
    _serve_replans()
