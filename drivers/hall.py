"""Driver for the dEPM rig's Hall-sensor board.

The board (three MLX90395-like 3-axis Hall sensors read over I2C by a small computer) streams
newline-delimited JSON over TCP (docs/hall-board.md): first a `hello` line that describes the
board (sensor sensitivity, range, offsets of the sensors, rate), then one `sample` line per read
with a sequence number, the board's timestamp, the raw 16-bit counts and saturation flags.

`HallBoard` reads that stream with a deadline on every line and counts sequence gaps (lost
samples); `HallStream` does the same in a thread of its own so a run can stream joint targets
while the samples pile up. The driver hands over fields per sensor; turning them into the 8-vector
U at the reference sensor (seed 003 eq. 24) is physics, not the board's:
`rigctl.physics.magnetics.field_vector_from_sensors`, used by the dEPM program's sensors
(`rigctl.rigs.depm.sensors`).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.core.errors import (
    ConfigError,
    DeviceTimeout,
    Disconnected,
    ProtocolError,
    RigError,
)
from rigctl.core.transport import Transport, open_transport

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
MAX_LINE_BYTES = 4096
GARBLED_STREAK = 5  # garbled lines in a row that end a `HallStream` (fewer are skipped)


@dataclass(frozen=True)
class BoardInfo:
    """What the `hello` line says: sensor model, LSB (T), range (T), offsets (n, 3) m, rate (Hz)."""

    board: str
    sensor: str
    lsb_T: float
    range_T: float
    offsets_m: np.ndarray
    rate_hz: float


@dataclass(frozen=True)
class HallSample:
    """One read of every sensor: field (n, 3) T, saturated (n, 3) bool, the board's time stamp
    (s, its own clock) and when it arrived here (`time.monotonic()`, s)."""

    seq: int
    t_s: float
    field_T: np.ndarray
    saturated: np.ndarray
    received_s: float


class HallBoard:
    """The board's sample stream on a transport; `read()` returns the next sample."""

    def __init__(self, transport: Transport, *, name: str = "hall board", timeout_s: float = 1.0) -> None:
        if timeout_s <= 0:
            raise ConfigError(f"timeout_s must be positive, got {timeout_s}", device=name)
        self.name = name
        self.timeout_s = timeout_s
        self._transport = transport
        self.last_seq: int | None = None
        self.received = 0
        self.missed = 0  # samples lost in sequence gaps
        self.gaps: list[tuple[int, int]] = []  # (last seq before, first seq after)
        self.info = self._hello()

    @classmethod
    def open(cls, url: str, *, name: str = "hall board", timeout_s: float = 1.0) -> "HallBoard":
        try:
            transport = open_transport(url, timeout_s=timeout_s)
        except Disconnected as err:
            raise Disconnected(f"cannot connect: {err}", device=name) from None
        try:
            return cls(transport, name=name, timeout_s=timeout_s)
        except RigError:
            transport.close()
            raise

    def _line(self) -> dict[str, Any]:
        try:
            raw = self._transport.read_until(b"\n", timeout_s=self.timeout_s, max_bytes=MAX_LINE_BYTES)
        except DeviceTimeout:
            raise DeviceTimeout(f"no sample within {self.timeout_s:g} s (the board stopped "
                                "streaming)", device=self.name) from None
        except Disconnected as err:
            raise Disconnected(f"link lost ({err})", device=self.name) from None
        except ProtocolError as err:
            raise ProtocolError(str(err), device=self.name) from None
        try:
            message = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise ProtocolError(f"not a JSON line: {raw[:60]!r}", device=self.name) from None
        if not isinstance(message, dict):
            raise ProtocolError(f"not a JSON object: {raw[:60]!r}", device=self.name)
        return message

    def _hello(self) -> BoardInfo:
        message = self._line()
        if message.get("type") != "hello":
            raise ProtocolError(f"expected a hello line first, got {str(message)[:80]}",
                                device=self.name)
        if message.get("version") != PROTOCOL_VERSION:
            raise ProtocolError(f"stream version {message.get('version')!r}; this driver reads "
                                f"version {PROTOCOL_VERSION}", device=self.name)
        try:
            offsets = np.asarray(message["offsets_mm"], dtype=float) * 1e-3
            info = BoardInfo(board=str(message["board"]), sensor=str(message["sensor"]),
                             lsb_T=float(message["lsb_uT"]) * 1e-6,
                             range_T=float(message["range_mT"]) * 1e-3,
                             offsets_m=offsets, rate_hz=float(message["rate_hz"]))
        except (KeyError, TypeError, ValueError) as err:
            raise ProtocolError(f"bad hello line: {err}", device=self.name) from None
        if offsets.ndim != 2 or offsets.shape[1] != 3 or info.lsb_T <= 0:
            raise ProtocolError(f"bad hello line: offsets {offsets.shape}, lsb {info.lsb_T}",
                                device=self.name)
        return info

    def read(self) -> HallSample:
        """The next sample; DeviceTimeout if none within the timeout, ProtocolError if garbled."""
        while True:
            message = self._line()
            kind = message.get("type")
            if kind == "sample":
                break
            if kind == "error":
                log.warning("%s: board reports: %s", self.name, message.get("error"))
                continue
            raise ProtocolError(f"unexpected line type {kind!r}", device=self.name)
        n = len(self.info.offsets_m)
        try:
            seq = int(message["seq"])
            raw = np.asarray(message["raw"], dtype=float)
            flags = np.asarray(message["sat"], dtype=int)
            t_s = float(message["t_s"])
        except (KeyError, TypeError, ValueError, OverflowError) as err:  # 1e999 -> int(inf)
            raise ProtocolError(f"bad sample line: {err}", device=self.name) from None
        if raw.shape != (n, 3) or flags.shape != (n,):
            raise ProtocolError(f"sample has raw {raw.shape} and sat {flags.shape}; the board has "
                                f"{n} sensors", device=self.name)
        if self.last_seq is not None and seq != self.last_seq + 1:
            if seq <= self.last_seq:
                raise ProtocolError(f"sequence went back from {self.last_seq} to {seq}",
                                    device=self.name)
            self.missed += seq - self.last_seq - 1
            self.gaps.append((self.last_seq, seq))
            log.warning("%s: %d sample(s) lost (seq %d -> %d)", self.name, seq - self.last_seq - 1,
                        self.last_seq, seq)
        self.last_seq = seq
        self.received += 1
        saturated = ((flags[:, None] >> np.arange(3)) & 1).astype(bool)
        return HallSample(seq, t_s, raw * self.info.lsb_T, saturated, time.monotonic())

    def close(self) -> None:
        self._transport.close()


