"""The one run: a rig program streamed to an actuator group, with the same control on every rig.

A run is the meeting of two things that differ per rig and everything that does not:

- the *program* (`RigProgram`: global moves, pair formation, wall contact, a field sequence, a
  manual hold) says what to command each cycle, what "hold still" means when paused, and whether a
  late cycle slips the schedule (field programs: a path must not be bunched) or skips it (the arm
  servo: a target in the past is worthless);
- the *actuators* (`Actuators`: six supplies, the coil board, two arms) take one setpoint per
  channel each cycle and report what they did, drop everything on an e-stop from any thread, and
  ramp down and confirm their safe state at the end.

The engine owns the rest, once for every rig: the run record (plan, rig, events, the channel-typed
stream), the order of start-up (the program finds its agents and opens its sensors before anything
is energised), the stream loop, the states (`RunState`), pause / pause now / resume / abort /
e-stop from any thread, Ctrl-C and SIGTERM as an abort, faults named by device, the safe end (the
record says `safe` only when every device confirmed it, and names each one that did not), progress
and one summary shape.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np

from rigctl.core.config import RigConfig, dump_rig
from rigctl.core.errors import LimitError, RigError, interrupt_name, shielded_from_interrupts, take_interrupt
from rigctl.core.record import RunRecord
from rigctl.core.stream import StreamLoop, StreamStats
from rigctl.physics.thermal import WindingMonitor
from rigctl.run.actuators import Actuators
from rigctl.run.certificate import Certificate, Check, certify
from rigctl.run.control import EStopped, RunControl, RunState
from rigctl.run.interruptions import HoldLimit
from rigctl.run.summary import AgentResult, RunSummary

log = logging.getLogger(__name__)

REACH_AGAIN_S = 0.5  # a device not confirmed safe after the run: reached again this often


INTERRUPTED_AGAIN = ("interrupted again while the run stopped: it went on to safe and recorded its "
                     "end (rigctl estop cuts a ramp short)")


@dataclass
class Step:
    """One cycle's command: setpoints (n_channels,), the program sample it belongs to, and the
    move (plan step) being driven, -1 while ramping, holding or paused."""

    setpoints: np.ndarray
    sample: int
    move: int
    stage: str | None = None  # what the progress line shows (None: "move k/n")
    t_s: float | None = None  # the program's time of this sample (None: the stream's)
    # the progress line's stage when it is not `move` (None: `move`): off a terminal a line is
    # printed per new stage, and a pair run's stages (the furthest segment reached, the hold) are
    # not the record's moves (the segment driven now, -1 while holding)
    stage_key: int | None = None


@dataclass
class Outcome:
    """What the program reports once the actuators are safe: each agent's result, whether the
    goal was reached, where the positions came from, and the rig's own metrics."""

    agents: list[AgentResult] = field(default_factory=list)
    reached: bool = False
    positions_from: str = "unknown"
    tolerance_mm: float | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    replans: int = 0  # closed loop: re-plans from the camera
    # closed loop: frames, lost frames, tracker against truth
    tracking: dict[str, Any] | None = None
    tolerance_unit: str = "mm"
    details: list[str] = field(default_factory=list)  # lines the summary shows of the metrics
    gave_up: RigError | None = None  # the closed loop gave up (a fault of the run, not a device)


@dataclass
class RunContext:
    """What a program gets from the engine at `start`: the record, the bench's backdoor (emulated
    rigs), and a line on the operator's terminal."""

    rig: RigConfig
    record: RunRecord
    backdoor: Any
    say: Callable[[str], None]
    on_frame: Callable[[Any, Any], None] | None = None  # a camera frame and its TrackedState


