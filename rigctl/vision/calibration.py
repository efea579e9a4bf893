"""Camera calibration: which floor point (mm) each pixel sees.

The floor is a plane, so after the lens distortion is removed a pixel maps to the floor by a plane
homography H (3 x 3, undistorted px -> mm). Four or more points whose floor positions are known fix
H: the corners of the workspace boundary, or markers (robots or dots) put at known places. Lens
distortion cannot be told from perspective with so few points; when it matters, the camera's
intrinsics (K and OpenCV's k1 k2 p1 p2 k3, from a checkerboard calibration) are given and the
points are undistorted before H is fitted.

`calibrate_camera` is what `rigctl calibrate camera` runs: grab a few frames, average them, find
the boundary corners (or the markers), fit H, report the fit residual. The result is a
`Calibration`, stored in the rig file's `[camera.calibration]` table.

Corners and markers are matched to their floor positions by geometry, not by order: the boundary is
a convex polygon whose corners keep their cyclic order in the picture (a camera does not mirror),
and of its n rotations the one that best agrees with `orientation_deg` is chosen: the angle on
screen, counter-clockwise as seen, of the floor's +x axis (0 = pointing right). For markers every
assignment of four of them is tried and the one that places all markers best wins (ties again
broken by the orientation).
"""

from __future__ import annotations

import itertools
import logging

import cv2
import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.camera_model import (
    UNDISTORT_CRITERIA,
    Calibration,
    CalibrationError,
    apply_homography,
    x_axis_angle_deg,
)
from rigctl.core.errors import ConfigError
from rigctl.physics.geometry import signed_area

log = logging.getLogger(__name__)


def _flips_handedness(h_px_to_mm: np.ndarray, pixels: np.ndarray) -> bool:
    """True when the map turns picture handedness (v down) into floor handedness (y up), as every
    camera that does not mirror must; tested at the pixels' centroid."""
    centre = pixels.mean(axis=0)
    a, b, c = apply_homography(h_px_to_mm, np.vstack([centre, centre + [1.0, 0.0], centre + [0.0, 1.0]]))
    du, dv = b - a, c - a
    return float(du[0] * dv[1] - du[1] * dv[0]) < 0


def _angle_gap_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def calibration_from_points(
    pixels: ArrayLike,
    points_mm: ArrayLike,
    *,
    camera_matrix: ArrayLike | None = None,
    dist_coeffs: ArrayLike | None = None,
    resolution: tuple[int, int] | None = None,
) -> Calibration:
    """Fit the homography to n >= 4 pixel / floor-point pairs, (n, 2) each (least squares, n > 4)."""
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    mm = np.asarray(points_mm, dtype=np.float64).reshape(-1, 2)
    if len(px) != len(mm):
        raise CalibrationError(f"{len(px)} pixels for {len(mm)} floor points", device="camera")
    if len(px) < 4:
        raise CalibrationError(f"need at least 4 points, got {len(px)}", device="camera")
    lens = _lens(camera_matrix, dist_coeffs)
    return _fit(lens, lens.undistort(px), mm, resolution)


def _lens(camera_matrix: ArrayLike | None, dist_coeffs: ArrayLike | None) -> Calibration:
    """A calibration that only knows the lens (identity homography): for undistorting points."""
    return Calibration(
        homography_px_to_mm=np.eye(3).tolist(),
        camera_matrix=None if camera_matrix is None else np.asarray(camera_matrix, float).tolist(),
        dist_coeffs=None if dist_coeffs is None else np.asarray(dist_coeffs, float).ravel().tolist(),
    )


def _fit(
    lens: Calibration, undistorted: np.ndarray, mm: np.ndarray, resolution: tuple[int, int] | None
) -> Calibration:
    """The least-squares homography from undistorted pixels (n, 2) to floor points (n, 2)."""
    h, _ = cv2.findHomography(undistorted, mm, 0)
    if h is None:
        raise CalibrationError(
            "the points do not determine a homography (collinear?)", device="camera"
        )
    residual = float(np.sqrt(np.mean(np.sum((apply_homography(h, undistorted) - mm) ** 2, axis=1))))
    return Calibration(
        homography_px_to_mm=(h / h[2, 2]).tolist(),
        camera_matrix=lens.camera_matrix,
        dist_coeffs=lens.dist_coeffs,
        resolution=resolution,
        residual_mm=residual,
    )


# -- corners ----------------------------------------------------------------------------------------


