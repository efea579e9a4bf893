"""Telemetry: the daemon's two PUB sockets and the thread that feeds them.

The stream must never wait on a subscriber, nor on the publisher. Its cycles arrive in batches
(`CycleBatch`, about every 20 ms from the stream process), and `offer_cycles` appends each to a
bounded in-memory queue (a deque append: no lock, no wake-up; when the queue is full the oldest
batch goes and its cycles are counted as dropped) and returns. The publisher thread wakes every
`TELEMETRY_BATCH_S`, takes every queued cycle, and sends them as one `actuators` message (every
cycle, at the stream rate, unless `currents_hz` decimates), the latest `field` (from the
actuation matrix) and, at `stream_hz`, period-error statistics, a few short bursts of Python a
second. Sends use `zmq.NOBLOCK`; a PUB socket never blocks anyway, it drops for a subscriber
whose queue (`DATA_SEND_HWM` messages) is full.

A rig whose coils heat also has `winding`, ten times a second (`WindingEstimate`): the running
run's live winding model as its stream process reports it, and between runs the last estimate
cooling, from which the next run starts, until the windings are back at the room.

`state`, `fault` and `log` are never dropped on our side: they go into their own queue, which
wakes the publisher at once and is emptied before any sample, and out through a second PUB
socket (the events socket) whose per-subscriber queues hold `EVENTS_SEND_HWM` messages, so a
subscriber drowning in samples still has room for every state change. That queue is bounded too
(memory never grows without bound); reaching it would mean a subscriber that has read nothing
for hours, and the sequence numbers let it see the gap and ask `status` for the present.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np
import zmq
from pydantic import BaseModel

from rigctl.apps.daemon.messages import (
    DATA_SEND_HWM,
    EVENTS_SEND_HWM,
    TELEMETRY_BATCH_S,
    ActuatorsMsg,
    AgentsMsg,
    FaultMsg,
    FieldMsg,
    FrameMsg,
    LogMsg,
    StateMsg,
    StreamMsg,
    Topic,
    WindingMsg,
)
from rigctl.core.channels import Channel
from rigctl.physics.thermal import WindingMonitor, Windings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CycleBatch:
    """Stream cycles, a row each: `t` (n,) s on the publisher's clock, `sample` and `move` (n,),
    `commanded` and `measured` (n, n_channels), `period_error_s` (n,), NaN where unknown. How a
    run in another process hands its cycles over (`offer_cycles`)."""

    t: np.ndarray
    sample: np.ndarray
    move: np.ndarray
    commanded: np.ndarray
    measured: np.ndarray
    period_error_s: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    @staticmethod
    def row(t: float, sample: int, move: int, commanded: np.ndarray, measured: np.ndarray,
            period_error_s: float | None) -> list[float]:
        """One cycle as a row of floats (`from_rows`): what a run queues per cycle."""
        return [t, sample, move, *np.asarray(commanded, dtype=float).tolist(),
                *np.asarray(measured, dtype=float).tolist(),
                np.nan if period_error_s is None else period_error_s]

    @staticmethod
    def from_rows(rows: np.ndarray | list[list[float]]) -> "CycleBatch":
        """Cycles from their rows (`row`), one (n, 4 + 2 n_channels) array: how the stream
        process sends them, one array for the daemon's reader to unpickle instead of six."""
        a = np.asarray(rows, dtype=float)
        k = (a.shape[1] - 4) // 2
        return CycleBatch(a[:, 0], a[:, 1].astype(np.int64), a[:, 2].astype(np.int64),
                          a[:, 3:3 + k], a[:, 3 + k:3 + 2 * k], a[:, 3 + 2 * k])

    @staticmethod
    def joined(batches: list["CycleBatch"]) -> "CycleBatch":
        if len(batches) == 1:
            return batches[0]
        return CycleBatch(*(np.concatenate([getattr(b, f) for b in batches])
                            for f in ("t", "sample", "move", "commanded", "measured",
                                      "period_error_s")))