class RigProgram(Protocol):
    plan: Any
    info: dict[str, Any]  # what `load` and `status` tell of it: name, size, planned duration
    rate_hz: float
    late: str  # "slip" or "skip"
    n_moves: int
    duration_s: float

    # read only here (the engine never sets them): a program may make them properties
    @property
    def paused(self) -> bool: ...
    @property
    def suspended(self) -> str | None:
        """Why the run cannot go on by itself now (tracking lost), else None."""

    def start(self, ctx: RunContext) -> None:
        """Before anything is connected: place the agents (emulated bench), find them with the
        camera, open the program's sensors. Nothing may be energised here."""

    def connected(self, actuators: Actuators) -> None:
        """The actuators are open, outputs still off: read where they are (the arms' joints) and
        refuse (LimitError) what cannot start from there."""

    def next(self, k: int, measured: np.ndarray | None) -> Step | None: ...

    def pause(self, immediate: bool) -> None: ...

    def pause_to_cool(self) -> None:
        """A winding reached its warning: pause at the end of the move with the actuators as
        cool as the program allows (the field off where nothing drifts without it, else held)."""

    def resume(self) -> None: ...

    def abort(self) -> None: ...

    @property
    def aborted(self) -> bool: ...

    def finish(self, ctx: RunContext) -> Outcome: ...

    def close(self) -> None: ...

    def checks(self) -> list[Check]:
        """The pre-flight of the whole plan on this rig (`rigctl.run.certificate`), no I/O."""


