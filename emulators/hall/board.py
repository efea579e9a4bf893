"""The emulated Hall-sensor board: three MLX90395-like 3-axis sensors read by a small computer that
streams their counts as newline-delimited JSON over TCP (docs/hall-board.md).

`HallSensorModel` is pure: the true field at each sensor plus Gaussian noise, quantised to the
sensor's LSB and clipped at its range, with saturation flags. `HallBoardServer` puts the board on a
shared `EmulatorServer` loop: every `period_s` (real time) it asks `field_at(points_m)` for the
field at the sensors (the bench computes it from the emulated arms' *actual* joints: forward
kinematics, then the EPM dipole model) and sends one sample to every client, stamped with the
simulated time `now()`.

Sensor figures (seed 003 Sec. 4.1, MLX90395): range +-50 mT, 2.5 uT/LSB (16-bit). The noise is not
given there; 3 uT RMS per axis is an assumption of the order of a Hall sensor at a high
oversampling setting.

Faults, besides the link's own (`endpoint.drop_link/stall/corrupt/restore`): `skip(n)` loses the
next n samples (the sequence numbers jump), as when the reader computer misses I2C reads.

`place(offsets_mm)` moves the sensors (the six-coil bench's probe array). The `hello` is the only
place a client learns where the sensors are and how many there are, and it comes once, first on a
connection (docs/hall-board.md); so the board closes its connections when its sensors move, as a
reader computer does when it is restarted with a new board file, and each client's next connection
starts with a hello that names the new positions. Without that, a connected client would go on
placing the new sensors' readings at the old positions (or fail on a different count).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rigctl.emulators.server import EmulatorServer, Session

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
PAPER_OFFSETS_MM = ((0.0, 0.0, 0.0), (50.0, 0.0, 0.0), (0.0, 50.0, 0.0))  # seed 003 Fig. 4(b)


@dataclass(frozen=True)
class SensorSpec:
    """An MLX90395-like 3-axis Hall sensor."""

    name: str = "MLX90395"
    lsb_T: float = 2.5e-6
    range_T: float = 50e-3
    noise_T: float = 3e-6  # RMS per axis: an assumption, see the module docstring

    @property
    def max_count(self) -> int:
        return int(round(self.range_T / self.lsb_T))


class HallSensorModel:
    """What the sensors report for a true field: noise, quantisation, saturation."""

    def __init__(self, spec: SensorSpec = SensorSpec(), *, seed: int = 0) -> None:
        self.spec = spec
        self._rng = np.random.default_rng(seed)

    def measure(self, field_T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw counts (n, 3) int and saturation flags (n, 3) bool for true fields (n, 3) T."""
        field = np.asarray(field_T, dtype=float)
        noisy = field + self._rng.normal(0.0, self.spec.noise_T, field.shape)
        counts = np.rint(noisy / self.spec.lsb_T)
        limit = self.spec.max_count
        saturated = np.abs(counts) >= limit
        return np.clip(counts, -limit, limit).astype(int), saturated


def sample_line(seq: int, t_s: float, counts: np.ndarray, saturated: np.ndarray) -> str:
    """One `sample` line: per sensor a saturation bit mask (bit 0 x, 1 y, 2 z)."""
    flags = (saturated.astype(int) << np.arange(3)).sum(axis=1)
    return json.dumps({"type": "sample", "seq": seq, "t_s": round(t_s, 6),
                       "raw": counts.tolist(), "sat": flags.tolist()}, separators=(",", ":"))


class HallBoardServer:
    """The board on the emulator loop: a `hello` to each new client, then samples to all."""

    def __init__(self, server: EmulatorServer, *, field_at: Callable[[np.ndarray], np.ndarray],
                 now: Callable[[], float], offsets_mm=PAPER_OFFSETS_MM,
                 centre_m=(0.0, 0.0, 0.0), spec: SensorSpec = SensorSpec(), rate_hz: float = 100.0,
                 seed: int = 0, host: str = "127.0.0.1", port: int = 0,
                 name: str = "hall board") -> None:
        if not rate_hz > 0:
            raise ValueError("rate_hz must be positive")
        self.server = server
        self.name = name
        self.field_at = field_at
        self.now = now
        self.centre_m = np.asarray(centre_m, dtype=float)
        self.offsets_mm, self.points_m = self._positions(offsets_mm)
        self.model = HallSensorModel(spec, seed=seed)
        self.rate_hz = rate_hz
        self.seq = 0
        self.skip_remaining = 0
        self.sessions: set[Session] = set()
        self.endpoint = server.serve_sessions_tcp(self, name=name, host=host, port=port)
        self.url = self.endpoint.url
        server.every(1.0 / rate_hz, self.tick)

    def _positions(self, offsets_mm) -> tuple[np.ndarray, np.ndarray]:
        """Offsets (n, 3) mm from the centre, and the sensors' points (n, 3) m."""
        offsets = np.asarray(offsets_mm, dtype=float)
        if offsets.ndim != 2 or offsets.shape[1] != 3 or len(offsets) < 1:
            raise ValueError(f"offsets_mm must be (n, 3) with n >= 1, got {offsets.shape}")
        return offsets, self.centre_m + offsets * 1e-3

    def place(self, offsets_mm) -> None:
        """Move the sensors to `offsets_mm` (n, 3) mm and close every connection, so that each
        client's next one starts with a hello naming them (module docstring). Call in the loop
        thread or through `server.call`."""
        self.offsets_mm, self.points_m = self._positions(offsets_mm)
        for session in list(self.sessions):
            session.close()

    # -- SessionHandler -------------------------------------------------------------------------
    def connected(self, session: Session) -> None:
        spec = self.model.spec
        session.send(json.dumps({
            "type": "hello", "version": PROTOCOL_VERSION, "board": "rigctl emulated hall board",
            "sensor": spec.name, "lsb_uT": spec.lsb_T * 1e6, "range_mT": spec.range_T * 1e3,
            "offsets_mm": self.offsets_mm.tolist(), "rate_hz": self.rate_hz}))
        self.sessions.add(session)

    def received(self, session: Session, line: str) -> None:
        session.send(json.dumps({"type": "error", "error": "the board takes no commands; it "
                                 "streams samples to every client"}))

    def disconnected(self, session: Session) -> None:
        self.sessions.discard(session)

    # -- streaming ------------------------------------------------------------------------------
    def tick(self) -> None:
        self.seq += 1
        if self.skip_remaining > 0:
            self.skip_remaining -= 1
            return
        if not self.sessions:
            return
        counts, saturated = self.model.measure(self.field_at(self.points_m))
        line = sample_line(self.seq, self.now(), counts, saturated)
        for session in list(self.sessions):
            session.send(line)

    def skip(self, n: int) -> None:
        """Lose the next n samples (call in the loop thread or through `server.call`)."""
        if n < 1:
            raise ValueError("n must be >= 1")
        self.skip_remaining = n

    def close(self) -> None:
        self.endpoint.close()
