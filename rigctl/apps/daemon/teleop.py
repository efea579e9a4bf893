"""The daemon's teleoperation commands: `teleop` starts a session (or ends one) and `steer` carries
the operator's live input to it (docs/teleoperation.md).

A session is admitted as `execute` admits a plan: one at a time, only from idle with the rig
safe; it is then the daemon's active run (kind "teleop"), streamed by the stream process like any
other (`rigctl.run.teleop.TeleopProgram`), ended by `teleop {"end": true}`, `abort` or `estop`.
`steer` is answered here on the command thread: the input is checked and clipped to the rig's
ranges (the reply names what was clipped) and sent to the stream process, whose stream loop
drops it once it is `SILENCE_S` old. The dead-man is there, not here and not in the page: a
daemon whose command thread stalls, a client that dies, a page that loses its connection all
come to the same silence in the stream."""

from __future__ import annotations

import threading
from typing import Any

from rigctl.apps.daemon.active_run import ActiveRun
from rigctl.apps.daemon.commands import HOLD_START_TIMEOUT_S, _start_error
from rigctl.apps.daemon.messages import ErrorCode
from rigctl.apps.daemon.parts import DaemonParts
from rigctl.apps.daemon.states import Refusal, S
from rigctl.core.errors import ConfigError
from rigctl.run.teleop import NO_TELEOP, TeleopPlan


class TeleopCommands(DaemonParts):
    """The `Daemon`'s `teleop` and `steer` handlers (mixed in beside `Commands`)."""

    def _cmd_teleop(self, args: Any) -> dict[str, Any]:
        """Start a session on this rig (on the worker: it waits until it streams), or end it."""
        with self._lock:
            active = self._active if self._active is not None and \
                self._active.kind == "teleop" else None
            if args.end:
                if active is None:
                    raise Refusal(ErrorCode.WRONG_STATE, "no teleoperation session to end")
                active.job.end()
                return {"state": self.state.value, "pending": "to rest, then end"}
            if self.kind.teleop is None:
                raise Refusal(ErrorCode.WRONG_STATE, f"teleop: {NO_TELEOP} ({self.kind.name})")
            self._require(S.IDLE, doing="start teleoperation")
            self._require_safe("start teleoperation")
            if self._active is not None:
                raise Refusal(ErrorCode.BUSY, "the last run is still stopping")
        try:
            drive = self.kind.teleop(self.rig, args.mode)
        except ConfigError as err:
            raise Refusal(ErrorCode.BAD_ARGS, str(err)) from None
        # the certificate of any input on this rig is checked here, before anything is opened
        # the stream process's host (RunHost): started, streaming, error and result besides RunLike
        job: Any = self._prepare(TeleopPlan(rig=self.rig.rig.kind, mode=args.mode))
        active = ActiveRun("teleop", job, None, dict(job.info), drive=drive)
        with self._lock:
            if self.state != S.IDLE or self._active is not None or self._stop.is_set():
                raise Refusal(ErrorCode.WRONG_STATE, f"state changed to {self.state.value}")
            self._activate(active, "execute")
        if self.rig.emulated and self.kind.scene == "camera":  # the agents' truth, as it goes
            threading.Thread(target=self._sample_agents, args=(active,), name="daemon-agents",
                             daemon=True).start()
        if not job.started.wait(HOLD_START_TIMEOUT_S):
            job.estop()  # still connecting: it must not switch on after teleop has failed
        if not job.streaming:
            assert active.thread is not None  # _activate started it
            active.thread.join(HOLD_START_TIMEOUT_S)
            raise job.error or _start_error(job.result, "teleoperation session")
        for name in self.devices:
            self._device(name, "ok", "teleoperation")
        return {"state": self.state.value, **drive.describe(), "silence_s": job.info["silence_s"]}

    def _cmd_steer(self, args: Any) -> dict[str, Any]:
        """The operator's input now (None: let go), clipped to the rig's ranges."""
        active = self._active
        if active is None or active.kind != "teleop":
            raise Refusal(ErrorCode.WRONG_STATE,
                          "no teleoperation session: start one with teleop")
        if args.input is None:
            active.job.steer(None)
            return {"input": None}
        try:
            values, clipped = active.drive.clip(args.input)
        except ConfigError as err:
            raise Refusal(ErrorCode.BAD_ARGS, f"steer: {err}") from None
        active.job.steer(values.tolist())
        names = [c.name for c in active.drive.components]
        return {"input": dict(zip(names, values.tolist())), "clipped": clipped}