class Run(RunControl):
    """One program on one rig. `execute()` records, starts the program, energises, streams and
    returns the summary; `pause`, `resume`, `abort` and `estop` may be called from any thread.
    `connect` opens the rig's actuators (outputs off)."""

    def __init__(self, program: RigProgram, rig: RigConfig, connect: Callable[[RigConfig], Actuators],
                 *, runs_dir: str | Path = "runs", progress_out: TextIO | None = None,
                 on_cycle: Callable[[int, int, np.ndarray, np.ndarray], None] | None = None,
                 on_state: Callable[[RunState, dict[str, Any]], None] | None = None,
                 on_frame: Callable[[Any, Any], None] | None = None,
                 on_winding: Callable[[float, list[float], str], None] | None = None,
                 winding_start_C: Sequence[float] | None = None) -> None:
        self.program = program
        self.on_frame = on_frame  # handed to the program's tracking loop (`TrackingLoop.tap`)
        # the live winding model's estimate ten times a second (monotonic s, C per winding, its
        # state), and where it starts (None: the room; a daemon's windings still warm from the
        # last run: `rigctl.apps.daemon.telemetry.WindingEstimate`)
        self.on_winding = on_winding
        self.winding_start_C = winding_start_C
        # called on the stream thread once its loop has ended, before the devices are made safe
        # and the summary written (a daemon's watch on the stream process stops timing it there)
        self.on_stream_end: Callable[[], None] | None = None
        self.plan = program.plan
        self.info = program.info
        self.rig = rig
        self.connect = connect
        self.runs_dir = Path(runs_dir)
        self.progress_out = progress_out
        self.on_cycle = on_cycle
        self._init_control(on_state)
        self._abort_reason: str | None = None
        self._decided_at: float | None = None  # when the stream loop decided to end (monotonic)
        # every limit on the whole plan, before anything can be opened: refused here, no I/O
        t0 = time.perf_counter()
        certificate = certify(rig, program.plan.kind, getattr(program.plan, "name", None) or "plan",
                              program.checks())
        certificate.elapsed_s = round(time.perf_counter() - t0, 4)
        self.certificate: Certificate = certificate.require()

    # -- control, from any thread ---------------------------------------------------------------
    def pause(self, immediate: bool = False) -> None:
        self.program.pause(immediate)

    def resume(self) -> None:
        self.program.resume()

    def abort(self, reason: str = "aborted by the operator") -> None:
        self._abort_reason = reason
        self.program.abort()

    # -- the run --------------------------------------------------------------------------------
    def execute(self) -> RunSummary:
        """The run, start to summary. From the moment it stops (the ramp to safe) until its
        summary is written, a Ctrl-C or SIGTERM is noted, not raised: the ramp would be left
        half-way (a supply holds its setpoint) and the record without its end."""
        with ExitStack() as winding_down:
            summary = self._execute(winding_down)
        if take_interrupt() is not None:
            self._say(INTERRUPTED_AGAIN)
        return summary

    def _open_record(self) -> RunRecord:
        """The run's record, begun with what it runs: the plan, the rig file (its field
        calibration copied beside it), the pre-flight certificate."""
        from rigctl.plans.schema import dump_plan

        program, rig = self.program, self.rig
        record = RunRecord(self.runs_dir, getattr(program.plan, "name", None) or "plan")
        record.write_file("plan.json", dump_plan(program.plan))
        snapshot, files = rig.for_record()  # the snapshot names its own copies of the rig's files
        if snapshot.emulation is not None and snapshot.emulation.backdoor_token is not None:
            # the bench's secret stays in its own rig file (mode 0600), out of a record others read
            snapshot = snapshot.model_copy(update={"emulation": snapshot.emulation.model_copy(
                update={"backdoor_token": None})})
        for name, text in files.items():
            record.write_file(name, text)
        record.write_file("rig.toml", dump_rig(snapshot))
        record.event("prepared", rate_hz=program.rate_hz, duration_s=program.duration_s,
                     **{k: v for k, v in program.info.items() if k not in ("duration_s",)})
        record.write_file("certificate.json", self.certificate.to_json())
        record.event("certified", checks=len(self.certificate.checks),
                     rig_sha256=self.certificate.rig_hash)
        return record

    def _to_safe(self, actuators: Actuators, record: RunRecord,
                 faults: list[dict[str, Any]]) -> list[str]:
        """Ramp every actuator down (at once after an e-stop) and close it; the devices not
        confirmed safe, tried again, are returned, recorded and added to `faults`."""
        # an e-stop during this ramp cuts it short (the drivers latch at zero)
        ramp_s = 0.0 if self._estop.is_set() else self.rig.stream.ramp_down_s
        # from here every command to every device is on its way to safe: how long after
        # the run decided to stop (the loop's last cycle, or the error that ended it)
        now = time.monotonic()
        record.event("stopping", ramp_s=ramp_s, after_decision_s=round(
            now - (self._decided_at if self._decided_at is not None else now), 6))
        unconfirmed = actuators.stop(ramp_s)
        self._supplies = None  # off and closed: nothing left for an e-stop to write to
        if unconfirmed:
            unconfirmed = self._reach_again(type(actuators), unconfirmed, record)
        if not unconfirmed:
            record.event("safe", devices=actuators.names)
            return unconfirmed
        record.event("unsafe", devices=unconfirmed, reason="not confirmed safe: check these by hand")
        named = {f["device"] for f in faults}
        for name in unconfirmed:  # e.g. its link dropped while the run ramped down
            if name not in named:
                faults.append({"device": name, "kind": "Unconfirmed",
                               "reason": f"{name}: not confirmed safe when the run stopped "
                                         "(check it by hand)"})
        return unconfirmed

    def _execute(self, winding_down: ExitStack) -> RunSummary:
        from rigctl.emulators.backdoor import BackdoorClient
        from rigctl.run.progress import Progress

        program, rig = self.program, self.rig
        record = self.record = self._open_record()
        started = time.monotonic()
        faults: list[dict[str, Any]] = []
        stats: StreamStats | None = None
        backdoor = BackdoorClient.of(rig.emulation) if rig.emulation else None
        ctx = RunContext(rig, record, backdoor, self._say, self.on_frame)
        actuators: Actuators | None = None
        unconfirmed: list[str] | None = None
        refused: LimitError | None = None
        self.progress = Progress(self.progress_out, program.n_moves, program.duration_s)
        try:
            try:
                program.start(ctx)  # agents placed and found, sensors open: nothing energised
                actuators = self._supplies = self.connect(rig)
                for name in actuators.names:
                    record.event("connected", device=name)
                program.connected(actuators)
                if self._estop.is_set():  # e-stopped while connecting: never switch on
                    raise EStopped()
                _raise_lost_interrupt()
                actuators.energise()
                record.event("energised", devices=actuators.names)
                self._set_state(RunState.RUNNING)
                stats = self._stream(actuators)
            except KeyboardInterrupt as interrupt:
                winding_down.enter_context(shielded_from_interrupts())  # a second one: noted
                take_interrupt()  # handled here
                self.abort(f"operator interrupt ({interrupt_name(interrupt)})")
                record.event("abort", reason=self._abort_reason)
                self._say(f"aborted by {interrupt_name(interrupt)}: every device to safe, then the "
                          "summary")
        except LimitError as err:
            if self.state != RunState.PREPARED:  # a limit met while running is a fault
                self._stopped_by(err, record, faults)
            else:  # refused where the program stands (the arms' approach): nothing was energised
                refused = err
                record.event("refused", reason=str(err),
                             violations=[str(v) for v in getattr(err, "violations", [])])
        except RigError as err:
            self._stopped_by(err, record, faults)
        except EStopped:
            record.event("estop", reason="before the outputs were switched on")
        finally:
            winding_down.enter_context(shielded_from_interrupts())
            if actuators is not None:
                unconfirmed = self._to_safe(actuators, record, faults)
            self.progress.done()
        try:
            outcome = program.finish(ctx)
        finally:
            program.close()
            if backdoor is not None:
                backdoor.close()
        aborted = program.aborted or self._abort_reason is not None
        if refused is not None:
            faults.append({"device": refused.device, "reason": str(refused), "kind": "Refused"})
        self._end_state(faults, aborted=aborted or refused is not None, gave_up=outcome.gave_up,
                        abort_reason=self._abort_reason or (
                            None if refused is None else f"refused: {refused}"))
        summary = RunSummary(
            reached=outcome.reached and not faults, agents=outcome.agents, run=str(record.path),
            duration_s=time.monotonic() - started, positions_from=outcome.positions_from,
            tolerance_mm=outcome.tolerance_mm, faults=faults,
            stream=None if stats is None else stats.as_dict(),
            safe=actuators is None or not unconfirmed,
            unsafe_devices=list(unconfirmed or []), metrics=outcome.metrics,
            replans=outcome.replans, tracking=outcome.tracking,
            tolerance_unit=outcome.tolerance_unit, details=outcome.details,
            state=self.state.value, rig_kind=rig.rig.kind, plan_kind=program.plan.kind,
            refused=None if refused is None else str(refused))
        record.finish(summary.as_dict())
        return summary

    def _stream(self, actuators: Actuators) -> StreamStats:
        record, program = self.record, self.program
        assert record is not None
        record.open_stream(actuators.channels, rate_hz=program.rate_hz)
        loop = self.stream_loop = StreamLoop(program.rate_hz, late=program.late)
        wake = getattr(program, "attach_wake", None)
        if wake is not None:
            wake(loop.wake)
        measured: np.ndarray | None = None
        hold = HoldLimit(self.rig.stream.paused_limit_s, self.rig.stream.suspended_limit_s)
        heat = _HeatWatch(self, actuators, record, program.rate_hz)

        def cycle(k: int) -> bool:
            nonlocal measured
            _raise_lost_interrupt()
            if self._estop.is_set():
                self._decided_at = time.monotonic()
                self._finish_estop(actuators, record)
                return False
            step = program.next(k, measured)
            if step is None:
                self._decided_at = time.monotonic()
                return False
            if program.suspended is not None:
                self._set_state(RunState.SUSPENDED, reason=program.suspended)
            else:
                self._set_state(RunState.PAUSED if program.paused else RunState.RUNNING)
            if self.state is not RunState.RUNNING or hold.held is not None:
                why = hold.over(None if self.state is RunState.RUNNING else self.state.value,
                                time.monotonic(), program.suspended)
                if why is not None and self._abort_reason is None:
                    record.event("abort", reason=why)
                    log.warning("run ended: %s", why)
                    self.abort(why)
            measured = actuators.cycle(step.setpoints)
            record.stream_row(step.sample, step.move, step.setpoints, measured, loop.last_error_s)
            heat.update(measured)
            if self.on_cycle is not None:
                self.on_cycle(step.sample, step.move, step.setpoints, measured)
            self.progress.update(step.move if step.stage_key is None else step.stage_key,
                                 k / program.rate_hz if step.t_s is None else step.t_s, step.stage)
            return True

        try:
            return loop.run(cycle)
        except BaseException:  # a device's error (or Ctrl-C) ended the loop: decided now
            if self._decided_at is None:
                self._decided_at = time.monotonic()
            raise
        finally:
            record.event("stream_stats", **loop.stats().as_dict())
            if self.on_stream_end is not None:
                self.on_stream_end()

    def _reach_again(self, group: type, unconfirmed: list[str], record: RunRecord) -> list[str]:
        """Devices `stop` could not confirm safe, of a group that holds its output unattended
        (`make_safe_directly`): reached anew every REACH_AGAIN_S for `stream.unsafe_retry_s`, each
        one confirmed recorded as `safe`; those still unconfirmed (Ctrl-C stops the trying: it
        comes as a noted interrupt, the run is winding down)."""
        make_safe = getattr(group, "make_safe_directly", None)
        limit_s = self.rig.stream.unsafe_retry_s
        if make_safe is None or limit_s <= 0:
            return unconfirmed
        self._say(f"not confirmed safe: {', '.join(unconfirmed)}; reaching "
                  f"{'it' if len(unconfirmed) == 1 else 'them'} again for {limit_s:g} s")
        left, t0 = list(unconfirmed), time.monotonic()
        try:
            while left and time.monotonic() - t0 < limit_s and take_interrupt() is None:
                time.sleep(REACH_AGAIN_S)
                result = make_safe(self.rig)
                reached = [name for name in left if result.get(name, "not reached") is None]
                if reached:
                    left = [name for name in left if name not in reached]
                    record.event("safe", devices=reached, reason="reached again after the run",
                                 after_s=round(time.monotonic() - t0, 3))
                    self._say(f"made safe once reached again: {', '.join(reached)}")
        except KeyboardInterrupt:  # raised where the CLI's handler is not installed
            pass
        if left and time.monotonic() - t0 < limit_s:
            self._say("stopped trying")
        return left

    def _say(self, text: str) -> None:
        if self.progress_out is not None:
            print(f"  {text}", file=self.progress_out, flush=True)


