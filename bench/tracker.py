"""Tracker benchmark: prints one JSON object.

- `tracker`: frames per second of `Tracker.update` alone on raw frames (grey, 8 bit, as a
  machine-vision camera delivers them: decode excluded), on one core (`cv2.setNumThreads(1)` and
  the process pinned to one CPU), at 659 x 494 and 1280 x 1024 with 2, 4 and 8 robots moving, with
  the per-frame p50 / p99 time and the tracking error against the scene's ground truth (mm; the
  robots' radius is `radius_mm`). Next to it, from the same frames in the same run (passes
  interleaved): `floor_fps`, OpenCV's own floor (`cv2.threshold` + `cv2.findContours` on the whole
  picture at the tracker's threshold), and `cost_over_floor`, our mean time per frame over the
  floor's (below 1: cheaper than OpenCV's least pass). `jpeg`: the same with each frame's JPEG
  (quality 85) decoded to grey inside the timing, ours and the floor's.
- `jpeg_decode_ms`: `cv2.imdecode` of one emulated frame (quality 85) to BGR at each resolution,
  one core (what the camera driver's VideoCapture pays per frame).
- `stream`: through the emulated MJPEG camera at 60 fps, read by the camera driver
  (VideoCapture): latency from a frame's stamped capture time to the tracker's result, p50 / p99
  (this part uses every core: the camera is another machine on a rig).
- `command`: closed-loop runs of the example plan on the emulated bench (slip 0.85, spread, noise):
  latency from the capture time of the frame a supervisor decision used to the first command
  after it leaving the stream loop, p50 / p99, for decisions to go on and for re-plans (these
  include the RRT's time); `received_*` the same from the frame's arrival at the camera driver,
  and `opencv_floor` OpenCV's cost per frame of the same camera in the same runs
  (`bench/closed_loop.py`'s figures, which runs 20 seeds and reports the success share).

Run: `.venv/bin/python bench/tracker.py [--seconds S]`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import cv2
import numpy as np

from rigctl.drivers.camera import CameraDriver
from rigctl.emulators.camera import CameraModel, Renderer, Scene, serve_camera
from rigctl.emulators.server import EmulatorServer
from rigctl.plans.workspace import ShapeWorkspace
from rigctl.vision.tracker import Tracker

RADIUS_MM = 5.0
WORKSPACE = ShapeWorkspace(
    ("rect", (0, 0, 400, 400)), [("rect", (150, 170, 100, 40)), ("disk", (300, 300, 25))]
)
RESOLUTIONS = ((659, 494), (1280, 1024))
ROBOT_COUNTS = (2, 4, 8)
FRAMES = 120
STEP_MM = np.array([0.25, 0.15])  # per frame: 15 mm/s and 9 mm/s at 60 fps


def starts(n: int) -> np.ndarray:
    """n robot positions (n, 2) mm, spread over the free floor."""
    grid = np.array([[40.0, 40.0], [120.0, 60.0], [220.0, 50.0], [330.0, 70.0],
                     [50.0, 250.0], [120.0, 320.0], [220.0, 260.0], [200.0, 350.0]])
    return grid[:n]


def decoded_frames(camera: CameraModel, n: int, count: int = FRAMES
                   ) -> tuple[list[np.ndarray], np.ndarray, list[bytes]]:
    """`count` (FRAMES) pictures of n robots moving, through JPEG and back, with the truth
    (count, n, 2)."""
    renderer = Renderer(camera, seed=7)
    path = starts(n)[None] + np.arange(count)[:, None, None] * STEP_MM
    jpegs = []
    for positions in path:
        image = renderer.render(Scene(WORKSPACE, positions, np.full(n, RADIUS_MM)))
        jpegs.append(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 85])[1].tobytes())
    frames = [cv2.imdecode(np.frombuffer(j, np.uint8), cv2.IMREAD_COLOR) for j in jpegs]
    return frames, path, jpegs


def opencv_floor(pictures: list, threshold: float, decode: bool = False) -> list[float]:
    """OpenCV's own cost per picture (s): `cv2.threshold` and `cv2.findContours` (external, simple
    chains) on the whole picture (grey, (H, W) uint8), after `cv2.imdecode` to grey when `decode`
    (the pictures are then JPEG bytes). What the least tracker built on OpenCV pays per frame."""
    durations = []
    for picture in pictures:
        started = time.perf_counter()
        if decode:
            picture = cv2.imdecode(np.frombuffer(picture, np.uint8), cv2.IMREAD_GRAYSCALE)
        _, mask = cv2.threshold(picture, threshold, 255, cv2.THRESH_BINARY_INV)
        cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        durations.append(time.perf_counter() - started)
    return durations


def tracked(calibration, path: np.ndarray, pictures: list, decode: bool = False
            ) -> tuple[list[float], list[np.ndarray], float]:
    """One pass of a fresh tracker over the pictures (grey arrays, or JPEG bytes decoded to grey
    inside the timing when `decode`): seconds per frame after the first (which sets the grey
    levels), the error (n,) mm of each frame against `path`, and the tracker's threshold."""
    def picture(k: int) -> np.ndarray:
        if decode:
            return cv2.imdecode(np.frombuffer(pictures[k], np.uint8), cv2.IMREAD_GRAYSCALE)
        return pictures[k]

    tracker = Tracker(calibration, RADIUS_MM, path[0], roi_mm=WORKSPACE.bounds)
    tracker.update(picture(0))
    durations, errors = [], []
    for k in range(1, len(pictures)):
        started = time.perf_counter()
        robots = tracker.update(picture(k), k / 60.0)
        durations.append(time.perf_counter() - started)
        errors.append(np.linalg.norm(np.array([r.position_mm for r in robots]) - path[k], axis=1))
    return durations, errors, float(tracker.threshold)


