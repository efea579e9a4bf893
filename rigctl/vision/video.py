"""Video in the run record: the frames the tracker read, as `video.avi` in the record, and each
frame's time on the record's clock in the side series `series/video.csv` (`RunRecord.open_series`:
`frame` its index in the video, `t_s` when the picture was taken, s since the run started,
`camera_frame` the tracker's count of fresh frames, as in the `tracked` events).

Why MJPEG in AVI, written by OpenCV: a record must stay readable after a crash (`rigctl.core.record`),
and an MP4 is not: its index (the `moov` box) is written when the file is closed, so a process
killed mid-run leaves a file no player opens (measured: 44 bytes after 100 frames). An AVI of
JPEG pictures is read without its index by every player (VLC, mpv, ffplay, OpenCV), so a crash
loses only the last unflushed frames. OpenCV writes it with no dependency rigctl does not already
have; its wheels have no H.264 encoder (x264 is GPL, opencv-python ships an LGPL FFmpeg), and PyAV,
which has one, is a wheel of tens of MB more. The camera on the wire is MJPEG already, so nothing
is lost that was there. `rigctl report RUN --video` makes the MP4 a paper or a browser wants.

Never late: the tracking thread only `offer`s a frame, which is a time comparison and a
`put_nowait` on a bounded queue; a full queue drops the frame and counts it (`dropped`), never
waits. A thread (`video-pipe`) hands each queued frame, raw, to a process of its own
(`python -m rigctl.vision.video`) that encodes and writes the file at `WRITER_NICE` steps nicer
than the run: the encoder shares no interpreter lock with the stream thread, and on a loaded
machine it gets the CPU the stream and the tracker leave (a writer thread in the run's process,
even one made nicer, left the stream's period-error p99 1.26 and 1.32 times that of runs without
video, where two sets of runs without it differed by 1.17; `bench/video.py` at load 5-6). When
that is too little the pipe fills, the thread waits on it (without the lock) and the queue drops
frames. The child ends when the pipe closes, also when the run's process dies, and closes its
file first.

Rate: a camera faster than the video needs (the emulated one sends 60 frames/s) is subsampled on a
grid of 1/`fps_max`: a frame is taken when its time reaches the next due time (less a quarter
period, for the camera's jitter), so the video keeps
`fps_max` frames a second on average, and every frame of a slower camera. The file's nominal rate
is `fps_max`; the series has the truth (a gap there is a frame the camera or the queue dropped).
"""

from __future__ import annotations

import logging
import os
import queue
import struct
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import cv2
import numpy as np

from rigctl.core.children import end_child

log = logging.getLogger(__name__)

VIDEO_FILE = "video.avi"
VIDEO_SERIES = "video"  # series/video.csv
FOURCC = "MJPG"
QUEUE_FRAMES = 8  # at 20 frames/s, 0.4 s of encoder stall before frames are dropped
WRITER_NICE = 10  # the writer process's nice above the run's


