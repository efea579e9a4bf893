"""Run viewer benchmark: how long the viewer takes to open a long record and to seek in it, in
headless Chromium. Prints one JSON object.

A record of `--minutes` (default 10) is synthesised with the record writer's own API
(`RunRecord`: six supply channels at `--rate` Hz, `tracked` events at 10 Hz, moves; its video
through `VideoRecorder`, the recorder a run uses, at `--fps` 15 frames/s, each picture the floor
with both agents and its frame number). The record's clock is set before each write so that a
10-minute record is written in well under 10 minutes (`RunRecord.t0`: what it stamps is
`monotonic() - t0`). Beside it, the floor: the same record of `--floor-seconds` (10 s).

`read_s`: the server's first read of the record, timed here (its modules imported before). `rigctl
view RUN --no-browser` serves each (its own process, as a user runs it: `view_start_s` from its
start to its URL, which it prints once it has read the record, its readers' imports included);
Chromium opens the page and the script waits for the page to be ready with its first frame shown
(`open_s`: from `get` to then; `open_warm_s`: the page opened again). Then `--seeks` seeks to
seeded random instants (`seek_ms`: from `rigctlViewer.seek(t)` in the page to the frame nearest t
decoded and shown, measured in the page on its clock). The floor's figures are measured the same
way in the same run, and the ratios long / floor say what the record's length costs. The issue's
figure: a 10-minute record opens and seeks in under 1 s.

Run: `.venv/bin/python bench/viewer.py [--minutes 10] [--fps 15] [--seeks 20]`; `--smoke`: a
20-second record, 3 seeks.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from rigctl.core.channels import symmetric
from rigctl.core.record import RunRecord
from rigctl.vision.video import VideoRecorder

CHROMIUM = Path(os.environ.get("RIGCTL_CHROMIUM", "/usr/bin/chromium"))
CHROMEDRIVER = Path(os.environ.get("RIGCTL_CHROMEDRIVER", "/usr/bin/chromedriver"))
SIZE = (640, 480)  # px of the synthetic camera
PX_PER_MM = 2.0
# the synthetic camera looks straight down: x mm = u / 2, y mm = (480 - v) / 2
RIG_TOML = f"""[rig]
name = "synthetic viewer bench"
kind = "six-coil"

[camera]
resolution = [{SIZE[0]}, {SIZE[1]}]

