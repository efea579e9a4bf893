"""Run states and the control every run shares: the state (each change recorded and handed to
`on_state`), the e-stop taken on any thread and finished on the stream thread, faults and the
end state. A pause is a state, not an error; abort (ramp down, end cleanly) and e-stop (drop
every output now) differ."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from enum import Enum
from typing import TYPE_CHECKING, Any

from rigctl.core.errors import RigError
from rigctl.core.record import RunRecord
from rigctl.core.stream import StreamLoop

if TYPE_CHECKING:
    from rigctl.run.actuators import Actuators

log = logging.getLogger(__name__)


class RunState(str, Enum):
    """What a run is doing. A pause is a state, not an error; abort and e-stop differ: abort ramps
    the field down and ends cleanly, e-stop drops every output at once."""

    PREPARED = "prepared"
    RUNNING = "running"
    PAUSED = "paused"
    SUSPENDED = "suspended"  # the run cannot go on by itself (tracking lost): held until it can
    FAULTED = "faulted"
    ESTOPPED = "estopped"
    ABORTED = "aborted"
    DONE = "done"


class RunControl:
    """What every run shares of its control: the state (each change written to the record as a
    `state` event and handed to `on_state`) and the e-stop, taken on the calling thread and
    finished on the stream thread. A run calls `_init_control` in its constructor, sets `record`,
    `stream_loop` and `_supplies` as it goes, and calls `_finish_estop` from its stream cycle."""

    def _init_control(self, on_state: Callable[[RunState, dict[str, Any]], None] | None) -> None:
        self.on_state = on_state
        self.state = RunState.PREPARED
        # what the last state change said (why suspended, which device)
        self.state_info: dict[str, Any] = {}
        self.record: RunRecord | None = None
        self.stream_loop: StreamLoop | None = None  # while streaming: its timing, for telemetry
        self._estop = threading.Event()
        self._estop_at: float | None = None
        self._estop_zeroed_at: float | None = None  # every supply told 0 A and off (any thread)
        self._supplies: Actuators | None = None  # once connected: e-stop writes to them directly

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
        self.state, self.state_info = state, dict(info)
        if self.record is not None:
            self.record.event("state", state=state.value, **info)
        if self.on_state is not None:
            self.on_state(state, dict(info))

    def _finish_estop(self, supplies: Actuators, record: RunRecord) -> None:
        """On the stream thread, once it sees the e-stop: zero every supply again (belt and
        braces) and record how long after the request the supplies were zeroed."""
        seen = time.monotonic()
        supplies.zero_now()
        done = time.monotonic()
        # from the request: when every supply had been told zero and switched off (by the
        # thread that took the e-stop, or else by this one), and when this thread saw it
        asked = self._estop_at or seen
        direct = self._estop_zeroed_at
        told = min(done, direct or done)
        record.event("estop_zeroed",
                     after_request_s=round(told - asked, 6),
                     # on the wall clock too, for a client on this machine to measure from its
                     # own click or request (bench/console.py: the page's E-STOP click)
                     told_unix=round(time.time() - (time.monotonic() - told), 6),
                     seen_after_request_s=round(seen - asked, 6),
                     stream_zeroed_after_request_s=round(done - asked, 6),
                     direct=direct is not None)

    def _stopped_by(self, err: RigError, record: RunRecord, faults: list[dict[str, Any]]) -> None:
        """A device error ended the run: a fault (recorded, added to `faults`, state faulted),
        unless the e-stop caused it (switching on after it latched, say)."""
        if self._estop.is_set():
            record.event("estop", reason=f"while starting or stopping: {err}")
            return
        faults.append({"device": err.device, "reason": str(err), "kind": type(err).__name__})
        record.event("fault", device=err.device, reason=str(err), kind=type(err).__name__)
        log.error("run stopped: %s", err)
        self._set_state(RunState.FAULTED, device=err.device, reason=str(err))

    def _end_state(self, faults: list[dict[str, Any]], *, aborted: bool,
                   gave_up: RigError | None = None, abort_reason: str | None = None) -> None:
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
            faults.append({"device": None, "reason": abort_reason or "aborted by the operator",
                           "kind": "Abort"})
            # a device that failed while the abort ramped down makes the run faulted, as the
            # daemon says it is: the abort did not end it cleanly
            failed = next((f for f in faults if f["device"] is not None
                           and f["kind"] not in ("Abort", "Refused")), None)
            if failed is not None:
                self._set_state(RunState.FAULTED, device=failed["device"], reason=failed["reason"])
            else:
                self._set_state(RunState.ABORTED)
        elif not faults:
            self._set_state(RunState.DONE)


class EStopped(Exception):
    """E-stop arrived before the supplies were switched on (not a fault: nothing to report)."""


