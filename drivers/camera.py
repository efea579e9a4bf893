"""Camera driver: frames from OpenCV's `VideoCapture`, a device index, a video file or a stream URL.

A source is a camera index (`0`, or the string `"0"`), a stream URL (`http://...`, `rtsp://...`,
e.g. an MJPEG camera or the emulated one), or a video file (a recorded experiment). Live sources
are read by one thread that blocks in `VideoCapture.read()` and keeps only the newest frame, so a
slow consumer gets the freshest picture instead of a growing backlog; `read()` waits for a frame
newer than the last one it returned. A video file is read in order, one frame per `read()`, with no
thread and no frame ever skipped.

Each `Frame` carries `t_capture`, the monotonic clock when the driver received it, and `t_source`,
the source's own time of the picture where known. A stream cannot pass per-frame headers through
`VideoCapture`, so a camera that stamps its frames writes the capture time and frame number into
the picture itself (`write_stamp`, the way machine-vision cameras embed frame info into the first
pixels); with `stamped=True` the driver reads the stamp back, and paints the stamp rows over with
the first row below them so nothing downstream mistakes it for the scene. For a video file
`t_source` is the file's own time of the frame.

When a live stream breaks (the read fails, or nothing arrives for `timeout_s`), the driver reopens it,
at most `reconnect_attempts` times in a row with a doubling delay; a frame arriving resets the count.
When the attempts are spent, `read()` raises `Disconnected`. `read()` raises `DeviceTimeout` when no
new frame comes within its timeout while the link is still being retried.
"""

from __future__ import annotations

import logging
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rigctl.core.errors import ConfigError, DeviceTimeout, Disconnected
from rigctl.core.transport import camera_source

log = logging.getLogger(__name__)

# The embedded stamp: a row-major grid of STAMP_BLOCK x STAMP_BLOCK px blocks from the top-left
# corner, each black (0) or white (1). Blocks align with JPEG's 8 x 8 blocks, so they survive
# compression. Layout: sync 1010, 48 bits of monotonic time in microseconds, 20 bits of frame
# number (modulo 2**20), 8 bits CRC-32 (low byte) of the 9 payload bytes.
STAMP_BLOCK = 8
_SYNC = (1, 0, 1, 0)
_TIME_BITS = 48
_FRAME_BITS = 20
_CRC_BITS = 8
STAMP_BITS = len(_SYNC) + _TIME_BITS + _FRAME_BITS + _CRC_BITS