class HallStream:
    """Reads a `HallBoard` in a thread; `drain()` hands over the samples read so far.

    A fault in the reader (timeout, lost link, `GARBLED_STREAK` garbled lines in a row) ends the
    thread; the next `drain()` or `check()` raises it, so the caller sees it within one of its own
    cycles. A garbled line on its own is skipped and counted (`garbled`).
    """

    def __init__(self, board: HallBoard, *, max_samples: int = 1_000_000) -> None:
        self.board = board
        self._samples: deque[HallSample] = deque(maxlen=max_samples)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._error: RigError | None = None
        self.garbled = 0  # lines skipped as garbled
        self._thread = threading.Thread(target=self._run, name=f"{board.name} reader", daemon=True)

    def start(self) -> "HallStream":
        self._thread.start()
        return self

    def _run(self) -> None:
        streak = 0  # garbled lines in a row
        while not self._stop.is_set():
            try:
                sample = self.board.read()
            except ProtocolError as err:
                # one garbled line costs one sample (the next line is read on its own, and the
                # sequence numbers count the loss); GARBLED_STREAK in a row is a broken link
                streak += 1
                self.garbled += 1
                if streak < GARBLED_STREAK and not self._stop.is_set():
                    log.warning("%s; the line is skipped", err)
                    continue
                if not self._stop.is_set():
                    self._error = err
                return
            except RigError as err:
                if not self._stop.is_set():
                    self._error = err
                return
            except Exception as err:  # never end silently: the run must see why the samples stopped
                if not self._stop.is_set():
                    self._error = ProtocolError(f"Hall board reader stopped: {type(err).__name__}: "
                                                f"{err}", device=self.board.name)
                return
            streak = 0
            with self._lock:
                self._samples.append(sample)

    @property
    def error(self) -> RigError | None:
        """The fault that ended the reader, if any."""
        return self._error

    def check(self) -> None:
        if self._error is not None:
            raise self._error

    def drain(self, *, check: bool = True) -> list[HallSample]:
        """The samples read so far (oldest first). `check=False`: also after the reader ended
        with a fault (`error`), so the samples read before it are not lost with it."""
        if check:
            self.check()
        with self._lock:
            out = list(self._samples)
            self._samples.clear()
        return out

    def stop(self) -> None:
        """End the reader and close the board's link (the blocked read returns at once)."""
        self._stop.set()
        self.board.close()
        self._thread.join(timeout=2.0 + self.board.timeout_s)