def _raise_lost_interrupt() -> None:
    """Raise a Ctrl-C or SIGTERM that was signalled but lost (see `on_interrupt_signal`)."""
    interrupt = take_interrupt()
    if interrupt is not None:
        raise interrupt


class _HeatWatch:
    """The winding model (`rigctl.physics.thermal`) run live on what the actuators report driving their
    windings, whichever drives them (`Windings.volts_per_unit`): the supplies' measured currents,
    or the drive the coil board applied (its SyRens put a voltage on the coils, whose current
    nothing measures). Its estimate is the run record's `winding` series (written as it goes)
    and the run's `on_winding`, ten a second; at a winding's warning the run pauses at the end
    of the move (once, until it cools 2 K below), at its limit the run is aborted: the program
    ramps down (the board stops its coils at once)."""

    COOL_K = 2.0

    def __init__(self, run: Run, actuators: Actuators, record: RunRecord, rate_hz: float) -> None:
        self.run, self.record = run, record
        windings = actuators.windings
        self.monitor = None if windings is None else WindingMonitor(windings, run.winding_start_C)
        if windings is None:
            return
        self.every = max(1, round(rate_hz / 10))  # ten rows a second
        self.series = record.open_series(
            "winding", ["t_s", *windings.names], {"t_s": "s", **dict.fromkeys(windings.names, "C")})
        self.period = 1.0 / rate_hz
        self.last: float | None = None
        # a measured current is a sample of what flowed until now; a drive is what the board
        # applies from now until the next cycle: the time since the last one had the last drive
        self.held = None if windings.volts_per_unit is None else np.zeros(len(windings.names))
        self.cycles = 0
        self.warned = False
        self.stopped = False

    def update(self, driven: np.ndarray) -> None:
        monitor = self.monitor
        if monitor is None:
            return
        now = time.monotonic()
        dt = self.period if self.last is None else now - self.last
        self.last = now
        if self.held is None:
            state = monitor.update(driven, dt)
        else:
            state = monitor.update(self.held, dt)
            self.held[:] = driven
        self.cycles += 1
        if self.cycles % self.every == 1 or self.every == 1:
            temperatures = monitor.temperature_C.tolist()
            self.series.row([now - self.record.t0, *temperatures])
            if self.run.on_winding is not None:
                self.run.on_winding(now, temperatures, state)
        w = monitor.windings
        if state == "limit" and not self.stopped:
            self.stopped = True
            name, temperature = monitor.hottest()
            self.record.event("thermal_limit", coil=name, winding_C=round(temperature, 2))
            self.run.abort(f"coil {name}: winding at {temperature:.1f} C, its limit: ramped down")
        elif state == "warning" and not self.warned:
            self.warned = True
            name, temperature = monitor.hottest()
            self.record.event("thermal_warning", coil=name, winding_C=round(temperature, 2))
            self.run._say(f"coil {name}: winding at {temperature:.1f} C (warning): pausing at the "
                          "end of the move; resume once it has cooled")
            self.run.program.pause_to_cool()
        elif self.warned and (monitor.temperature_C < w.warning_C - self.COOL_K).all():
            self.warned = False
