"""Camera calibration: fitted from a rendered picture, checked against the camera that took it.

The emulated camera's own projection (`CameraModel.project`, OpenCV's projectPoints on its pose and
intrinsics) is the independent truth; the calibration only ever sees the picture."""

import tomllib

import numpy as np
import pytest
import tomli_w
from pydantic import ValidationError

from rigctl.core.camera_model import Calibration, CalibrationError
from rigctl.emulators.camera.render import CameraModel, Renderer, Scene
from rigctl.plans.workspace import ShapeWorkspace
from rigctl.vision.calibration import (
    boundary_corners_mm,
    calibrate_picture,
    calibration_from_points,
)

BOUNDARY = ("rect", (0.0, 0.0, 400.0, 300.0))
WORKSPACE = ShapeWorkspace(BOUNDARY, [("rect", (100, 150, 80, 40)), ("disk", (280, 200, 30))])
GRID = np.stack(np.meshgrid(np.linspace(0, 400, 9), np.linspace(0, 300, 7)), -1).reshape(-1, 2)


def picture(camera, robots=np.zeros((0, 2)), radius=5.0, seed=1):
    scene = Scene(WORKSPACE, robots, np.full(len(robots), radius))
    return Renderer(camera, seed=seed).render(scene)


def worst_error_mm(calibration, camera):
    """Largest floor error over the workspace when the calibration reads the camera's pixels."""
    return float(np.max(np.linalg.norm(calibration.to_mm(camera.project(GRID)) - GRID, axis=1)))


@pytest.mark.parametrize("tilt, azimuth", [(0, 0), (18, 40), (25, 200)])
def test_corners_of_a_tilted_camera_give_the_floor_to_a_tenth_of_a_mm(tilt, azimuth):
    camera = CameraModel.overhead(WORKSPACE.bounds, tilt_deg=tilt, tilt_azimuth_deg=azimuth)
    calibration = calibrate_picture(picture(camera), corners_mm=boundary_corners_mm(BOUNDARY))
    assert worst_error_mm(calibration, camera) < 0.15
    assert calibration.resolution == (659, 494)


def test_corners_through_a_distorting_lens_with_known_intrinsics():
    camera = CameraModel.overhead(WORKSPACE.bounds, tilt_deg=10, tilt_azimuth_deg=120,
                                  distortion=(-0.15, 0.03, 0, 0, 0))
    calibration = calibrate_picture(
        picture(camera), corners_mm=boundary_corners_mm(BOUNDARY),
        camera_matrix=camera.camera_matrix, dist_coeffs=camera.dist_coeffs,
    )
    assert worst_error_mm(calibration, camera) < 0.2
    # and back: floor -> pixel through the same lens
    np.testing.assert_allclose(calibration.to_px(GRID), camera.project(GRID), atol=0.2)


def test_the_orientation_decides_between_the_rotations_of_a_square_workspace():
    square = ("rect", (0.0, 0.0, 300.0, 300.0))
    workspace = ShapeWorkspace(square)
    # yaw 90: the picture's up is the floor's -x, so the floor's +x points down: -90 deg on screen
    camera = CameraModel.overhead(workspace.bounds, tilt_deg=8, tilt_azimuth_deg=10, yaw_deg=90)
    image = Renderer(camera, seed=2).render(Scene(workspace, np.zeros((0, 2)), np.zeros(0)))
    right = calibrate_picture(image, corners_mm=boundary_corners_mm(square), orientation_deg=-90)
    wrong = calibrate_picture(image, corners_mm=boundary_corners_mm(square), orientation_deg=0)
    grid = GRID * 0.75
    assert np.max(np.linalg.norm(right.to_mm(camera.project(grid)) - grid, axis=1)) < 0.15
    assert np.max(np.linalg.norm(wrong.to_mm(camera.project(grid)) - grid, axis=1)) > 100
    assert right.floor_angle_deg() == pytest.approx(-90, abs=5)


def test_markers_in_any_order_on_a_tilted_camera():
    camera = CameraModel.overhead(WORKSPACE.bounds, tilt_deg=20, tilt_azimuth_deg=300, yaw_deg=-15)
    markers = np.array([[40.0, 40.0], [360.0, 30.0], [370.0, 270.0], [60.0, 260.0], [230.0, 110.0]])
    image = picture(camera, robots=markers[::-1], radius=4.0)  # drawn in another order
    calibration = calibrate_picture(image, markers_mm=markers, orientation_deg=15,
                                    marker_radius_mm=4.0)
    assert worst_error_mm(calibration, camera) < 0.3
    assert calibration.residual_mm < 0.1


