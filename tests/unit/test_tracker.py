"""The tracker against the renderer's ground truth: the scene says where each robot is, the picture
is drawn from it through a tilted, distorting, noisy camera, and the tracker must find every robot
there, under its own name, through contact and occlusion.

The calibration handed to the tracker is the camera's exact one (`CameraModel.calibration`, checked in
test_render.py), so these tests measure the tracker alone; fitting one is test_calibration.py's."""

import math

import numpy as np
import pytest

from rigctl.emulators.camera.render import CameraModel, Renderer, Scene
from rigctl.plans.workspace import ShapeWorkspace
from rigctl.vision.tracker import Tracker, TrackerSettings, find_dark_blobs

RADIUS = 5.0
WORKSPACE = ShapeWorkspace(
    ("rect", (0, 0, 400, 400)), [("rect", (100, 150, 80, 40)), ("disk", (300, 300, 30))]
)


@pytest.fixture(scope="module")
def rig():
    camera = CameraModel.overhead(
        WORKSPACE.bounds, tilt_deg=12, tilt_azimuth_deg=35, yaw_deg=4, distortion=(-0.1, 0.02)
    )
    return camera, Renderer(camera, seed=11), camera.calibration()


def run(rig, path, occluded=lambda k: ()):
    """Render every frame of `path` (frames, n, 2) and track it; the tracked states per frame."""
    camera, renderer, calibration = rig
    tracker = Tracker(calibration, RADIUS, path[0], roi_mm=WORKSPACE.bounds)
    states = []
    for k, positions in enumerate(path):
        hidden = [i for i in occluded(k)]
        glare = np.column_stack([positions[hidden], np.full(len(hidden), 1.6 * RADIUS)])
        scene = Scene(WORKSPACE, positions, np.full(len(positions), RADIUS), glare.reshape(-1, 3))
        states.append(tracker.update(renderer.render(scene), t_s=k / 60.0))
    return states


def errors(states, path):
    found = np.array([[r.position_mm for r in state] for state in states])
    return np.linalg.norm(found - path, axis=2)


def test_four_robots_tracked_to_a_fraction_of_their_radius(rig):
    k = np.arange(90)[:, None]
    starts = np.array([[30.0, 30.0], [220.0, 60.0], [60.0, 330.0], [370.0, 200.0]])
    # a shared global move with a turn, as under a rolling field
    step = np.where(k < 45, [0.35, 0.2], [-0.1, 0.4])
    path = starts[None] + np.cumsum(step, axis=0)[:, None, :]
    states = run(rig, path)
    err = errors(states, path)
    assert err.max() < 0.2 * RADIUS
    assert err.mean() < 0.05 * RADIUS
    assert not any(r.lost for state in states for r in state)
    assert min(r.confidence for r in states[-1]) > 0.7


def test_identity_kept_while_two_robots_touch_and_roll_round_each_other(rig):
    # A comes from the left, B from the right; they touch, B orbits A by 180 degrees in contact
    # (so their order along x swaps), then they part.
    a0, b0 = np.array([150.0, 250.0]), np.array([250.0, 250.0])
    frames = []
    for s in np.linspace(0, 1, 30):  # approach to contact: centres 2 r apart
        frames.append([a0 + s * np.array([45.0, 0.0]), b0 - s * np.array([45.0, 0.0])])
    a = a0 + [45.0, 0.0]
    for angle in np.linspace(0, math.pi, 45):  # B rolls round A, always in contact
        frames.append([a, a + 2 * RADIUS * np.array([math.cos(angle), math.sin(angle)])])
    b = frames[-1][1]
    for s in np.linspace(0, 1, 20):  # and away again
        frames.append([a + s * np.array([0.0, -20.0]), b + s * np.array([-20.0, 0.0])])
    path = np.array(frames)
    states = run(rig, path)
    err = errors(states, path)
    assert err.max() < 0.2 * RADIUS, f"worst frame {int(np.argmax(err.max(axis=1)))}"
    assert not any(r.lost for state in states for r in state)
    assert states[-1][0].position_mm[0] > states[-1][1].position_mm[0]  # order along x did swap


def test_three_robots_in_a_row_of_contacts_are_all_found(rig):
    row = np.array([[200.0, 100.0], [210.0, 100.0], [220.0, 100.0]])
    path = np.array([row + [0.2 * k, 0.1 * k] for k in range(20)])
    err = errors(run(rig, path), path)
    assert err.max() < 0.2 * RADIUS


