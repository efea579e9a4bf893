"""The fixed-rate stream loop: one cycle per sample of the command program, on an absolute schedule.

Cycle k is due at t0 + k / rate. The loop sleeps until a cycle is due, runs it, and records how
late it started (the period error). It never skips a sample: a field program is a path, and
dropping samples would change where the robots go. Nor does it bunch samples to catch up: a cycle
counts as late when it starts more than `late_fraction` of a period after its due time, and a late
cycle moves the rest of the schedule back by its lateness (the slip), so the next sample still
leaves a period after it. Two cycles therefore never start less than (1 - late_fraction) periods
apart (unless `wake` asks for it, which only a constant hold does). Sending a stretch of the
program at full speed would turn the field many times faster than the realizer allowed; the coils'
L/R lag then cuts the corners of the path (a steering turn and the roll after it overlap, and the
magnets roll about a wrong axis), so a stall that was caught up moved the robots off the plan. A
stall that slips only holds the field for a while: the path pauses, and the run ends later by the
total slip, which the stats report.

The loop owns timing only; what a cycle does (send currents, read them back) is the caller's.

While any loop runs, the interpreter is tuned for it (`_StreamingInterpreter`): the GIL is handed
over every `SWITCH_INTERVAL_S` instead of every 5 ms, so a thread doing seconds of Python (a
re-plan's realize and allocate, the tracker, a telemetry batch) delays a cycle by at most that
much each time the stream thread comes back from a socket; and the objects that exist when the
stream starts are frozen out of the garbage collector, whose full collections of a big heap
(scipy, OpenCV, pydantic, a planner's tree) otherwise stop every thread for 15-240 ms.
"""

from __future__ import annotations

import gc
import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rigctl.core.priority import favour

log = logging.getLogger(__name__)

SWITCH_INTERVAL_S = 2e-4  # GIL hand-over while streaming; CPython's default is 5e-3


