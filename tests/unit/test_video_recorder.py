"""The record's video (`rigctl.vision.video.VideoRecorder`): a camera faster than the video is
subsampled to the video's rate and a slower one keeps every frame, a writer that cannot keep up
makes `offer` drop and count frames instead of waiting, what is written is a file OpenCV opens
with each frame's time in the record's series, and a run's process killed mid-run loses none of
the frames it handed over (the writer process closes the file when its pipe ends)."""

from pathlib import Path

import cv2
import numpy as np

from rigctl.core.record import RunRecord, read_series
from rigctl.vision.video import VIDEO_FILE, VideoRecorder

W, H = 160, 120


def picture(k: int) -> np.ndarray:
    """Frame k: a white disc whose x is 10 + 2k px on grey, so a frame read back says which it is."""
    image = np.full((H, W, 3), 60, np.uint8)
    cv2.circle(image, (10 + 2 * k, 60), 6, (255, 255, 255), -1)
    return image


def read_back(path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, image = capture.read()
        if not ok:
            return frames
        frames.append(image)


def test_a_60_fps_camera_is_taken_at_20_fps_on_the_records_clock(tmp_path):
    record = RunRecord(tmp_path, "video")
    video = VideoRecorder(record, fps_max=20.0, queue_frames=64)  # room for all: no drops
    times = 0.5 + np.arange(60) / 60.0  # one second of a 60 frames/s camera
    queued = []
    for k, t in enumerate(times):
        if video.offer(picture(k), float(t), k):
            queued.append(k)
    video.close()
    record.close()
    # every third frame: 0, 3, 6, ... (the grid of 1/20 s from the first one)
    assert queued == list(range(0, 60, 3))
    assert video.written == 20 and video.dropped == 0 and video.skipped == 40
    series = read_series(record.path, "video")
    np.testing.assert_array_equal(series["frame"], np.arange(20))
    np.testing.assert_array_equal(series["camera_frame"], queued)
    np.testing.assert_allclose(series["t_s"], times[queued], atol=1e-6)
    frames = read_back(record.path / VIDEO_FILE)
    assert len(frames) == 20 and frames[0].shape == (H, W, 3)
    for frame, k in zip(frames, queued):  # the disc where frame k had it
        row = frame[60, :, 1].astype(int)
        assert abs(int(np.argmax(row > 150)) - (10 + 2 * k - 6)) <= 2


def test_a_slower_camera_keeps_every_frame(tmp_path):
    record = RunRecord(tmp_path, "video")
    video = VideoRecorder(record, fps_max=20.0, queue_frames=64)
    for k in range(30):  # 12 frames/s, with a gap of a second after frame 9
        t = k / 12.0 + (1.0 if k >= 10 else 0.0)
        assert video.offer(picture(k), t, k)
    video.close()
    record.close()
    assert video.written == 30 and video.skipped == 0
    assert len(read_back(record.path / VIDEO_FILE)) == 30


def test_a_writer_that_cannot_keep_up_costs_dropped_frames_not_waiting(tmp_path):
    """1000 due frames offered at once (far faster than any encoder): the queue of 4 fills, the
    rest are dropped and counted, and every frame is either written or counted as dropped."""
    record = RunRecord(tmp_path, "video")
    video = VideoRecorder(record, fps_max=20.0, queue_frames=4)
    image = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    queued = sum(video.offer(image, k / 20.0, k) for k in range(1000))
    video.close()
    record.close()
    assert video.dropped > 900
    assert queued == video.written and video.written + video.dropped == 1000
    assert len(read_series(record.path, "video")["t_s"]) == video.written
    assert len(read_back(record.path / VIDEO_FILE)) == video.written


def test_report_video_of_a_record_without_video_draws_the_scene(tmp_path):
    """A record with a plan and `tracked` events but no video (video off, an older record): the
    MP4 is 1280x720, one frame per 1/20 s of its tracked span, and the agent drawn where the
    tracker had it moves right as it did (its disc's pixels gone from the left, new on the right)."""
    import json

    from rigctl.apps.report_video import COLOURS, render_video

    plan = {"schema": "rigctl.plan/1", "kind": "global-moves", "rig": "six-coil", "name": "slide",
            "workspace": {"boundary": {"rect": [0.0, 0.0, 400.0, 400.0]}, "obstacles": []},
            "agents": [{"start": [80.0, 300.0], "goal": [280.0, 300.0], "radius": 8.0},
                       {"start": [80.0, 100.0], "goal": [80.0, 100.0], "radius": 8.0}],
            "moves": [[200.0, 0.0]], "expected": [[[280.0, 300.0], [80.0, 100.0]]],
            "tolerance_mm": 1.0, "min_separation_mm": 0.0}
    record = RunRecord(tmp_path, "slide")
    record.write_file("plan.json", json.dumps(plan))
    times = 0.5 + np.arange(11) / 10.0  # 10 tracked events a second over 1 s
    for k, t in enumerate(times):
        x = 80.0 + 200.0 * (t - times[0])
        record.event("tracked", positions_mm=[[x, 300.0], [80.0, 100.0]], lost=[False, False],
                     frame=3 * k, t_frame_s=float(t))
    record.close()
    out = tmp_path / "slide.mp4"
    rendered = render_video(record.path, out)
    assert rendered.scene == "drawn"
    frames = read_back(out)
    assert len(frames) == int(np.floor(1.0 * 20)) + 1 == rendered.frames
    assert frames[0].shape == (720, 1280, 3)
    blue = np.array(COLOURS[0], dtype=int)

    def agent_0(frame):
        return (np.abs(frame[40:550, :720].astype(int) - blue).sum(axis=2) < 60)

    first, last = agent_0(frames[0]), agent_0(frames[-1])
    gone_x = np.flatnonzero((first & ~last).any(axis=0)).mean()
    new_x = np.flatnonzero((last & ~first).any(axis=0)).mean()
    assert new_x > gone_x + 50, (gone_x, new_x)


def test_a_writer_that_cannot_write_says_why_and_the_offers_go_on(tmp_path):
    """video.avi cannot be made (a folder of that name is in the way): the recorder says why in the
    writer's own words, and offering frames neither blocks nor raises."""
    record = RunRecord(tmp_path, "video")
    (record.path / VIDEO_FILE).mkdir()
    video = VideoRecorder(record, fps_max=20.0)
    for k in range(40):
        video.offer(picture(k % 20), k / 20.0, k)
    video.close()
    record.close()
    assert video.failure is not None and "cannot write" in video.failure, video.failure
    # every offer answered: handed over (into the pipe's buffer before the writer ended), dropped
    # or skipped (once the failure was known)
    assert video.written + video.dropped + video.skipped == 40 and video.written < 40


CRASHING_RUN = """
import os, sys
import numpy as np
from rigctl.apps.testing import wait_for
from rigctl.core.record import RunRecord
from rigctl.vision.video import VideoRecorder

record = RunRecord(sys.argv[1], "crash")
video = VideoRecorder(record, fps_max=20.0, queue_frames=64)
for k in range(12):
    video.offer(np.full((120, 160, 3), 20 * k, np.uint8), k / 20.0, k)
wait_for(lambda: video.written == 12, 30.0, "the frames handed to the writer")
print(record.path, video._proc.pid, flush=True)
os.kill(os.getpid(), 9)  # the run's process dies without closing anything
"""


def test_a_run_killed_mid_run_leaves_every_frame_it_handed_over(tmp_path):
    """The run's process is SIGKILLed with the video open: the writer process reads to the end of
    its pipe, closes the file and ends, and the record holds a video of all 12 frames (each its
    own grey) and their times."""
    import os
    import subprocess
    import sys

    from rigctl.apps.testing import wait_for

    done = subprocess.run([sys.executable, "-c", CRASHING_RUN, str(tmp_path)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == -9, done.stderr[-2000:]
    path, pid = done.stdout.split()

    def writer_gone() -> bool:
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            return True
        return Path(f"/proc/{pid}/status").is_file() and "zombie" in Path(
            f"/proc/{pid}/status").read_text()

    wait_for(writer_gone, 30.0, "the writer process to end")
    frames = read_back(Path(path) / VIDEO_FILE)
    assert len(frames) == 12
    greys = [int(np.median(f)) for f in frames]
    assert all(abs(g - 20 * k) <= 3 for k, g in enumerate(greys)), greys
    np.testing.assert_allclose(read_series(path, "video")["t_s"], np.arange(12) / 20.0)
