"""The emulated overhead camera's picture: a pinhole camera above the floor, drawn per pixel.

Nothing is drawn in image space and then warped. The camera model gives, once, the point of the floor
(z = 0, mm) that every pixel centre looks at, through the lens distortion and the perspective of a
tilted camera; the picture is then the floor's appearance at those points. The workspace (floor,
obstacles, the wall outside the boundary) comes from the workspace's clearance, the robots are discs
of their radius whose coverage of each pixel is computed from the distance of that pixel's floor
point to the robot's centre. Whatever the tracker finds must therefore be where the scene put it:
the renderer has no notion of pixels-per-mm or of the homography the tracker uses.

Per frame only the robots' neighbourhoods are drawn; the workspace layer (lit, blurred) is cached for
the workspace object it was made for. Sensor noise is read from a bank of seeded Gaussian noise at a
random offset each frame, which costs a copy instead of a million random draws.

Conventions: images are (H, W, 3) uint8 BGR, pixel (u, v) = (column, row) with the centre of the
top-left pixel at (0, 0) as in OpenCV. World points are (x, y) mm on the floor; the camera looks down
so that world +y is up in the picture (before tilt and yaw).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.camera_model import Calibration
from rigctl.plans.workspace import Workspace

log = logging.getLogger(__name__)

PAPER_RESOLUTION = (659, 494)  # (width, height) px of the seeds' overhead camera
PAPER_FPS = 60.0

_NOISE_PAD = 64  # the noise bank is this much larger than the image in each direction


class CameraModel:
    """A pinhole camera with OpenCV's distortion model, looking at the floor plane z = 0.

    camera_matrix: (3, 3) intrinsics K in px; dist_coeffs: (5,) k1, k2, p1, p2, k3;
    rotation: (3, 3) world -> camera; translation_mm: (3,) so that X_cam = R X_world + t.
    The camera's z axis points from the camera towards the scene; image v grows downwards.
    """

    def __init__(
        self,
        width_px: int,
        height_px: int,
        camera_matrix: ArrayLike,
        dist_coeffs: ArrayLike,
        rotation: ArrayLike,
        translation_mm: ArrayLike,
    ) -> None:
        self.width_px = int(width_px)
        self.height_px = int(height_px)
        self.camera_matrix = np.asarray(camera_matrix, dtype=float).reshape(3, 3)
        self.dist_coeffs = np.zeros(5)
        coeffs = np.asarray(dist_coeffs, dtype=float).reshape(-1)
        self.dist_coeffs[: len(coeffs)] = coeffs
        self.rotation = np.asarray(rotation, dtype=float).reshape(3, 3)
        self.translation_mm = np.asarray(translation_mm, dtype=float).reshape(3)
        self._rvec = cv2.Rodrigues(self.rotation)[0]

    @classmethod
    def overhead(
        cls,
        bounds_mm: Sequence[float],
        *,
        resolution: tuple[int, int] = PAPER_RESOLUTION,
        height_mm: float = 600.0,
        tilt_deg: float = 0.0,
        tilt_azimuth_deg: float = 0.0,
        yaw_deg: float = 0.0,
        margin: float = 0.04,
        distortion: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0),
    ) -> "CameraModel":
        """A camera `height_mm` from the centre of `bounds_mm` (xmin, ymin, xmax, ymax), facing it.

        tilt_deg: angle between the optical axis and the vertical; the camera leans away from the
        centre towards `tilt_azimuth_deg` (0 = +x). yaw_deg turns the picture about the optical axis.
        The focal length is chosen so the bounds fill the picture but for `margin` (a fraction of the
        width and height) on every side, without distortion.
        """
        width, height = int(resolution[0]), int(resolution[1])
        xmin, ymin, xmax, ymax = (float(b) for b in bounds_mm)
        target = np.array([(xmin + xmax) / 2.0, (ymin + ymax) / 2.0, 0.0])
        tilt, azimuth, yaw = (math.radians(a) for a in (tilt_deg, tilt_azimuth_deg, yaw_deg))
        towards_camera = np.array(
            [math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)]
        )
        eye = target + height_mm * towards_camera
        z_axis = -towards_camera
        up_hint = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        y_axis = -(up_hint - (up_hint @ z_axis) * z_axis)  # image rows grow away from "up"
        y_axis /= np.linalg.norm(y_axis)
        x_axis = np.cross(y_axis, z_axis)
        rotation = np.stack([x_axis, y_axis, z_axis])
        translation = -rotation @ eye
        corners = np.array([[xmin, ymin, 0], [xmax, ymin, 0], [xmax, ymax, 0], [xmin, ymax, 0]])
        cam = corners @ rotation.T + translation
        xn, yn = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
        focal = min(
            (0.5 - margin) * width / max(np.max(np.abs(xn)), 1e-12),
            (0.5 - margin) * height / max(np.max(np.abs(yn)), 1e-12),
        )
        matrix = np.array(
            [[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
        )
        return cls(width, height, matrix, distortion, rotation, translation)

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in px."""
        return (self.width_px, self.height_px)

    @property
    def homography_mm_to_px(self) -> np.ndarray:
        """(3, 3) floor mm -> undistorted px: K [r1 r2 t], scaled so that H[2, 2] = 1."""
        h = self.camera_matrix @ np.column_stack(
            [self.rotation[:, 0], self.rotation[:, 1], self.translation_mm]
        )
        return h / h[2, 2]

    def calibration(self) -> Calibration:
        """This camera's exact pixel -> floor calibration (what a perfect calibration would find)."""
        h = np.linalg.inv(self.homography_mm_to_px)
        return Calibration(
            homography_px_to_mm=(h / h[2, 2]).tolist(),
            camera_matrix=self.camera_matrix.tolist(),
            dist_coeffs=self.dist_coeffs.tolist(),
            resolution=self.resolution,
            residual_mm=0.0,
        )

    def project(self, points_mm: ArrayLike) -> np.ndarray:
        """Pixel positions (n, 2) of floor points (n, 2) mm, lens distortion included."""
        p = np.asarray(points_mm, dtype=float).reshape(-1, 2)
        if len(p) == 0:
            return np.zeros((0, 2))
        world = np.column_stack([p, np.zeros(len(p))])
        px, _ = cv2.projectPoints(
            world, self._rvec, self.translation_mm, self.camera_matrix, self.dist_coeffs
        )
        return px.reshape(-1, 2)

    def floor_points(self, pixels: ArrayLike) -> np.ndarray:
        """Floor points (n, 2) mm seen at pixels (n, 2), lens distortion removed."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if len(px) == 0:
            return np.zeros((0, 2))
        normalised = cv2.undistortPoints(
            px, self.camera_matrix, self.dist_coeffs,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10),
        ).reshape(-1, 2)
        plane = np.column_stack([self.rotation[:, 0], self.rotation[:, 1], self.translation_mm])
        rays = np.column_stack([normalised, np.ones(len(normalised))])
        world = rays @ np.linalg.inv(plane).T
        return world[:, :2] / world[:, 2:3]

    def floor_map(self) -> np.ndarray:
        """(H, W, 2) floor point (mm) at every pixel centre."""
        v, u = np.mgrid[0 : self.height_px, 0 : self.width_px]
        pixels = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
        return self.floor_points(pixels).reshape(self.height_px, self.width_px, 2)


@dataclass(frozen=True)
class Appearance:
    """Colours (BGR, 0-255) and imperfections of the emulated picture.

    lighting_gradient: relative brightness change from one side of the picture to the other, along
    `lighting_angle_deg` (0 = towards +u); vignetting: relative darkening in the corners;
    noise_sigma: sensor noise, grey levels (1 sigma); blur_sigma_px: Gaussian blur of the optics.
    """

    floor_bgr: tuple[float, float, float] = (188.0, 198.0, 204.0)
    obstacle_bgr: tuple[float, float, float] = (150.0, 124.0, 108.0)
    robot_bgr: tuple[float, float, float] = (40.0, 38.0, 42.0)
    glare_bgr: tuple[float, float, float] = (246.0, 246.0, 246.0)
    lighting_gradient: float = 0.25
    lighting_angle_deg: float = 30.0
    vignetting: float = 0.12
    noise_sigma: float = 3.0
    blur_sigma_px: float = 0.8


@dataclass(frozen=True)
class Scene:
    """What the camera sees at one instant.

    positions_mm: (n, 2) robot centres; radii_mm: (n,) robot radii; occluders_mm: (m, 3) glare discs
    (x, y, radius) drawn over everything (a reflection, a hand, a tool in the way).
    """

    workspace: Workspace
    positions_mm: np.ndarray
    radii_mm: np.ndarray
    occluders_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


class Renderer:
    """Draws scenes as seen by one camera. Not thread-safe: one renderer per rendering thread.

    The workspace layer is made on the first frame of a workspace and reused while the scene's
    workspace is the same object. `seed` fixes the noise, so equal scenes give equal frames.
    """

    def __init__(
        self, camera: CameraModel, appearance: Appearance = Appearance(), *, seed: int = 0
    ) -> None:
        self.camera = camera
        self.appearance = appearance
        self._rng = np.random.default_rng(seed)
        self._floor = camera.floor_map()  # (H, W, 2) mm
        self._mm_per_px = _pixel_size_mm(self._floor)  # (H, W)
        self._gain = _lighting(camera.resolution, appearance)  # (H, W) relative brightness
        height, width = camera.height_px, camera.width_px
        self._noise = (
            self._rng.standard_normal((height + _NOISE_PAD, width + _NOISE_PAD), dtype=np.float32)
            * np.float32(appearance.noise_sigma)
        )
        self._workspace: Workspace | None = None
        self._sharp: np.ndarray | None = None  # (H, W, 3) float32, lit
        self._background: np.ndarray | None = None  # the same, blurred
        blur = appearance.blur_sigma_px
        self._blur_margin = int(math.ceil(3 * blur)) + 1 if blur > 0 else 0

    def background(self, workspace: Workspace) -> np.ndarray:
        """The lit, blurred picture of the empty workspace, (H, W, 3) float32."""
        return self._layers(workspace)[1]

    def _layers(self, workspace: Workspace) -> tuple[np.ndarray, np.ndarray]:
        """The empty workspace, lit, before and after the blur; both (H, W, 3) float32."""
        if self._background is None or workspace is not self._workspace:
            clearance = workspace.clearance(self._floor.reshape(-1, 2)).reshape(self._mm_per_px.shape)
            free = np.clip(clearance / self._mm_per_px + 0.5, 0.0, 1.0)[..., None]
            floor = np.asarray(self.appearance.floor_bgr, dtype=np.float32)
            obstacle = np.asarray(self.appearance.obstacle_bgr, dtype=np.float32)
            sharp = (obstacle + free * (floor - obstacle)) * self._gain[..., None]
            sharp = sharp.astype(np.float32)
            self._sharp = sharp
            self._background = self._blur(sharp)
            self._workspace = workspace
        assert self._sharp is not None  # made with the background
        return self._sharp, self._background

    def render(self, scene: Scene) -> np.ndarray:
        """The camera's picture of `scene`, (H, W, 3) uint8 BGR."""
        sharp, blurred = self._layers(scene.workspace)
        picture = blurred.copy()
        positions = np.asarray(scene.positions_mm, dtype=float).reshape(-1, 2)
        radii = np.broadcast_to(np.asarray(scene.radii_mm, dtype=float), (len(positions),))
        robots = [(centre, float(radius)) for centre, radius in zip(positions, radii)]
        robot_colour = np.asarray(self.appearance.robot_bgr, dtype=np.float32)
        glare_colour = np.asarray(self.appearance.glare_bgr, dtype=np.float32)
        # The blurred background is reused, and blur is linear: adding the blurred change each disc
        # makes to the sharp picture gives the blurred picture with the discs in it. Robots never
        # overlap one another; occluders are drawn over the robots beneath them.
        for centre, radius in robots:
            box = self._pixel_box(centre, radius)
            if box is not None:
                region = _region(box)
                cover = self._cover(box, centre, radius)
                change = cover[..., None] * (robot_colour * self._gain[region][..., None]
                                             - sharp[region])
                picture[region] += self._blur(change)
        for x, y, radius in np.asarray(scene.occluders_mm, dtype=float).reshape(-1, 3):
            centre = np.array([x, y])
            box = self._pixel_box(centre, radius)
            if box is None:
                continue
            region = _region(box)
            gain = self._gain[region][..., None]
            beneath = sharp[region].copy()
            for robot_centre, robot_radius in robots:
                cover = self._cover(box, robot_centre, robot_radius)
                beneath += cover[..., None] * (robot_colour * gain - beneath)
            cover = self._cover(box, centre, radius)
            picture[region] += self._blur(cover[..., None] * (glare_colour * gain - beneath))
        return self._expose(picture)

    def blank(self) -> np.ndarray:
        """A black frame with sensor noise (the lens cap on, the lamp off), (H, W, 3) uint8."""
        return self._expose(np.zeros((self.camera.height_px, self.camera.width_px, 3), np.float32))

    # -- drawing --------------------------------------------------------------------------------

    def _cover(self, box: tuple[int, int, int, int], centre: np.ndarray, radius: float) -> np.ndarray:
        """Fraction (h, w) float32 of each pixel of `box` covered by the disc (centre, radius)."""
        region = _region(box)
        floor = self._floor[region]
        distance = np.hypot(floor[..., 0] - centre[0], floor[..., 1] - centre[1])
        return np.clip((radius - distance) / self._mm_per_px[region] + 0.5, 0, 1).astype(np.float32)

    def _pixel_box(self, centre: np.ndarray, radius: float) -> tuple[int, int, int, int] | None:
        """Rows [top, bottom) and columns [left, right) that a disc (plus blur) can touch."""
        angles = np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False)
        ring = centre + 1.1 * radius * np.column_stack([np.cos(angles), np.sin(angles)])
        px = self.camera.project(np.vstack([ring, centre]))
        pad = 2 + self._blur_margin
        left = int(math.floor(px[:, 0].min())) - pad
        right = int(math.ceil(px[:, 0].max())) + pad + 1
        top = int(math.floor(px[:, 1].min())) - pad
        bottom = int(math.ceil(px[:, 1].max())) + pad + 1
        left, top = max(left, 0), max(top, 0)
        right, bottom = min(right, self.camera.width_px), min(bottom, self.camera.height_px)
        if left >= right or top >= bottom:
            return None
        return top, bottom, left, right

    def _blur(self, picture: np.ndarray) -> np.ndarray:
        sigma = self.appearance.blur_sigma_px
        if sigma <= 0:
            return picture
        return cv2.GaussianBlur(picture, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)

    def _expose(self, picture: np.ndarray) -> np.ndarray:
        """Add sensor noise and quantise to uint8."""
        height, width = picture.shape[:2]
        dy, dx = self._rng.integers(0, _NOISE_PAD, size=2)
        noise = self._noise[dy : dy + height, dx : dx + width]
        picture += noise[..., None]
        np.clip(picture, 0.0, 255.0, out=picture)
        return (picture + 0.5).astype(np.uint8)


def _region(box: tuple[int, int, int, int]) -> tuple[slice, slice]:
    top, bottom, left, right = box
    return slice(top, bottom), slice(left, right)


def _pixel_size_mm(floor: np.ndarray) -> np.ndarray:
    """Side (mm) of the floor patch each pixel sees, (H, W): sqrt of the Jacobian's determinant."""
    d_du = np.gradient(floor, axis=1)
    d_dv = np.gradient(floor, axis=0)
    area = np.abs(d_du[..., 0] * d_dv[..., 1] - d_du[..., 1] * d_dv[..., 0])
    return np.sqrt(np.maximum(area, 1e-12))


def _lighting(resolution: tuple[int, int], appearance: Appearance) -> np.ndarray:
    """Relative brightness (H, W) float32: a linear gradient times a radial vignette."""
    width, height = resolution
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    su = (u - (width - 1) / 2.0) / width
    sv = (v - (height - 1) / 2.0) / height
    angle = math.radians(appearance.lighting_angle_deg)
    gradient = 1.0 + appearance.lighting_gradient * (su * math.cos(angle) + sv * math.sin(angle))
    r2 = (su**2 + sv**2) / 0.5
    return (gradient * (1.0 - appearance.vignetting * r2)).astype(np.float32)
