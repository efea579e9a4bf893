"""The six-coil current program's sequencer: each stream cycle's setpoints, with pause, resume
and abort applied at the right sample.

The requests are the engine's (`rigctl.run.interruptions.Requests`, as every rig's program takes
them); what is the six-coil's own is when and how each takes effect on a current program: at a
move's end or at once, by ramps, never by a jump. Its `requests.wake` stays a no-op: a resume or
an abort must not pull the next sample forward while the field is moving (the coils' L/R lag
would cut the path's corners, `rigctl.core.stream`); only a hold at a move's end is woken
(`SupervisedSequencer.release`, through `wake`)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from rigctl.rigs.six_coil.allocate import CurrentProgram
from rigctl.run.interruptions import Requests


class Sequencer:
    """Chooses each stream cycle's setpoints: the program's next sample, or a hold or a ramp when
    the run is paused, resumed or aborted. `requests` come from any thread; `next()` runs on the
    stream thread and applies them at the right sample: a plain pause at the end of the current
    move (the field holds, the magnets stay aligned), an immediate pause at once (the field ramps
    to zero, and back up to where it was on resume), a pause to cool at the end of the move and
    then as an immediate one, an abort by ramping to zero and finishing."""

    def __init__(self, currents: CurrentProgram, move_ends: list[int], ramp_samples: int) -> None:
        self.program = currents.currents_A
        self.segments = currents.segment
        self.boundaries = {0, *move_ends}
        self.ramp_samples = max(1, ramp_samples)
        self.index = 0  # next program sample
        self.requests = Requests()
        self._lock = threading.Lock()
        self._ramped_off = False  # paused with the field ramped to zero: ramp back up on resume
        self._queue: list[np.ndarray] = []  # ramp samples to send before anything else
        self._last = np.zeros(self.program.shape[1])
        self.paused = False
        self.aborted = False
        # Called after a hold is released so the next sample leaves at once (the stream loop's
        # `wake`); a no-op until a loop is attached.
        self.wake: Callable[[], None] = lambda: None

    def _queue_ramp_to(self, target: np.ndarray) -> None:
        fractions = np.linspace(0.0, 1.0, self.ramp_samples + 1)[1:]
        self._queue = [self._last + (target - self._last) * f for f in fractions]

    def next(self) -> tuple[np.ndarray, int, int] | None:
        """(setpoints (n,), program sample index, move index or -1) for this cycle; None when done."""
        requests = self.requests
        with self._lock:
            for _ in range(3):  # at most: start a ramp, then send its first sample
                if self._queue:
                    self._last = self._queue.pop(0)
                    return self._last, self.index, -1
                if requests.abort_wanted and not self.aborted:
                    self.aborted = True
                    self._queue_ramp_to(np.zeros_like(self._last))
                    continue
                if self.aborted:
                    return None
                if requests.pause_wanted:
                    if self.paused:
                        return self._last, self.index, -1
                    at_move_end = self.index in self.boundaries
                    if requests.immediate or (at_move_end and requests.field_off):
                        self.paused = self._ramped_off = True
                        self._queue_ramp_to(np.zeros_like(self._last))
                        continue
                    if at_move_end:
                        self.paused = True
                        return self._last, self.index, -1
                elif self.paused:  # resume
                    self.paused = False
                    ramped_off, self._ramped_off = self._ramped_off, False
                    if ramped_off and self.index < len(self.program):
                        self._queue_ramp_to(self.program[self.index])
                        continue
                break
            if self.index >= len(self.program):
                return None
            k = self.index
            self.index += 1
            self._last = self.program[k]
            return self._last, k, int(self.segments[k])
