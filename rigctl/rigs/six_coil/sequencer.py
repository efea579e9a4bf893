"""The six-coil current program's sequencer: each stream cycle's setpoints, with pause, resume
and abort applied at the right sample."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from rigctl.rigs.six_coil.allocate import CurrentProgram


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
        self._field_off = False  # a pause at the end of the move that ramps the field off
        self._abort_requested = False
        self._queue: list[np.ndarray] = []  # ramp samples to send before anything else
        self._last = np.zeros(self.program.shape[1])
        self.paused = False
        self.aborted = False
        # Called after a hold is released so the next sample leaves at once (the stream loop's
        # `wake`); a no-op until a loop is attached.
        self.wake: Callable[[], None] = lambda: None

    def request_pause(self, immediate: bool = False, field_off: bool = False) -> None:
        """Pause at the end of the move (`immediate`: now, ramping the field off); `field_off`:
        at the end of the move, then ramp the field off (the coils cool)."""
        with self._lock:
            self._pause_requested = True
            self._immediate = self._immediate or immediate
            self._field_off = self._field_off or field_off

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
                        if self._field_off:  # as a pause now from here: back up on resume
                            self._immediate, self._field_off = True, False
                            self._queue_ramp_to(np.zeros_like(self._last))
                            continue
                        return self._last, self.index, -1
                elif self.paused:  # resume
                    self.paused = False
                    self._field_off = False
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


