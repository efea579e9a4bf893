"""The emulated camera on a real socket, read through OpenCV's VideoCapture by the camera driver, as
an IP camera would be: robots tracked against the scene's ground truth at each frame's stamped
capture time, and the stream's faults (dropped, frozen, black frames, an occluded robot, a stalled
and a dropped link) seen by the driver and the tracker as they would be on a rig."""

import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from rigctl.core.errors import DeviceTimeout, Disconnected
from rigctl.drivers.camera import CameraDriver, write_stamp
from rigctl.emulators.camera import CameraModel, Renderer, Scene, serve_camera
from rigctl.emulators.server import EmulatorServer
from rigctl.plans.workspace import ShapeWorkspace
from rigctl.vision.calibration import boundary_corners_mm, calibrate_camera
from rigctl.vision.tracker import Tracker

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

RADIUS = 5.0
WORKSPACE = ShapeWorkspace(("rect", (0, 0, 400, 400)), [("rect", (150, 150, 60, 60))])
STARTS = np.array([[40.0, 50.0], [300.0, 60.0], [80.0, 300.0]])
VELOCITY_MM_S = np.array([12.0, 8.0])


def truth_at(t_s: float, t0: float) -> np.ndarray:
    """Where the robots are at monotonic time t_s: straight lines from STARTS at t0."""
    return STARTS + VELOCITY_MM_S * (t_s - t0)


@pytest.fixture
def stream():
    camera_model = CameraModel.overhead(WORKSPACE.bounds, tilt_deg=8, tilt_azimuth_deg=70)
    t0 = time.monotonic()

    def scene() -> Scene:
        return Scene(WORKSPACE, truth_at(time.monotonic(), t0), np.full(len(STARTS), RADIUS))

    with EmulatorServer() as server:
        camera = serve_camera(server, scene, Renderer(camera_model, seed=3), fps=60)
        yield camera, camera_model.calibration(), t0


def open_driver(camera, **options):
    options = {"stamped": True, "timeout_s": 1.0, "reconnect_attempts": 3,
               "reconnect_delay_s": 0.05, **options}
    return CameraDriver(camera.url, **options)


def read_captured_after(driver, t_s, limit=60):
    """The first frame captured after monotonic time t_s (frames already on their way come first)."""
    for _ in range(limit):
        frame = driver.read()
        if frame.t_source > t_s:
            return frame
    raise AssertionError(f"no frame captured after {t_s} in {limit} frames")


def test_robots_tracked_through_the_stream_at_each_frames_capture_time(stream):
    camera, calibration, t0 = stream
    with open_driver(camera) as driver:
        first = driver.read()
        tracker = Tracker(calibration, RADIUS, truth_at(first.t_source, t0), roi_mm=WORKSPACE.bounds)
        worst, numbers, latencies = 0.0, [], []
        for _ in range(30):
            frame = driver.read()
            robots = tracker.update(frame.image, frame.t_source)
            found = np.array([r.position_mm for r in robots])
            gaps = np.linalg.norm(found - truth_at(frame.t_source, t0), axis=1)
            worst = max(worst, float(gaps.max()))
            numbers.append(frame.source_number)
            latencies.append(frame.t_capture - frame.t_source)
    assert worst < 0.2 * RADIUS
    assert all(b > a for a, b in zip(numbers, numbers[1:]))
    assert 0.0 < float(np.median(latencies)) < 0.1  # render + JPEG + HTTP + decode, same clock


def test_dropped_and_frozen_frames_show_in_the_frame_numbers_and_stamps(stream):
    camera, _, _ = stream
    with open_driver(camera) as driver:
        last_before = driver.read()
        camera.drop_frames(6)
        called = time.monotonic()
        frame = driver.read()
        while frame.t_source <= called:  # captured before the call, still on its way
            last_before, frame = frame, driver.read()
        # the six frames numbered after the call were never sent
        assert frame.source_number - last_before.source_number >= 7
        camera.freeze()
        frozen = [driver.read() for _ in range(6)][-3:]  # frames on their way arrive first
        assert len({f.source_number for f in frozen}) == 1
        assert len({f.t_source for f in frozen}) == 1
        assert all(f.repeated for f in frozen)
        camera.restore()
        fresh = read_captured_after(driver, time.monotonic())
        assert fresh.source_number > frozen[0].source_number and not fresh.repeated