def test_occluded_robot_is_lost_then_found_again_under_its_name(rig):
    starts = np.array([[60.0, 60.0], [200.0, 80.0], [330.0, 120.0]])
    k = np.arange(70)[:, None]
    path = starts[None] + (k * np.array([0.3, 0.25]))[:, None, :]
    hidden = range(20, 40)  # robot 1 under a glare disc, still moving
    states = run(rig, path, occluded=lambda i: (1,) if i in hidden else ())
    for i, state in enumerate(states):
        robot = state[1]
        if i in hidden:
            assert robot.lost and robot.confidence == 0.0
            assert robot.frames_unseen == i - 19
            # reported where it was last seen, not where it went
            np.testing.assert_allclose(robot.position_mm, path[19, 1], atol=1.0)
        else:
            assert not robot.lost
            assert np.linalg.norm(robot.position_mm - path[i, 1]) < 0.2 * RADIUS
        assert not state[0].lost and not state[2].lost


def test_black_frames_lose_everyone_and_tracking_resumes(rig):
    camera, renderer, calibration = rig
    positions = np.array([[60.0, 60.0], [200.0, 80.0]])
    tracker = Tracker(calibration, RADIUS, positions, roi_mm=WORKSPACE.bounds)
    scene = Scene(WORKSPACE, positions, np.full(2, RADIUS))
    tracker.update(renderer.render(scene))
    assert all(r.lost for r in tracker.update(renderer.blank()))
    assert all(r.lost for r in tracker.update(renderer.blank()))
    moved = Scene(WORKSPACE, positions + [3.0, -2.0], np.full(2, RADIUS))
    robots = tracker.update(renderer.render(moved))
    assert not any(r.lost for r in robots)
    np.testing.assert_allclose([r.position_mm for r in robots], positions + [3.0, -2.0], atol=1.0)


def test_levels_are_estimated_between_the_robots_and_the_floor(rig):
    camera, renderer, calibration = rig
    positions = np.array([[60.0, 60.0], [200.0, 80.0]])
    tracker = Tracker(calibration, RADIUS, positions, roi_mm=WORKSPACE.bounds)
    tracker.update(renderer.render(Scene(WORKSPACE, positions, np.full(2, RADIUS))))
    appearance = renderer.appearance
    def grey(bgr):  # ITU-R 601 luma, as OpenCV's BGR2GRAY
        return 0.114 * bgr[0] + 0.587 * bgr[1] + 0.299 * bgr[2]
    robot_grey, obstacle_grey = grey(appearance.robot_bgr), grey(appearance.obstacle_bgr)
    # between the robots' grey and the darkest thing that is not a robot (lighting spans +-20 %)
    assert 0.8 * robot_grey < tracker.dark_level < 1.25 * robot_grey
    assert 1.25 * robot_grey < tracker.threshold < 0.8 * obstacle_grey


def test_a_robot_far_from_where_it_was_put_is_not_taken_for_it(rig):
    camera, renderer, calibration = rig
    truth = np.array([[60.0, 60.0], [250.0, 80.0]])
    settings = TrackerSettings(acquire_radius_mm=20.0)
    tracker = Tracker(calibration, RADIUS, [[60.0, 60.0], [150.0, 80.0]], roi_mm=WORKSPACE.bounds,
                      settings=settings)
    robots = tracker.update(renderer.render(Scene(WORKSPACE, truth, np.full(2, RADIUS))))
    assert not robots[0].lost and robots[1].lost  # 100 mm away from where robot 1 should be


def test_find_dark_blobs_returns_marker_centres(rig):
    camera, renderer, _ = rig
    markers = np.array([[40.0, 40.0], [360.0, 50.0], [350.0, 360.0], [50.0, 350.0], [220.0, 240.0]])
    image = renderer.render(Scene(WORKSPACE, markers, np.full(5, 4.0)))
    found = find_dark_blobs(image)
    expected = camera.project(markers)
    assert len(found) == 5
    nearest = np.min(np.linalg.norm(expected[:, None] - found[None], axis=2), axis=1)
    assert nearest.max() < 0.3


def test_why_tracking_is_lost_names_the_camera_and_the_agents_it_does_not_see(rig):
    from rigctl.core.config import CameraSettings
    from rigctl.vision.tracking import TrackedState, TrackingLoop

    settings = CameraSettings(url="http://127.0.0.1:9/stream", timeout_s=1.5, calibration=rig[2])
    loop = TrackingLoop(settings, np.array([1.0, 1.0]), np.zeros((2, 2)))
    assert loop.why_lost(0.0) == "camera: no fresh frame for 1.5 s"
    loop._latest = TrackedState(positions_mm=np.zeros((2, 2)), lost=np.array([False, True]),
                                t_source=0.0, t_tracked=0.0, frame=1)
    assert loop.why_lost(0.0, "particle") == "camera: particle(s) [1] not found"
    loop.failure = RuntimeError("gave up after 3 reconnections")
    assert loop.why_lost(0.0) == "camera: gave up after 3 reconnections"


