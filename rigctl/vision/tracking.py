"""The tracking loop: the camera and the tracker in their own thread, publishing the robots'
latest positions. Tracking is *lost* when no fresh frame came for `camera.timeout_s` (a frozen,
dropped or stalled stream) or a robot was not found in `LOST_AFTER_FRAMES` frames in a row
(black-out, occlusion). A camera whose link is gone is reopened every `REOPEN_S` for as long as
tracking runs: the run stays suspended meanwhile, and its own limit ends it. Every camera rig's
run reads it.

`record_to(record)` also writes the tracked positions into the run record (`tracked` events, at
most `hz` a second, from a thread of its own): the stream thread must not pay for a JSON line per
frame, and the report draws the measured paths from them on every camera rig. When the rig's
camera says `record_video` (the default), it also starts the record's video (`rigctl.vision.video`):
the tracking thread offers each fresh frame to it and never waits for it; `stop` closes it and
writes a `video` event with what it wrote and dropped."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rigctl.core.config import CameraSettings
from rigctl.core.errors import ConfigError, DeviceTimeout, Disconnected, RigError
from rigctl.core.priority import favour
from rigctl.core.record import RunRecord
from rigctl.drivers.camera import CameraDriver
from rigctl.vision.tracker import Tracker
from rigctl.vision.video import VideoRecorder

log = logging.getLogger(__name__)

LOST_AFTER_FRAMES = 3  # a robot unseen this many fresh frames in a row: tracking lost
REOPEN_S = 1.0  # a camera whose driver gave up is reopened this often until tracking stops


@dataclass(frozen=True)
class TrackedState:
    """The robots after one fresh frame. positions_mm (n, 2); lost (n,) robot not seen for
    LOST_AFTER_FRAMES frames; t_source: monotonic s the picture was taken (stamp) or received;
    t_tracked: monotonic s the tracker finished; frame: fresh frames tracked before this one;
    t_received: monotonic s the camera driver had the picture (decoded), None if not told."""

    positions_mm: np.ndarray
    lost: np.ndarray
    t_source: float
    t_tracked: float
    frame: int
    t_received: float | None = None


class TrackingLoop:
    """The camera and the tracker in their own thread, publishing the latest `TrackedState`.

    camera: the rig's camera settings (url, stamped, timeout_s, calibration); radii_mm (n,),
    initial_mm (n, 2) where the robots were put; roi_mm: the workspace's bounds; on_floor: where a
    robot's centre can be (`Tracker`).
    """

    def __init__(self, camera: CameraSettings, radii_mm: np.ndarray, initial_mm: np.ndarray, *,
                 roi_mm: tuple[float, float, float, float] | None = None,
                 on_floor: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        if camera.calibration is None:
            raise ConfigError("the rig's camera has no calibration: run `rigctl calibrate camera`")
        self.camera = camera
        self.tracker = Tracker(camera.calibration, radii_mm, initial_mm, roi_mm=roi_mm,
                               on_floor=on_floor)
        self.timeout_s = camera.timeout_s
        self.frames = 0  # fresh frames tracked
        self.lost_frames = 0  # frames missed (dropped, repeated) or with a robot not found
        self.failure: RigError | None = None
        self._cond = threading.Condition()
        self._latest: TrackedState | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._driver: CameraDriver | None = None
        self._record: RunRecord | None = None
        self._record_period_s = 0.1
        self._recorder: threading.Thread | None = None
        self._tap: Callable[[np.ndarray, TrackedState], None] | None = None
        self.video: VideoRecorder | None = None

    def tap(self, on_frame: Callable[[np.ndarray, TrackedState], None] | None) -> None:
        """From now on, hand every fresh frame's image (h, w[, 3] uint8) and what the tracker made
        of it to `on_frame`, on the tracking thread: it must return at once (the daemon's
        console keeps the latest and encodes it on a thread of its own). None: no tap."""
        self._tap = on_frame

    def record_to(self, record: RunRecord, hz: float = 10.0) -> None:
        """From now on, write the tracked positions into `record` (a `RunRecord`) as `tracked`
        events: `{"event": "tracked", "positions_mm": [[x, y], ...], "lost": [bool, ...],
        "frame": n, "t_frame_s": s}`, at most `hz` a second and only for a fresh frame;
        `t_frame_s` is when the picture was taken, on the record's clock. Before or after
        `start`; `stop` ends it. Called again, it writes to the new record. With the camera's
        `record_video`, the frames go into the record's video too (`VideoRecorder`)."""
        if hz <= 0:
            raise ConfigError(f"tracked events need a positive rate, got {hz:g} Hz")
        video = VideoRecorder(record, self.camera.video_fps) if self.camera.record_video else None
        with self._cond:
            self._record = record
            self._record_period_s = 1.0 / hz
            old, self.video = self.video, video
        self._close_video(old)
        if self._recorder is None:
            self._recorder = threading.Thread(target=self._record_run, name="tracking-record",
                                              daemon=True)
            self._recorder.start()

    def _record_run(self) -> None:
        # Its own thread, not the tracker's: a slow disk must not delay the next frame, and the
        # stream thread never sees any of it.
        last_frame: int | None = None
        last_written = -float("inf")
        while not self._stop.is_set():
            with self._cond:
                record, period = self._record, self._record_period_s
                state = self._latest
                if (state is None or record is None or state.frame == last_frame
                        or self.failure is not None):
                    self._cond.wait(0.1)  # woken by the next frame (or stop)
                    continue
            wait = last_written + period - time.monotonic()
            if wait > 0:
                self._stop.wait(wait)  # not more than hz a second: take the newest frame then
                continue
            last_frame, last_written = state.frame, time.monotonic()
            try:
                record.event("tracked", positions_mm=np.round(state.positions_mm, 4).tolist(),
                             lost=[bool(x) for x in state.lost], frame=int(state.frame),
                             t_frame_s=round(state.t_source - record.t0, 4))
            except Exception:  # a record closed under us: the run is over, tracking goes on
                log.debug("tracked event not written", exc_info=True)

    def start(self, acquire_timeout_s: float = 5.0) -> TrackedState:
        """Open the camera, start tracking, and return the first state with every robot seen;
        DeviceTimeout if that does not come within `acquire_timeout_s`."""
        self._driver = CameraDriver(self.camera.url, stamped=self.camera.stamped,
                                    timeout_s=self.camera.timeout_s,
                                    reconnect_attempts=self.camera.reconnect_attempts).open()
        self._thread = threading.Thread(target=self._run, name="tracking", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + acquire_timeout_s
        with self._cond:
            while True:
                state = self._latest
                if state is not None and not state.lost.any() and not (
                        self.tracker.frames_unseen > 0).any():
                    return state
                if self.failure is not None:
                    raise self.failure
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"the robots were not found within {acquire_timeout_s:g} s",
                                        device="camera")
                self._cond.wait(remaining)

    def stop(self) -> None:
        """Stop tracking and close the camera; again, nothing more."""
        if self._stop.is_set():
            return
        self._stop.set()
        with self._cond:
            self._cond.notify_all()  # the recorder waits on it
        if self._thread is not None:
            self._thread.join(self.timeout_s + 2.0)
        if self._recorder is not None:
            self._recorder.join(2.0)
        if self._driver is not None:
            self._driver.close()
        with self._cond:
            video, self.video = self.video, None
        self._close_video(video)

    def _close_video(self, video: VideoRecorder | None) -> None:
        """Write what `video` has queued, close it, and say in its record what it wrote."""
        if video is None:
            return
        video.close()
        log.info("video: %d frames in %s, %d dropped (queue full)", video.written, video.path,
                 video.dropped)
        try:
            video.record.event("video", **video.counts())
        except Exception:  # a record closed under us: the file and its series are there
            log.debug("video event not written", exc_info=True)

    def latest(self) -> TrackedState | None:
        with self._cond:
            return self._latest

    def ok(self, now: float | None = None) -> bool:
        """Tracking holds: a fresh frame within `timeout_s` and every robot found."""
        state = self.latest()
        now = time.monotonic() if now is None else now
        return (self.failure is None and state is not None and not state.lost.any()
                and now - state.t_tracked <= self.timeout_s)

    def why_lost(self, now: float | None = None, agent: str = "robot") -> str:
        """What is wrong while `ok` is False, naming the camera or the agents it does not see."""
        state = self.latest()
        now = time.monotonic() if now is None else now
        if self.failure is not None:
            return f"camera: {self.failure}"
        if state is not None and state.lost.any():
            return f"camera: {agent}(s) {np.flatnonzero(state.lost).tolist()} not found"
        return f"camera: no fresh frame for {self.timeout_s:g} s"

    def wait(self, timeout_s: float) -> None:
        """Block until the next fresh frame is tracked or `timeout_s` passes."""
        with self._cond:
            self._cond.wait(timeout_s)

    def captured_after(self, t_s: float, timeout_s: float) -> TrackedState | None:
        """The first state from a picture taken after monotonic `t_s`, waiting up to `timeout_s`;
        None if none comes or tracking is lost meanwhile."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                state = self._latest
                if state is not None and state.t_source > t_s and not state.lost.any():
                    return state
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self.failure is not None:
                    return None
                self._cond.wait(remaining)

    def _reopen(self, driver: CameraDriver) -> CameraDriver | None:
        """A new driver on the same camera once it opens; None if tracking stops first."""
        driver.close()
        while not self._stop.wait(REOPEN_S):
            with self._cond:
                self._cond.notify_all()  # waiters re-check staleness
            fresh = CameraDriver(self.camera.url, stamped=self.camera.stamped,
                                 timeout_s=self.camera.timeout_s,
                                 reconnect_attempts=self.camera.reconnect_attempts)
            try:
                fresh.open()
            except Disconnected:
                continue
            log.warning("tracking: the camera is back")
            self._driver = fresh
            return fresh
        return None

    def _run(self) -> None:
        favour("tracking thread")  # the closed loop waits for its frames
        driver = self._driver
        assert driver is not None
        last_t: float | None = None
        last_number: int | None = None
        while not self._stop.is_set():
            try:
                frame = driver.read(timeout_s=min(0.1, self.timeout_s))
            except DeviceTimeout:
                with self._cond:
                    self._cond.notify_all()  # waiters re-check staleness
                continue
            except Disconnected as err:
                # the driver spent its quick reconnections: tracking is lost (the run suspends,
                # and ends once suspended for its limit) and the camera is reopened every second
                log.error("tracking: %s; reopening the camera every %g s", err, REOPEN_S)
                driver = self._reopen(driver)
                if driver is None:
                    return
                continue
            except RigError as err:
                log.error("tracking: %s", err)
                with self._cond:
                    self.failure = err
                    self._cond.notify_all()
                return
            t = frame.t_source if frame.t_source is not None else frame.t_capture
            if frame.repeated or (last_t is not None and t <= last_t):
                self.lost_frames += 1
                continue
            if frame.source_number is not None and last_number is not None:
                self.lost_frames += max(0, frame.source_number - last_number - 1)
            last_t, last_number = t, frame.source_number
            robots = self.tracker.update(frame.image, t)
            unseen = np.array([r.frames_unseen for r in robots])
            if (unseen > 0).any():
                self.lost_frames += 1
            state = TrackedState(
                positions_mm=np.array([r.position_mm for r in robots]),
                lost=unseen >= LOST_AFTER_FRAMES,
                t_source=t, t_tracked=time.monotonic(), frame=self.frames,
                t_received=frame.t_capture)
            with self._cond:
                self.frames += 1
                self._latest = state
                self._cond.notify_all()
                video, record = self.video, self._record
            if video is not None and record is not None:  # a time check and a put_nowait: never waits for the disk
                video.offer(frame.image, t - record.t0, state.frame)
            if self._tap is not None:
                self._tap(frame.image, state)


