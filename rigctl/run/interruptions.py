"""What interrupts a running program: the operator's requests, from any thread (pause at the end
of the present move or at once, resume, abort: the program reads them on the stream thread and
decides when each takes effect; `wake`, the stream loop's, makes the next cycle leave at once), and
lost tracking, which suspends the run until the camera sees the agents again; and the limit on
how long a run may stay paused or suspended."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rigctl.core.errors import DeviceTimeout

if TYPE_CHECKING:
    from rigctl.core.record import RunRecord


class Requests:
    """`pause_wanted`, `immediate` (pause now), `field_off` (pause at the end of the move with the
    outputs ramped off: the coils cool) and `abort_wanted`, as the operator (or the winding
    monitor) asked; a resume clears all but the abort."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.pause_wanted = False
        self.immediate = False
        self.field_off = False
        self.abort_wanted = False
        self.wake: Callable[[], None] = lambda: None

    def pause(self, immediate: bool = False, field_off: bool = False) -> None:
        with self._lock:
            self.pause_wanted = True
            self.immediate = self.immediate or immediate
            self.field_off = self.field_off or field_off

    def resume(self) -> None:
        with self._lock:
            self.pause_wanted = self.immediate = self.field_off = False
        self.wake()  # a hold: the next command may as well leave now

    def abort(self) -> None:
        self.abort_wanted = True
        self.wake()


class RequestedControl:
    """A program's `pause`, `resume` and `abort` (the engine's calls, from any thread), kept in
    its `requests` for the stream thread to act on; and `connected`, for a program whose outputs
    start at zero as the devices do (nothing to read from them)."""

    requests: Requests

    def connected(self, actuators: Any) -> None:  # each rig kind's own (an arm pair, supplies)
        pass

    def pause(self, immediate: bool = False) -> None:
        self.requests.pause(immediate)

    def pause_to_cool(self) -> None:
        """A winding at its warning: a plain pause (the program holds as it always does)."""
        self.requests.pause(False)

    def resume(self) -> None:
        self.requests.resume()

    def abort(self) -> None:
        self.requests.abort()


class Suspension:
    """Lost tracking: `reason` (a program's `suspended`: None while tracking holds) and `since`
    (monotonic s), each change a `suspend` / `resume` event in `record` (a `RunRecord`, once the
    run has one) and a line for the operator (`say`). Lost longer than `limit_s` (None: no limit),
    or the camera itself failed (`failure`), it is a fault of the camera."""

    def __init__(self, limit_s: float | None = None) -> None:
        self.limit_s = limit_s
        self.reason: str | None = None
        self.since: float | None = None
        self.count = 0  # suspensions ended
        self.record: RunRecord | None = None
        self.say: Callable[[str], None] = lambda text: None

    def lost(self, now: float, reason: str, failure: Exception | None = None,
             **info: object) -> None:
        if failure is not None:
            raise DeviceTimeout(f"{reason}: the camera failed ({failure})", device="camera")
        if self.since is None:
            self.since, self.reason = now, reason
            if self.record is not None:
                self.record.event("suspend", reason=reason, **info)
            self.say(f"suspended: {reason}")
        elif self.limit_s is not None and now - self.since > self.limit_s:
            raise DeviceTimeout(f"{reason}, for {self.limit_s:g} s", device="camera")

    def regained(self, now: float, **info: object) -> float:
        """Tracking holds again: the seconds it was lost (0 if it was not)."""
        if self.since is None:
            return 0.0
        lost_s = now - self.since
        self.since = self.reason = None
        self.count += 1
        if self.record is not None:
            self.record.event("resume", after_s=round(lost_s, 3), **info)
        self.say(f"tracking regained after {lost_s:.2f} s")
        return lost_s


class HoldLimit:
    """How long a run may stay paused (`paused_s`) or suspended (`suspended_s`) before it ramps
    down and ends: no state holds current indefinitely. `over(held, now)` is called every cycle
    with "paused", "suspended" or None (running); it gives the reason to end the run once the
    same hold has lasted past its limit, else None."""

    def __init__(self, paused_s: float, suspended_s: float) -> None:
        self.limits = {"paused": paused_s, "suspended": suspended_s}
        self.held: str | None = None
        self.since = 0.0

    def over(self, held: str | None, now: float, why: str | None = None) -> str | None:
        if held != self.held:
            self.held, self.since = held, now
            return None
        if held is None or now - self.since <= self.limits[held]:
            return None
        return (f"{held} for more than {self.limits[held]:g} s ({why or 'by the operator'}; the "
                f"rig file's [stream] {held}_limit_s): ramped down")
