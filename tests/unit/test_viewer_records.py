"""What the run viewer's server reads (rigctl.apps.console.records): each frame of a record's
Motion-JPEG AVI found by walking its chunks (OpenCV's decode of the file is the reference, also
of a file a crash cut off), channels decimated without losing a peak, and a crashed record's
stream read whole once the journal's rows the Parquet parts hold are passed over unparsed."""

from __future__ import annotations

import io
import json
import struct
import time

import cv2
import numpy as np
import pytest

from rigctl.apps.console.records import avi_frames, decimate, read_frame
from rigctl.core.channels import Channel
from rigctl.core.record import RunRecord, read_stream
from rigctl.vision.video import HEADER, write_video

LEVELS = [10, 60, 110, 160, 210, 250, 30]


def written_avi(path, levels=LEVELS, size=(48, 36)) -> None:
    """An AVI as the record's writer makes it (`write_video`, OpenCV's FFmpeg, MJPG), frame k a
    solid grey of levels[k] with its index as a white square's column."""
    w, h = size
    pipe = io.BytesIO()
    for k, level in enumerate(levels):
        image = np.full((h, w, 3), level, np.uint8)
        image[2:6, 4 * k + 2:4 * k + 6] = 255
        pipe.write(struct.pack(HEADER, h, w) + image.tobytes())
    pipe.seek(0)
    assert write_video(str(path), 15.0, pipe) == len(levels)