def test_missing_markers_are_an_error_not_a_guess():
    camera = CameraModel.overhead(WORKSPACE.bounds)
    markers = np.array([[40.0, 40.0], [360.0, 30.0], [370.0, 270.0], [60.0, 260.0], [230.0, 110.0]])
    image = picture(camera, robots=markers[:3], radius=4.0)
    with pytest.raises(CalibrationError):
        calibrate_picture(image, markers_mm=markers)


def test_homography_from_points_matches_a_hand_built_mapping():
    # 0.5 mm per px, origin at pixel (20, 580), v downwards: x = 0.5 (u - 20), y = 0.5 (580 - v)
    pixels = np.array([[20.0, 580.0], [620.0, 580.0], [620.0, 80.0], [20.0, 80.0], [300.0, 300.0]])
    floor = np.column_stack([0.5 * (pixels[:, 0] - 20), 0.5 * (580 - pixels[:, 1])])
    calibration = calibration_from_points(pixels, floor)
    probe = np.array([[111.0, 222.0], [600.5, 100.25]])
    np.testing.assert_allclose(
        calibration.to_mm(probe),
        np.column_stack([0.5 * (probe[:, 0] - 20), 0.5 * (580 - probe[:, 1])]),
        atol=1e-6,
    )
    np.testing.assert_allclose(calibration.mm_per_px(probe), [0.5, 0.5], rtol=1e-6)
    assert calibration.residual_mm < 1e-6
    assert calibration.floor_angle_deg() == pytest.approx(0.0, abs=1e-6)


def test_calibration_survives_the_rig_file():
    camera = CameraModel.overhead(WORKSPACE.bounds, tilt_deg=10, distortion=(-0.1, 0.0, 0, 0, 0))
    calibration = calibrate_picture(
        picture(camera), corners_mm=boundary_corners_mm(BOUNDARY),
        camera_matrix=camera.camera_matrix, dist_coeffs=camera.dist_coeffs,
    )
    text = tomli_w.dumps({"camera": {"calibration": calibration.model_dump(exclude_none=True)}})
    back = Calibration.model_validate(tomllib.loads(text)["camera"]["calibration"])
    probe = camera.project(GRID)
    np.testing.assert_allclose(back.to_mm(probe), calibration.to_mm(probe), atol=1e-9)


def test_a_singular_homography_is_refused():
    with pytest.raises(ValidationError):
        Calibration(homography_px_to_mm=[[1, 0, 0], [2, 0, 0], [0, 0, 1]])
    with pytest.raises(ValidationError):
        Calibration(homography_px_to_mm=[[1, 0], [0, 1]])


def test_boundary_corners_come_counter_clockwise():
    np.testing.assert_allclose(boundary_corners_mm(("rect", (10, 20, 30, 40))),
                               [[10, 20], [40, 20], [40, 60], [10, 60]])
    clockwise = [(0, 0), (0, 10), (10, 10), (10, 0)]
    corners = boundary_corners_mm(("polygon", clockwise))
    x, y = corners[:, 0], corners[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    assert area == pytest.approx(100.0)
    with pytest.raises(CalibrationError):
        boundary_corners_mm(("disk", (0, 0, 5)))


def test_the_floor_corners_are_the_free_floors_where_walls_line_the_boundary():
    from rigctl.plans.workspace import ShapeWorkspace
    from rigctl.vision.calibration import floor_corners_mm

    walls = [("rect", (0, 0, 400, 50)), ("rect", (0, 350, 400, 50)), ("rect", (0, 0, 50, 400)),
             ("rect", (350, 0, 50, 400)), ("rect", (150, 150, 25, 100))]  # and one inside
    maze = floor_corners_mm(ShapeWorkspace(("rect", (0, 0, 400, 400)), walls), 4)
    inner = np.array([[50, 50], [350, 50], [350, 350], [50, 350]], dtype=float)
    start = int(np.argmin(np.hypot(*(maze - inner[0]).T)))  # counter-clockwise, from any corner
    np.testing.assert_allclose(np.roll(maze, -start, axis=0), inner, atol=0.1)
    open_floor = floor_corners_mm(ShapeWorkspace(("polygon", [(0, 0), (60, 10), (20, 50)])), 3)
    start = int(np.argmin(np.hypot(*open_floor.T)))
    np.testing.assert_allclose(np.roll(open_floor, -start, axis=0), [[0, 0], [60, 10], [20, 50]],
                               atol=0.05)
