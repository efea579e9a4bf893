"""The emulated camera's picture against hand-worked projection: the renderer must draw the scene
where a pinhole camera would see it, so the tracker's tests can take the scene as ground truth."""

import math

import numpy as np
import pytest

from rigctl.emulators.camera.render import Appearance, CameraModel, Renderer, Scene
from rigctl.plans.workspace import ShapeWorkspace

BOUNDS = (0.0, 0.0, 400.0, 300.0)
WORKSPACE = ShapeWorkspace(("rect", (0, 0, 400, 300)), [("rect", (250, 100, 80, 60))])
PLAIN = Appearance(lighting_gradient=0.0, vignetting=0.0, noise_sigma=0.0, blur_sigma_px=0.0)


def darkness_centroid(image, floor_grey, robot_grey, box):
    """Centroid (u, v) and area (px) of the darkness (0 = floor, 1 = robot) inside box (top, bottom,
    left, right) of a greyscale-ish BGR picture."""
    top, bottom, left, right = box
    patch = image[top:bottom, left:right, 1].astype(float)
    weight = np.clip((floor_grey - patch) / (floor_grey - robot_grey), 0, 1)
    v, u = np.mgrid[top:bottom, left:right]
    total = weight.sum()
    return np.array([(weight * u).sum() / total, (weight * v).sum() / total]), total


def test_straight_down_camera_projects_like_the_pinhole_formula():
    camera = CameraModel.overhead(BOUNDS, resolution=(659, 494), height_mm=600.0, margin=0.04)
    f = camera.camera_matrix[0, 0]
    cx, cy = (659 - 1) / 2, (494 - 1) / 2
    points = np.array([[0.0, 0.0], [400.0, 300.0], [123.0, 45.0], [200.0, 150.0]])
    # Looking straight down from 600 mm above (200, 150): u = cx + f dx / 600, v = cy - f dy / 600.
    expected = np.column_stack(
        [cx + f * (points[:, 0] - 200) / 600, cy - f * (points[:, 1] - 150) / 600]
    )
    np.testing.assert_allclose(camera.project(points), expected, atol=1e-9)
    # The bounds fill the picture but for the 4 % margin on the tighter axis (here the height:
    # 300 mm over 494 px is tighter than 400 mm over 659 px).
    assert f * 300 / 600 == pytest.approx(494 * (1 - 2 * 0.04))


@pytest.mark.parametrize(
    "tilt, azimuth, yaw, k1", [(0, 0, 0, 0.0), (15, 60, 20, -0.12), (25, 250, -90, 0.08)]
)
def test_floor_points_invert_projection(tilt, azimuth, yaw, k1):
    camera = CameraModel.overhead(
        BOUNDS, tilt_deg=tilt, tilt_azimuth_deg=azimuth, yaw_deg=yaw, distortion=(k1, 0.01, 0, 0, 0)
    )
    rng = np.random.default_rng(3)
    points = rng.uniform((0, 0), (400, 300), size=(50, 2))
    np.testing.assert_allclose(camera.floor_points(camera.project(points)), points, atol=1e-6)


def test_the_cameras_own_calibration_reads_its_pixels_back_to_the_floor():
    camera = CameraModel.overhead(BOUNDS, tilt_deg=20, tilt_azimuth_deg=300, yaw_deg=30,
                                  distortion=(-0.12, 0.02, 0.001, -0.001, 0.0))
    rng = np.random.default_rng(8)
    points = rng.uniform((0, 0), (400, 300), size=(40, 2))
    calibration = camera.calibration()
    np.testing.assert_allclose(calibration.to_mm(camera.project(points)), points, atol=1e-6)
    np.testing.assert_allclose(calibration.to_px(points), camera.project(points), atol=1e-6)


def test_a_robot_is_a_disc_of_its_radius_where_the_camera_sees_its_centre():
    camera = CameraModel.overhead(BOUNDS, resolution=(659, 494))
    renderer = Renderer(camera, PLAIN)
    centre, radius = np.array([120.3, 80.7]), 6.0
    image = renderer.render(Scene(WORKSPACE, centre[None], np.array([radius])))
    mm_per_px = 600.0 / camera.camera_matrix[0, 0]
    u, v = camera.project(centre[None])[0]
    box = (int(v) - 15, int(v) + 16, int(u) - 15, int(u) + 16)
    floor_grey, robot_grey = PLAIN.floor_bgr[1], PLAIN.robot_bgr[1]
    found, area_px = darkness_centroid(image, floor_grey, robot_grey, box)
    np.testing.assert_allclose(found, [u, v], atol=0.05)
    assert area_px == pytest.approx(math.pi * (radius / mm_per_px) ** 2, rel=0.02)


