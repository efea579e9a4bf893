"""The run viewer (issue 39, item 4) in headless Chromium, served by `rigctl view RUN --no-browser`
as a user runs it, on a record of a closed-loop run on the emulated six-coil bench (three turns,
its camera's video recorded by the run).

Scrubbed to an instant, the page shows the video frame whose time on the record's clock is the
nearest: the frame-time table is read here from `series/video.csv` with numpy, the frames are
decoded here from `video.avi` by OpenCV, and the picture the page shows is read back from its
<img> as pixels, so the test holds whatever index the page believes it shows. A copy of the
record without its video (as records were before video) opens with the scene drawn from the
tracked positions, which are the `tracked` events' at that instant. Both pages fit 1280x720."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from rigctl.core.config import load_rig
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.rigs.six_coil.global_moves import execute_plan
from tests.browser.pages import js, no_horizontal_scroll
from tests.integration.test_video_record import fast, frames_of, three_turns_down

OLD = "old-style-"  # the copy without video


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    """A finished closed-loop run with its video, and beside it a copy without the video."""
    folder = tmp_path_factory.mktemp("viewer")
    with EmulatedBenchProcess("six-coil", folder / "bench.toml") as rig_path:
        rig = load_rig(rig_path)
        summary = execute_plan(three_turns_down(), fast(rig), runs_dir=folder / "runs",
                               progress_out=None, closed_loop=True)
    run = Path(summary.run)
    assert not summary.faults and (run / "video.avi").is_file(), summary.faults
    old = run.parent / (OLD + run.name)
    shutil.copytree(run, old, ignore=shutil.ignore_patterns("video.*"))
    assert not (old / "video.avi").exists() and not (old / "series" / "video.csv").exists()
    return run, old


@pytest.fixture(scope="module")
def viewer(record):
    """`rigctl view RUN --no-browser`: its URL (the record's page) from its first line."""
    run, _ = record
    proc = subprocess.Popen([sys.executable, "-m", "rigctl", "view", str(run), "--no-browser"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = proc.stdout.readline().strip()
    assert url.startswith("http://127.0.0.1:"), proc.stderr.read()
    yield url
    proc.terminate()
    assert proc.wait(20) == 0  # SIGTERM ends it cleanly


def open_viewer(browser, url: str):
    driver = browser(1280, 720)
    driver.get(url)
    deadline = time.monotonic() + 30.0
    while not js(driver, "window.rigctlViewer && (rigctlViewer.ready || rigctlViewer.error)"):
        assert time.monotonic() < deadline, "the viewer did not load within 30 s"
        time.sleep(0.05)
    assert js(driver, "rigctlViewer.error") is None, js(driver, "rigctlViewer.error")
    return driver


def scrub_to(driver, t_s: float) -> float:
    """Drag's effect on the timeline: its value set and its `input` event; the time it took."""
    return float(driver.execute_script(
        "const s = document.getElementById('scrub'); s.value = arguments[0];"
        "s.dispatchEvent(new Event('input')); return parseFloat(s.value);", t_s))


def shown_picture(driver) -> np.ndarray:
    """The picture in the page's <img>, as pixels (BGR), once the frame asked for has loaded."""
    deadline = time.monotonic() + 10.0
    while not js(driver, "!rigctlViewer.fetching && rigctlViewer.shownFrame === "
                 "rigctlViewer.wantedFrame && document.getElementById('frame').complete"):
        assert time.monotonic() < deadline, "the frame did not load within 10 s"
        time.sleep(0.02)
    data_url = driver.execute_script(
        "const img = document.getElementById('frame'), c = document.createElement('canvas');"
        "c.width = img.naturalWidth; c.height = img.naturalHeight;"
        "c.getContext('2d').drawImage(img, 0, 0); return c.toDataURL('image/png');")
    png = base64.b64decode(data_url.split(",", 1)[1])
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def difference(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(float) - b.astype(float)).mean())


def test_the_frame_shown_is_the_one_nearest_the_scrubbed_time(record, viewer, browser,
                                                               screenshots):
    run, _ = record
    table = np.genfromtxt(run / "series" / "video.csv", delimiter=",", names=True)
    times = np.asarray(table["t_s"], dtype=float)
    frames = frames_of(run / "video.avi")
    assert len(frames) == len(times)
    # frames that differ clearly from the next one (the magnets rolling): there, the nearest
    # frame and the one before the instant are different pictures
    steps = [difference(frames[k], frames[k + 1]) for k in range(len(frames) - 1)]
    moving = [k for k, d in enumerate(steps) if d > 1.0]
    assert len(moving) >= 3, steps
    chosen = [moving[len(moving) // 4], moving[len(moving) // 2], moving[3 * len(moving) // 4]]
    driver = open_viewer(browser, viewer)
    assert js(driver, "rigctlViewer.scene") == "camera"
    for k in chosen:
        for fraction, nearest in ((0.35, k), (0.65, k + 1)):
            t = scrub_to(driver, times[k] + fraction * (times[k + 1] - times[k]))
            expected = int(np.argmin(np.abs(times - t)))
            assert expected == nearest  # the scrubbed value kept its place between the two
            shown = shown_picture(driver)
            assert shown.shape == frames[0].shape
            off = [difference(shown, f) for f in frames]
            # JPEG decoders differ by a level or so; the neighbours differ by more than 1
            assert off[expected] < 0.5 * steps[k], (k, fraction, off[expected], steps[k])
            assert int(np.argmin(off)) == expected or off[int(np.argmin(off))] == off[expected]
            assert js(driver, "document.getElementById('clock').textContent") == f"t = {t:.2f} s"
    assert no_horizontal_scroll(driver)
    # the timeline in view without scrolling (the window's inner height: less than 720 here)
    assert js(driver, "document.getElementById('timeline').getBoundingClientRect().bottom "
              "<= window.innerHeight")
    screenshots(driver, "viewer-six-coil")


def test_a_record_without_video_opens_with_the_scene_drawn_from_the_tracked_positions(
        record, viewer, browser, screenshots):
    _, old = record
    driver = open_viewer(browser, viewer.split("?")[0] + f"?run={old.name}")
    assert js(driver, "rigctlViewer.scene") == "drawn"
    assert js(driver, "document.getElementById('frame').hidden")
    tracked = [json.loads(line) for line in (old / "events.jsonl").read_text().splitlines()]
    tracked = [e for e in tracked if e["event"] == "tracked" and e.get("positions_mm")]
    assert len(tracked) >= 10
    for e in (tracked[len(tracked) // 3], tracked[2 * len(tracked) // 3]):
        driver.execute_script("rigctlViewer.seek(arguments[0])", round(e["t_frame_s"], 4))
        drawn = np.asarray(js(driver, "rigctlViewer.agentsMm"), dtype=float)
        np.testing.assert_allclose(drawn, np.asarray(e["positions_mm"]), atol=0.01)
    assert no_horizontal_scroll(driver)
    assert js(driver, "document.getElementById('timeline').getBoundingClientRect().bottom "
              "<= window.innerHeight")
    screenshots(driver, "viewer-no-video")