class _StreamingInterpreter:
    """Context manager: short GIL switch interval and a frozen heap while at least one stream
    loop runs (nested and concurrent loops count; the first in sets, the last out restores).
    One per process, because what it tunes (the interpreter) is one per process."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._saved_interval = sys.getswitchinterval()

    def __enter__(self) -> None:
        with self._lock:
            self._users += 1
            if self._users == 1:
                self._saved_interval = sys.getswitchinterval()
                sys.setswitchinterval(min(SWITCH_INTERVAL_S, self._saved_interval))
                gc.collect(1)  # young garbage goes now, not into the frozen generation
                gc.freeze()

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0:
                gc.unfreeze()
                sys.setswitchinterval(self._saved_interval)


_STREAMING = _StreamingInterpreter()


@dataclass(frozen=True)
class StreamStats:
    """Timing of one stream run. Period errors in seconds (start time minus due time)."""

    rate_hz: float
    cycles: int
    late_cycles: int
    period_error_p50_s: float
    period_error_p99_s: float
    period_error_max_s: float
    overrun_cycles: int  # cycles whose own work took longer than one period
    slip_s: float = 0.0  # how far late cycles moved the schedule back, in total
    skipped_cycles: int = 0  # late = "skip": cycles passed over because they were due while late

    @property
    def late_share(self) -> float:
        return self.late_cycles / self.cycles if self.cycles else 0.0

    def as_dict(self) -> dict:
        return {
            "rate_hz": self.rate_hz,
            "cycles": self.cycles,
            "late_cycles": self.late_cycles,
            "late_share": self.late_share,
            "overrun_cycles": self.overrun_cycles,
            "slip_s": self.slip_s,
            "skipped_cycles": self.skipped_cycles,
            "period_error_us": {
                "p50": self.period_error_p50_s * 1e6,
                "p99": self.period_error_p99_s * 1e6,
                "max": self.period_error_max_s * 1e6,
            },
        }


class StreamLoop:
    """Run `cycle(k)` for k = 0, 1, ... at `rate_hz` until it returns False. `late` is what a
    late cycle does: "slip" moves the schedule back (a field program, see the module docstring);
    "skip" keeps the schedule and passes over the cycles that fell due meanwhile (k jumps), for a
    servo of positions, whose stale targets only make the arm race after the present one."""

    def __init__(self, rate_hz: float, *, late_fraction: float = 0.5, late: str = "slip") -> None:
        if rate_hz <= 0:
            raise ValueError(f"stream rate must be positive, got {rate_hz}")
        if late not in ("slip", "skip"):
            raise ValueError(f"late must be 'slip' or 'skip', got {late!r}")
        self.late = late
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.late_fraction = late_fraction
        self._errors: np.ndarray = np.zeros(0)
        self._wake = threading.Event()
        self._count = 0
        self._late = 0
        self._overruns = 0
        self._slip_s = 0.0
        self._skipped = 0
        self.last_error_s: float | None = None  # the period error of the cycle now running

    def wake(self) -> None:
        """Run the next cycle now instead of at its due time, and keep the schedule from there.

        For a caller that was holding the outputs constant (a run waiting at the end of a move for
        the camera's verdict): moving the phase of a constant hold changes nothing physical, and
        the next command leaves up to a period sooner. Thread-safe."""
        self._wake.set()

    def run(self, cycle: Callable[[int], bool | None], max_cycles: int | None = None) -> StreamStats:
        """Run until `cycle` returns False (or `max_cycles` cycles ran), on the calling thread,
        favoured over ordinary work where the machine allows it (`rigctl.core.priority`)."""
        restore = favour("stream thread")
        try:
            with _STREAMING:
                return self._run(cycle, max_cycles)
        finally:
            restore()

    def _run(self, cycle: Callable[[int], bool | None], max_cycles: int | None) -> StreamStats:
        self._errors = np.empty(max_cycles if max_cycles is not None else 4096)
        self._count = self._late = self._overruns = self._skipped = 0
        self._slip_s = 0.0
        late_after = self.late_fraction * self.period_s
        t0 = time.perf_counter() + self.period_s  # first cycle one period from now
        k = 0  # the schedule's cycle index (jumps when late = "skip")
        n = 0  # cycles run
        while max_cycles is None or n < max_cycles:
            if n == len(self._errors):
                self._errors = np.resize(self._errors, 2 * len(self._errors))
            due = t0 + k * self.period_s
            wait = due - time.perf_counter()
            if wait > 0 and self._wake.wait(wait):
                # woken early: this cycle is due now, and the schedule moves with it
                now = time.perf_counter()
                t0 -= due - now
                due = now
            self._wake.clear()
            start = time.perf_counter()
            error = start - due
            self._errors[n] = error
            self.last_error_s = error
            self._count = n + 1
            if error > late_after:
                self._late += 1
                if self.late == "skip":
                    if error >= self.period_s:
                        # a servo of positions: the targets due while late are worthless
                        # now; go on with the one due at this time (k jumps, t0 stays)
                        skipped = int(error / self.period_s)
                        k += skipped
                        self._skipped += skipped
                else:
                    # late: the schedule moves back with this cycle instead of the next ones
                    # bunching up to catch up (see the module docstring)
                    t0 += error
                    self._slip_s += error
            keep_going = cycle(k)
            if time.perf_counter() - start > self.period_s:
                self._overruns += 1
            k += 1
            n += 1
            if keep_going is False:
                break
        return self.stats()

    def stats(self) -> StreamStats:
        errors = self._errors[: self._count]
        if errors.size == 0:
            return StreamStats(self.rate_hz, 0, 0, 0.0, 0.0, 0.0, 0)
        return StreamStats(
            rate_hz=self.rate_hz,
            cycles=int(errors.size),
            late_cycles=self._late,
            period_error_p50_s=float(np.percentile(errors, 50)),
            period_error_p99_s=float(np.percentile(errors, 99)),
            period_error_max_s=float(errors.max()),
            overrun_cycles=self._overruns,
            slip_s=self._slip_s,
            skipped_cycles=self._skipped,
        )
