"""`rigctl view RUN --no-browser` as a user runs it (its own process): it prints a URL that serves
the run viewer's page, the record's list, its document, each video frame by index and the video
file with HTTP Range; Ctrl-C ends it with status 0; a run that is not there is one line and exit
2. The record is written here with the record writer's own API (`RunRecord`, `VideoRecorder`),
its frames solid grey levels, so what is served is checked against what was written."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from rigctl.core.channels import symmetric
from rigctl.core.record import RunRecord
from rigctl.vision.video import VideoRecorder

LEVELS = [20 + 20 * k for k in range(10)]  # frame k is this grey level all over
FPS = 15.0


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    record = RunRecord(tmp_path_factory.mktemp("view") / "runs", "ten grey frames")
    record.write_file("plan.json", json.dumps({"name": "ten grey frames"}))
    record.open_stream(symmetric(["x+", "x-"], "A", [20.0, 20.0], "supplies"), 100.0)
    video = VideoRecorder(record, FPS)
    for k, level in enumerate(LEVELS):
        record.stream_row(k, 0, [0.1 * k, 0.0], [0.1 * k, 0.0])
        video.offer(np.full((120, 160, 3), level, np.uint8), 0.5 + k / FPS, k)
        while video.written + video.dropped < k + 1 and video.failure is None:
            time.sleep(0.002)  # each frame handed over before the next: none dropped
    video.close()
    record.finish({"reached": True, "faults": []})
    assert video.written == len(LEVELS), video.counts()
    return record.path


@pytest.fixture(scope="module")
def served(run):
    proc = subprocess.Popen([sys.executable, "-m", "rigctl", "view", run.name, "--runs",
                             str(run.parent), "--no-browser"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = proc.stdout.readline().strip()
    assert url.startswith("http://127.0.0.1:"), proc.stderr.read()
    yield url, proc
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def get(url: str, headers: dict | None = None) -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}),
                                    timeout=10) as reply:
            return reply.status, dict(reply.headers), reply.read()
    except urllib.error.HTTPError as err:
        return err.code, dict(err.headers), err.read()


def test_the_printed_url_serves_the_page_and_the_record(run, served):
    url, _ = served
    base = url.split("/viewer")[0]
    assert url == f"{base}/viewer?run={run.name}"
    status, headers, page = get(url)
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    assert b"/static/viewer.js" in page and b"/static/plots.js" in page
    for script in ("viewer.js", "plots.js", "viewer.css"):
        assert get(f"{base}/static/{script}")[0] == 200
    runs = json.loads(get(f"{base}/records")[2])
    assert [(r["id"], r["video"]) for r in runs] == [(run.name, True)]

    document = json.loads(get(f"{base}/records/{run.name}/data.json")[2])
    table = np.genfromtxt(run / "series" / "video.csv", delimiter=",", names=True)
    assert document["video"]["frames"] == len(LEVELS)
    np.testing.assert_allclose(document["video"]["t_s"], table["t_s"], atol=1e-6)
    assert document["plan"] == "ten grey frames" and document["scene"]["kind"] == "camera"

    for k in (0, 3, len(LEVELS) - 1):
        status, headers, jpeg = get(f"{base}/records/{run.name}/frames/{k}.jpg")
        assert status == 200 and headers["Content-Type"] == "image/jpeg"
        picture = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert abs(float(picture.mean()) - LEVELS[k]) < 3, (k, picture.mean())
    assert get(f"{base}/records/{run.name}/frames/{len(LEVELS)}.jpg")[0] == 404
    assert get(f"{base}/records/no-such-run/data.json")[0] == 404
    assert get(f"{base}/records/..%2F..%2Fetc/data.json")[0] == 404

    whole = (run / "video.avi").read_bytes()
    status, headers, part = get(f"{base}/records/{run.name}/video", {"Range": "bytes=100-299"})
    assert status == 206 and part == whole[100:300]
    assert headers["Content-Range"] == f"bytes 100-299/{len(whole)}"
    # another site's name for this address (DNS rebinding) reads nothing of the record
    for path in ("records", f"records/{run.name}/data.json", f"records/{run.name}/frames/0.jpg",
                 f"records/{run.name}/video"):
        assert get(f"{base}/{path}", {"Host": "rebind.example:80"})[0] == 403, path


def test_ctrl_c_ends_it_cleanly(served):
    _, proc = served
    proc.send_signal(signal.SIGINT)
    assert proc.wait(20) == 0
    assert "viewer stopped" in proc.stderr.read()


def test_a_run_that_is_not_there_is_one_line_and_exit_2(tmp_path):
    done = subprocess.run([sys.executable, "-m", "rigctl", "view", "nothing-here", "--runs",
                           str(tmp_path), "--no-browser"], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2
    assert done.stderr.startswith("error: no run record at nothing-here")
    assert len(done.stderr.strip().splitlines()) == 1 and done.stdout == ""
