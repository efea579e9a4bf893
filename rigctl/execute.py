"""Execute a plan on a rig: validate, realize, allocate, check every limit, then energise and stream.

Order matters for safety. Everything that can refuse a plan (schema, semantics, whole turns,
current and voltage limits) runs before a single connection is opened. Only then are the supplies
identified, configured and switched on, and the current program streamed at the rig's rate. Any
device fault stops the stream, ramps every other supply to zero and switches it off, and is
reported as a fault naming the device and the reason; the run record keeps everything up to it.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from rigctl.allocate import CurrentProgram, allocate
from rigctl.config import RigConfig, dump_rig
from rigctl.devices import CoilSupplies
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.errors import PlanError, RigError
from rigctl.plans.schema import Plan, check_plan, contact_for_rig, dump_plan, simulate
from rigctl.realize import FieldProgram, realize_global_moves
from rigctl.record import RunRecord
from rigctl.stream import StreamLoop, StreamStats

if TYPE_CHECKING:
    from rigctl.supervisor import Supervisor, SupervisorSettings

log = logging.getLogger(__name__)


@dataclass
class AgentResult:
    final: list[float] | None
    goal: list[float]
    error_mm: float | None
    truth_error_mm: float | None = None  # closed loop on an emulator: ground truth's error too

    def as_dict(self) -> dict:
        out = {"final": self.final, "goal": self.goal, "error_mm": self.error_mm}
        if self.truth_error_mm is not None:
            out["truth_error_mm"] = self.truth_error_mm
        return out


@dataclass
class RunSummary:
    reached: bool
    agents: list[AgentResult]
    run: str
    duration_s: float
    positions_from: str
    tolerance_mm: float
    faults: list[dict] = field(default_factory=list)
    stream: dict | None = None
    replans: int = 0
    tracking: dict | None = None  # closed loop: tracked vs ground truth, lost frames

    def as_dict(self) -> dict:
        return {
            "replans": self.replans,
            "tracking": self.tracking,
            "reached": self.reached,
            "agents": [a.as_dict() for a in self.agents],
            "run": self.run,
            "duration_s": round(self.duration_s, 3),
            "positions_from": self.positions_from,
            "tolerance_mm": self.tolerance_mm,
            "faults": self.faults,
            "stream": self.stream,
        }


class Progress:
    """One status line on a terminal (rewritten in place), or a line per move elsewhere."""

    def __init__(self, out: TextIO | None, n_moves: int, duration_s: float) -> None:
        self.out = out
        self.n_moves = n_moves
        self.duration_s = duration_s
        self.tty = bool(out is not None and out.isatty())
        self._last_move = -2
        self._last_draw = 0.0

    def update(self, move: int, t_s: float, what: str | None = None) -> None:
        """`t_s` s into the run, in `move` (-1: a ramp or hold, not a line of its own off a
        terminal). `what` names the stage for runs whose stages are not global moves (a pair
        run's segments and hold); a new line off a terminal still comes only with a new `move`."""
        if self.out is None:
            return
        now = time.monotonic()
        if move == self._last_move and (not self.tty or now - self._last_draw < 0.2):
            return
        new_move = move != self._last_move
        self._last_move, self._last_draw = move, now
        what = what or self._move_name(move)
        line = f"  {what:<14} {t_s:6.1f} s / {self.duration_s:.1f} s planned"
        if self.tty:
            self.out.write("\r" + line.ljust(50))
            self.out.flush()
        elif new_move and move >= 0:
            self.out.write(line + "\n")

    def _move_name(self, move: int) -> str:
        if move < 0:
            return "ramp/hold"
        if move < self.n_moves:
            return f"move {move + 1}/{self.n_moves}"
        return f"correction {move + 1 - self.n_moves}"  # spliced in by the closed loop's re-plans

    def done(self) -> None:
        if self.out is not None and self.tty:
            self.out.write("\n")


def prepare(plan: Plan, rig: RigConfig) -> tuple[Plan, FieldProgram, CurrentProgram]:
    """Everything that can refuse a plan, with no I/O: returns the plan (expected filled), its
    field program and the allocated currents. Raises PlanError or LimitError naming what is wrong."""
    if plan.rig != rig.rig.kind:
        raise PlanError(
            f"the plan is for a {plan.rig} rig but the rig file describes a {rig.rig.kind} rig"
        )
    if rig.rig.kind != "six-coil":
        raise PlanError(f"executing on a {rig.rig.kind} rig is not implemented yet")
    if plan.expected is None:
        plan = simulate(plan)
    check_plan(plan)
    program = realize_global_moves(np.asarray(plan.moves, dtype=float).reshape(-1, 2), rig)
    return plan, program, allocate(program, rig)


class RunState(str, Enum):
    """What a run is doing. A pause is a state, not an error; abort and e-stop differ: abort ramps
    the field down and ends cleanly, e-stop drops every output at once."""

    PREPARED = "prepared"
    RUNNING = "running"
    PAUSED = "paused"
    FAULTED = "faulted"
    ESTOPPED = "estopped"
    ABORTED = "aborted"
    DONE = "done"


# -- run control shared by `Run` and `rigctl.pair_run.PairRun` ----------------------------------

class RunControl:
    """What every run shares of its control: the state (each change written to the record as a
    `state` event and handed to `on_state`) and the e-stop, taken on the calling thread and
    finished on the stream thread. A run calls `_init_control` in its constructor, sets `record`,
    `stream_loop` and `_supplies` as it goes, and calls `_finish_estop` from its stream cycle."""

    def _init_control(self, on_state: Callable[[RunState, dict], None] | None) -> None:
        self.on_state = on_state
        self.state = RunState.PREPARED
        self.record: RunRecord | None = None
        self.stream_loop: StreamLoop | None = None  # while streaming: its timing, for telemetry
        self._estop = threading.Event()
        self._estop_at: float | None = None
        self._estop_zeroed_at: float | None = None  # every supply told 0 A and off (any thread)
        self._supplies: CoilSupplies | None = None  # once connected: e-stop writes to them directly

    def estop(self, asked_at: float | None = None) -> list[str]:
        """Drop every output now: the calling thread itself tells every connected supply 0 A and
        output off (latched: the stream thread can send nothing but zero after it), then wakes the
        stream thread, which stops the stream and closes the supplies. Returns the supplies the
        e-stop could not be sent to (dead links). `asked_at` (`time.monotonic()`) is when the
        e-stop was asked for, if before this call (another process took it): the record measures
        from it."""
        self._estop_at = time.monotonic() if asked_at is None else asked_at
        self._estop.set()
        unreached: list[str] = []
        supplies = self._supplies
        if supplies is not None:
            unreached = supplies.emergency_zero()
            self._estop_zeroed_at = time.monotonic()
        loop = self.stream_loop
        if loop is not None:
            loop.wake()
        return unreached

    def _set_state(self, state: RunState, **info: object) -> None:
        if state == self.state:
            return
        self.state = state
        if self.record is not None:
            self.record.event("state", state=state.value, **info)
        if self.on_state is not None:
            self.on_state(state, dict(info))

    def _finish_estop(self, supplies: CoilSupplies, record: RunRecord) -> None:
        """On the stream thread, once it sees the e-stop: zero every supply again (belt and
        braces) and record how long after the request the supplies were zeroed."""
        seen = time.monotonic()
        supplies.zero_now()
        done = time.monotonic()
        # from the request: when every supply had been told zero and switched off (by the
        # thread that took the e-stop, or else by this one), and when this thread saw it
        asked = self._estop_at or seen
        direct = self._estop_zeroed_at
        record.event("estop_zeroed",
                     after_request_s=round(min(done, direct or done) - asked, 6),
                     seen_after_request_s=round(seen - asked, 6),
                     stream_zeroed_after_request_s=round(done - asked, 6),
                     direct=direct is not None)

    def _stopped_by(self, err: RigError, record: RunRecord, faults: list[dict]) -> None:
        """A device error ended the run: a fault (recorded, added to `faults`, state faulted),
        unless the e-stop caused it (switching on after it latched, say)."""
        if self._estop.is_set():
            record.event("estop", reason=f"while starting or stopping: {err}")
            return
        faults.append({"device": err.device, "reason": str(err), "kind": type(err).__name__})
        record.event("fault", device=err.device, reason=str(err), kind=type(err).__name__)
        log.error("run stopped: %s", err)
        self._set_state(RunState.FAULTED, device=err.device, reason=str(err))

    def _end_state(self, faults: list[dict], *, aborted: bool,
                   gave_up: RigError | None = None) -> None:
        """The final state once the supplies are safe: an e-stop, the closed loop giving up
        (`gave_up`) or an abort, each also added to `faults`; done when nothing went wrong."""
        if self._estop.is_set():
            faults.append({"device": None, "reason": "emergency stop", "kind": "EStop"})
            self._set_state(RunState.ESTOPPED)
        elif gave_up is not None:
            faults.append({"device": gave_up.device, "reason": f"closed loop gave up: {gave_up}",
                           "kind": type(gave_up).__name__})
            self._set_state(RunState.FAULTED, device=gave_up.device, reason=str(gave_up))
        elif aborted:
            faults.append({"device": None, "reason": "aborted by the operator", "kind": "Abort"})
            self._set_state(RunState.ABORTED)
        elif not faults:
            self._set_state(RunState.DONE)


# -- end of the shared run control ----------------------------------------------------------------


class Sequencer:
    """Chooses each stream cycle's setpoints: the program's next sample, or a hold or a ramp when
    the run is paused, resumed or aborted. Requests come from any thread; `next()` runs on the
    stream thread and applies them at the right sample: a plain pause at the end of the current
    move (the field holds, the magnets stay aligned), an immediate pause at once (the field ramps
    to zero, and back up to where it was on resume), an abort by ramping to zero and finishing."""

    def __init__(self, currents: CurrentProgram, move_ends: list[int], ramp_samples: int) -> None:
        self.program = currents.currents_A
        self.segments = currents.segment
        self.boundaries = {0, *move_ends}
        self.ramp_samples = max(1, ramp_samples)
        self.index = 0  # next program sample
        self._lock = threading.Lock()
        self._pause_requested = False
        self._immediate = False
        self._abort_requested = False
        self._queue: list[np.ndarray] = []  # ramp samples to send before anything else
        self._last = np.zeros(self.program.shape[1])
        self.paused = False
        self.aborted = False
        # Called after a hold is released so the next sample leaves at once (the stream loop's
        # `wake`); a no-op until a loop is attached.
        self.wake: Callable[[], None] = lambda: None

    def request_pause(self, immediate: bool = False) -> None:
        with self._lock:
            self._pause_requested = True
            self._immediate = self._immediate or immediate

    def request_resume(self) -> None:
        with self._lock:
            self._pause_requested = False

    def request_abort(self) -> None:
        with self._lock:
            self._abort_requested = True

    def _queue_ramp_to(self, target: np.ndarray) -> None:
        fractions = np.linspace(0.0, 1.0, self.ramp_samples + 1)[1:]
        self._queue = [self._last + (target - self._last) * f for f in fractions]

    def next(self) -> tuple[np.ndarray, int, int] | None:
        """(setpoints (n,), program sample index, move index or -1) for this cycle; None when done."""
        with self._lock:
            for _ in range(3):  # at most: start a ramp, then send its first sample
                if self._queue:
                    self._last = self._queue.pop(0)
                    return self._last, self.index, -1
                if self._abort_requested and not self.aborted:
                    self.aborted = True
                    self._queue_ramp_to(np.zeros_like(self._last))
                    continue
                if self.aborted:
                    return None
                if self._pause_requested:
                    if self.paused:
                        return self._last, self.index, -1
                    if self._immediate:
                        self.paused = True
                        self._queue_ramp_to(np.zeros_like(self._last))
                        continue
                    if self.index in self.boundaries:
                        self.paused = True
                        return self._last, self.index, -1
                elif self.paused:  # resume
                    self.paused = False
                    if self._immediate and self.index < len(self.program):
                        self._immediate = False
                        self._queue_ramp_to(self.program[self.index])
                        continue
                    self._immediate = False
                break
            if self.index >= len(self.program):
                return None
            k = self.index
            self.index += 1
            self._last = self.program[k]
            return self._last, k, int(self.segments[k])


class Run(RunControl):
    """One plan on one rig. Construction refuses a bad plan (PlanError, LimitError) without I/O;
    `execute()` then energises, streams and returns the summary. `pause`, `resume`, `abort` and
    `estop` may be called from any thread while `execute()` runs."""

    def __init__(
        self,
        plan: Plan,
        rig: RigConfig,
        *,
        runs_dir: str | Path = "runs",
        progress_out: TextIO | None = None,
        on_cycle: Callable[[int, int, np.ndarray, np.ndarray], None] | None = None,
        on_state: Callable[[RunState, dict], None] | None = None,
        closed_loop: bool = False,
        supervisor_settings: SupervisorSettings | None = None,
    ) -> None:
        self.plan, self.field_program, self.currents = prepare(plan, rig)
        self.rig = rig
        self.runs_dir = Path(runs_dir)
        self.progress_out = progress_out
        self.on_cycle = on_cycle
        self._init_control(on_state)
        ramp = max(1, round(rig.stream.ramp_down_s * rig.stream.rate_hz))
        ends = [self.field_program.move_end_index(i) for i in range(self.field_program.n_moves)]
        self.sequencer = Sequencer(self.currents, ends, ramp)
        self._backdoor: BackdoorClient | None = None
        self.supervisor: Supervisor | None = None
        if closed_loop:
            from rigctl.supervisor import Supervisor, SupervisorSettings

            self.supervisor = Supervisor(
                self.plan, rig, self.field_program, self.currents, ramp_samples=ramp,
                settings=supervisor_settings or SupervisorSettings(),
                truth=self._truth if rig.emulation else None)
            self.sequencer = self.supervisor.sequencer

    def _truth(self) -> np.ndarray:
        """The emulator's true positions (n, 2) mm (the supervisor measures the tracker with it)."""
        return _truth_of(self._backdoor)

    # -- control, from any thread ---------------------------------------------------------------
    def pause(self, immediate: bool = False) -> None:
        self.sequencer.request_pause(immediate)

    def resume(self) -> None:
        self.sequencer.request_resume()

    def abort(self) -> None:
        self.sequencer.request_abort()

    # -- the run --------------------------------------------------------------------------------
    def execute(self) -> RunSummary:
        plan, rig = self.plan, self.rig
        record = self.record = RunRecord(self.runs_dir, plan.name or "plan")
        record.write_file("plan.json", dump_plan(plan))
        record.write_file("rig.toml", dump_rig(rig))
        record.event("prepared", samples=len(self.currents.t_s), rate_hz=rig.stream.rate_hz,
                     duration_s=self.field_program.duration_s)
        started = time.monotonic()
        faults: list[dict] = []
        stats: StreamStats | None = None
        backdoor = BackdoorClient(rig.emulation.backdoor) if rig.emulation else None
        self._backdoor = backdoor
        supplies: CoilSupplies | None = None
        try:
            if backdoor is not None:
                backdoor.request(
                    "place",
                    workspace=_portable_workspace(plan),
                    agents=[{"position": list(a.start), "radius": a.radius} for a in plan.agents],
                    contact=contact_for_rig(plan.rig),
                    min_separation_mm=plan.min_separation_mm,
                )
                record.event("placed", agents=[list(a.start) for a in plan.agents])
            if self.supervisor is not None:
                self.supervisor.start(record)  # the robots are found before anything is energised
            supplies = self._supplies = CoilSupplies.connect(rig)
            for name, url, identity in zip(supplies.names, [c.url for c in rig.coils],
                                           supplies.identities):
                record.event("connected", device=name, url=url, identity=identity)
            if self._estop.is_set():  # e-stopped while connecting: never switch on
                raise _EStopped()
            supplies.energise()
            record.event("energised", devices=supplies.names)
            self._set_state(RunState.RUNNING)
            stats = self._stream(supplies)
        except RigError as err:
            self._stopped_by(err, record, faults)
        except _EStopped:
            record.event("estop", reason="before the supplies were switched on")
        except KeyboardInterrupt:
            self.sequencer.aborted = True
            record.event("abort", reason="operator interrupt")
        finally:
            if supplies is not None:
                # an e-stop during this ramp cuts it short (the drivers latch at zero)
                supplies.stop(ramp_s=0.0 if self._estop.is_set() else rig.stream.ramp_down_s)
                self._supplies = None  # off and closed: nothing left for an e-stop to write to
                record.event("safe", supplies=supplies.names)
            if self.supervisor is not None:
                self.supervisor.stop()
        self._end_state(faults, aborted=self.sequencer.aborted,
                        gave_up=self.supervisor.fault if self.supervisor is not None else None)

        duration = time.monotonic() - started
        agents, positions_from = _final_positions(plan, backdoor)
        if self.supervisor is not None and self.supervisor.final_positions is not None:
            agents, positions_from = _tracked_final_positions(
                agents, self.supervisor.final_positions)
        if backdoor is not None:
            backdoor.close()
        tolerance = plan.tolerance_mm
        reached = not faults and all(
            a.error_mm is not None and a.error_mm <= tolerance for a in agents)
        summary = RunSummary(
            reached=reached, agents=agents, run=str(record.path), duration_s=duration,
            positions_from=positions_from, tolerance_mm=tolerance, faults=faults,
            stream=None if stats is None else stats.as_dict(),
            **(self.supervisor.summary() if self.supervisor is not None else {}),
        )
        record.finish(summary.as_dict())
        return summary

    def _stream(self, supplies: CoilSupplies) -> StreamStats:
        record, sequencer = self.record, self.sequencer
        assert record is not None
        record.open_stream(supplies.names, rate_hz=self.rig.stream.rate_hz)
        loop = self.stream_loop = StreamLoop(self.rig.stream.rate_hz)
        sequencer.wake = loop.wake
        progress = Progress(self.progress_out, len(self.plan.moves), self.field_program.duration_s)
        t_s = self.currents.t_s

        def cycle(_: int) -> bool:
            if self._estop.is_set():
                self._finish_estop(supplies, record)
                return False
            step = sequencer.next()
            if step is None:
                return False
            setpoints, k, move = step
            self._set_state(RunState.PAUSED if sequencer.paused else RunState.RUNNING)
            measured = supplies.cycle(setpoints)
            record.stream_row(k, move, setpoints, measured, loop.last_error_s)
            if self.on_cycle is not None:
                self.on_cycle(k, move, setpoints, measured)
            progress.update(move, float(t_s[min(k, len(t_s) - 1)]))
            return True

        try:
            return loop.run(cycle)
        finally:
            progress.done()
            record.event("stream_stats", **loop.stats().as_dict())


class _EStopped(Exception):
    """E-stop arrived before the supplies were switched on (not a fault: nothing to report)."""


def execute_plan(
    plan: Plan,
    rig: RigConfig,
    *,
    runs_dir: str | Path = "runs",
    progress_out: TextIO | None = sys.stderr,
    closed_loop: bool | None = None,
    supervisor_settings: SupervisorSettings | None = None,
) -> RunSummary:
    """Run `plan` on `rig` and return the summary. Refusals (PlanError, LimitError) raise before
    anything is opened; device faults during the run are caught, reported and recorded.
    `closed_loop` (default: whenever the rig has a camera) runs the camera supervisor."""
    if closed_loop is None:
        closed_loop = rig.camera is not None
    return Run(plan, rig, runs_dir=runs_dir, progress_out=progress_out, closed_loop=closed_loop,
               supervisor_settings=supervisor_settings).execute()


def _portable_workspace(plan: Plan) -> dict:
    """The plan's workspace as JSON for another process: an image path made absolute."""
    workspace = plan.workspace.model_dump(mode="json", exclude_none=True)
    if "image" in workspace and plan.base_dir is not None:
        workspace["image"] = str((Path(plan.base_dir) / workspace["image"]).resolve())
    return workspace


def _final_positions(plan: Plan, backdoor: BackdoorClient | None) -> tuple[list[AgentResult], str]:
    goals = [list(map(float, a.goal)) for a in plan.agents]
    if backdoor is None:
        return [AgentResult(None, g, None) for g in goals], "unknown (no camera loop yet)"
    try:
        truth = backdoor.request("truth")
    except RigError as err:
        log.error("could not read ground truth: %s", err)
        return [AgentResult(None, g, None) for g in goals], "unknown (backdoor failed)"
    results = []
    for position, goal in zip(truth["agents"], goals):
        error = float(np.hypot(position[0] - goal[0], position[1] - goal[1]))
        results.append(AgentResult([round(p, 4) for p in position], goal, round(error, 4)))
    return results, "emulator ground truth (the camera loop does not exist yet)"


def _tracked_final_positions(
    truth: list[AgentResult], tracked: np.ndarray
) -> tuple[list[AgentResult], str]:
    """Final positions from the camera (closed loop); ground truth's error kept when emulated."""
    results = []
    for result, position in zip(truth, tracked):
        error = float(np.hypot(position[0] - result.goal[0], position[1] - result.goal[1]))
        results.append(AgentResult([round(float(p), 4) for p in position], result.goal,
                                   round(error, 4), result.error_mm))
    return results, "camera (closed loop)" + (
        "; emulator ground truth in truth_error_mm" if any(
            r.error_mm is not None for r in truth) else "")


def _truth_of(backdoor: BackdoorClient | None) -> np.ndarray:
    if backdoor is None:
        raise RigError("no emulator backdoor", device="bench backdoor")
    return np.array(backdoor.request("truth")["agents"], dtype=float)


def format_summary(summary: RunSummary) -> str:
    lines = [f"run record: {summary.run}", f"duration: {summary.duration_s:.1f} s"]
    if summary.stream:
        s = summary.stream
        e = s["period_error_us"]
        lines.append(
            f"stream: {s['cycles']} cycles at {s['rate_hz']:g} Hz; period error p50 {e['p50']:.0f} us,"
            f" p99 {e['p99']:.0f} us, max {e['max']:.0f} us; late {s['late_cycles']}"
            f" ({100 * s['late_share']:.1f} %)"
        )
    lines.append(f"positions from: {summary.positions_from}")
    lines.append("agent  final (mm)            goal (mm)             error (mm)")
    for i, a in enumerate(summary.agents):
        final = "unknown" if a.final is None else f"({a.final[0]:.2f}, {a.final[1]:.2f})"
        goal = f"({a.goal[0]:.2f}, {a.goal[1]:.2f})"
        if a.error_mm is None:
            verdict, err = "", "?"
        else:
            verdict = "ok" if a.error_mm <= summary.tolerance_mm else "MISSED"
            err = f"{a.error_mm:.3f}"
        lines.append(f"{i:>5}  {final:<20}  {goal:<20}  {err:>8}  {verdict}")
    if summary.faults:
        for f in summary.faults:
            lines.append(f"FAULT: {f['reason']}")
    else:
        lines.append("faults: none")
    lines.append(
        f"REACHED: every agent within {summary.tolerance_mm:g} mm of its goal"
        if summary.reached
        else f"NOT REACHED (tolerance {summary.tolerance_mm:g} mm)"
    )
    return "\n".join(lines)


def summary_json_line(summary: RunSummary | Any) -> str:
    """Any run's summary (anything with `as_dict`) as the one JSON line `--json` prints."""
    return json.dumps(summary.as_dict(), separators=(",", ":"))