class WindingEstimate:
    """The daemon's estimate of its windings: a run's live model, taken as the stream process
    reports it (`from_run`, ten times a second), and while none reports, the last estimate
    cooling at zero drive by the same model (`rigctl.physics.thermal.WindingMonitor`), so that what is
    published never falls back to the room when a run ends, nor does the next run start from it
    (`start_C` is its start). Thread-safe."""

    QUIET_S = 0.5  # no report from a run for this long: it has ended, the windings cool
    AT_REST_K = 0.05  # cooled this close to the room: nothing to publish until a run heats them

    def __init__(self, windings: Windings) -> None:
        self.windings = windings
        self._monitor = WindingMonitor(windings)
        self._lock = threading.Lock()
        self._at = time.monotonic()  # when the estimate holds
        self._heard = -float("inf")  # when a run last reported
        self._state = "ok"

    def from_run(self, t: float, temperatures_C: list[float], state: str) -> None:
        """A run's estimate at monotonic `t`."""
        with self._lock:
            self._monitor.temperature_C[:] = temperatures_C
            self._at, self._heard, self._state = t, time.monotonic(), state

    def now(self) -> tuple[float, list[float], str, str] | None:
        """(monotonic s it holds at, C per winding, "ok"/"warning"/"limit", "run"/"cooling"), or
        None at rest: no run reports and every winding is back at the room."""
        with self._lock:
            now = time.monotonic()
            if now - self._heard < self.QUIET_S:
                return self._at, self._monitor.temperature_C.tolist(), self._state, "run"
            if now > self._at:
                self._state = self._monitor.update(np.zeros(len(self.windings.names)), now - self._at)
                self._at = now
            temperatures = self._monitor.temperature_C
            if (np.abs(temperatures - self.windings.ambient_C) < self.AT_REST_K).all():
                return None
            return self._at, temperatures.tolist(), self._state, "cooling"

    def start_C(self) -> list[float]:
        """Where the next run's model starts: the estimate now."""
        self.now()
        with self._lock:
            return [float(t) for t in self._monitor.temperature_C]


@dataclass
class PublisherStats:
    dropped: int = 0  # samples dropped from the in-memory queue (publisher too slow)
    sent: dict[str, int] | None = None