def opencv_frames(path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, image = capture.read()
        if not ok:
            capture.release()
            return frames
        frames.append(image)


def test_every_frame_of_the_avi_is_found_by_its_index(tmp_path):
    path = tmp_path / "video.avi"
    written_avi(path)
    found = avi_frames(path)
    reference = opencv_frames(path)
    assert len(found) == len(reference) == len(LEVELS)
    for k, (offset, size) in enumerate(found):
        jpeg = read_frame(path, offset, size)
        assert jpeg[:2] == b"\xff\xd8"  # a whole JPEG, as the browser gets it
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert np.abs(image.astype(int) - reference[k]).mean() < 1.0, k
        assert abs(float(np.median(image)) - LEVELS[k]) <= 3, k


def test_a_file_cut_off_by_a_crash_gives_its_whole_frames(tmp_path):
    path = tmp_path / "video.avi"
    written_avi(path)
    offset, size = avi_frames(path)[4]
    cut = tmp_path / "cut.avi"
    cut.write_bytes(path.read_bytes()[:offset + size // 2])  # the writer killed in frame 4
    found = avi_frames(cut)
    assert len(found) == 4
    for k, (o, s) in enumerate(found):
        image = cv2.imdecode(np.frombuffer(read_frame(cut, o, s), np.uint8), cv2.IMREAD_GRAYSCALE)
        assert abs(float(np.median(image)) - LEVELS[k]) <= 3, k


def test_decimation_keeps_every_peak_and_the_time_order():
    t = np.arange(100_000) * 0.01  # 1000 s at 100 Hz
    y = np.sin(t)
    y[12_345] = 50.0  # one sample's spike
    y[77_777] = -40.0
    y[50_000:50_500] = np.nan  # a gap in the measurement
    td, yd = decimate(t, y, 1600)
    assert len(td) <= 1600 and (np.diff(td) > 0).all()
    assert np.nanmax(yd) == 50.0 and np.nanmin(yd) == -40.0
    # each kept sample is a sample of the series
    index = np.round(td / 0.01).astype(int)
    np.testing.assert_array_equal(yd, y[index])
    # the sine's extremes (+-1) are in every stretch of the run a plot pixel covers
    assert np.isclose(np.nanmax(yd[(td > 300) & (td < 310)]), 1.0, atol=1e-3)
    short_t, short_y = t[:100], y[:100]
    assert decimate(short_t, short_y, 1600)[0] is short_t


def test_a_crashed_record_s_stream_is_read_whole(tmp_path):
    record = RunRecord(tmp_path, "crash")
    record.open_stream([Channel("x+", "A")], rate_hz=100.0)  # parts of 500 rows
    n = 1234
    for k in range(n):
        record.stream_row(k, 0, [0.001 * k], [0.002 * k])
    record.close()
    # a crash before the last part was written: its 234 rows are only in the journal
    (record.path / "stream" / "part-00002.parquet").unlink()
    assert len(list((record.path / "stream").glob("part-*.parquet"))) == 2
    stream = read_stream(record.path)
    assert stream["source"] == "parquet+journal"
    np.testing.assert_array_equal(stream["sample"], np.arange(n))
    np.testing.assert_allclose(stream["cmd_x+_A"], 0.001 * np.arange(n), atol=1e-5)
    np.testing.assert_allclose(stream["meas_x+_A"], 0.002 * np.arange(n), atol=1e-5)


def test_a_dual_epm_record_shows_its_arms_at_the_recorded_joints(tmp_path):
    """The arms from the recorded joints: turning the left arm's first joint (its axis is the
    vertical through its base, the rig file's base having no rotation) by 0.5 rad turns every
    point of that arm about that vertical by 0.5 rad and moves none of the right arm's."""
    from rigctl.apps.cli.init import template
    from rigctl.apps.console.records import record_document
    from rigctl.core.config import load_rig
    from rigctl.rigs.depm.actuators import arm_channels

    (tmp_path / "rig.toml").write_text(template("depm"))
    rig = load_rig(tmp_path / "rig.toml")
    record = RunRecord(tmp_path / "runs", "arms")
    record.write_file("rig.toml", template("depm"))
    record.write_file("plan.json", json.dumps({"name": "arms", "rig": "depm"}))
    channels = arm_channels(rig)
    record.open_stream(channels, rate_hz=100.0)
    q = np.zeros(len(channels))
    q[[3, 10]] = 1.0  # both elbows bent: the far points are off the first joint's axis
    for k in range(200):
        q[0] = 0.0 if k < 100 else 0.5
        record.t0 = time.monotonic() - 0.01 * k  # row k at 0.01 k s on the record's clock
        record.stream_row(k, 0, q, q)
    record.finish({"rig": "depm", "reached": True})
    document = record_document(record.path)
    assert document["scene"]["kind"] == "arms" and document["video"] is None
    arms = document["arms"]
    assert arms["t"][0] == 0.0 and arms["t"][-1] == pytest.approx(1.99, abs=1e-3)
    before, after = arms["frames"][0], arms["frames"][-1]
    assert [a["name"] for a in before] == ["left", "right"]
    base = np.array([-800.0, 0.0, -500.0])
    left0, left1 = (np.asarray(f[0]["points_mm"]) for f in (before, after))
    assert left0.shape == (9, 3)
    np.testing.assert_allclose(left0[0], base, atol=0.1)
    c, s = np.cos(0.5), np.sin(0.5)
    turned = (left0[:, :2] - base[:2]) @ np.array([[c, s], [-s, c]]) + base[:2]
    np.testing.assert_allclose(left1[:, :2], turned, atol=0.2)  # points rounded to 0.1 mm
    np.testing.assert_allclose(left1[:, 2], left0[:, 2], atol=0.1)
    assert np.linalg.norm(left1[8, :2] - left0[8, :2]) > 100  # the EPM went round, visibly
    np.testing.assert_allclose(after[1]["points_mm"], before[1]["points_mm"], atol=0.1)
    np.testing.assert_allclose(before[1]["points_mm"][0], [800.0, 0.0, -500.0], atol=0.1)


def test_a_nan_in_an_event_reaches_the_page_as_null(tmp_path):
    """A browser's JSON.parse refuses NaN: an event's NaN field is null in the document."""
    from rigctl.apps.console.records import Records

    record = RunRecord(tmp_path, "nan")
    record.event("stream_stats", late_share=float("nan"), p99_s=float("inf"), cycles=3)
    record.finish({"reached": None})
    body = Records(tmp_path).document(record.path).decode()
    assert "NaN" not in body and "Infinity" not in body
    event = next(e for e in json.loads(body)["events"] if e["event"] == "stream_stats")
    assert event["late_share"] is None and event["p99_s"] is None and event["cycles"] == 3


def test_a_file_whose_writer_was_killed_before_it_wrote_its_sizes(tmp_path):
    """A writer killed mid-run has not gone back to write its lists' sizes (left 0) nor the
    index: every frame is still found, once."""
    path = tmp_path / "video.avi"
    written_avi(path)
    data = bytearray(path.read_bytes())
    data[4:8] = b"\0\0\0\0"  # RIFF 'AVI ' size
    movi = data.find(b"movi")
    data[movi - 4:movi] = b"\0\0\0\0"  # LIST 'movi' size
    index = data.find(b"idx1")
    killed = tmp_path / "killed.avi"
    killed.write_bytes(bytes(data[:index]))  # no index either
    found = avi_frames(killed)
    assert found == avi_frames(path)
    assert len(found) == len(LEVELS)
