"""The daemon's command handlers (`_cmd_<command>`, docs/daemon-protocol.md): each checks the
state it may run in (`rigctl.apps.daemon.states`), does its work or refuses (`Refusal`, a limit,
a plan error) and returns its result; `load` prepares a plan, `execute` and `hold` make it the
active run (`rigctl.apps.daemon.active_run`)."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.apps.daemon.active_run import ActiveRun
from rigctl.apps.daemon.messages import PROTOCOL, ErrorCode, HoldArgs
from rigctl.apps.daemon.parts import DaemonParts
from rigctl.apps.daemon.plan_runs import MAX_PLANS, RunLike
from rigctl.apps.daemon.states import ACTIVE, Refusal, S
from rigctl.core import errors
from rigctl.core.errors import ConfigError, RigError
from rigctl.run.hold import CANNOT_PAUSE, HoldPlan

log = logging.getLogger(__name__)

HOLD_START_TIMEOUT_S = 30.0  # hold waits this long for the rig to stream the hold



@dataclass
class _LoadedPlan:
    plan_id: str
    plan: Any
    info: dict[str, Any]
    prepared: RunLike | None



class Commands(DaemonParts):
    """The `Daemon`'s command handlers, by name in its `_handlers`."""

    # -- commands -------------------------------------------------------------------------------
    def _cmd_ping(self, _: Any) -> dict[str, Any]:
        return {"protocol": PROTOCOL, "pid": os.getpid(),
                "telemetry": self.endpoints.as_dict() if self.endpoints else None}

    def _cmd_status(self, _: Any) -> dict[str, Any]:
        with self._lock:
            active = self._active
            run = None
            if active is not None:
                run = {"kind": active.kind, "id": active.run_id, "plan_id": active.plan_id,
                       "sample": active.sample, "move": active.move, **active.info}
            return {
                "state": self.state.value,
                "device": self._state_info.get("device"),
                "reason": self._state_info.get("reason"),
                "rig": {"name": self.rig.rig.name, "kind": self.rig.rig.kind,
                        "emulated": self.rig.emulated},
                "run": run,
                "last_run": self.last_run,
                "plans": list(self._plans),
                "devices": [dict(d) for d in self.devices.values()],
                "last_fault": self.last_fault,
                "hold": self.held,
                "manual_field_mT": (self.held or {}).get("field_mT"),  # set_field's, six-coil
                "tracked": self.goals.status(),  # where plan_goals starts from (goals.py)
                "uptime_s": round(time.monotonic() - self.t0, 3),
            }

    def _cmd_load(self, args: Any) -> dict[str, Any]:
        plan = self.factory.parse_plan(args.plan)
        plan_id = hashlib.sha256(json.dumps(args.plan, sort_keys=True).encode()).hexdigest()[:12]
        prepared = self._prepare(plan)
        info = dict(prepared.info)
        with self._lock:
            self._plans[plan_id] = _LoadedPlan(plan_id, plan, info, prepared)
            self._plans.move_to_end(plan_id)
            while len(self._plans) > MAX_PLANS:
                self._plans.popitem(last=False)
        log.info("plan %s loaded: %s", plan_id, info)
        return {"plan_id": plan_id, **info}

    def _prepare(self, plan: Any) -> RunLike:
        # the daemon reaches a device a run left unconfirmed itself, for as long as it serves
        # (`_make_safe_when_reachable`): the run's own bounded retry is a local run's
        rig = self.rig.model_copy(update={"stream": self.rig.stream.model_copy(
            update={"unsafe_retry_s": 0.0})})
        return self.factory.prepare(plan, rig, runs_dir=self.runs_dir,
                                    on_cycles=self._on_cycles, on_state=self._on_run_state)

    def _cmd_execute(self, args: Any) -> dict[str, Any]:
        with self._lock:
            if self._active is not None and self._active.kind == "hold":
                raise Refusal(ErrorCode.WRONG_STATE,
                              'a manual hold is on: release it first (hold {"release": true})')
            self._require(S.IDLE, doing="execute a plan")
            self._require_safe("execute a plan")
            if self._active is not None:
                raise Refusal(ErrorCode.BUSY, "the last run is still stopping")
            loaded = self._plans.get(args.plan_id)
            if loaded is None:
                raise Refusal(ErrorCode.UNKNOWN_PLAN,
                              f"no plan {args.plan_id!r} loaded; load it first")
            run, loaded.prepared = loaded.prepared, None
        if run is None:  # executed before: prepare again (the plan was checked at load)
            run = self._prepare(loaded.plan)
        active = ActiveRun("plan", run, loaded.plan_id, dict(loaded.info))
        self._activate(active, "execute")
        if self.rig.emulated and getattr(loaded.plan, "agents", None) is not None:
            threading.Thread(target=self._sample_agents, args=(active,), name="daemon-agents",
                             daemon=True).start()
        return {"plan_id": loaded.plan_id, "state": self.state.value, **loaded.info}

    def _activate(self, active: ActiveRun, event: str) -> None:
        """`active` becomes the daemon's run (an e-stop reaches it from now on), on its thread."""
        with self._lock:
            self._active = active
            self._transition(event)
            active.thread = threading.Thread(target=self._run_thread, args=(active,),
                                             name=f"daemon-{active.kind}")
            active.thread.start()

    def _cmd_pause(self, args: Any) -> dict[str, Any]:
        with self._lock:
            self._require(*ACTIVE, doing="pause")
            assert self._active is not None  # in an ACTIVE state
            if self._active.kind == "hold":
                raise Refusal(ErrorCode.WRONG_STATE, f'{CANNOT_PAUSE} (hold {{"release": true}})')
            if self._active.kind == "teleop":
                raise Refusal(ErrorCode.WRONG_STATE, 'a teleoperation session cannot be paused: '
                              'let go of the input, or end it (teleop {"end": true})')
            self._active.job.pause(args.immediate)
        return {"state": self.state.value, "pending": "pause now" if args.immediate
                else "pause at the end of the current move"}

    def _cmd_resume(self, _: Any) -> dict[str, Any]:
        with self._lock:
            self._require(S.PAUSED, doing="resume")
            assert self._active is not None  # paused
            self._active.job.resume()
        return {"state": self.state.value, "pending": "resume"}

    def _cmd_abort(self, _: Any) -> dict[str, Any]:
        with self._lock:
            self._require(*ACTIVE, doing="abort")
            assert self._active is not None  # in an ACTIVE state
            self._active.job.abort()
        return {"state": self.state.value, "pending": "ramp down and stop"}

    def _cmd_estop(self, _: Any) -> dict[str, Any]:
        active = self._active
        unreached: list[str] = []
        if active is not None:  # first, before any lock: the supplies are zeroed from this thread
            unreached = active.job.estop() or []
        with self._lock:
            if self._active is not None and self._active is not active:  # started meanwhile
                active = self._active
                unreached = active.job.estop() or []
            self._transition("estop", reason="emergency stop")
            self.held = None
            for name in unreached:
                self._device(name, "fault", "e-stop could not be sent: link down (its own "
                             "watchdog or interlock must stop it)")
        if active is None:
            threading.Thread(target=self._make_safe_directly, name="daemon-estop").start()
        log.warning("EMERGENCY STOP")
        if active is None:
            zeroing = "directly (no run active)"
        elif unreached:
            zeroing = (f"sent to every device but {', '.join(unreached)} (link down: check that "
                       "supply by hand)")
        else:
            zeroing = "done: every device told to stop (supplies 0 A and off, coils off, arms held)"
        return {"state": self.state.value, "zeroing": zeroing, "unreached": unreached}

    def _cmd_reset(self, _: Any) -> dict[str, Any]:
        with self._lock:
            if self.state == S.IDLE:
                return {"state": "idle"}
            self._require(S.FAULTED, S.ESTOPPED, doing="reset")
            if self._active is not None:
                raise Refusal(ErrorCode.BUSY, "the run is still stopping; retry in a moment")
            self._transition("reset")
        return {"state": self.state.value}

    def _cmd_hold(self, args: Any) -> dict[str, Any]:
        """A manual hold (any rig), retargeted while one is on, released by `release` or by a
        target at the rig's rest (zero). Limits are checked here before anything moves: the
        target's, and the ramp's from what is held now (between the setpoints the stream last
        reported and the target it ramps to: the ramp's checks are linear or convex in its
        start); an arm pose's first ramp is checked in the stream process once the arms' joints
        are read, before they move."""
        with self._lock:
            active = self._active if self._active is not None and self._active.kind == "hold" else None
            if not args.release:
                self._require_safe("hold")
        request = None
        if not args.release:
            try:
                request = self.kind.hold(self.rig, args.target)
            except ConfigError as err:
                raise Refusal(ErrorCode.BAD_ARGS, f"hold: {err}") from None
        if active is not None and active.released:
            raise Refusal(ErrorCode.BUSY, "the hold is being released; retry in a moment")
        if request is None or request.at_rest:
            if active is not None:
                active.job.release(args.ramp_s)
                active.released = True
                self.held = None
            return {"hold": None, "released": active is not None,
                    "setpoints": [0.0] * len(self.channels)}
        if active is not None:
            starts = [s for s in (active.setpoints, active.commanded) if s is not None]
        else:
            starts = [np.zeros(len(self.channels))] if request.pose_now is None else []
        for start in starts:
            request.check_ramp(np.asarray(start, dtype=float), args.ramp_s)
        reply = {"hold": request.target, "channels": [c.name for c in self.channels],
                 "setpoints": request.setpoints.round(4).tolist()}
        with self._lock:
            if active is not None and self._active is active:
                active.job.retarget(request.target, request.setpoints, args.ramp_s)
                active.setpoints, self.held = request.setpoints, request.target
                active.info["target"] = request.target
                return reply
            self._require(S.IDLE, doing="hold")
            if self._active is not None:
                raise Refusal(ErrorCode.BUSY, "the last run is still stopping")
        # streamed by the stream process; this (the worker) waits until it streams or cannot start
        # the stream process's host (RunHost): started, streaming, error and result besides RunLike
        job: Any = self._prepare(HoldPlan(rig=self.rig.rig.kind, target=request.target,
                                     ramp_s=args.ramp_s))
        active = ActiveRun("hold", job, None, dict(job.info), setpoints=request.setpoints)
        with self._lock:
            if self.state != S.IDLE or self._active is not None or self._stop.is_set():
                raise Refusal(ErrorCode.WRONG_STATE, f"state changed to {self.state.value}")
            self.held = request.target
            self._activate(active, "hold")
        if not job.started.wait(HOLD_START_TIMEOUT_S):
            job.estop()  # still connecting: it must not switch on after hold has failed
        if not job.streaming:  # it could not start (a device, a limit at the arms): say why
            assert active.thread is not None  # _activate started it
            active.thread.join(HOLD_START_TIMEOUT_S)
            raise job.error or _start_error(job.result)
        for name in self.devices:
            self._device(name, "ok", "manual hold")
        return reply

    def _cmd_set_field(self, args: Any) -> dict[str, Any]:
        """The six-coil shorthand of `hold {"target": {"field_mT": ...}}` (zero releases)."""
        result = self._cmd_hold(HoldArgs(target={"field_mT": args.field_mT}, ramp_s=args.ramp_s))
        return {"field_mT": args.field_mT, "currents_A": result["setpoints"]}

    def _cmd_runs(self, args: Any) -> list[dict[str, Any]]:
        from rigctl.core.record import list_runs

        return list_runs(self.runs_dir, limit=args.limit)

    def _cmd_run(self, args: Any) -> dict[str, Any]:
        if "/" in args.run or args.run.startswith(".") or not (self.runs_dir / args.run).is_dir():
            raise Refusal(ErrorCode.UNKNOWN_RUN, f"no run {args.run!r} in {self.runs_dir}")
        from rigctl.core.record import describe_run

        return describe_run(self.runs_dir / args.run)


def _start_error(summary: Any, what: str = "manual hold") -> RigError:
    """Why a hold (or a teleoperation session: `what`) that never streamed ended, from its
    summary's first fault (as the error class the stream process named, so a limit is answered
    as a limit)."""
    if summary is not None and summary.refused:  # a limit where the actuators stand (the arms)
        return errors.LimitError(summary.refused)
    fault = summary.faults[0] if summary is not None and summary.faults else None
    if fault is None:
        return RigError(f"the {what} did not start within {HOLD_START_TIMEOUT_S:g} s")
    error_class = getattr(errors, fault["kind"], None)
    if not (isinstance(error_class, type) and issubclass(error_class, RigError)):
        error_class = RigError
    return error_class(fault["reason"])