def test_occlusion_and_black_out_lose_robots_until_restored(stream):
    camera, calibration, t0 = stream
    with open_driver(camera) as driver:
        frame = driver.read()
        tracker = Tracker(calibration, RADIUS, truth_at(frame.t_source, t0), roi_mm=WORKSPACE.bounds)
        tracker.update(frame.image, frame.t_source)
        camera.occlude(2)
        frame = read_captured_after(driver, time.monotonic())
        lost = [r.lost for r in tracker.update(frame.image, frame.t_source)]
        assert lost == [False, False, True]
        camera.black_out()
        frame = read_captured_after(driver, time.monotonic())
        assert all(r.lost for r in tracker.update(frame.image, frame.t_source))
        camera.restore()
        frame = read_captured_after(driver, time.monotonic())
        robots = tracker.update(frame.image, frame.t_source)
        assert not any(r.lost for r in robots)
        found = np.array([r.position_mm for r in robots])
        assert np.max(np.linalg.norm(found - truth_at(frame.t_source, t0), axis=1)) < 0.2 * RADIUS


def test_driver_reconnects_after_the_link_drops_and_gives_up_past_its_bound(stream):
    camera, _, _ = stream
    with open_driver(camera, reconnect_attempts=3) as driver:
        driver.read()
        camera.endpoint.stall()
        with pytest.raises(DeviceTimeout):
            for _ in range(5):  # frames already on their way arrive first
                driver.read(timeout_s=0.3)
        camera.endpoint.drop_link()
        with pytest.raises(DeviceTimeout):
            driver.read(timeout_s=0.2)  # reconnecting, refused
        camera.restore()
        frame = driver.read(timeout_s=5.0)
        assert driver.reconnects >= 1 and frame.image.shape == (494, 659, 3)
        camera.endpoint.drop_link()
        started = time.monotonic()
        with pytest.raises(Disconnected):
            while True:
                driver.read(timeout_s=5.0)
        # three refused reopenings, 0.05 + 0.1 + 0.2 s apart
        assert time.monotonic() - started < 3.0


def test_other_paths_are_not_found(stream):
    camera, _, _ = stream
    with pytest.raises(urllib.error.HTTPError) as answer:
        urllib.request.urlopen(camera.url.replace("/stream.mjpg", "/nothing"), timeout=2)
    assert answer.value.code == 404


def test_calibrate_camera_reads_the_stream_and_finds_the_floor(stream):
    camera, truth, _ = stream
    calibration = calibrate_camera(
        camera.url, corners_mm=boundary_corners_mm(("rect", (0, 0, 400, 400))), stamped=True,
        frames=3,
    )
    probe = np.array([[10.0, 10.0], [390.0, 20.0], [200.0, 380.0], [120.0, 250.0]])
    pixels = truth.to_px(probe)  # where the camera sees them (its exact homography)
    assert np.max(np.linalg.norm(calibration.to_mm(pixels) - probe, axis=1)) < 0.3
    assert calibration.resolution == (659, 494)


def test_a_recorded_experiment_replays_frame_by_frame_with_its_stamps(tmp_path):
    camera_model = CameraModel.overhead(WORKSPACE.bounds)
    renderer = Renderer(camera_model, seed=5)
    path = tmp_path / "run.avi"
    fourcc = cv2.VideoWriter_fourcc(*"MJPG")
    writer = cv2.VideoWriter(str(path), fourcc, 30.0, camera_model.resolution)
    for k in range(12):
        image = renderer.render(Scene(WORKSPACE, STARTS + k * 2.0, np.full(len(STARTS), RADIUS)))
        write_stamp(image, 100.0 + k / 30.0, k)
        writer.write(image)
    writer.release()
    with CameraDriver(str(path), stamped=True) as replay:
        frames = list(replay)
    assert [f.source_number for f in frames] == list(range(12))
    np.testing.assert_allclose([f.t_source for f in frames], 100.0 + np.arange(12) / 30.0, atol=2e-6)
    assert not any(f.repeated for f in frames)
    with CameraDriver(str(path)) as replay:  # without stamps: the file's own clock and numbering
        frames = list(replay)
    np.testing.assert_allclose([f.t_source for f in frames], np.arange(12) / 30.0, atol=1e-3)
    assert [f.source_number for f in frames] == list(range(12))
