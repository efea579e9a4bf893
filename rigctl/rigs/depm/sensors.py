"""The Hall board as a field-sequence run sees it: samples, U by eq. 24, and a link that may drop.

The board is a sensor, not an actuator: the program owns it. `HallWatch` keeps a `HallStream`
reading in its own thread and hands over what it read (`poll`). When the reader ends with a fault
(link lost, timeout, garbage) or no sample arrives for a while, `poll` says why (the program then
suspends the run: the arms hold their pose) and a background thread opens the board again every
`RECONNECT_S` until it answers, so the run goes on by itself once samples come back. Opening never
happens on the stream thread, which must not block on a connect.

`sensor_estimator` is eq. 24 as a matrix, built once per run from the board's fixed offsets.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from rigctl.core.errors import RigError
from rigctl.drivers.hall import HallBoard, HallSample, HallStream
from rigctl.physics.magnetics import field_vector_from_sensors

log = logging.getLogger(__name__)

RECONNECT_S = 0.5  # between attempts to open a lost board again
MIN_SILENCE_S = 0.5  # no sample for this long (or 20 sample periods, if longer): trouble
HALL_NAME = "hall board"


def sensor_estimator(offsets_m: np.ndarray) -> np.ndarray:
    """E (8, 3 n) with U = E @ fields.ravel() (T, T/m at the reference sensor) for the n sensors'
    fields (n, 3) T at `offsets_m` (n, 3) m: `field_vector_from_sensors` (eq. 24) is linear in the
    fields, so its matrix is its value on the unit fields. It depends only on the board's fixed
    sensor offsets: built once per run instead of a least-squares fit per batch of samples.
    ConfigError if the offsets cannot give all five gradient terms."""
    n_values = 3 * len(offsets_m)
    unit_fields = np.eye(n_values).reshape(n_values, len(offsets_m), 3)
    return field_vector_from_sensors(unit_fields, offsets_m).T


def _reason(err: RigError) -> str:
    """The fault without the device's name in front (the caller names the board)."""
    return str(err.args[0]) if err.args else str(err)


class HallWatch:
    """The board's samples for a run, surviving a lost link. `open()` (raises if the board does
    not answer at the start), `poll()` from the stream thread, `close()` from any."""

    def __init__(self, url: str, *, timeout_s: float, name: str = HALL_NAME) -> None:
        self.url, self.timeout_s, self.name = url, timeout_s, name
        self._lock = threading.Lock()
        self._stream: HallStream | None = None
        self._closed = threading.Event()
        self._reconnect: threading.Thread | None = None
        self._reason: str | None = None  # why there are no samples now (None: they come)
        self._last_sample_s = time.monotonic()
        self._missed_before = 0  # samples lost in gaps on boards opened before this one
        self.outages = 0
        self.offsets_m: np.ndarray | None = None
        self.silence_s = MIN_SILENCE_S

    def open(self) -> HallWatch:
        board = HallBoard.open(self.url, name=self.name, timeout_s=self.timeout_s)
        self.offsets_m = board.info.offsets_m
        self.silence_s = max(MIN_SILENCE_S, 20.0 / board.info.rate_hz)
        self._stream = HallStream(board).start()
        self._last_sample_s = time.monotonic()
        return self

    @property
    def missed(self) -> int:
        """Samples lost in sequence gaps (not counting outages of the link)."""
        with self._lock:
            stream = self._stream
        return self._missed_before + (stream.board.missed if stream is not None else 0)

    def poll(self) -> tuple[list[HallSample], str | None]:
        """The samples read since the last poll, and why none come now (None: all is well)."""
        with self._lock:
            stream = self._stream
        samples: list[HallSample] = []
        if stream is not None:
            samples = stream.drain(check=False)
            if samples:
                self._last_sample_s = samples[-1].received_s
            error = stream.error
            if error is not None:
                self._lost(stream, _reason(error))
        now = time.monotonic()
        with self._lock:
            reason = self._reason
        if reason is None and now - self._last_sample_s > self.silence_s:
            reason = f"no samples for {now - self._last_sample_s:.1f} s"
        return samples, reason

    def _lost(self, stream: HallStream, reason: str) -> None:
        with self._lock:
            if self._stream is not stream:
                return
            self._stream = None
            self._reason = reason
            self._missed_before += stream.board.missed
            self.outages += 1
        log.warning("%s: %s; opening it again every %g s", self.name, reason, RECONNECT_S)
        self._reconnect = threading.Thread(target=self._reopen, args=(stream,),
                                           name=f"{self.name} reconnect", daemon=True)
        self._reconnect.start()

    def _reopen(self, old: HallStream) -> None:
        old.stop()
        while not self._closed.wait(RECONNECT_S):
            try:
                board = HallBoard.open(self.url, name=self.name, timeout_s=self.timeout_s)
            except RigError as err:
                log.debug("%s: not back yet: %s", self.name, err)
                continue
            if self.offsets_m is not None and not np.allclose(board.info.offsets_m, self.offsets_m):
                board.close()
                with self._lock:
                    self._reason = "the board came back with other sensor offsets"
                return
            stream = HallStream(board).start()
            with self._lock:
                if self._closed.is_set():
                    stream.stop()
                    return
                self._stream = stream
                self._reason = None
                self._last_sample_s = time.monotonic()
            log.warning("%s: back; samples again", self.name)
            return

    def close(self) -> None:
        self._closed.set()
        with self._lock:
            stream, self._stream = self._stream, None
        if stream is not None:
            self._missed_before += stream.board.missed
            stream.stop()
        if self._reconnect is not None:
            self._reconnect.join(timeout=2.0 + self.timeout_s)