class TelemetryPublisher:
    """Owns the data and events PUB sockets (bound by `start`) and the publisher thread.

    `offer_cycles` is for the thread that hands cycles over; `publish_event` and `publish_agents`
    for any thread; `windings` (None: nothing heats) is published at `winding_hz`.
    Rates in Hz; a rate of 0 means every sample.
    """

    def __init__(
        self,
        context: zmq.Context[zmq.Socket[bytes]],
        data_endpoint: str,
        events_endpoint: str,
        *,
        channels: list[Channel],
        actuation_matrix_T_per_A: np.ndarray | None = None,
        field_offset_T: np.ndarray | None = None,
        currents_hz: float = 0.0,
        field_hz: float = 100.0,
        stream_hz: float = 10.0,
        queue_batches: int = 4096,
        batch_s: float = TELEMETRY_BATCH_S,
        secure: Callable[[zmq.Socket[bytes]], None] | None = None,
        clock_origin: float | None = None,
        windings: WindingEstimate | None = None,
        winding_hz: float = 10.0,
    ) -> None:
        self.context = context
        self.channel_names = [c.name for c in channels]
        self.channel_units = [c.unit for c in channels]
        self.actuation = actuation_matrix_T_per_A
        # an MPEM rig's current-independent Offset field at the centre (T): B = A I + offset
        self.field_offset = np.zeros(3) if field_offset_T is None else np.asarray(field_offset_T)
        self.currents_period = 1.0 / currents_hz if currents_hz > 0 else 0.0
        self.field_period = 1.0 / field_hz if field_hz > 0 else 0.0
        self.stream_period = 1.0 / stream_hz if stream_hz > 0 else 0.0
        self.windings = windings
        self.winding_period = 1.0 / winding_hz
        self.t0 = time.monotonic() if clock_origin is None else clock_origin
        self._data = self._bind(data_endpoint, DATA_SEND_HWM, secure)
        self._events = self._bind(events_endpoint, EVENTS_SEND_HWM, secure)
        self.data_endpoint = self._data.getsockopt_string(zmq.LAST_ENDPOINT)
        self.events_endpoint = self._events.getsockopt_string(zmq.LAST_ENDPOINT)
        self.batch_s = batch_s
        self._cond = threading.Condition()
        self._samples: deque[CycleBatch] = deque(maxlen=queue_batches)
        self._offered = 0  # cycles; written by the one thread that offers
        self._consumed = 0
        self._pending_reset: float | None = None
        self._priority: deque[tuple[str, BaseModel]] = deque(maxlen=EVENTS_SEND_HWM)
        self._stopping = False
        self._seq: dict[str, int] = {t.value: 0 for t in Topic}
        self._seq_lock = threading.Lock()
        self.stats = PublisherStats(sent={t.value: 0 for t in Topic})
        self._last_sent = {"actuators": -1e9, "field": -1e9, "stream": -1e9}
        self._errors: deque[float] = deque(maxlen=1000)
        self._late = 0
        self._cycles = 0
        self._rate_hz = 0.0
        self._thread = threading.Thread(target=self._serve, name="telemetry", daemon=True)

    def _bind(self, endpoint: str, hwm: int,
              secure: Callable[[zmq.Socket[bytes]], None] | None) -> zmq.Socket[bytes]:
        sock = self.context.socket(zmq.PUB)
        sock.setsockopt(zmq.SNDHWM, hwm)
        sock.setsockopt(zmq.LINGER, 0)
        # a vanished subscriber is noticed by heartbeats and its queue freed
        sock.setsockopt(zmq.HEARTBEAT_IVL, 2000)
        sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, 6000)
        if secure is not None:
            secure(sock)
        sock.bind(endpoint)
        return sock

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        with self._cond:
            self._stopping = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        self._data.close(linger=0)
        self._events.close(linger=0)

    def now(self) -> float:
        return time.monotonic() - self.t0

    # -- producers ------------------------------------------------------------------------------
    def reset_stream(self, rate_hz: float) -> None:
        """A new stream starts: period-error statistics begin again (at the next batch)."""
        self._pending_reset = rate_hz

    def offer_cycles(self, batch: CycleBatch) -> None:
        """Stream cycles, from the one thread that hands them over (the reader of the stream
        process): an append, nothing else (the oldest batch goes when the queue is full)."""
        self._samples.append(batch)
        self._offered += len(batch)

    def publish_event(self, topic: Topic, **fields: object) -> None:
        """state, fault or log: queued ahead of every sample, sent on the events socket."""
        with self._cond:
            self._priority.append((topic.value, _event_model(topic, self._next_seq(topic), self.now(),
                                                             fields)))
            self._cond.notify()

    def publish_agents(self, move: int, tracked: list[Any] | None, expected: list[Any] | None,
                       source: str) -> None:
        with self._cond:
            msg = AgentsMsg(seq=self._next_seq(Topic.AGENTS), t=self.now(), move=move,
                            tracked_mm=tracked, expected_mm=expected, source=source)
            self._priority.append((Topic.AGENTS.value, msg))
            self._cond.notify()

    def publish_frame(self, jpeg_b64: str, width: int, height: int, t_source: float,
                      t_source_unix: float, positions_mm: list[Any], tracked_px: list[Any], lost: list[Any],
                      frame: int) -> None:
        """A camera frame (JPEG, base64; `t_source` monotonic s) from the stream process's reader
        thread, sent by the publisher thread like `agents`."""
        msg = FrameMsg.model_construct(
            seq=self._next_seq(Topic.FRAME), t=self.now(), topic="frame", jpeg_b64=jpeg_b64,
            width=width, height=height, t_source=round(t_source - self.t0, 6),
            t_source_unix=t_source_unix, positions_mm=positions_mm, tracked_px=tracked_px,
            lost=lost, frame=frame)
        with self._cond:
            self._priority.append((Topic.FRAME.value, msg))
            self._cond.notify()

    def _next_seq(self, topic: Topic) -> int:
        with self._seq_lock:
            seq = self._seq[topic.value]
            self._seq[topic.value] = seq + 1
            return seq

    # -- the publisher thread -------------------------------------------------------------------
    def _serve(self) -> None:
        next_batch = next_winding = time.monotonic() + self.batch_s
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._priority or self._stopping,
                                    timeout=max(0.0, next_batch - time.monotonic()))
                events = list(self._priority)
                self._priority.clear()
                stopping = self._stopping
            for topic, msg in events:
                self._send(topic, msg)
            if time.monotonic() >= next_batch or stopping:
                next_batch = time.monotonic() + self.batch_s
                chunks: list[CycleBatch] = []
                while self._samples:
                    chunks.append(self._samples.popleft())
                self._consumed += sum(len(c) for c in chunks)
                queued = sum(len(c) for c in list(self._samples))
                self.stats.dropped = self._offered - self._consumed - queued
                if chunks:
                    self._publish_batch(CycleBatch.joined(chunks))
            now = time.monotonic()
            if self.windings is not None and now >= next_winding:
                # ten a second on average; after a stall the next one, not a burst
                next_winding = max(next_winding + self.winding_period, now)
                self._publish_winding(self.windings)
            if stopping:
                return

    def _send(self, topic: str, msg: BaseModel) -> None:
        sock = self._events if topic in ("state", "fault", "log") else self._data
        try:
            sock.send_multipart([topic.encode(), msg.model_dump_json().encode()], flags=zmq.NOBLOCK)
            if self.stats.sent is not None:
                self.stats.sent[topic] += 1
        except zmq.Again:  # PUB drops rather than blocks; kept for completeness
            log.debug("telemetry %s dropped", topic)

    def _publish_winding(self, estimate: WindingEstimate) -> None:
        now = estimate.now()
        if now is None:
            return
        at, temperatures, state, source = now
        w = estimate.windings
        self._send("winding", WindingMsg(
            seq=self._next_seq(Topic.WINDING), t=round(at - self.t0, 6), names=list(w.names),
            temperature_C=[round(t, 4) for t in temperatures], warning_C=w.warning_C.tolist(),
            limit_C=w.limit_C.tolist(), state=cast("Literal['ok', 'warning', 'limit']", state),
            source=cast("Literal['run', 'cooling']", source)))

    def _publish_batch(self, batch: CycleBatch) -> None:
        if self._pending_reset is not None:
            self._rate_hz, self._pending_reset = self._pending_reset, None
            self._errors.clear()
            self._late = self._cycles = 0
        errors = batch.period_error_s[~np.isnan(batch.period_error_s)]
        self._errors.extend(errors.tolist())
        self._cycles += len(batch)
        if self._rate_hz:
            self._late += int(np.count_nonzero(errors > 0.5 / self._rate_hz))
        kept = np.arange(len(batch))
        if self.currents_period > 0:
            chosen = []
            for i, t in enumerate(batch.t.tolist()):
                if t - self._last_sent["actuators"] >= self.currents_period:
                    self._last_sent["actuators"] = t
                    chosen.append(i)
            kept = np.array(chosen, dtype=int)
        if kept.size:
            self._send("actuators", ActuatorsMsg.model_construct(
                seq=self._next_seq(Topic.ACTUATORS), t=float(batch.t[kept[-1]]),
                topic="actuators", channels=self.channel_names, units=self.channel_units,
                times=batch.t[kept].round(6).tolist(),
                samples=batch.sample[kept].tolist(), moves=batch.move[kept].tolist(),
                commanded=batch.commanded[kept].round(5).tolist(),
                measured=batch.measured[kept].round(5).tolist()))
        t_last, commanded, measured = float(batch.t[-1]), batch.commanded[-1], batch.measured[-1]
        if self.actuation is not None and t_last - self._last_sent["field"] >= self.field_period:
            self._last_sent["field"] = t_last
            self._send("field", FieldMsg(
                seq=self._next_seq(Topic.FIELD), t=t_last,
                commanded_mT=((self.actuation @ commanded + self.field_offset) * 1e3
                              ).round(6).tolist(),
                measured_mT=((self.actuation @ measured + self.field_offset) * 1e3
                             ).round(6).tolist()))
        if t_last - self._last_sent["stream"] >= self.stream_period:
            self._last_sent["stream"] = t_last
            recent = np.asarray(self._errors) * 1e6
            p50, p99, worst = ((np.percentile(recent, 50), np.percentile(recent, 99), recent.max())
                               if recent.size else (0.0, 0.0, 0.0))
            self._send("stream", StreamMsg(
                seq=self._next_seq(Topic.STREAM), t=t_last, rate_hz=self._rate_hz,
                cycles=self._cycles, late_cycles=self._late,
                period_error_p50_us=round(float(p50), 1), period_error_p99_us=round(float(p99), 1),
                period_error_max_us=round(float(worst), 1), dropped_samples=self.stats.dropped))


def _event_model(topic: Topic, seq: int, t: float, fields: dict[str, Any]) -> BaseModel:
    models: dict[Topic, type[BaseModel]] = {Topic.STATE: StateMsg, Topic.FAULT: FaultMsg,
                                            Topic.LOG: LogMsg}
    if topic not in models:
        raise ValueError(f"{topic.value} is not an event topic")
    return models[topic](seq=seq, t=t, **fields)