def figures(ours: list[float], floor: list[float]) -> dict:
    """frames/s from the mean time, p50 / p99 (ms), the floor's frames/s from the same frames and
    our cost over the floor's (mean time per frame over the floor's: 1 costs what OpenCV alone
    costs, below 1 is cheaper than it); `fps_p50` / `floor_fps_p50` from the median times."""
    d, f = np.array(ours), np.array(floor)
    return {
        "fps": round(1.0 / float(d.mean()), 1),
        "p50_ms": round(1e3 * float(np.percentile(d, 50)), 3),
        "p99_ms": round(1e3 * float(np.percentile(d, 99)), 3),
        "floor_fps": round(1.0 / float(f.mean()), 1),
        "cost_over_floor": round(float(d.mean() / f.mean()), 3),
        # the same from the medians: on a shared machine a few preempted frames move the means
        "fps_p50": round(1.0 / float(np.percentile(d, 50)), 1),
        "floor_fps_p50": round(1.0 / float(np.percentile(f, 50)), 1),
    }


def time_tracker(seconds: float, frames_per_pass: int = FRAMES) -> tuple[dict, dict]:
    """Per resolution and robot count: our tracker on raw grey frames and on their JPEGs, each
    next to OpenCV's floor on the same frames, passes interleaved so both see the same machine."""
    results: dict = {}
    decode: dict = {}
    for width, height in RESOLUTIONS:
        key = f"{width}x{height}"
        camera = CameraModel.overhead(WORKSPACE.bounds, resolution=(width, height), tilt_deg=6)
        calibration = camera.calibration()
        results[key] = {}
        for n in ROBOT_COUNTS:
            frames, path, jpegs = decoded_frames(camera, n, frames_per_pass)
            # raw frames as a machine-vision camera delivers them (mono 8 bit), decode excluded
            raw = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames]
            ours, floor, ours_jpeg, floor_jpeg, errors = [], [], [], [], []
            deadline = time.perf_counter() + seconds
            while time.perf_counter() < deadline or not ours:
                durations, e, threshold = tracked(calibration, path, raw)
                ours += durations
                errors += e
                floor += opencv_floor(raw[1:], threshold)
                ours_jpeg += tracked(calibration, path, jpegs, decode=True)[0]
                floor_jpeg += opencv_floor(jpegs[1:], threshold, decode=True)
            e = np.concatenate(errors)
            results[key][str(n)] = {
                **figures(ours, floor),
                "mean_error_mm": round(float(e.mean()), 4),
                "max_error_mm": round(float(e.max()), 4),
                "jpeg": figures(ours_jpeg, floor_jpeg),
            }
        buffer = np.frombuffer(jpegs[0], np.uint8)
        started = time.perf_counter()
        repeats = 200
        for _ in range(repeats):
            cv2.imdecode(buffer, cv2.IMREAD_COLOR)
        decode[key] = round(1e3 * (time.perf_counter() - started) / repeats, 3)
    return results, decode