def find_boundary_corners(
    image: np.ndarray,
    n_corners: int = 4,
    *,
    camera_matrix: ArrayLike | None = None,
    dist_coeffs: ArrayLike | None = None,
) -> np.ndarray:
    """The n corners (n, 2) px (undistorted if intrinsics are given) of the bright floor region.

    The floor is the largest bright region (Otsu threshold); its outline, simplified to an n-gon,
    gives the sides roughly. Each side is then measured to a fraction of a pixel: across it, at
    points along the outline, the picture's profile is read and the edge put where it crosses
    half-way between the floor's and the wall's local grey (so an uneven lighting does not move it);
    a line is fitted to those edge points (undistorted first), and the corners are the
    intersections of neighbouring lines. Returned clockwise on screen, starting anywhere.
    """
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    smooth = cv2.GaussianBlur(gray, (5, 5), 0)
    _, bright = cv2.threshold(smooth, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=4)
    if count < 2:
        raise CalibrationError("no bright floor region in the picture", device="camera")
    floor_label = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    floor = np.where(labels == floor_label, 255, 0).astype(np.uint8)
    contours, _ = cv2.findContours(floor, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    vertices_at = _polygon_vertices(outline, n_corners)
    rough = outline[vertices_at]
    middle = rough.mean(axis=0)
    profile_image = cv2.GaussianBlur(gray, (3, 3), 0).astype(np.float32)
    lines = []
    for i in range(n_corners):
        start, stop = vertices_at[i], vertices_at[(i + 1) % n_corners]
        side = outline[start:stop] if stop > start else np.vstack([outline[start:], outline[:stop]])
        trim = max(3, len(side) // 10)  # the outline rounds off near the corners
        side = side[trim:-trim]
        if len(side) < 4:
            raise CalibrationError("a boundary side is too short to measure", device="camera")
        side = side[:: max(1, len(side) // 60)]
        chord = rough[(i + 1) % n_corners] - rough[i]
        normal = np.array([chord[1], -chord[0]]) / np.linalg.norm(chord)
        if (side.mean(axis=0) - middle) @ normal < 0:
            normal = -normal  # pointing out of the floor
        edges = _edge_points(profile_image, side, normal)
        if len(edges) < 4:
            raise CalibrationError("could not measure a boundary side (covered?)", device="camera")
        if camera_matrix is not None and dist_coeffs is not None:
            k = np.asarray(camera_matrix, dtype=float)
            edges = cv2.undistortPoints(
                edges.reshape(-1, 1, 2), k, np.asarray(dist_coeffs, dtype=float), P=k,
                criteria=UNDISTORT_CRITERIA,
            ).reshape(-1, 2)
        vx, vy, x0, y0 = cv2.fitLine(edges.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
        lines.append((np.array([x0, y0], float), np.array([vx, vy], float)))
    corners = np.array(
        [_intersect(lines[i - 1], lines[i]) for i in range(n_corners)], dtype=float
    )
    if signed_area(corners) < 0:  # findContours order varies; report clockwise on screen
        corners = corners[::-1]
    return corners


def _edge_points(gray: np.ndarray, points: np.ndarray, normal: np.ndarray,
                 reach_px: float = 8.0, step_px: float = 0.25) -> np.ndarray:
    """Where the grey level crosses half-way from the floor to the wall, along `normal` (pointing to
    the wall) through each of `points` (m, 2); a point whose profile has no clean crossing is
    left out."""
    offsets = np.arange(-reach_px, reach_px + step_px / 2, step_px)
    samples = points[:, None, :] + offsets[None, :, None] * normal[None, None, :]
    map_x = samples[..., 0].astype(np.float32)
    map_y = samples[..., 1].astype(np.float32)
    profiles = cv2.remap(gray, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ends = max(2, len(offsets) // 8)
    inside = profiles[:, :ends].mean(axis=1)
    outside = profiles[:, -ends:].mean(axis=1)
    level = (inside + outside) / 2.0
    found = []
    for row, profile in enumerate(profiles):
        if inside[row] - outside[row] < 10.0:
            continue
        below = np.nonzero(profile <= level[row])[0]
        if len(below) == 0 or below[0] == 0:
            continue
        j = below[0]
        a, b = profile[j - 1], profile[j]
        fraction = (a - level[row]) / (a - b) if a != b else 0.5
        offset = offsets[j - 1] + fraction * step_px
        found.append(points[row] + offset * normal)
    return np.array(found).reshape(-1, 2)


def _polygon_vertices(outline: np.ndarray, n: int) -> list[int]:
    """Indices into `outline` of the n vertices of its simplification to an n-gon."""
    perimeter = cv2.arcLength(outline.astype(np.float32).reshape(-1, 1, 2), True)
    low, high = 0.001 * perimeter, 0.2 * perimeter
    for _ in range(40):
        epsilon = (low + high) / 2
        approx = cv2.approxPolyDP(outline.astype(np.float32).reshape(-1, 1, 2), epsilon, True)
        if len(approx) > n:
            low = epsilon
        elif len(approx) < n:
            high = epsilon
        else:
            points = approx.reshape(-1, 2)
            index = [int(np.argmin(np.sum((outline - p) ** 2, axis=1))) for p in points]
            return sorted(index)
    raise CalibrationError(
        f"the floor's outline is not a {n}-gon (are all boundary corners in view and nothing "
        "covering the boundary?)", device="camera",
    )


def _intersect(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    (p, d), (q, e) = a, b
    matrix = np.column_stack([d, -e])
    if abs(np.linalg.det(matrix)) < 1e-9:
        raise CalibrationError("two neighbouring boundary sides are parallel", device="camera")
    s, _ = np.linalg.solve(matrix, q - p)
    return p + s * d


def calibration_from_corners(
    corners_px: ArrayLike,
    corners_mm: ArrayLike,
    *,
    orientation_deg: float = 0.0,
    camera_matrix: ArrayLike | None = None,
    dist_coeffs: ArrayLike | None = None,
    resolution: tuple[int, int] | None = None,
) -> Calibration:
    """Match the picture's boundary corners (n, 2) (undistorted px, any rotation) to the boundary's
    floor corners (n, 2) mm (in order around the boundary) and fit.

    The picture order is taken as the floor order seen through a camera that does not mirror; of the
    n cyclic rotations, the best fit wins, and among equally good fits the one whose floor +x axis
    points closest to `orientation_deg` in the picture.
    """
    px = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    mm = np.asarray(corners_mm, dtype=float).reshape(-1, 2)
    n = len(mm)
    if len(px) != n:
        raise CalibrationError(f"found {len(px)} corners, the boundary has {n}", device="camera")
    # Floor y is up and picture v is down: a camera that does not mirror flips the shoelace sign.
    if (signed_area(px) > 0) == (signed_area(mm) > 0):
        px = px[::-1]
    candidates = []
    for shift in range(n):
        rolled = np.roll(px, -shift, axis=0)
        h, _ = cv2.findHomography(rolled, mm, 0)
        if h is None:
            continue
        error = float(np.sqrt(np.mean(np.sum((apply_homography(h, rolled) - mm) ** 2, axis=1))))
        angle = x_axis_angle_deg(np.linalg.inv(h), resolution)
        candidates.append((error, _angle_gap_deg(angle, orientation_deg), shift))
    if not candidates:
        raise CalibrationError("no homography fits the corners", device="camera")
    best_error = min(c[0] for c in candidates)
    scale = float(np.max(np.ptp(mm, axis=0)))
    tied = [c for c in candidates if c[0] <= best_error + 1e-3 * scale]
    _, _, shift = min(tied, key=lambda c: c[1])
    # the corners are undistorted already: only the lens is carried over
    return _fit(_lens(camera_matrix, dist_coeffs), np.roll(px, -shift, axis=0), mm, resolution)


# -- markers ----------------------------------------------------------------------------------------


def calibration_from_markers(
    marker_px: ArrayLike,
    markers_mm: ArrayLike,
    *,
    orientation_deg: float = 0.0,
    tolerance_mm: float | None = None,
    camera_matrix: ArrayLike | None = None,
    dist_coeffs: ArrayLike | None = None,
    resolution: tuple[int, int] | None = None,
) -> Calibration:
    """Fit from markers seen at `marker_px` (m, 2) whose floor positions are `markers_mm` (n, 2), in no
    particular order (m >= n >= 4; extra detections are ignored).

    Every assignment of four detections to the first four markers is tried (m!/(m-4)! of them); the
    homography that puts the most markers within `tolerance_mm` (default: 2 % of the markers'
    extent) of a detection wins, then the smallest residual, then the orientation closest to
    `orientation_deg`. A symmetric pattern has several equal winners: the orientation decides.
    """
    detected = np.asarray(marker_px, dtype=float).reshape(-1, 2)
    known = np.asarray(markers_mm, dtype=float).reshape(-1, 2)
    if len(known) < 4:
        raise CalibrationError("need at least 4 markers", device="camera")
    if len(detected) < len(known):
        raise CalibrationError(
            f"saw {len(detected)} markers, expected {len(known)}", device="camera"
        )
    if len(detected) > 9:
        raise CalibrationError(f"too many marker candidates ({len(detected)})", device="camera")
    lens = _lens(camera_matrix, dist_coeffs)
    undistorted = lens.undistort(detected)
    extent = float(np.max(np.ptp(known, axis=0)))
    tolerance = 0.02 * extent if tolerance_mm is None else float(tolerance_mm)
    anchors = known[:4].astype(np.float32)
    best: tuple | None = None
    for chosen in itertools.permutations(range(len(detected)), 4):
        h = cv2.getPerspectiveTransform(undistorted[list(chosen)].astype(np.float32), anchors)
        if h is None or not np.all(np.isfinite(h)) or not _flips_handedness(h, undistorted):
            continue
        placed = apply_homography(h, undistorted)  # every detection on the floor
        gaps = np.linalg.norm(known[:, None, :] - placed[None, :, :], axis=2)
        nearest = gaps.min(axis=1)
        inliers = int(np.sum(nearest <= tolerance))
        rms = float(np.sqrt(np.mean(nearest**2)))
        key = (-inliers, round(rms / max(tolerance, 1e-12), 2))
        if best is None or key < best[0]:
            best = (key, [(h, np.argmin(gaps, axis=1))])
        elif key == best[0]:
            best[1].append((h, np.argmin(gaps, axis=1)))
    if best is None or -best[0][0] < len(known):
        found = 0 if best is None else -best[0][0]
        raise CalibrationError(
            f"only {found} of {len(known)} markers fit one homography", device="camera"
        )
    fits = []
    for h, match in best[1]:
        angle = x_axis_angle_deg(np.linalg.inv(h), resolution)
        fits.append((_angle_gap_deg(angle, orientation_deg), match))
    _, match = min(fits, key=lambda f: f[0])
    if len(set(match.tolist())) != len(known):
        raise CalibrationError("two markers matched the same detection", device="camera")
    return _fit(lens, undistorted[match], known, resolution)


# -- the `rigctl calibrate camera` logic ----------------------------------------------------------


def calibrate_camera(
    source: str | int,
    *,
    corners_mm: ArrayLike | None = None,
    markers_mm: ArrayLike | None = None,
    marker_radius_mm: float | None = None,
    orientation_deg: float = 0.0,
    camera_matrix: ArrayLike | None = None,
    dist_coeffs: ArrayLike | None = None,
    frames: int = 5,
    stamped: bool = False,
    timeout_s: float = 5.0,
    max_residual_mm: float = 1.0,
) -> Calibration:
    """Calibrate the camera at `source` (index, stream URL or video file) from one averaged picture.

    Give `corners_mm` (n, 2), the workspace boundary's corners in order (a rect's four corners), or
    `markers_mm` (n, 2), known floor positions of dark round markers (robots put there by hand) of
    radius `marker_radius_mm`. Raises CalibrationError when the residual exceeds `max_residual_mm`.
    """
    from rigctl.drivers.camera import CameraDriver

    if (corners_mm is None) == (markers_mm is None):
        raise ConfigError("give exactly one of corners_mm and markers_mm")
    with CameraDriver(source, stamped=stamped, timeout_s=timeout_s) as camera:
        pictures = []
        for _ in range(max(1, frames)):
            try:
                pictures.append(camera.read().image.astype(np.float32))
            except EOFError:
                break
    if not pictures:
        raise CalibrationError(f"no frame from {source}", device="camera")
    picture = (np.mean(pictures, axis=0) + 0.5).astype(np.uint8)
    return calibrate_picture(
        picture, corners_mm=corners_mm, markers_mm=markers_mm, marker_radius_mm=marker_radius_mm,
        orientation_deg=orientation_deg, camera_matrix=camera_matrix, dist_coeffs=dist_coeffs,
        max_residual_mm=max_residual_mm,
    )


def calibrate_picture(
    picture: np.ndarray,
    *,
    corners_mm: ArrayLike | None = None,
    markers_mm: ArrayLike | None = None,
    marker_radius_mm: float | None = None,
    orientation_deg: float = 0.0,
    camera_matrix: ArrayLike | None = None,
    dist_coeffs: ArrayLike | None = None,
    max_residual_mm: float = 1.0,
) -> Calibration:
    """`calibrate_camera` on a picture already taken, (H, W, 3) uint8."""
    height, width = picture.shape[:2]
    resolution = (width, height)
    if corners_mm is not None:
        corners = np.asarray(corners_mm, dtype=float).reshape(-1, 2)
        found = find_boundary_corners(
            picture, len(corners), camera_matrix=camera_matrix, dist_coeffs=dist_coeffs
        )
        calibration = calibration_from_corners(
            found, corners, orientation_deg=orientation_deg, camera_matrix=camera_matrix,
            dist_coeffs=dist_coeffs, resolution=resolution,
        )
    else:
        from rigctl.vision.tracker import find_dark_blobs

        markers = np.asarray(markers_mm, dtype=float).reshape(-1, 2)
        blobs = find_dark_blobs(picture, expected=len(markers))
        calibration = calibration_from_markers(
            blobs, markers, orientation_deg=orientation_deg, camera_matrix=camera_matrix,
            dist_coeffs=dist_coeffs, resolution=resolution,
        )
        if marker_radius_mm is not None:
            _check_marker_size(calibration, blobs, marker_radius_mm)
    if calibration.residual_mm is not None and calibration.residual_mm > max_residual_mm:
        raise CalibrationError(
            f"fit residual {calibration.residual_mm:.3g} mm exceeds {max_residual_mm} mm "
            "(wrong corners/markers, or lens distortion: give the camera intrinsics)",
            device="camera",
        )
    log.info("camera calibrated: residual %.3g mm", calibration.residual_mm or 0.0)
    return calibration


def _check_marker_size(calibration: Calibration, blobs: np.ndarray, radius_mm: float) -> None:
    """Markers too small to be measured, or a calibration that folds the floor, are errors."""
    scale = calibration.mm_per_px(blobs)
    if not np.all(np.isfinite(scale)) or np.any(scale <= 0):
        raise CalibrationError("the calibration folds the floor over", device="camera")
    if np.any(radius_mm / scale < 1.5):
        raise CalibrationError(
            f"markers of radius {radius_mm} mm are under 1.5 px in the picture", device="camera"
        )


def boundary_corners_mm(boundary: object) -> np.ndarray:
    """The corners (n, 2) mm, counter-clockwise, of a workspace boundary: a plan's shape
    (an object with `rect` or `polygon`) or a ("rect", (x, y, w, h)) / ("polygon", vertices) tuple."""
    if isinstance(boundary, tuple):
        kind, value = boundary
    else:
        kind, value = next(
            ((k, getattr(boundary, k)) for k in ("rect", "polygon", "disk")
             if getattr(boundary, k, None) is not None),
            (None, None),
        )
    if kind == "rect":
        x, y, w, h = (float(v) for v in value)
        return np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]])
    if kind == "polygon":
        vertices = np.asarray(value, dtype=float).reshape(-1, 2)
        return vertices if signed_area(vertices) > 0 else vertices[::-1]
    raise CalibrationError(
        f"a {kind} boundary has no corners; calibrate from markers instead", device="camera"
    )


def floor_corners_mm(workspace, n_corners: int, *, pitch_mm: float | None = None) -> np.ndarray:
    """The corners (n, 2) mm, counter-clockwise, of the floor the camera sees bright: the outline
    of the workspace's free space (`workspace`: a `rigctl.plans.workspace.Workspace`), which is
    the boundary's unless obstacles line it (the walls of a maze). Found as the camera's are, by
    `find_boundary_corners` on a top-down picture of the free space at `pitch_mm` per pixel
    (default: 1/1500 of its larger side)."""
    xmin, ymin, xmax, ymax = workspace.bounds
    pitch_mm = pitch_mm or max(xmax - xmin, ymax - ymin) / 1500.0
    margin = 4 * pitch_mm
    xs = np.arange(xmin - margin, xmax + margin, pitch_mm)
    ys = np.arange(ymin - margin, ymax + margin, pitch_mm)[::-1]  # rows downwards: y up, unmirrored
    grid = np.stack(np.meshgrid(xs, ys), axis=-1)
    clearance = workspace.clearance(grid.reshape(-1, 2)).reshape(grid.shape[:2])
    picture = (255.0 * np.clip(clearance / pitch_mm + 0.5, 0.0, 1.0)).astype(np.uint8)
    px = find_boundary_corners(picture, n_corners)
    mm = np.column_stack([xs[0] + px[:, 0] * pitch_mm, ys[0] - px[:, 1] * pitch_mm])
    return mm if signed_area(mm) > 0 else mm[::-1]


__all__ = [
    "Calibration",
    "CalibrationError",
    "boundary_corners_mm",
    "calibrate_camera",
    "calibrate_picture",
    "calibration_from_corners",
    "calibration_from_markers",
    "calibration_from_points",
    "find_boundary_corners",
    "floor_corners_mm",
]
