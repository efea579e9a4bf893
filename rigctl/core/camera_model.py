"""The camera's pixel -> floor map: lens intrinsics and a plane homography (the rig file's
`[camera.calibration]` table). `rigctl.vision.calibration` fits it; the tracker and the emulated
camera apply it."""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import ArrayLike
from pydantic import BaseModel, ConfigDict, PrivateAttr, field_validator

from rigctl.core.errors import RigError

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)


class CalibrationError(RigError, ValueError):
    """The picture does not show what the calibration needs (corners, markers), or the fit is poor."""


class Calibration(BaseModel):
    """Pixel -> floor mapping of one camera (the rig file's `[camera.calibration]` table).

    homography_px_to_mm: 3 x 3, undistorted pixel (u, v, 1) -> floor (x, y, 1) mm up to scale;
    camera_matrix (3 x 3 px) and dist_coeffs (k1, k2, p1, p2, k3) when the lens distortion is
    removed first; resolution: (width, height) px the calibration was made at; residual_mm: RMS
    distance between the fitted and the known floor points.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    homography_px_to_mm: list[list[float]]
    camera_matrix: list[list[float]] | None = None
    dist_coeffs: list[float] | None = None
    resolution: tuple[int, int] | None = None
    residual_mm: float | None = None

    @field_validator("homography_px_to_mm")
    @classmethod
    def _invertible_3x3(cls, h: list[list[float]]) -> list[list[float]]:
        matrix = np.asarray(h, dtype=float)
        if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
            raise ValueError("homography_px_to_mm must be 3 rows of 3 finite numbers")
        if abs(np.linalg.det(matrix)) < 1e-300:
            raise ValueError("homography_px_to_mm is singular")
        return h

    @field_validator("camera_matrix")
    @classmethod
    def _matrix_3x3(cls, k: list[list[float]] | None) -> list[list[float]] | None:
        if k is not None and np.asarray(k, dtype=float).shape != (3, 3):
            raise ValueError("camera_matrix must be 3 rows of 3 numbers")
        return k

    _cache: tuple | None = PrivateAttr(default=None)

    def _arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """H, its inverse, K and the distortion as arrays, made once per set of field values.

        The cache remembers which field objects it was made from: `model_copy(update=...)` copies
        private attributes, and the copy must not reuse the original's arrays.
        """
        key = (id(self.homography_px_to_mm), id(self.camera_matrix), id(self.dist_coeffs))
        if self._cache is None or self._cache[0] != key:
            h = np.asarray(self.homography_px_to_mm, dtype=float)
            k = None if self.camera_matrix is None else np.asarray(self.camera_matrix, dtype=float)
            d = None
            if self.dist_coeffs is not None:
                d = np.zeros(max(5, len(self.dist_coeffs)))
                d[: len(self.dist_coeffs)] = self.dist_coeffs
            self._cache = (key, (h, np.linalg.inv(h), k, d))
        return self._cache[1]

    @property
    def homography(self) -> np.ndarray:
        """(3, 3) undistorted px -> mm."""
        return self._arrays()[0]

    def undistort(self, pixels: ArrayLike) -> np.ndarray:
        """Pixels (n, 2) with the lens distortion removed (unchanged without intrinsics)."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        _, _, k, d = self._arrays()
        if k is None or d is None or len(px) == 0 or not np.any(d):
            return px
        return cv2.undistortPoints(
            px.reshape(-1, 1, 2), k, d, P=k, criteria=UNDISTORT_CRITERIA
        ).reshape(-1, 2)

    def to_mm(self, pixels: ArrayLike) -> np.ndarray:
        """Floor points (n, 2) mm seen at pixels (n, 2)."""
        return apply_homography(self._arrays()[0], self.undistort(pixels))

    def to_px(self, points_mm: ArrayLike) -> np.ndarray:
        """Pixels (n, 2) where floor points (n, 2) mm appear, lens distortion included."""
        _, inverse, k, d = self._arrays()
        px = apply_homography(inverse, np.asarray(points_mm, dtype=float).reshape(-1, 2))
        if k is None or d is None or not np.any(d) or len(px) == 0:
            return px
        normalised = apply_homography(np.linalg.inv(k), px)
        world = np.column_stack([normalised, np.ones(len(px))])
        projected, _ = cv2.projectPoints(world, np.zeros(3), np.zeros(3), k, d)
        return projected.reshape(-1, 2)

    def mm_per_px(self, pixels: ArrayLike) -> np.ndarray:
        """Side (mm) of the floor patch a pixel sees at pixels (n, 2): sqrt |det J| (undistorted)."""
        px = self.undistort(pixels)
        h = self._arrays()[0]
        step = 0.5
        dx = (apply_homography(h, px + [step, 0.0]) - apply_homography(h, px - [step, 0.0])) / (2 * step)
        dy = (apply_homography(h, px + [0.0, step]) - apply_homography(h, px - [0.0, step])) / (2 * step)
        return np.sqrt(np.abs(dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]))

    def floor_angle_deg(self) -> float:
        """Screen angle (deg, counter-clockwise as seen) of the floor's +x at the picture centre."""
        return x_axis_angle_deg(self._arrays()[1], self.resolution)


def apply_homography(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    q = p @ h[:, :2].T + h[:, 2]
    return q[:, :2] / q[:, 2:3]


def x_axis_angle_deg(h_mm_to_px: np.ndarray, resolution: tuple[int, int] | None) -> float:
    """The angle in the picture of the floor's +x direction where the picture's centre looks."""
    centre_px = (
        np.array([[(resolution[0] - 1) / 2.0, (resolution[1] - 1) / 2.0]])
        if resolution is not None else np.zeros((1, 2))
    )
    centre_mm = apply_homography(np.linalg.inv(h_mm_to_px), centre_px)
    ends = apply_homography(h_mm_to_px, np.vstack([centre_mm, centre_mm + [1.0, 0.0]]))
    du, dv = ends[1] - ends[0]
    return math.degrees(math.atan2(-dv, du))  # v grows downwards: flip it for a screen angle