def stamp_rows(width_px: int) -> int:
    """How many pixel rows the stamp occupies in a picture `width_px` wide."""
    per_row = width_px // STAMP_BLOCK
    if per_row < 1:
        raise ValueError(f"a picture {width_px} px wide is too narrow for a frame stamp")
    return -(-STAMP_BITS // per_row) * STAMP_BLOCK


def _payload_bits(t_us: int, number: int) -> np.ndarray:
    payload = (t_us << _FRAME_BITS) | number
    payload_bytes = payload.to_bytes(9, "big")
    crc = zlib.crc32(payload_bytes) & 0xFF
    word = (payload << _CRC_BITS) | crc
    n = _TIME_BITS + _FRAME_BITS + _CRC_BITS
    bits = [(word >> (n - 1 - i)) & 1 for i in range(n)]
    return np.array(list(_SYNC) + bits, dtype=np.uint8)


def write_stamp(image: np.ndarray, t_monotonic_s: float, frame_number: int) -> None:
    """Write capture time (monotonic s) and frame number into the top rows of `image` (H, W, 3)."""
    t_us = int(round(t_monotonic_s * 1e6)) % (1 << _TIME_BITS)
    bits = _payload_bits(t_us, int(frame_number) % (1 << _FRAME_BITS))
    per_row = image.shape[1] // STAMP_BLOCK
    rows = stamp_rows(image.shape[1]) // STAMP_BLOCK
    grid = np.zeros(rows * per_row, dtype=np.uint8)
    grid[: len(bits)] = bits * 255
    blocks = np.kron(grid.reshape(rows, per_row), np.ones((STAMP_BLOCK, STAMP_BLOCK), np.uint8))
    image[: blocks.shape[0], : blocks.shape[1]] = blocks[..., None]


def read_stamp(image: np.ndarray) -> tuple[float, int] | None:
    """(capture time s, frame number mod 2**20) from a stamped picture, or None if there is none."""
    height, width = image.shape[:2]
    rows_px = stamp_rows(width)
    if height < rows_px:
        return None
    per_row = width // STAMP_BLOCK
    plane = image[:rows_px, : per_row * STAMP_BLOCK]
    if plane.ndim == 3:
        plane = plane[..., 1]
    # The middle of each block: away from the ringing JPEG leaves at block edges.
    cells = plane.reshape(rows_px // STAMP_BLOCK, STAMP_BLOCK, per_row, STAMP_BLOCK)
    inner = cells[:, 2:-2, :, 2:-2].mean(axis=(1, 3)).reshape(-1)[:STAMP_BITS]
    bits = (inner > 127.5).astype(np.uint8)
    if tuple(bits[: len(_SYNC)]) != _SYNC:
        return None
    word = 0
    for bit in bits[len(_SYNC) :]:
        word = (word << 1) | int(bit)
    crc = word & 0xFF
    payload = word >> _CRC_BITS
    if zlib.crc32(payload.to_bytes(9, "big")) & 0xFF != crc:
        return None
    return (payload >> _FRAME_BITS) / 1e6, payload & ((1 << _FRAME_BITS) - 1)


def erase_stamp(image: np.ndarray) -> None:
    """Paint the stamp rows of `image` with the first row below them."""
    rows = stamp_rows(image.shape[1])
    if image.shape[0] > rows:
        image[:rows] = image[rows]


@dataclass(frozen=True)
class Frame:
    """One picture. image: (H, W, 3) uint8 BGR; index: frames this driver returned before it;
    t_capture: monotonic s when the driver received it; t_source: the source's time of the picture
    (monotonic s of the camera's stamp, or the position in a video file) or None; source_number: the
    camera's own frame number (stamp, or frame index in a file) or None; repeated: the source sent
    the same picture as the frame before (a frozen camera)."""

    image: np.ndarray
    index: int
    t_capture: float
    t_source: float | None = None
    source_number: int | None = None
    repeated: bool = False


def _source_kind(source: str | int) -> tuple[str, str | int]:
    kind, target = camera_source(source)
    if kind == "file" and not Path(str(target)).is_file():
        raise ConfigError(f"camera source: no video file {target}")
    return kind, target


class CameraDriver:
    """Frames from one camera source; see the module docstring.

    timeout_s: how long `read()` waits by default, and how long a live source may stay silent
    before the driver reconnects; reconnect_attempts: reopenings in a row before giving up;
    reconnect_delay_s: the first delay between reopenings (then doubled, at most 2 s).
    """

    def __init__(
        self,
        source: str | int,
        *,
        name: str = "camera",
        stamped: bool = False,
        timeout_s: float = 2.0,
        reconnect_attempts: int = 5,
        reconnect_delay_s: float = 0.1,
    ) -> None:
        self.kind, self.target = _source_kind(source)
        self.source = source
        self.name = name
        self.stamped = stamped
        self.timeout_s = float(timeout_s)
        self.reconnect_attempts = int(reconnect_attempts)
        self.reconnect_delay_s = float(reconnect_delay_s)
        self.reconnects = 0  # reopenings that succeeded
        self._capture: cv2.VideoCapture | None = None
        self._count = 0
        self._last_fingerprint: tuple[object, ...] | None = None
        # live sources: the reader thread hands over the newest frame through these
        self._cond = threading.Condition()
        self._latest: tuple[np.ndarray, float] | None = None
        self._latest_seq = 0
        self._returned_seq = 0
        self._failure: Exception | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- life cycle -----------------------------------------------------------------------------

    def open(self) -> "CameraDriver":
        """Open the source (and start the reader thread for a live one); Disconnected if it fails."""
        if self._capture is not None or self._thread is not None:
            raise RuntimeError(f"{self.name}: already open")
        self._stop.clear()
        self._failure = None
        self._capture = self._open_capture()
        if self.kind != "file":
            self._thread = threading.Thread(
                target=self._read_live, name=f"{self.name}-reader", daemon=True
            )
            self._thread.start()
        log.info("%s: opened %s %s", self.name, self.kind, self.target)
        return self

    def close(self) -> None:
        """Release the source and end the reader thread (within about `timeout_s`). Idempotent."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(self.timeout_s + 1.0)
            if thread.is_alive():  # it releases its capture itself when read() returns
                log.warning("%s: reader thread still blocked in VideoCapture.read()", self.name)
                return
        capture, self._capture = self._capture, None
        if capture is not None:
            capture.release()

    def __enter__(self) -> "CameraDriver":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- frames ---------------------------------------------------------------------------------

    def read(self, timeout_s: float | None = None) -> Frame:
        """The next frame: for a live source the newest one not yet returned, waiting for it.

        DeviceTimeout if none comes within `timeout_s` (default: the driver's), Disconnected when the
        source is gone for good, EOFError at the end of a video file.
        """
        if self.kind == "file":
            return self._read_file()
        if self._thread is None:
            raise RuntimeError(f"{self.name}: not open")
        wait = self.timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + wait
        with self._cond:
            while self._latest_seq == self._returned_seq:
                if self._failure is not None:
                    raise self._failure
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"no frame within {wait:.3g} s", device=self.name)
                self._cond.wait(remaining)
            image, t_capture = self._latest  # type: ignore[misc]
            self._returned_seq = self._latest_seq
        return self._frame(image, t_capture)

    def __iter__(self) -> Iterator[Frame]:
        """Frames until the end of a file (live sources: until an error)."""
        while True:
            try:
                yield self.read()
            except EOFError:
                return

    def _frame(self, image: np.ndarray, t_capture: float, t_file: float | None = None,
               number_in_file: int | None = None) -> Frame:
        t_source, number = t_file, number_in_file
        if self.stamped:
            stamp = read_stamp(image)
            if stamp is not None:
                t_source, number = stamp
                erase_stamp(image)
            else:
                log.debug("%s: frame without a readable stamp", self.name)
        if self.stamped and number is not None:
            fingerprint: tuple[object, ...] = (t_source, number)
        else:
            fingerprint = (image[::17, ::13].tobytes(),)
        repeated = fingerprint == self._last_fingerprint
        self._last_fingerprint = fingerprint
        frame = Frame(image, self._count, t_capture, t_source, number, repeated)
        self._count += 1
        return frame

    def _read_file(self) -> Frame:
        if self._capture is None:
            raise RuntimeError(f"{self.name}: not open")
        ok, image = self._capture.read()
        t_capture = time.monotonic()
        if not ok:
            raise EOFError(f"{self.name}: end of {self.target}")
        position_s = self._capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        number = int(self._capture.get(cv2.CAP_PROP_POS_FRAMES)) - 1
        return self._frame(image, t_capture, position_s, number)

    # -- live sources ---------------------------------------------------------------------------

    def _open_capture(self) -> cv2.VideoCapture:
        timeout_ms = int(self.timeout_s * 1000)
        if self.kind == "device":
            capture = cv2.VideoCapture(self.target)  # an index, or /dev/video0 (V4L2)
        elif self.kind == "stream":
            capture = cv2.VideoCapture(
                str(self.target), cv2.CAP_FFMPEG,
                [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms,
                 cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms],
            )
        else:
            capture = cv2.VideoCapture(str(self.target))
        if not capture.isOpened():
            capture.release()
            raise Disconnected(f"cannot open {self.kind} {self.target}", device=self.name)
        return capture

    def _read_live(self) -> None:
        """Reader thread: newest frame into the slot; reconnect a bounded number of times."""
        failures = 0
        while not self._stop.is_set():
            capture = self._capture
            ok, image = (False, None) if capture is None else capture.read()
            if self._stop.is_set():
                break
            if ok and image is not None:
                failures = 0
                with self._cond:
                    self._latest = (image, time.monotonic())
                    self._latest_seq += 1
                    self._cond.notify_all()
                continue
            failures += 1
            if failures > self.reconnect_attempts:
                self._give_up(f"lost after {self.reconnect_attempts} reconnection attempts")
                return
            delay = min(self.reconnect_delay_s * 2 ** (failures - 1), 2.0)
            log.warning("%s: stream broke; reconnecting in %.2f s (attempt %d of %d)",
                        self.name, delay, failures, self.reconnect_attempts)
            if capture is not None:
                capture.release()
            self._capture = None
            if self._stop.wait(delay):
                break
            try:
                self._capture = self._open_capture()
                self.reconnects += 1
                log.info("%s: reconnected to %s", self.name, self.target)
            except Disconnected as err:
                log.warning("%s", err)
        capture, self._capture = self._capture, None
        if capture is not None:
            capture.release()

    def _give_up(self, reason: str) -> None:
        log.error("%s: %s", self.name, reason)
        with self._cond:
            self._failure = Disconnected(reason, device=self.name)
            self._cond.notify_all()
