"""The tracker: where each robot is on the floor (mm), frame after frame, under the same name.

Robots are dark discs on a brighter floor. Each frame:

1. detect, coarse: the workspace's part of the picture, in grey, shrunk so a robot is still a few
   pixels across, thresholded; connected dark regions of a robot's size (or a few robots' size:
   robots that touch make one region) are the candidates;
2. detect, fine: each candidate is measured at full resolution as the centroid of its darkness
   (pixels darker than the threshold weigh up to 1 as they approach the robots' grey level), which
   is sub-pixel and does not depend on the blur; a region as dark as k robots is split into k by a
   few rounds of weighted k-means seeded with where the robots are predicted to be, which for two
   equal discs in contact converges to their centres (the bisector of two touching equal discs is
   their common tangent);
3. map: pixel -> mm through the calibration (lens distortion removed first); a detection whose
   centre is off the floor a robot can stand on (outside the workspace's boundary, inside an
   obstacle: a dish's dark rim, a drawn wall) is not a robot and is dropped;
4. associate: predicted positions (constant velocity) against detections by the Hungarian method,
   each robot only within its gate (a few radii; the gate of a lost robot grows with every frame it
   is missed, so it is found again where it reappears). A robot matched nowhere is `lost`: its
   position stays where it was last seen and its confidence is 0.

Confidence (0..1) is a plain heuristic: how close the detection's darkness is to one robot's
(a half-hidden robot scores about 0.5), times 0.8 for a robot split from a touching pair, times how
well it agrees with the prediction (exp(-d^2 / 2r^2)).

Speed: while every robot was seen in the frame before, steps 1-2 run only in windows around the
robots (each robot's gate and disc, on the coarse pass's pixel grid, so they find exactly what the
whole picture's pass finds there; a dark region cut by a window's edge sends the frame to the whole
picture); otherwise one colour conversion and one resize of the workspace's part of the picture.
Then one connected-components pass, and per region one table look-up and cv2.moments on a few
hundred pixels (bench/tracker.py: frames/s next to OpenCV's threshold + contours on the same
frames).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import linear_sum_assignment

from rigctl.core.errors import ConfigError

if TYPE_CHECKING:
    from rigctl.core.camera_model import Calibration

log = logging.getLogger(__name__)

_UNMATCHED = 1e9  # Hungarian cost of a pair outside the gate
_KMEANS_ROUNDS = 8
_GROW_ONE = np.ones((3, 3), np.uint8)  # grows a region by one pixel, diagonals included
_MIN_CONTRAST = 30.0  # grey levels between robots and floor below which a frame is not usable


@dataclass(frozen=True)
class TrackerSettings:
    """Detection and association parameters.

    threshold: grey level (0-255) below which a pixel belongs to a robot; None: estimated from the
    first usable frame, a third of the way from the robots' grey to the floor's. dark_level: the
    robots' grey level (None: estimated likewise). gate_radii: how far (in robot radii) a detection
    may be from a robot's prediction. lost_growth_radii: added to a lost robot's gate per missed
    frame. acquire_radius_mm: the gate around the initial positions for the first sighting.
    min_fill / max_per_region: a region darker than min_fill robots is ignored, one darker than
    max_per_region + 0.5 robots is not a robot. downscale: shrink factor of the coarse pass (None: the
    largest that keeps a robot >= 2.5 px in radius). nominal_fps: frame rate assumed when frames come
    without timestamps.
    """

    threshold: float | None = None
    dark_level: float | None = None
    gate_radii: float = 2.5
    lost_growth_radii: float = 2.0
    acquire_radius_mm: float = 30.0
    min_fill: float = 0.3
    max_per_region: int = 4
    downscale: int | None = None
    nominal_fps: float = 60.0


@dataclass(frozen=True)
class TrackedRobot:
    """One robot after a frame. position_mm (2,) and velocity_mm_s (2,) on the floor; pixel (2,) where
    it was seen; lost: not seen in this frame (position is the last one seen); frames_unseen: frames
    in a row it was not seen."""

    index: int
    position_mm: np.ndarray
    velocity_mm_s: np.ndarray
    pixel: np.ndarray
    confidence: float
    lost: bool
    frames_unseen: int


@dataclass(frozen=True)
class Detection:
    """A robot-like dark region: pixel (2,) centroid (full-resolution px), darkness (weight, px) and
    whether it was split from a region holding several robots."""

    pixel: np.ndarray
    weight_px: float
    split: bool


class Tracker:
    """Tracks n robots of known radii from known starting positions.

    calibration: pixel -> floor mapping; radii_mm: (n,); initial_mm: (n, 2) where the robots are put
    (the plan's start); roi_mm: (xmin, ymin, xmax, ymax) of the floor to search (the workspace's
    bounds; None: the whole picture); on_floor: points (m, 2) mm -> (m,) bool, where a robot's
    centre can be (the workspace's free floor; None: anywhere in the picture).
    """

    def __init__(
        self,
        calibration: "Calibration",
        radii_mm: ArrayLike,
        initial_mm: ArrayLike,
        *,
        roi_mm: Sequence[float] | None = None,
        on_floor: Callable[[np.ndarray], np.ndarray] | None = None,
        settings: TrackerSettings = TrackerSettings(),
    ) -> None:
        self.calibration = calibration
        self.settings = settings
        self.positions_mm = np.array(initial_mm, dtype=float).reshape(-1, 2)
        n = len(self.positions_mm)
        self.radii_mm = np.broadcast_to(np.asarray(radii_mm, dtype=float), (n,)).copy()
        if n == 0 or np.any(self.radii_mm <= 0):
            raise ValueError("need at least one robot, each with a positive radius")
        self.roi_mm = None if roi_mm is None else tuple(float(v) for v in roi_mm)
        self.on_floor = on_floor
        self.velocities_mm_s = np.zeros((n, 2))
        self.pixels = calibration.to_px(self.positions_mm)
        self.frames_unseen = np.ones(n, dtype=int)  # not seen yet
        self.ever_seen = np.zeros(n, dtype=bool)
        self.confidences = np.zeros(n)
        self.threshold = settings.threshold
        self.dark_level = settings.dark_level
        self.frames = 0
        self._last_t: float | None = None
        self._geometry: tuple | None = None  # per picture size: crop box, downscale, radius px
        self._weights: tuple | None = None  # (levels, weight per grey level), _weight_table
        self._fill = None  # darkness of one robot relative to pi r_px^2, learned from isolated robots

    # -- public ---------------------------------------------------------------------------------

    def update(self, image: np.ndarray, t_s: float | None = None) -> list[TrackedRobot]:
        """Track the robots in a picture (H, W, 3) BGR or (H, W) grey taken at `t_s` (s, any clock)."""
        dt = self._advance_clock(t_s)
        # the floor's scale where each robot was last seen, for its window and its darkness
        mm_per_px = self.calibration.mm_per_px(self.pixels)
        detections = self._detect_near_robots(image, dt, mm_per_px)
        if detections is None:
            detections = self.detect(image)
        found_mm = np.zeros((0, 2))
        if detections:
            found_mm = self.calibration.to_mm(np.array([d.pixel for d in detections]))
        if self.on_floor is not None and detections:
            on = np.asarray(self.on_floor(found_mm), dtype=bool)
            detections = [d for d, keep in zip(detections, on) if keep]
            found_mm = found_mm[on]
        self._associate(detections, found_mm, dt, mm_per_px)
        self.frames += 1
        return self.robots

    @property
    def robots(self) -> list[TrackedRobot]:
        """The robots' state after the last frame."""
        return [
            TrackedRobot(
                index=i,
                position_mm=self.positions_mm[i].copy(),
                velocity_mm_s=self.velocities_mm_s[i].copy(),
                pixel=self.pixels[i].copy(),
                confidence=float(self.confidences[i]),
                lost=bool(self.frames_unseen[i] > 0),
                frames_unseen=int(self.frames_unseen[i]),
            )
            for i in range(len(self.positions_mm))
        ]

    def detect(self, image: np.ndarray) -> list[Detection]:
        """Robot-like dark regions in `image`, touching robots split using the current predictions."""
        geometry = self._frame_geometry(image.shape[:2])
        top, bottom, left, right, _, radius_px = geometry
        gray = _grey(image[top:bottom, left:right])
        if self.threshold is None or self.dark_level is None:
            if not self._estimate_levels(gray, radius_px):
                return []
        detections, _ = self._detect_in(gray, (top, left), geometry, (False, False, False, False))
        return detections

    # -- internals ------------------------------------------------------------------------------

    def _detect_near_robots(
        self, image: np.ndarray, dt: float, mm_per_px: np.ndarray
    ) -> list[Detection] | None:
        """`detect` in windows around the robots only, when every robot was seen last frame; None
        when the whole picture must be searched instead.

        A window holds a robot's gate and the robot's own disc (so every detection `_associate`
        could match lies inside one), on the coarse pass's pixel grid, so its coarse pixels, regions
        and centroids are exactly those of the whole picture's pass. A dark region cut by a window's
        inner edge is the one thing that could differ (a region larger than the window, a robot
        beyond its gate): then the frame is searched whole. A 1280 x 1024 picture's four robots are
        about 5 % of its pixels."""
        if self.threshold is None or self.dark_level is None or self.frames_unseen.any():
            return None
        geometry = self._frame_geometry(image.shape[:2])
        top, bottom, left, right, scale, _ = geometry
        windows = self._windows(dt, geometry, mm_per_px)
        if windows is None:
            return None
        height, width = bottom - top, right - left
        detections: list[Detection] = []
        for r0, r1, c0, c1 in windows:
            gray = _grey(image[top + r0 : top + r1, left + c0 : left + c1])
            inner = (r0 > 0, r1 < height, c0 > 0, c1 < width)
            found, clipped = self._detect_in(gray, (top + r0, left + c0), geometry, inner)
            if clipped:
                return None
            detections += found
        return detections

    def _windows(
        self, dt: float, geometry: tuple, mm_per_px: np.ndarray
    ) -> list[tuple[int, int, int, int]] | None:
        """Boxes (row0, row1, col0, col1) px in the crop, multiples of the coarse shrink, each
        holding one or more robots' gates (`_associate`: gate radius plus twice the distance moved
        at the robot's speed, as the prediction moves too) plus a robot's radius and two coarse
        pixels; overlapping or touching boxes merged. None if a robot is outside the crop."""
        top, bottom, left, right, scale, _ = geometry
        speed_mm_s = np.hypot(*self.velocities_mm_s.T)
        reach_mm = (self.settings.gate_radii + 1.0) * self.radii_mm + 2.0 * speed_mm_s * dt
        reach_px = reach_mm / mm_per_px + 2 * scale
        height, width = bottom - top, right - left
        boxes = []
        for (x, y), reach in zip(self.pixels - (left, top), reach_px):
            box = [max(math.floor((y - reach) / scale), 0) * scale,
                   min(math.ceil((y + reach) / scale) * scale, height),
                   max(math.floor((x - reach) / scale), 0) * scale,
                   min(math.ceil((x + reach) / scale) * scale, width)]
            if box[0] >= box[1] or box[2] >= box[3]:
                return None
            boxes.append(box)
        merged = True
        while merged and len(boxes) > 1:
            merged = False
            for i in range(len(boxes)):
                for j in range(i + 1, len(boxes)):
                    a, b = boxes[i], boxes[j]
                    if a[0] <= b[1] and b[0] <= a[1] and a[2] <= b[3] and b[2] <= a[3]:
                        boxes[i] = [min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]),
                                    max(a[3], b[3])]
                        del boxes[j]
                        merged = True
                        break
                if merged:
                    break
        return [tuple(b) for b in boxes]

    def _detect_in(
        self, gray: np.ndarray, origin: tuple[int, int], geometry: tuple,
        inner: tuple[bool, bool, bool, bool],
    ) -> tuple[list[Detection], bool]:
        """The detections in `gray` (h, w), a part of the picture whose top-left pixel is `origin`
        (row, col) in the picture, h and w multiples of the coarse shrink; and whether a dark
        region touches one of its `inner` edges (top, bottom, left, right: edges that are not the
        crop's own), where it may go on outside."""
        scale, radius_px = geometry[4], geometry[5]
        threshold, dark = float(self.threshold), float(self.dark_level)  # type: ignore[arg-type]
        height, width = gray.shape
        small = (
            cv2.resize(gray, (width // scale, height // scale), interpolation=cv2.INTER_AREA)
            if scale > 1 else gray
        )
        _, mask = cv2.threshold(small, threshold, 255, cv2.THRESH_BINARY_INV)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        # plain ints from here on: a window holds a region or two, numpy per value would cost more
        boxes = stats.tolist()
        if any(inner):
            rows_small, cols_small = mask.shape
            for x, y, w, h, _ in boxes[1:]:
                if ((inner[0] and y == 0) or (inner[1] and y + h == rows_small)
                        or (inner[2] and x == 0) or (inner[3] and x + w == cols_small)):
                    return [], True
        top, left = origin
        one_robot = math.pi * radius_px**2
        fill = self._fill if self._fill is not None else _expected_fill(radius_px)
        min_area = self.settings.min_fill * one_robot * fill / scale**2
        max_area = (self.settings.max_per_region + 0.5) * one_robot / scale**2
        detections: list[Detection] = []
        predicted_px = self.pixels  # last known pixel positions are good seeds for splitting
        seeds = None
        weight_of = self._weight_table(threshold, dark)
        for label in range(1, count):
            x, y, w, h, area = boxes[label]
            if not min_area <= area <= max_area:
                continue
            if seeds is None:
                seeds = np.round(predicted_px).astype(int).tolist()
            # full-resolution box of this region, one coarse pixel larger on every side
            r0, r1 = max((y - 1) * scale, 0), min((y + h + 1) * scale, height)
            c0, c1 = max((x - 1) * scale, 0), min((x + w + 1) * scale, width)
            # A coarse pixel brighter than the threshold may hold full pixels darker than it: the
            # region grown by one coarse pixel (the same as growing it by `scale` full pixels).
            region = (labels[max(y - 1, 0) : y + h + 1, max(x - 1, 0) : x + w + 1] == label)
            region = cv2.dilate(region.view(np.uint8), _GROW_ONE)
            if scale > 1:
                region = cv2.resize(region, None, fx=scale, fy=scale,
                                    interpolation=cv2.INTER_NEAREST)
            region = region[: r1 - r0, : c1 - c0]
            weight: np.ndarray = cv2.LUT(gray[r0:r1, c0:c1], weight_of)
            weight *= region
            moments = cv2.moments(weight)
            total = moments["m00"]
            if total <= 0:
                continue
            robots_here = self._count_robots(
                total / (one_robot * fill), region, (r0 + top, c0 + left), seeds
            )
            if robots_here == 1:
                centre = np.array([moments["m10"] / total + (c0 + left),
                                   moments["m01"] / total + (r0 + top)])
                detections.append(Detection(centre, total, False))
            else:
                rows, cols = np.nonzero(weight)
                w_values = weight[rows, cols]
                points = np.column_stack([cols + (c0 + left), rows + (r0 + top)]).astype(np.float64)
                for centre, part in _split(points, w_values, robots_here, predicted_px):
                    detections.append(Detection(centre, part, True))
        return detections, False

    def _weight_table(self, threshold: float, dark: float) -> np.ndarray:
        """(256,) float32: how much a pixel of each grey level counts as robot, 0 at the threshold
        and brighter, 1 at the robots' grey and darker (a ramp between); made once per levels."""
        if self._weights is None or self._weights[0] != (threshold, dark):
            span = 1.0 / max(threshold - dark, 1.0)
            grey = np.arange(256, dtype=np.float32)
            self._weights = ((threshold, dark), np.clip((threshold - grey) * span, 0.0, 1.0))
        return self._weights[1]

    def _count_robots(
        self, darkness: float, region: np.ndarray, origin: tuple[int, int],
        seeds_px: list[list[int]],
    ) -> int:
        """How many robots make one dark region: its darkness in robots, unless the robots expected
        inside it (their last pixel, rounded: seeds_px [[col, row], ...]) agree with it within
        35 %; one robot's darkness depends on the blur, the expectation does not."""
        height, width = region.shape
        expected = 0
        for col, row in seeds_px:
            row, col = row - origin[0], col - origin[1]
            if 0 <= row < height and 0 <= col < width and region[row, col]:
                expected += 1
        if expected >= 1 and abs(darkness / expected - 1.0) < 0.35:
            count = expected
        else:
            count = int(round(darkness))
        return min(max(count, 1), self.settings.max_per_region)

    def _advance_clock(self, t_s: float | None) -> float:
        nominal = 1.0 / self.settings.nominal_fps
        if t_s is None:
            return nominal
        dt = nominal if self._last_t is None else float(t_s) - self._last_t
        self._last_t = float(t_s)
        return dt if dt > 0 else nominal

    def _frame_geometry(self, shape: tuple[int, int]) -> tuple[int, int, int, int, int, float]:
        """Crop box (top, bottom, left, right), coarse shrink factor and a robot's radius (px)."""
        if self._geometry is not None and self._geometry[0] == shape:
            return self._geometry[1]
        height, width = shape
        calibrated = self.calibration.resolution
        if calibrated is not None and tuple(calibrated) != (width, height):
            raise ConfigError(
                f"pictures are {width} x {height} px but the camera was calibrated at "
                f"{calibrated[0]} x {calibrated[1]}: calibrate again at this resolution",
                device="camera",
            )
        if self.roi_mm is None:
            centre_px = np.array([[(width - 1) / 2.0, (height - 1) / 2.0]])
            top, bottom, left, right = 0, height, 0, width
        else:
            xmin, ymin, xmax, ymax = self.roi_mm
            t = np.linspace(0.0, 1.0, 21)
            outline = np.vstack([
                np.column_stack([xmin + (xmax - xmin) * t, np.full_like(t, ymin)]),
                np.column_stack([xmin + (xmax - xmin) * t, np.full_like(t, ymax)]),
                np.column_stack([np.full_like(t, xmin), ymin + (ymax - ymin) * t]),
                np.column_stack([np.full_like(t, xmax), ymin + (ymax - ymin) * t]),
            ])
            px = self.calibration.to_px(outline)
            centre_px = self.calibration.to_px([[(xmin + xmax) / 2, (ymin + ymax) / 2]])
            pad = 4
            left = max(int(math.floor(px[:, 0].min())) - pad, 0)
            right = min(int(math.ceil(px[:, 0].max())) + pad + 1, width)
            top = max(int(math.floor(px[:, 1].min())) - pad, 0)
            bottom = min(int(math.ceil(px[:, 1].max())) + pad + 1, height)
            if left >= right or top >= bottom:
                raise ConfigError(
                    "the workspace is outside the camera's picture (wrong calibration?)",
                    device="camera",
                )
        mm_per_px = float(self.calibration.mm_per_px(centre_px)[0])
        radius_px = float(np.min(self.radii_mm)) / mm_per_px
        scale = self.settings.downscale or max(1, int(radius_px / 2.5))
        # crop to whole coarse pixels so coarse pixel (i, j) is exactly full pixels i*s .. i*s+s-1
        bottom -= (bottom - top) % scale
        right -= (right - left) % scale
        geometry = (top, bottom, left, right, scale, radius_px)
        self._geometry = (shape, geometry)
        log.debug("tracker geometry: crop %s, shrink %d, robot radius %.2f px", geometry[:4], scale,
                  radius_px)
        return geometry

    def _estimate_levels(self, gray: np.ndarray, radius_px: float) -> bool:
        """Set the robots' grey and the threshold from a picture with the robots in view."""
        flat = gray.reshape(-1)
        robot_px = len(self.positions_mm) * math.pi * radius_px**2
        k = int(min(max(robot_px * 0.3, 5), flat.size - 1))
        dark = float(np.partition(flat, k)[k]) if self.dark_level is None else self.dark_level
        floor = float(np.median(flat))
        if floor - dark < _MIN_CONTRAST:
            log.info("tracker: picture without contrast (robots %.0f, floor %.0f); waiting",
                     dark, floor)
            return False
        self.dark_level = dark
        if self.threshold is None:
            self.threshold = dark + (floor - dark) / 3.0
        log.info("tracker: robots at grey %.0f, floor %.0f, threshold %.0f", dark, floor,
                 self.threshold)
        return True

    def _associate(
        self, detections: list[Detection], found_mm: np.ndarray, dt: float, mm_per_px: np.ndarray
    ) -> None:
        """Match the detections (their floor points found_mm (m, 2)) to the robots; mm_per_px (n,)
        the floor's scale at each robot's last pixel."""
        n = len(self.positions_mm)
        unseen = self.frames_unseen
        if not detections:
            self._miss(np.ones(n, dtype=bool))
            return
        moving = unseen == 0
        predicted = self.positions_mm + np.where(moving[:, None], self.velocities_mm_s * dt, 0.0)
        speed = np.hypot(*self.velocities_mm_s.T) * moving
        gate = self.settings.gate_radii * self.radii_mm + speed * dt
        gate = np.where(self.ever_seen,
                        gate + self.settings.lost_growth_radii * self.radii_mm * unseen,
                        np.maximum(gate, self.settings.acquire_radius_mm))
        distance = np.linalg.norm(predicted[:, None, :] - found_mm[None, :, :], axis=2)
        # A robot seen last frame wins a detection over a lost one at the same distance.
        cost = np.where(distance <= gate[:, None], distance + np.where(moving, 0.0, gate)[:, None],
                        _UNMATCHED)
        rows, cols = linear_sum_assignment(cost)
        matched = np.zeros(n, dtype=bool)
        radius_px = self.radii_mm / mm_per_px
        one_robot_px = math.pi * radius_px**2
        fill = self._fill if self._fill is not None else _expected_fill(float(radius_px.min()))
        for i, j in zip(rows, cols):
            if cost[i, j] >= _UNMATCHED:
                continue
            detection = detections[j]
            matched[i] = True
            if self.ever_seen[i]:
                elapsed = dt * (1 + unseen[i])
                velocity = (found_mm[j] - self.positions_mm[i]) / elapsed
                self.velocities_mm_s[i] = 0.5 * self.velocities_mm_s[i] + 0.5 * velocity
            innovation = float(distance[i, j])
            self.positions_mm[i] = found_mm[j]
            self.pixels[i] = detection.pixel
            ratio = detection.weight_px / (one_robot_px[i] * fill)
            confidence = max(0.0, 1.0 - abs(ratio - 1.0))
            confidence *= 0.8 if detection.split else 1.0
            if self.ever_seen[i]:
                confidence *= math.exp(-0.5 * (innovation / self.radii_mm[i]) ** 2)
            self.confidences[i] = confidence
            self.frames_unseen[i] = 0
            self.ever_seen[i] = True
            if not detection.split and 0.6 < ratio < 1.5:
                measured = detection.weight_px / one_robot_px[i]
                self._fill = measured if self._fill is None else 0.9 * self._fill + 0.1 * measured
        self._miss(~matched)
        if len(detections) > int(matched.sum()):
            log.debug("tracker: %d detections matched no robot", len(detections) - int(matched.sum()))

    def _miss(self, missed: np.ndarray) -> None:
        if not missed.any():
            return
        newly = missed & (self.frames_unseen == 0)
        for i in np.nonzero(newly)[0]:
            log.info("tracker: robot %d lost at (%.1f, %.1f) mm", i, *self.positions_mm[i])
        self.frames_unseen[missed] += 1
        self.confidences[missed] = 0.0
        self.velocities_mm_s[missed] = 0.0


def _grey(image: np.ndarray) -> np.ndarray:
    """A picture (h, w, 3) BGR or (h, w) grey, in grey (uint8)."""
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image


def _expected_fill(radius_px: float) -> float:
    """Darkness of one robot relative to pi r^2 before any isolated robot was measured: the weight
    ramp and the optics' blur lose about a pixel around the edge."""
    return max(0.2, (1.0 - 1.0 / max(radius_px, 1.5)) ** 2)


def _split(
    points: np.ndarray, weights: np.ndarray, k: int, seeds_px: np.ndarray
) -> list[tuple[np.ndarray, float]]:
    """Weighted k-means of pixels (m, 2) into k robots, seeded with the nearest predictions."""
    centroid = (weights @ points) / weights.sum()
    order = np.argsort(np.linalg.norm(seeds_px - centroid, axis=1))
    centres = [seeds_px[i] for i in order[:k]]
    while len(centres) < k:  # fewer predictions than robots here: start from the farthest pixel
        gaps = np.min(np.linalg.norm(points[:, None, :] - np.array(centres)[None], axis=2), axis=1)
        centres.append(points[int(np.argmax(gaps))])
    centres_arr = np.array(centres, dtype=np.float64)
    for _ in range(_KMEANS_ROUNDS):
        owner = np.argmin(
            np.sum((points[:, None, :] - centres_arr[None, :, :]) ** 2, axis=2), axis=1
        )
        moved = centres_arr.copy()
        for c in range(k):
            mine = owner == c
            if mine.any():
                moved[c] = (weights[mine] @ points[mine]) / weights[mine].sum()
        if np.allclose(moved, centres_arr, atol=1e-4):
            centres_arr = moved
            break
        centres_arr = moved
    owner = np.argmin(np.sum((points[:, None, :] - centres_arr[None, :, :]) ** 2, axis=2), axis=1)
    return [(centres_arr[c], float(weights[owner == c].sum())) for c in range(k)]


def find_dark_blobs(
    image: np.ndarray, *, expected: int | None = None, max_blobs: int = 9
) -> np.ndarray:
    """Centroids (m, 2) px of round dark blobs (markers, robots) in a picture, largest first.

    The threshold is a third of the way from the darkest pixels to the median grey; blobs of at least
    6 px, not much longer than wide, and within a factor 2.5 of the median blob's area are kept.
    `expected` only limits how many are returned (at most `max_blobs`).
    """
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    flat = gray.reshape(-1)
    k = max(10, int(flat.size * 2e-4))
    dark = float(np.partition(flat, k)[k])
    floor = float(np.median(flat))
    if floor - dark < _MIN_CONTRAST:
        return np.zeros((0, 2))
    threshold = dark + (floor - dark) / 3.0
    _, mask = cv2.threshold(gray, threshold, 255, cv2.THRESH_BINARY_INV)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    candidates = []
    span = 1.0 / max(threshold - dark, 1.0)
    for label in range(1, count):
        x, y, w, h, area = stats[label]
        if area < 6 or max(w, h) > 2.0 * min(w, h) or area < 0.45 * w * h:
            continue
        patch = gray[y : y + h, x : x + w].astype(np.float32)
        weight = np.clip((threshold - patch) * span, 0, 1) * (labels[y : y + h, x : x + w] == label)
        total = float(weight.sum())
        v, u = np.mgrid[y : y + h, x : x + w]
        candidates.append((area, np.array([(weight * u).sum() / total, (weight * v).sum() / total])))
    if not candidates:
        return np.zeros((0, 2))
    median = float(np.median([a for a, _ in candidates]))
    kept = [(a, c) for a, c in candidates if median / 2.5 <= a <= median * 2.5]
    kept.sort(key=lambda item: -item[0])
    limit = max_blobs if expected is None else min(max_blobs, max(expected, len(kept)))
    return np.array([c for _, c in kept[:limit]])