def stream_latency(seconds: float) -> dict:
    camera_model = CameraModel.overhead(WORKSPACE.bounds, tilt_deg=6)
    t0 = time.monotonic()
    n = 4

    def scene() -> Scene:
        step = (time.monotonic() - t0) * 60.0
        return Scene(WORKSPACE, starts(n) + step * STEP_MM, np.full(n, RADIUS_MM))

    latencies, skipped = [], 0
    with EmulatorServer() as server:
        camera = serve_camera(server, scene, Renderer(camera_model, seed=3), fps=60.0)
        with CameraDriver(camera.url, stamped=True) as driver:
            first = driver.read()
            tracker = Tracker(camera_model.calibration(), RADIUS_MM,
                              starts(n) + (first.t_source - t0) * 60.0 * STEP_MM,
                              roi_mm=WORKSPACE.bounds)
            previous = first.source_number
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                frame = driver.read()
                tracker.update(frame.image, frame.t_source)
                latencies.append(time.monotonic() - frame.t_source)
                skipped += max(0, frame.source_number - previous - 1)
                previous = frame.source_number
    lat = np.array(latencies)
    return {
        "frames": len(lat),
        "frames_skipped": skipped,
        "capture_to_tracked_p50_ms": round(1e3 * float(np.percentile(lat, 50)), 2),
        "capture_to_tracked_p99_ms": round(1e3 * float(np.percentile(lat, 99)), 2),
    }


def command_latency(runs: int) -> dict:
    """Frame -> corrected command through the whole closed loop (see the docstring)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from closed_loop import (  # the closed-loop bench, same folder
        ROOT,
        frame_to_command,
        one_seed,
        parser,
    )

    args = parser().parse_args(["--no-open-loop"])
    mismatch = ["--slip", "0.85", "--speed-spread", "0.01", "--noise", "0.05", "--drift", "0.005"]
    plan = ROOT / "plans" / "examples" / "fig4-quick.json"
    results = [one_seed(plan, 200 + i, mismatch, args) for i in range(runs)]
    return {"runs": runs, **frame_to_command(results)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=0.5, help="timing per configuration")
    parser.add_argument("--closed-loop-runs", type=int, default=2,
                        help="closed-loop runs for the frame-to-command latency (0: skip)")
    parser.add_argument("--smoke", action="store_true",
                        help="the smallest run of every stage, for the test suite: its figures "
                             "mean nothing")
    args = parser.parse_args()
    # the smoke run: one pass of 10 frames per configuration, half a second of camera stream
    frames_per_pass, stream_s = (10, 0.5) if args.smoke else (FRAMES, max(2.0, 4 * args.seconds))
    if args.smoke:
        args.seconds = 0.0
    cv2.setNumThreads(1)
    every_cpu = os.sched_getaffinity(0)
    one_cpu = {min(every_cpu)}
    os.sched_setaffinity(0, one_cpu)
    try:
        tracker, decode = time_tracker(args.seconds, frames_per_pass)
    finally:
        os.sched_setaffinity(0, every_cpu)
    stream = stream_latency(stream_s)
    command = command_latency(args.closed_loop_runs) if args.closed_loop_runs else None
    print(json.dumps({
        "machine": {"cpu": platform.processor() or platform.machine(), "cpus": len(every_cpu),
                    "opencv": cv2.__version__},
        "radius_mm": RADIUS_MM,
        "one_core": True,
        "tracker": tracker,
        "jpeg_decode_ms": decode,
        "stream": stream,
        "command": command,
    }, indent=2))


if __name__ == "__main__":
    main()