def test_robot_drawn_in_place_through_tilt_distortion_blur_and_noise():
    camera = CameraModel.overhead(
        BOUNDS, tilt_deg=20, tilt_azimuth_deg=135, yaw_deg=15, distortion=(-0.15, 0.03, 0, 0, 0)
    )
    appearance = Appearance(lighting_gradient=0.0, vignetting=0.0, noise_sigma=2.0, blur_sigma_px=1.0)
    renderer = Renderer(camera, appearance, seed=4)
    centres = np.array([[40.0, 40.0], [360.0, 260.0], [200.0, 40.0]])
    image = renderer.render(Scene(WORKSPACE, centres, np.full(3, 5.0)))
    for (u, v) in camera.project(centres):
        box = (int(v) - 14, int(v) + 15, int(u) - 14, int(u) + 15)
        found, _ = darkness_centroid(image, appearance.floor_bgr[1], appearance.robot_bgr[1], box)
        # perspective moves an ellipse's centre off the projected disc centre by far less than this
        np.testing.assert_allclose(found, [u, v], atol=0.15)


def test_obstacles_and_the_wall_outside_are_drawn_in_their_colour():
    camera = CameraModel.overhead(BOUNDS)
    image = Renderer(camera, PLAIN).render(Scene(WORKSPACE, np.zeros((0, 2)), np.zeros(0)))
    inside_obstacle, free, outside = camera.project([[290.0, 130.0], [100.0, 200.0], [-8.0, 150.0]])
    def at(p):
        return image[int(round(p[1])), int(round(p[0]))]
    np.testing.assert_allclose(at(inside_obstacle), PLAIN.obstacle_bgr, atol=1)
    np.testing.assert_allclose(at(free), PLAIN.floor_bgr, atol=1)
    np.testing.assert_allclose(at(outside), PLAIN.obstacle_bgr, atol=1)


def test_lighting_gradient_and_noise_have_the_set_size():
    gradient, sigma = 0.3, 4.0
    appearance = Appearance(lighting_gradient=gradient, lighting_angle_deg=0.0, vignetting=0.0,
                            noise_sigma=sigma, blur_sigma_px=0.0)
    camera = CameraModel.overhead(BOUNDS, resolution=(659, 494))
    empty = Scene(WORKSPACE, np.zeros((0, 2)), np.zeros(0))
    image = Renderer(camera, appearance, seed=5).render(empty)
    (ul, vl), (ur, vr) = camera.project([[40.0, 230.0], [370.0, 230.0]])  # free floor, far apart
    left = image[int(vl) - 20 : int(vl) + 20, int(ul) - 10 : int(ul) + 10, 1].astype(float)
    right = image[int(vr) - 20 : int(vr) + 20, int(ur) - 10 : int(ur) + 10, 1].astype(float)
    def gain(u):  # 1 + g (u - (W - 1) / 2) / W along u
        return 1 + gradient * (u - 329) / 659
    expected = gain(int(ur) - 0.5) / gain(int(ul) - 0.5)
    assert right.mean() / left.mean() == pytest.approx(expected, rel=0.01)
    assert left.std() == pytest.approx(sigma, rel=0.2)


def test_same_seed_same_frame_and_occluder_hides_the_robot():
    camera = CameraModel.overhead(BOUNDS)
    scene = Scene(WORKSPACE, np.array([[100.0, 100.0]]), np.array([5.0]))
    a = Renderer(camera, seed=9).render(scene)
    b = Renderer(camera, seed=9).render(scene)
    c = Renderer(camera, seed=10).render(scene)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    hidden = Scene(WORKSPACE, scene.positions_mm, scene.radii_mm, np.array([[100.0, 100.0, 8.0]]))
    image = Renderer(camera, seed=9).render(hidden)
    u, v = camera.project([[100.0, 100.0]])[0]
    patch = image[int(v) - 8 : int(v) + 9, int(u) - 8 : int(u) + 9, 1]
    assert patch.min() > 150  # nothing robot-dark left under the glare
    assert Renderer(camera).blank().mean() < 10