class VideoRecorder:
    """Frames into `record`'s `video.avi`, at most `fps_max` a second, by a writer process.

    `offer(image, t_s, camera_frame)` is for the tracking thread and returns at once; `close()`
    writes what is queued and closes the file. `written`, `dropped` (taken but the queue was full)
    and `skipped` (over the rate) count frames; `failure` says why nothing could be written."""

    def __init__(self, record, fps_max: float = 20.0, *, queue_frames: int = QUEUE_FRAMES) -> None:
        if fps_max <= 0:
            raise ValueError(f"a video needs a positive frame rate, got {fps_max:g}")
        self.record = record
        self.path: Path = record.path / VIDEO_FILE
        self.fps = float(fps_max)
        self._period_s = 1.0 / self.fps
        self._series = record.open_series(
            VIDEO_SERIES, ["frame", "t_s", "camera_frame"],
            {"frame": "index in video.avi", "t_s": "s since the run started (picture taken)",
             "camera_frame": "fresh frames the tracker read before it"})
        self.written = 0
        self.dropped = 0
        self.skipped = 0
        self.failure: str | None = None
        self._due_s = -np.inf
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, queue_frames))
        self._closed = False
        # started now, before the run streams: its imports take a few hundred ms of CPU. Its
        # messages (FFmpeg's among them) go to a file, read if it fails: a pipe nobody reads
        # during the run would stop it once full
        self._stderr = tempfile.TemporaryFile()
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "rigctl.vision.video", str(self.path), repr(self.fps)],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._stderr,
            process_group=0)  # a terminal's Ctrl-C is the run's; the pipe closing ends it. The
        # run's session (not one of its own): its niceness then ranks it behind the run's threads
        self._writer = threading.Thread(target=self._pipe, name="video-pipe", daemon=True)
        self._writer.start()

    def offer(self, image: np.ndarray, t_s: float, camera_frame: int) -> bool:
        """Take the frame `image` ((h, w, 3) BGR or (h, w) uint8, not changed afterwards) taken at
        `t_s` on the record's clock if it is due; True if it was queued. Never blocks."""
        # a quarter period early still counts: a camera whose frames fall on the grid (60 on 20
        # frames/s) would otherwise take the frame after, or not, by its jitter
        if self._closed or self.failure is not None or t_s < self._due_s - 0.25 * self._period_s:
            self.skipped += 1
            return False
        # on the grid while the camera keeps up; after a gap, the grid starts again from here
        next_due = self._due_s + self._period_s
        self._due_s = next_due if next_due > t_s else t_s + self._period_s
        try:
            self._queue.put_nowait((image, t_s, camera_frame))
        except queue.Full:
            self.dropped += 1
            return False
        return True

    def close(self, timeout_s: float = 15.0) -> None:
        """Write the frames still queued and close the file; again, nothing more."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)  # the writer empties the queue, so this waits at most a few frames
        self._writer.join(timeout_s)
        if self._writer.is_alive():
            log.error("video: the writer did not finish within %g s; %s may lack its last frames",
                      timeout_s, self.path)

    def _pipe(self) -> None:
        """Hand the queued frames to the writer process; runs until `close` queues None."""
        proc = self._proc
        assert proc.stdin is not None  # started with stdin=PIPE
        try:
            while (item := self._queue.get()) is not None:
                if self.failure is not None:  # the writer is gone: drain, the offers stop
                    self.dropped += 1
                    continue
                image, t_s, camera_frame = item
                if image.ndim == 2:
                    image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
                image = np.ascontiguousarray(image, dtype=np.uint8)
                try:
                    proc.stdin.write(struct.pack(HEADER, image.shape[0], image.shape[1]))
                    proc.stdin.write(image.data.cast("B"))
                except (BrokenPipeError, OSError) as err:
                    self.failure = f"the video writer process ended ({err})"
                    log.error("video: %s; the run goes on without video", self.failure)
                    self.dropped += 1
                    continue
                self._series.row((self.written, t_s, camera_frame))
                self.written += 1
        except Exception as err:  # the run goes on without its video; say so once
            self.failure = f"handing frames to the video writer failed: {err}"
            log.exception("video: %s", self.failure)
        finally:
            self._finish(proc)
            self._series.close()

    def _finish(self, proc: subprocess.Popen) -> None:
        try:  # closes the pipe: the child writes what it has, closes the file and ends
            if proc.stdin is not None:
                proc.stdin.close()
        except OSError:  # it had ended already (the failure is said)
            pass
        try:
            proc.wait(10.0)
        except subprocess.TimeoutExpired:
            end_child(proc, timeout_s=2.0)
            self.failure = self.failure or "the video writer did not finish within 10 s"
        if proc.returncode not in (0, None):  # its own last words say more than a broken pipe
            self._stderr.seek(0)
            lines = self._stderr.read().decode(errors="replace").strip().splitlines()
            said = lines[-1] if lines else f"exit status {proc.returncode}"
            self.failure = f"the video writer failed: {said}"
            log.error("video: %s", self.failure)
        self._stderr.close()

    def counts(self) -> dict:
        """What the recorder did, for the run's events: file, rate, frames written and lost."""
        return {"file": self.path.name, "fps": self.fps, "written": self.written,
                "dropped": self.dropped, "failure": self.failure}


# -- the writer process ---------------------------------------------------------------------------

HEADER = "<II"  # each frame on the pipe: height, width (px), then height * width * 3 bytes BGR


def write_video(path: str, fps: float, source=None) -> int:
    """Read frames from `source` (the pipe) and write them to `path` until it ends; returns the
    frames written, and writes no file when none came. The first frame sets the video's size.
    JPEG's 4:2:0 chroma wants even sides: FFmpeg would cut the last column of the 659 px wide
    camera, so the picture is padded instead (a pixel of the video stays the camera's pixel, for
    the calibration)."""
    source = source if source is not None else sys.stdin.buffer
    writer: cv2.VideoWriter | None = None
    written = 0
    header_size = struct.calcsize(HEADER)
    try:
        while len(header := source.read(header_size)) == header_size:
            h, w = struct.unpack(HEADER, header)
            data = source.read(h * w * 3)
            if len(data) != h * w * 3:
                break  # the run's process died mid-frame: keep what came whole
            image: np.ndarray = np.frombuffer(data, np.uint8).reshape(h, w, 3)
            if writer is None:
                size = (w + w % 2, h + h % 2)
                # through OpenCV's FFmpeg: 18 kB and 2.3 ms of CPU a 659 x 494 frame of the
                # emulated camera, where OpenCV's own MJPEG writer took 88 kB and 5.1 ms
                writer = cv2.VideoWriter(path, cv2.CAP_FFMPEG, cv2.VideoWriter.fourcc(*FOURCC),
                                         fps, size)
                if not writer.isOpened():
                    raise SystemExit(f"OpenCV cannot write {path} ({FOURCC}, {size[0]}x{size[1]})")
            if w > size[0] or h > size[1]:  # a camera reopened larger
                image = image[:size[1], :size[0]]
            if image.shape[:2] != (size[1], size[0]):
                image = cv2.copyMakeBorder(image, 0, size[1] - image.shape[0], 0,
                                           size[0] - image.shape[1], cv2.BORDER_REPLICATE)
            writer.write(image)
            written += 1
    finally:
        if writer is not None:
            writer.release()
    return written


if __name__ == "__main__":
    if hasattr(os, "nice"):
        os.nice(WRITER_NICE)
    cv2.setNumThreads(1)  # one core's worth at most, whatever the machine
    print(write_video(sys.argv[1], float(sys.argv[2])))
