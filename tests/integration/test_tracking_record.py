"""The tracking loop writes what it tracks into the run record (`TrackingLoop.record_to`): robots
moving on straight lines before the emulated camera on a real socket, their `tracked` events read
back from the record and compared with where the scene had them when each picture was taken."""

import threading
import time

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.config import CameraSettings
from rigctl.core.record import RunRecord, read_events
from rigctl.emulators.camera import CameraModel, Renderer, Scene, serve_camera
from rigctl.emulators.server import EmulatorServer
from rigctl.plans.workspace import ShapeWorkspace
from rigctl.vision.tracking import TrackingLoop

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

RADIUS = 5.0
WORKSPACE = ShapeWorkspace(("rect", (0, 0, 400, 400)), [("rect", (150, 150, 60, 60))])
STARTS = np.array([[40.0, 50.0], [300.0, 60.0]])
VELOCITY_MM_S = np.array([12.0, 8.0])
HZ = 10.0


def truth_at(t_s: float, t0: float) -> np.ndarray:
    return STARTS + VELOCITY_MM_S * (t_s - t0)


@pytest.fixture
def camera():
    model = CameraModel.overhead(WORKSPACE.bounds, tilt_deg=8, tilt_azimuth_deg=70)
    t0 = time.monotonic()

    def scene() -> Scene:
        return Scene(WORKSPACE, truth_at(time.monotonic(), t0), np.full(len(STARTS), RADIUS))

    with EmulatorServer() as server:
        served = serve_camera(server, scene, Renderer(model, seed=3), fps=60)
        settings = CameraSettings(url=served.url, stamped=True, timeout_s=1.0,
                                  calibration=model.calibration())
        yield settings, t0


def test_tracked_events_follow_the_robots_from_the_loops_own_thread(camera, tmp_path):
    settings, t0 = camera
    record = RunRecord(tmp_path, "tracked")
    writers: set[str] = set()
    event = record.event

    def spying_event(name, **fields):  # which thread writes the tracked events
        if name == "tracked":
            writers.add(threading.current_thread().name)
        event(name, **fields)

    record.event = spying_event
    loop = TrackingLoop(settings, np.full(len(STARTS), RADIUS),
                        truth_at(time.monotonic(), t0), roi_mm=WORKSPACE.bounds)
    loop.record_to(record, hz=HZ)  # before start: it waits for the first frame
    try:
        loop.start(acquire_timeout_s=10.0)

        def tracked() -> list[dict]:
            return [e for e in read_events(record.path) if e["event"] == "tracked"]

        wait_for(lambda: len(tracked()) >= 8, 30.0, "eight tracked events")
    finally:
        loop.stop()
        record.close()
    events = tracked()
    assert writers == {"tracking-record"}  # neither the tracker's thread nor the caller's
    frames = [e["frame"] for e in events]
    assert all(b > a for a, b in zip(frames, frames[1:]))  # each a fresh frame, once
    for e in events:
        positions = np.array(e["positions_mm"])
        assert positions.shape == (len(STARTS), 2)
        assert e["lost"] == [False] * len(STARTS)
        taken = e["t_frame_s"] + record.t0  # the capture time on the monotonic clock
        assert e["t_frame_s"] <= e["t"]
        gaps = np.linalg.norm(positions - truth_at(taken, t0), axis=1)
        assert gaps.max() < 0.2 * RADIUS, (e, truth_at(taken, t0))


def test_record_to_refuses_a_rate_that_is_not_positive(camera, tmp_path):
    from rigctl.core.errors import ConfigError

    settings, _ = camera
    loop = TrackingLoop(settings, np.full(len(STARTS), RADIUS), STARTS)
    with pytest.raises(ConfigError, match="positive rate"):
        loop.record_to(RunRecord(tmp_path, "r"), hz=0)
