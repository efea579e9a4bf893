"""The daemon's states and the one table of how they change (`TRANSITIONS`), and the refusal a
command meets in a state that does not allow it. Every change goes through `RunStates._transition`,
is published on the `state` topic, logged and told to systemd."""

from __future__ import annotations

import logging
from typing import Any

from rigctl.apps.daemon.messages import DaemonState, ErrorCode, Topic
from rigctl.apps.daemon.parts import DaemonParts

log = logging.getLogger(__name__)

S = DaemonState

ACTIVE = (S.RUNNING, S.PAUSED, S.SUSPENDED)


TRANSITIONS: dict[tuple[DaemonState, str], DaemonState] = {
    (S.IDLE, "execute"): S.RUNNING,
    (S.IDLE, "hold"): S.RUNNING,
    (S.RUNNING, "paused"): S.PAUSED,
    (S.PAUSED, "running"): S.RUNNING,
    (S.RUNNING, "suspended"): S.SUSPENDED,
    (S.PAUSED, "suspended"): S.SUSPENDED,
    (S.SUSPENDED, "running"): S.RUNNING,
    (S.SUSPENDED, "paused"): S.PAUSED,
    **{(s, "finished"): S.IDLE for s in ACTIVE},
    **{(s, "fault"): S.FAULTED for s in (*ACTIVE, S.IDLE)},
    **{(s, "estop"): S.ESTOPPED for s in S},
    (S.FAULTED, "reset"): S.IDLE,
    (S.ESTOPPED, "reset"): S.IDLE,
}
"""Every allowed state change. Anything else is refused (`wrong_state`) or, when a run reports
it late (a run that ends after an e-stop), ignored."""


RUN_EVENTS = {"running": "running", "paused": "paused", "suspended": "suspended",
              "faulted": "fault", "estopped": "estop", "aborted": "finished", "done": "finished"}
"""A `RunState` value -> the daemon event it causes (`prepared` causes none)."""



class Refusal(Exception):
    """Raised by a command handler: becomes an error reply with this code."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = code



class RunStates(DaemonParts):
    """The `Daemon`'s state (`state`, `_state_info`, under `_lock`) and its changes."""

    # -- state ----------------------------------------------------------------------------------
    def _transition(self, event: str, **info: Any) -> bool:
        """Apply `event` if TRANSITIONS allows it from the present state; publish the new state."""
        with self._lock:
            target = TRANSITIONS.get((self.state, event))
            if target is None:
                return False
            changed = target != self.state
            self.state = target
            self._state_info = {k: v for k, v in info.items() if k in ("device", "reason")}
        if changed:
            log.info("state %s (%s)", target.value, event)
            self._publish_state()
            self.notifier.status(f"{target.value}")
        return True

    def _publish_state(self) -> None:
        if self.publisher is None:
            return
        active = self._active
        self.publisher.publish_event(
            Topic.STATE, state=self.state, run=active.run_id if active else None,
            plan_id=active.plan_id if active else None,
            device=self._state_info.get("device"), reason=self._state_info.get("reason"))

    def _require(self, *states: DaemonState, doing: str) -> None:
        if self.state not in states:
            hint = " (send reset first)" if self.state in (S.FAULTED, S.ESTOPPED) else ""
            raise Refusal(ErrorCode.WRONG_STATE,
                          f"cannot {doing} while {self.state.value}{hint}")
