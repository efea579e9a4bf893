"""Video in every record of a camera rig (issue 39, item 3), on the emulated six-coil bench (its
own process, the camera over MJPEG): a closed-loop run of three turns leaves `video.avi` in its
record, which OpenCV opens, at 15 frames/s or more over the run, each frame's time within the run
and each frame the picture the tracker read then (the magnets where the tracker had them in the
same camera frame); `rigctl report RUN --video` renders it at 1280x720, one frame per 1/20 s of the
run. `[camera] record_video = false` leaves no video. One run is shared by the module's tests."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from rigctl.apps.cli.main import main as rigctl
from rigctl.core.camera_model import Calibration
from rigctl.core.config import load_rig
from rigctl.core.record import read_events, read_series
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import parse_plan
from rigctl.rigs.six_coil.global_moves import execute_plan

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
TURNS_MM = 30.0  # three whole turns of the bench's magnets (10 mm a turn)


def three_turns_down():
    """fig4-quick's workspace and magnets, one roll of three turns towards -y (nothing in the way)."""
    plan = json.loads((EXAMPLES / "fig4-quick.json").read_text())
    goals = [[a["start"][0], a["start"][1] - TURNS_MM] for a in plan["agents"]]
    for agent, goal in zip(plan["agents"], goals):
        agent["goal"] = goal
    plan.update(name="three turns down", moves=[[0.0, -TURNS_MM]], expected=[goals])
    return parse_plan(plan)


def fast(rig, **camera):
    """4 turns/s, a watchdog that tolerates a loaded machine, and `camera` settings."""
    return rig.model_copy(update={
        "field": rig.field.model_copy(update={"rolling_turns_per_s": 4.0,
                                              "steering_deg_per_s": 360.0}),
        "stream": rig.stream.model_copy(update={"reply_timeout_s": 1.0}),
        "camera": rig.camera.model_copy(update=camera),
    })


def frames_of(path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    assert capture.isOpened(), path
    frames = []
    while True:
        ok, image = capture.read()
        if not ok:
            capture.release()
            return frames
        frames.append(image)


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    folder = tmp_path_factory.mktemp("video-bench")
    with EmulatedBenchProcess("six-coil", folder / "bench.toml") as rig_path:
        yield load_rig(rig_path), folder


@pytest.fixture(scope="module")
def recorded(bench):
    rig, folder = bench
    assert rig.camera.record_video  # on by default for a camera rig
    summary = execute_plan(three_turns_down(), fast(rig), runs_dir=folder / "runs",
                           progress_out=None, closed_loop=True)
    assert not summary.faults, summary.faults
    return Path(summary.run), rig


def test_the_record_holds_the_video_the_tracker_read(recorded):
    run, rig = recorded
    frames = frames_of(run / "video.avi")
    times = read_series(run, "video")
    assert len(frames) == len(times["t_s"]) > 0
    w, h = rig.camera.resolution or (659, 494)
    assert frames[0].shape == (h + h % 2, w + w % 2, 3)  # padded to even sides (JPEG 4:2:0)
    events = read_events(run)
    t_end = events[-1]["t"]  # the run's last event ("done"), on the record's clock
    t = np.asarray(times["t_s"])
    assert (np.diff(t) > 0).all() and t[0] >= 0.0 and t[-1] <= t_end
    # >= 15 frames/s over the run: from when the camera found the robots to when the field was off
    tracking = next(e["t"] for e in events if e["event"] == "tracking")
    stopping = next(e["t"] for e in events if e["event"] == "stopping")
    inside = ((t >= tracking) & (t <= stopping)).sum()
    assert inside / (stopping - tracking) >= 15.0, (inside, tracking, stopping)
    video = next(e for e in events if e["event"] == "video")
    assert video["written"] == len(frames) and video["failure"] is None

    # each frame is the picture the tracker read: where a tracked event is of the same camera
    # frame, both magnets are at the pixels the calibration puts its positions at (dark discs on
    # the light floor: darker there than the floor 3 radii beside them)
    calibration = Calibration.model_validate(rig.camera.calibration.model_dump())
    by_camera_frame = {int(c): k for k, c in enumerate(times["camera_frame"])}
    same = [e for e in events if e["event"] == "tracked" and e["frame"] in by_camera_frame]
    assert len(same) >= 1  # tracked events come 10 a second: some of them share a video frame
    for e in same:
        k = by_camera_frame[e["frame"]]
        assert abs(t[k] - e["t_frame_s"]) < 1e-3  # the same picture, the same time
        grey = cv2.cvtColor(frames[k], cv2.COLOR_BGR2GRAY).astype(float)
        for position in np.asarray(e["positions_mm"]):
            at = calibration.to_px(position[None])[0]
            beside = calibration.to_px(position[None] + [[24.0, 0.0]])[0]

            def patch(px):
                u, v = np.round(px).astype(int)
                return grey[v - 2:v + 3, u - 2:u + 3].mean()

            assert patch(at) < patch(beside) - 30, (e["frame"], position, patch(at), patch(beside))


def test_report_video_renders_the_run_at_1280x720(recorded, tmp_path, capsys):
    run, _ = recorded
    out = tmp_path / "paper.mp4"
    assert rigctl(["report", str(run), "--video", str(out)]) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed and "the record's video" in printed
    frames = frames_of(out)
    assert frames[0].shape == (720, 1280, 3)
    # one frame per 1/20 s from the first picture to the end of the stream
    t_video = read_series(run, "video")["t_s"]
    t_stream = np.loadtxt(run / "stream.csv", delimiter=",", skiprows=1, usecols=0)
    span = max(t_video[-1], t_stream[-1]) - min(t_video[0], t_stream[0])
    assert len(frames) == int(np.floor(span * 20.0)) + 1
    # the strip's cursor (a black line across the strip's plot, between its frame's left and
    # right edges at x 83 and 1101 px) moves right with the time
    def cursor(frame):
        dark = (frame[600:660] < 50).all(axis=2).sum(axis=0)  # dark pixels in each column
        columns = np.flatnonzero(dark >= 50)
        return float(np.mean(columns[(columns > 90) & (columns < 1095)]))

    inner = frames[len(frames) // 10: -len(frames) // 10: 8]
    cursor = [cursor(f) for f in inner]
    assert all(b > a for a, b in zip(cursor, cursor[1:])), cursor


def test_record_video_false_leaves_no_video(bench):
    rig, folder = bench
    summary = execute_plan(three_turns_down(), fast(rig, record_video=False),
                           runs_dir=folder / "off", progress_out=None, closed_loop=True)
    assert not summary.faults, summary.faults
    run = Path(summary.run)
    assert not (run / "video.avi").exists() and read_series(run, "video") is None
    assert any(e["event"] == "tracked" for e in read_events(run))  # tracking itself went on