def test_a_dark_rim_off_the_floor_is_not_taken_for_a_hidden_robot():
    # A dish: a disc of floor inside a dark rim, the camera's picture a square around it. With
    # robot 0 under a glare disc from the first frame, the nearest dark thing within the
    # acquisition gate is a piece of the rim, where no robot's centre can be.
    dish = ShapeWorkspace(("disk", (0, 0, 23.0)), [])
    camera = CameraModel.overhead(dish.bounds, tilt_deg=12, tilt_azimuth_deg=35, yaw_deg=4,
                                  distortion=(-0.1, 0.02))
    renderer, calibration = Renderer(camera, seed=0), camera.calibration()
    put = np.array([[-4.0, -5.0], [-4.0, 5.0]])
    scene = Scene(dish, put, np.full(2, 0.5), np.array([[-4.0, -5.0, 0.8]]))

    def track(on_floor):
        tracker = Tracker(calibration, 0.5, put, roi_mm=dish.bounds, on_floor=on_floor)
        for k in range(10):
            robots = tracker.update(renderer.render(scene), t_s=k / 60.0)
        return robots

    fooled = track(None)[0]  # what the floor test is for: the rim is taken for robot 0
    assert not fooled.lost and math.hypot(*fooled.position_mm) > 23.0
    hidden, seen = track(dish.contains)
    assert hidden.lost and not seen.lost
    np.testing.assert_allclose(seen.position_mm, put[1], atol=0.1)


class WholePictureTracker(Tracker):
    """The tracker that searches the whole picture every frame (the second method)."""

    def _detect_near_robots(self, image, dt, mm_per_px):
        return None


def test_windows_around_the_robots_find_what_the_whole_picture_finds(rig):
    # Robots touching and orbiting, one hidden then back, one crossing the picture's edge and one
    # sweeping fast past an obstacle: the tracker's windows around the robots (taken whenever
    # every robot was seen last frame) must give, frame by frame, the whole picture's positions.
    camera, renderer, calibration = rig
    a = np.array([150.0, 250.0])
    orbit = [a + 2 * RADIUS * np.array([math.cos(t), math.sin(t)]) for t in np.linspace(0, 3, 40)]
    edge = [np.array([2.0 + 0.6 * k, 390.0 - 0.2 * k]) for k in range(40)]
    fast = [np.array([60.0 + 3.0 * k, 140.0]) for k in range(40)]  # 180 mm/s past the rect
    path = np.array([[a, orbit[k], edge[k], fast[k]] for k in range(40)])
    hidden = range(12, 16)
    # from frame 30, a row of six dark discs no robot is (too dark for robots that touch) touches
    # the orbiting pair from outside their window: the whole picture sees one region too dark for
    # robots, a window would see a piece of it
    row = a + [0.0, -2 * RADIUS] - np.arange(6)[:, None] * [0.0, 2 * RADIUS]

    images = []
    for k, positions in enumerate(path):
        glare = np.array([[*positions[1], 1.6 * RADIUS]]) if k in hidden else np.zeros((0, 3))
        drawn = np.vstack([positions, row]) if k >= 30 else positions
        images.append(renderer.render(Scene(WORKSPACE, drawn, np.full(len(drawn), RADIUS), glare)))

    def states(tracker):
        for k, image in enumerate(images):
            windowed = tracker._detect_near_robots(
                image, 1 / 60.0, calibration.mm_per_px(tracker.pixels)) is not None
            yield tracker.update(image, t_s=k / 60.0), windowed

    ours = list(states(Tracker(calibration, RADIUS, path[0], roi_mm=WORKSPACE.bounds)))
    whole = list(states(WholePictureTracker(calibration, RADIUS, path[0],
                                            roi_mm=WORKSPACE.bounds)))
    for (mine, _), (theirs, _) in zip(ours, whole):
        np.testing.assert_allclose([r.position_mm for r in mine], [r.position_mm for r in theirs],
                                   atol=1e-9)
        assert [r.lost for r in mine] == [r.lost for r in theirs]
    assert any(r.lost for r in ours[14][0]) and not any(r.lost for r in ours[20][0])
    assert all(r.lost for r in ours[-1][0][:2])  # the pair in the too-dark region
    # windows on every frame after one with every robot seen, but the one where the row came
    expected = [k > 0 and k != 30 and not any(r.lost for r in whole[k - 1][0])
                for k in range(len(path))]
    assert [w for _, w in ours] == expected
