"""The daemon's active run (a plan's or a manual hold), on its run thread: what the stream
process reports of it (cycles, camera frames, run states, faults) turned into the daemon's state,
device health and telemetry; the emulator's ground truth published while it runs; and the devices
a run could not confirm safe, made safe as soon as they answer."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.apps.daemon.messages import ErrorCode, Topic
from rigctl.apps.daemon.parts import DaemonParts
from rigctl.apps.daemon.states import RUN_EVENTS, Refusal
from rigctl.apps.daemon.telemetry import CycleBatch
from rigctl.core.errors import RigError

log = logging.getLogger(__name__)

AGENTS_HZ = 10.0

REZERO_S = 0.5  # how often a device not confirmed safe is tried again



@dataclass
class ActiveRun:
    """The run (a plan's or a manual hold) on the run thread, and what the stream thread last did."""

    kind: str  # "plan", "hold" or "teleop"
    job: Any
    plan_id: str | None
    info: dict[str, Any]
    thread: threading.Thread | None = None
    run_id: str | None = None
    sample: int = -1
    move: int = -1
    last_cycle: float = 0.0
    commanded: np.ndarray | None = None  # the latest setpoints the stream reported
    setpoints: np.ndarray | None = None  # a hold's: the target it ramps to and holds
    released: bool = False  # a hold's release was asked for
    drive: Any = None  # a teleoperation session's `TeleopDrive` (its inputs clipped here)



class RunWatch(DaemonParts):
    """The `Daemon`'s run thread and the callbacks the stream process's reports arrive by."""

    # -- the run thread and its callbacks (called on the stream thread) -------------------------
    def _run_thread(self, active: ActiveRun) -> None:
        if self.publisher is not None:
            self.publisher.reset_stream(self.rig.stream.rate_hz)
        summary = None
        try:
            summary = active.job.execute()
        except RigError as err:  # e.g. the stream process died: it said what it did about it
            log.error("the %s stopped: %s", active.kind, err)
            if active.kind == "plan" or getattr(active.job, "streaming", True):
                self._fault(err.device, str(err), type(err).__name__, active)
            # else a manual hold that never started: hold answers with the error
        except Exception as err:
            log.exception("the %s stopped with an unexpected error", active.kind)
            self._fault(None, f"internal error: {type(err).__name__}: {err}", "Internal", active)
        finally:
            with self._lock:
                self._active = None
                if active.kind == "hold":
                    self.held = None
                if summary is not None:
                    self.goals.saw_run(active.job, summary)  # where plan_goals starts from
                    self.last_run = {"id": active.run_id, "plan_id": active.plan_id,
                                     **{k: v for k, v in summary.as_dict().items()
                                        if k in ("reached", "faults", "duration_s", "run")}}
                self._transition("finished")
                for name, device in self.devices.items():
                    if device["health"] == "ok":
                        self._device(name, "off", "safe: ramped down, output off")
                unsafe = [n for n in (summary.unsafe_devices if summary else []) if n in self.devices]
                for name in unsafe:
                    self._device(name, "unsafe", "may still carry current: not confirmed safe; "
                                 "made safe as soon as it answers (check it by hand)")
                self.unsafe.update(unsafe)
            if unsafe:
                threading.Thread(target=self._make_safe_when_reachable, name="daemon-rezero",
                                 daemon=True).start()
            self._agents_stop.set()
            self._wakeup.wake()

    def _make_safe_when_reachable(self) -> None:
        """Every REZERO_S, the rig's direct make-safe until each device a run could not confirm
        safe (its link was down: a Kepco BOP then holds its last setpoint) has been reached; no
        run starts meanwhile (`_require_safe`)."""
        while self.unsafe and not self._stop.wait(REZERO_S):
            result = self.kind.make_safe(self.rig)
            with self._lock:
                for name in list(self.unsafe):
                    if result.get(name, "not reached") is None:
                        self.unsafe.discard(name)
                        self._device(name, "off", "made safe once its link answered again")
                        log.warning("%s: made safe once its link answered again", name)

    def _require_safe(self, doing: str) -> None:
        if self.unsafe:
            raise Refusal(ErrorCode.WRONG_STATE,
                          f"cannot {doing}: {', '.join(sorted(self.unsafe))} may still carry "
                          "current (not confirmed safe); the daemon makes it safe as soon as it "
                          "answers: check its link")

    def _on_cycles(self, batch: CycleBatch) -> None:
        """Cycles a run in the stream process ran (`t` on `time.monotonic()`), about every 20 ms:
        one append for the publisher, so this thread holds the GIL for microseconds."""
        active = self._active
        if active is not None:
            active.sample, active.move = int(batch.sample[-1]), int(batch.move[-1])
            active.last_cycle = float(batch.t[-1])
            active.commanded = batch.commanded[-1]
        if self.publisher is not None:
            self.publisher.offer_cycles(replace(batch, t=batch.t - self.t0))

    def _on_frame(self, *frame: Any) -> None:
        """A camera frame from the stream process (`runhost._FrameTap`), on its reader thread."""
        if self.publisher is not None:
            self.publisher.publish_frame(*frame)

    def _on_run_state(self, run_state: Any, info: dict[str, Any]) -> None:
        value = run_state.value
        active = self._active
        if active is not None and active.run_id is None and active.job.record is not None:
            active.run_id = Path(active.job.record.path).name
        if value == "running" and active is not None:
            for name in self.devices:
                self._device(name, "ok", "streaming")
        if value == "faulted":
            if active is not None and active.kind == "hold" and not active.job.streaming:
                return  # a hold that could not start: `hold` answers with why, the state stays
            self._fault(info.get("device"), str(info.get("reason")), "DeviceFault", active)
            return
        event = RUN_EVENTS.get(value)
        if event is not None and event != "finished":
            self._transition(event, **info)

    def _fault(self, device: str | None, reason: str, kind: str, active: ActiveRun | None) -> None:
        with self._lock:
            self.last_fault = {"device": device, "reason": reason, "kind": kind,
                               "run": active.run_id if active else None,
                               "t": round(time.monotonic() - self.t0, 3)}
            if device in self.devices:
                self._device(device, "fault", reason)
        if self.publisher is not None:
            self.publisher.publish_event(Topic.FAULT, device=device, reason=reason, kind=kind,
                                         run=active.run_id if active else None)
        self._transition("fault", device=device, reason=reason)

    def _device(self, name: str, health: str, detail: str) -> None:
        self.devices[name] = {**self.devices[name], "health": health, "detail": detail}

    def _sample_agents(self, active: ActiveRun) -> None:
        """On an emulated rig: the emulator's ground truth, published as `agents` and recorded in
        the run's event log, AGENTS_HZ times a second while the run lasts (a closed-loop run's
        camera positions are the supervisor's, in its own events and the summary)."""
        from rigctl.emulators.backdoor import BackdoorClient

        self._agents_stop.clear()
        plan = active.job.plan
        expected = plan.expected if plan.kind == "global-moves" else None  # positions per move
        starts = [list(a.start) for a in plan.agents] if expected is not None else []
        shown = -1  # the move whose expected positions are shown
        emulation, publisher = self.rig.emulation, self.publisher
        if emulation is None or publisher is None:  # started for an emulated rig, once bound
            return
        try:
            with BackdoorClient.of(emulation, timeout_s=1.0) as backdoor:
                while not self._agents_stop.wait(1.0 / AGENTS_HZ) and self._active is active:
                    truth = backdoor.request("truth")["agents"]
                    move = active.move
                    exp = None
                    if expected is not None:
                        # -1 (ramping, holding, paused): the last move's target, the starts before
                        # the first; a closed loop's re-planned moves past the plan's: its goal
                        if move >= 0:
                            shown = min(move, len(expected) - 1)
                        exp = [list(map(float, p)) for p in
                               (expected[shown] if shown >= 0 else starts)]
                    tracked = [[round(float(x), 4) for x in p] for p in truth]
                    publisher.publish_agents(move, tracked, exp, "emulator ground truth")
                    if active.job.record is not None:
                        active.job.record.event("agents", move=move, tracked=tracked)
        except (RigError, OSError, ValueError) as err:
            log.info("agent sampling stopped: %s", err)

    def _make_safe_directly(self) -> None:
        """E-stop with no run active: open every actuator anew and make it safe (the rig kind's
        `make_safe`: supplies to 0 A and off, the board's coils stopped, the arms held); best
        effort."""
        for name, err in self.kind.make_safe(self.rig).items():
            if name not in self.devices:
                continue
            if err is None:
                self._device(name, "off", "e-stop: made safe directly")
            else:
                self._device(name, "fault", f"e-stop could not reach it: {err}")


def _abort_quietly(active: ActiveRun) -> None:
    """Abort on the way out; a run whose stream process is already gone was made safe by the
    host's reader (supplies zeroed over new connections), so there is nothing more to do."""
    try:
        active.job.abort()
    except RigError as err:
        log.warning("abort on shutdown: %s", err)