[camera.calibration]
homography_px_to_mm = [[{1 / PX_PER_MM}, 0.0, 0.0], [0.0, {-1 / PX_PER_MM}, {SIZE[1] / PX_PER_MM}], [0.0, 0.0, 1.0]]
resolution = [{SIZE[0]}, {SIZE[1]}]
"""
COILS = ["x+", "x-", "y+", "y-", "z+", "z-"]
MOVES = 12
CENTRE_MM = np.array([160.0, 120.0])


def positions_mm(t_s: float, duration_s: float) -> np.ndarray:
    """Both agents at t (2, 2) mm: round a circle of 60 mm, half a turn apart, once a minute."""
    angle = 2 * np.pi * t_s / 60.0 + np.array([0.0, np.pi])
    return CENTRE_MM + 60.0 * np.column_stack([np.cos(angle), np.sin(angle)])


def picture(frame: int, t_s: float, duration_s: float) -> np.ndarray:
    image = np.full((SIZE[1], SIZE[0], 3), (170, 185, 190), np.uint8)
    for x, y in positions_mm(t_s, duration_s):
        cv2.circle(image, (int(round(x * PX_PER_MM)), int(round(SIZE[1] - y * PX_PER_MM))), 10,
                   (40, 40, 40), -1, cv2.LINE_AA)
    cv2.putText(image, f"frame {frame}", (20, 50), cv2.FONT_HERSHEY_SIMPLEX, 1.4, (0, 0, 0), 3,
                cv2.LINE_AA)
    return image


def synthesise(root: Path, seconds: float, fps: float, rate_hz: float) -> Path:
    """A finished record of `seconds` under `root` (see the module's docstring); its folder."""
    record = RunRecord(root, f"synthetic {seconds:g} s")

    def stamp(t_s: float) -> None:  # what is written next is stamped t_s on the record's clock
        record.t0 = time.monotonic() - t_s

    plan_moves = [positions_mm(seconds * (m + 1) / MOVES, seconds).tolist() for m in range(MOVES)]
    plan = {"version": 1, "name": f"synthetic {seconds:g} s", "rig": "six-coil",
            "workspace": {"boundary": {"rect": [20.0, 20.0, 280.0, 200.0]}, "obstacles": []},
            "agents": [{"start": p, "goal": g, "radius": 5.0} for p, g in
                       zip(positions_mm(0.0, seconds).tolist(), plan_moves[-1])],
            "moves": [[0.0, 0.0]] * MOVES, "expected": plan_moves}
    record.write_file("plan.json", json.dumps(plan))
    record.write_file("rig.toml", RIG_TOML)
    stamp(0.0)
    record.event("prepared", rate_hz=rate_hz, duration_s=seconds, moves=MOVES)
    record.open_stream(symmetric(COILS, "A", [20.0] * len(COILS), "supplies"), rate_hz)
    video = VideoRecorder(record, fps)
    rows = int(seconds * rate_hz)
    next_frame, next_tracked, frame = 0.0, 0.0, 0
    phases = np.arange(len(COILS)) * np.pi / 3
    for i in range(rows):
        t = i / rate_hz
        move = min(MOVES - 1, int(t / seconds * MOVES))
        currents = 8.0 * np.sin(2 * np.pi * t / 2.0 + phases)
        stamp(t)
        record.stream_row(i, move, currents, currents + 0.01)
        if t >= next_tracked:
            record.event("tracked", frame=frame, t_frame_s=t,
                         positions_mm=np.round(positions_mm(t, seconds), 4).tolist(),
                         lost=[False, False])
            next_tracked += 0.1
        if t >= next_frame - 1e-9:
            while frame - video.written > 4:  # at the writer's pace: the recorder drops nothing
                time.sleep(0.002)
            video.offer(picture(frame, t, seconds), t, frame)
            frame += 1
            next_frame += 1.0 / fps
        if i and i % int(seconds * rate_hz / MOVES) == 0:
            record.event("move_done", move=move)
    video.close()
    stamp(seconds)
    record.event("video", **video.counts())
    record.finish({"rig": "six-coil", "reached": True, "faults": [], "duration_s": seconds})
    return record.path


class Viewer:
    """`rigctl view RUN --no-browser` as a process; `url` from its first line."""

    def __init__(self, run: Path) -> None:
        started = time.perf_counter()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rigctl", "view", str(run), "--no-browser"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.url = self.proc.stdout.readline().strip()
        self.start_s = time.perf_counter() - started  # its imports and reading the record
        if not self.url.startswith("http"):
            raise SystemExit(f"rigctl view did not start: {self.proc.stderr.read()[-2000:]}")

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(20)


def browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--window-size=1280,720", "--hide-scrollbars"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)


READY = "return !!(window.rigctlViewer && rigctlViewer.ready && rigctlViewer.shownFrame !== null);"
SEEK = """
const [t, done] = arguments;
const V = rigctlViewer, start = performance.now();
const want = V.nearestIndex(V.data.video.t_s, Math.min(V.data.t_end_s, Math.max(V.data.t_start_s, t)));
V.seek(t);
const check = () => (V.shownFrame === want && !V.fetching) ? done({ms: performance.now() - start, frame: want})
                                                          : requestAnimationFrame(check);
check();
"""


def open_page(driver, url: str, timeout_s: float = 60.0) -> float:
    start = time.perf_counter()
    driver.get(url)
    while not driver.execute_script(READY):
        if time.perf_counter() - start > timeout_s:
            raise SystemExit(f"the viewer did not open {url} within {timeout_s:g} s")
        time.sleep(0.005)
    return time.perf_counter() - start


def read_time_s(run: Path) -> float:
    """The server's first read of the record (`record_document`), its modules imported before."""
    import rigctl.apps.report_video  # noqa: F401 - the readers' imports, outside the time
    from rigctl.apps.console.records import record_document

    started = time.perf_counter()
    record_document(run)
    return time.perf_counter() - started


def measure(driver, run: Path, seeks: int, rng: np.random.Generator) -> dict:
    read_s = read_time_s(run)
    viewer = Viewer(run)
    try:
        cold = open_page(driver, viewer.url)
        warm = open_page(driver, viewer.url)
        t_end = driver.execute_script("return rigctlViewer.data.t_end_s;")
        times = rng.uniform(0.0, t_end, seeks)
        driver.set_script_timeout(30)
        results = [driver.execute_async_script(SEEK, float(t)) for t in times]
        size = driver.execute_script("return JSON.stringify(rigctlViewer.data).length;")
    finally:
        viewer.close()
    ms = np.array([r["ms"] for r in results])
    return {"record_s": round(t_end, 2), "document_kB": round(size / 1e3, 1),
            "read_s": round(read_s, 3), "view_start_s": round(viewer.start_s, 3),
            "open_s": round(cold, 3),
            "open_warm_s": round(warm, 3),
            "seek_ms": {"median": round(float(np.median(ms)), 1),
                        "p90": round(float(np.percentile(ms, 90)), 1),
                        "max": round(float(ms.max()), 1), "n": len(ms)}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--floor-seconds", type=float, default=10.0)
    parser.add_argument("--fps", type=float, default=15.0)
    parser.add_argument("--rate", type=float, default=100.0, help="stream rows a second")
    parser.add_argument("--seeks", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--smoke", action="store_true", help="a 20-second record, 3 seeks")
    args = parser.parse_args()
    if args.smoke:
        args.minutes, args.floor_seconds, args.seeks = 20 / 60, 5.0, 3
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory(prefix="viewer-bench-") as tmp:
        started = time.perf_counter()
        long_run = synthesise(Path(tmp) / "runs", 60.0 * args.minutes, args.fps, args.rate)
        synthesis_s = time.perf_counter() - started
        floor_run = synthesise(Path(tmp) / "floor", args.floor_seconds, args.fps, args.rate)
        video_MB = (long_run / "video.avi").stat().st_size / 1e6
        driver = browser()
        try:
            floor = measure(driver, floor_run, args.seeks, rng)
            long = measure(driver, long_run, args.seeks, rng)
        finally:
            driver.quit()
    print(json.dumps({
        "record": {"minutes": round(args.minutes, 3), "fps": args.fps, "rate_hz": args.rate,
                   "video_MB": round(video_MB, 1), "synthesis_s": round(synthesis_s, 1)},
        "long": long, "floor": floor,
        "ratio_long_floor": {"read": round(long["read_s"] / floor["read_s"], 2),
                             "open": round(long["open_s"] / floor["open_s"], 2),
                             "seek_median": round(long["seek_ms"]["median"]
                                                  / max(floor["seek_ms"]["median"], 1e-3), 2)},
        "under_1s": {"open": long["open_s"] < 1.0, "seek_max": long["seek_ms"]["max"] < 1000.0},
        "machine": {"cpus": os.cpu_count(), "load_1min": round(os.getloadavg()[0], 2),
                    "python": platform.python_version()},
    }))


if __name__ == "__main__":
    main()
