"""`rigctl report RUN --video [OUT]`: a run record as an MP4 for a paper or a talk, 1280 x 720.

Each output frame is one instant of the run, `fps` a second on the record's clock (the times of
`series/video.csv` and of the `tracked` events, s since the run started), so the video plays in
real time whatever the camera or the recorder dropped:

- **the scene** (left): the record's video (`video.avi`, `rigctl.vision.video`), the latest frame
  taken at or before the instant; a record without video (video off, open loop, an old record) has
  the workspace drawn from the plan instead (boundary, obstacles; the agents as discs at their
  tracked positions). Over it: each agent's planned path (dashed, from its start through the
  positions the plan expects after each move), the position expected after the current move (ring),
  the tracked path so far (solid) and where the tracker has the agent now (circle of its radius),
  and its goal (star). Floor millimetres go to video pixels through the camera calibration of the
  record's `rig.toml` (`Calibration.to_px`), the same map the tracker used the other way;
- **the panel** (right): the time, the move being streamed (`move` of the stream: -1 between
  moves), re-plans and faults so far, each agent's distance to its goal, and the legend;
- **the strip** (bottom): the record's channels (the first channel group, measured), drawn once
  by matplotlib, with a cursor at the instant.

Geometry is drawn by OpenCV (antialiased), text by Pillow in matplotlib's DejaVu Sans (OpenCV's
Hershey fonts have no degree sign nor a readable small size). The file is MPEG-4 Part 2 in MP4
('mp4v', OpenCV's FFmpeg; its wheels have no H.264 encoder): VLC, mpv, QuickTime and the
players of Windows and macOS open it; a browser wants H.264 (`ffmpeg -i OUT -c:v libx264
-pix_fmt yuv420p web.mp4`).
"""

from __future__ import annotations

import logging
import tomllib
from dataclasses import dataclass
from pathlib import Path

import cv2
import matplotlib
import numpy as np
from matplotlib import font_manager
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image, ImageDraw, ImageFont

from rigctl.apps.report import (
    RUN_CLOCK,
    UNIT_LABELS,
    RunData,
    _agent_paths,
    _mark_events,
    _run_name,
    _tracked_positions,
    read_run,
)
from rigctl.core.camera_model import Calibration
from rigctl.core.errors import ConfigError
from rigctl.core.record import read_series, read_stream
from rigctl.vision.video import VIDEO_FILE, VIDEO_SERIES

log = logging.getLogger(__name__)

WIDTH, HEIGHT = 1280, 720
TITLE_H = 40  # px: the band with the run's name
STRIP_H = 170  # px: the channels under the scene
SCENE = (0, TITLE_H, 720, HEIGHT - STRIP_H)  # x0, y0, x1, y1 of the scene's box
PANEL_X = 736  # the panel's left edge
FPS = 20.0
BACKGROUND = (255, 255, 255)  # BGR and RGB alike
TEXT = (30, 30, 30)  # RGB, for Pillow
FOURCC = "mp4v"


@dataclass
class Rendered:
    """What `render_video` wrote: the file, its frames and rate, and where its scene came from."""

    path: Path
    frames: int
    fps: float
    scene: str  # "video" or "drawn"
    why: str  # where the scene came from, in words
    t_start_s: float
    t_end_s: float


def _bgr(colour: str) -> tuple[int, int, int]:
    r, g, b = (int(round(255 * c)) for c in matplotlib.colors.to_rgb(colour))
    return b, g, r


COLOURS = [_bgr(c) for c in matplotlib.rcParams["axes.prop_cycle"].by_key()["color"]]


def _font(size_px: int, bold: bool = False) -> ImageFont.FreeTypeFont:
    path = font_manager.findfont(font_manager.FontProperties(
        family="DejaVu Sans", weight="bold" if bold else "normal"))
    return ImageFont.truetype(path, size_px)


# -- what the record holds ------------------------------------------------------------------------

def _calibration(run_dir: Path) -> Calibration | None:
    """The camera calibration of the record's rig file snapshot, None if it has none."""
    try:
        rig = tomllib.loads((run_dir / "rig.toml").read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return None
    calibration = (rig.get("camera") or {}).get("calibration")
    return Calibration.model_validate(calibration) if calibration else None


def _radii_mm(plan: dict, n: int) -> np.ndarray:
    agents = plan.get("agents")
    if isinstance(agents, list):
        return np.array([float(a.get("radius", 1.0)) for a in agents[:n]] + [1.0] * (n - len(agents)))
    if isinstance(agents, dict) and "body_diameter_mm" in agents:  # a pair: both alike
        return np.full(n, 0.5 * float(agents["body_diameter_mm"]))
    return np.ones(n)


def _tracked(events: list[dict]) -> tuple[np.ndarray, np.ndarray] | None:
    """Times (k,) s on the record's clock and positions (k, agents, 2) mm of the `tracked`
    events (a lost agent NaN), ordered by the time the picture was taken."""
    positions = _tracked_positions(events)
    if positions is None:
        return None
    times = np.array([e.get("t_frame_s", e["t"]) for e in events
                      if e.get("event") == "tracked" and e.get("positions_mm")], dtype=float)
    order = np.argsort(times, kind="stable")
    return times[order], positions[order]


def _shape_points(shape: dict) -> np.ndarray:
    if "rect" in shape:
        x, y, w, h = shape["rect"]
        return np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], dtype=float)
    if "polygon" in shape:
        return np.asarray(shape["polygon"], dtype=float).reshape(-1, 2)
    if "disk" in shape:
        cx, cy, r = shape["disk"]
        a = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        return np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])
    return np.empty((0, 2))


# -- the scene ------------------------------------------------------------------------------------

class SceneMap:
    """Floor mm to pixels of the scene's box: through the camera (video) or a plain scale with y
    up (drawn); `size` (w, h) of the scene image before it is placed in the box."""

    def __init__(self, size: tuple[int, int], to_px, scale: float) -> None:
        self.size, self._to_px, self.px_per_mm = size, to_px, scale
        self.crop: tuple[int, int, int, int] | None = None  # of the camera's picture (video)

    def __call__(self, points_mm: np.ndarray) -> np.ndarray:
        return self._to_px(np.asarray(points_mm, dtype=float).reshape(-1, 2))


def _video_map(calibration: Calibration, camera_size: tuple[int, int],
               floor_mm: np.ndarray) -> SceneMap:
    """The camera's picture cropped to the floor points `floor_mm` (n, 2) (the workspace, the
    paths) with a margin, scaled into the scene's box; `crop` (x0, y0, x1, y1) camera px."""
    px = calibration.to_px(floor_mm[np.isfinite(floor_mm).all(axis=1)])
    px = px[np.isfinite(px).all(axis=1)]
    if len(px):
        low, high = px.min(axis=0), px.max(axis=0)
        margin = 0.06 * (high - low).max() + 8
        x0, y0 = np.maximum(np.floor(low - margin), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(high + margin), camera_size).astype(int)
    if not len(px) or x1 - x0 < 16 or y1 - y0 < 16:
        x0, y0, (x1, y1) = 0, 0, camera_size
    box_w, box_h = SCENE[2] - SCENE[0], SCENE[3] - SCENE[1]
    s = min(box_w / (x1 - x0), box_h / (y1 - y0))
    size = (int(round((x1 - x0) * s)), int(round((y1 - y0) * s)))
    centre = np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0])
    mm_per_px = float(np.median(calibration.mm_per_px(centre[None, :])))
    scene_map = SceneMap(size, lambda p: (calibration.to_px(p) - (x0, y0)) * s, s / mm_per_px)
    scene_map.crop = (int(x0), int(y0), int(x1), int(y1))
    return scene_map


def _drawn_map(workspace: dict, extra_mm: np.ndarray) -> tuple[SceneMap, tuple[float, ...]]:
    shapes = [workspace.get("boundary") or {}, *(workspace.get("obstacles") or [])]
    points = np.vstack([_shape_points(s) for s in shapes] + [extra_mm.reshape(-1, 2)])
    points = points[np.isfinite(points).all(axis=1)]
    if "image" in workspace:
        ox, oy = workspace.get("origin", [0.0, 0.0])
        points = np.vstack([points, [[ox, oy]]])
    x0, y0 = points.min(axis=0) - 5.0
    x1, y1 = points.max(axis=0) + 5.0
    box_w, box_h = SCENE[2] - SCENE[0] - 20, SCENE[3] - SCENE[1] - 20
    s = min(box_w / (x1 - x0), box_h / (y1 - y0))
    size = (int(round((x1 - x0) * s)), int(round((y1 - y0) * s)))

    def to_px(p: np.ndarray) -> np.ndarray:
        return np.column_stack([(p[:, 0] - x0) * s, (y1 - p[:, 1]) * s])  # y up, as on the plots

    return SceneMap(size, to_px, s), (x0, y0, x1, y1)


def _floor_points(plan: dict, extra_mm: np.ndarray) -> np.ndarray:
    """The floor the video shows: the workspace's boundary (else its obstacles) and `extra_mm`."""
    workspace = plan.get("workspace") or {}
    boundary = _shape_points(workspace.get("boundary") or {})
    if not len(boundary):
        boundary = np.vstack([np.empty((0, 2))] + [_shape_points(o) for o in
                                                    workspace.get("obstacles") or []])
    return np.vstack([boundary, extra_mm.reshape(-1, 2)])


def _draw_workspace(workspace: dict, scene_map: SceneMap, plan_dir: Path) -> np.ndarray:
    """The workspace from the plan on white: obstacles grey, the boundary's outline."""
    w, h = scene_map.size
    image = np.full((h, w, 3), 255, np.uint8)
    if "image" in workspace and (plan_dir / workspace["image"]).is_file():
        picture = cv2.imread(str(plan_dir / workspace["image"]))
        if picture is not None:
            scale = float(workspace.get("mm_per_px", 1.0))
            ox, oy = workspace.get("origin", [0.0, 0.0])
            ph, pw = picture.shape[:2]
            corners = scene_map(np.array([[ox, oy + ph * scale], [ox + pw * scale, oy]]))
            (a, b), (c, d) = np.round(corners).astype(int)
            a, b, c, d = max(a, 0), max(b, 0), min(c, w), min(d, h)
            if c > a and d > b:
                image[b:d, a:c] = cv2.resize(picture, (c - a, d - b), interpolation=cv2.INTER_AREA)
    for obstacle in workspace.get("obstacles") or []:
        poly = np.round(scene_map(_shape_points(obstacle)) * 16).astype(np.int32)
        cv2.fillPoly(image, [poly], (200, 200, 200), cv2.LINE_AA, shift=4)
        cv2.polylines(image, [poly], True, (90, 90, 90), 1, cv2.LINE_AA, shift=4)
    boundary = _shape_points(workspace.get("boundary") or {})
    if len(boundary):
        poly = np.round(scene_map(boundary) * 16).astype(np.int32)
        cv2.polylines(image, [poly], True, (60, 60, 60), 2, cv2.LINE_AA, shift=4)
    return image


def _fixed(points_px: np.ndarray) -> np.ndarray:
    return np.round(points_px * 16).astype(np.int32)  # OpenCV's sub-pixel points (shift 4)


def _dashed(image, points_px: np.ndarray, colour, thickness: int, dash_px: float = 9.0) -> None:
    """A dashed polyline (OpenCV draws none): dashes of `dash_px` along the path."""
    points_px = points_px[np.isfinite(points_px).all(axis=1)]
    if len(points_px) < 2:
        return
    steps = np.linalg.norm(np.diff(points_px, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(steps)])
    marks = np.arange(0.0, along[-1], dash_px)
    xs = np.interp(marks, along, points_px[:, 0])
    ys = np.interp(marks, along, points_px[:, 1])
    dots = np.column_stack([xs, ys])
    for a, b in zip(dots[0::2], dots[1::2]):
        cv2.line(image, tuple(_fixed(a)), tuple(_fixed(b)), colour, thickness, cv2.LINE_AA, shift=4)


def _star(image, centre_px: np.ndarray, colour, size_px: float) -> None:
    angles = np.pi / 2 + np.arange(10) * np.pi / 5
    radii = np.where(np.arange(10) % 2 == 0, size_px, 0.45 * size_px)
    points = centre_px + np.column_stack([radii * np.cos(angles), -radii * np.sin(angles)])
    cv2.fillPoly(image, [_fixed(points)], colour, cv2.LINE_AA, shift=4)
    cv2.polylines(image, [_fixed(points)], True, (0, 0, 0), 1, cv2.LINE_AA, shift=4)


# -- the strip ------------------------------------------------------------------------------------

class Strip:
    """The channels under the scene, drawn once; `at(t)` is a copy with the cursor at t s."""

    def __init__(self, data: RunData, t_range: tuple[float, float]) -> None:
        self.image = np.full((STRIP_H, WIDTH, 3), 255, np.uint8)
        self._x = None
        traces = data.traces
        if not traces:
            cv2.putText(self.image, "no actuator stream in this record", (40, STRIP_H // 2),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.6, (90, 90, 90), 1, cv2.LINE_AA)
            return
        group = traces[0].channel.group
        traces = [t for t in traces if t.channel.group == group]
        unit = traces[0].channel.unit
        fig = Figure(figsize=(WIDTH / 100, STRIP_H / 100), dpi=100)
        FigureCanvasAgg(fig)
        left, right, bottom, top = 0.065, 0.86, 0.25, 0.86
        ax = fig.add_axes((left, bottom, right - left, top - bottom))
        colours = matplotlib.rcParams["axes.prop_cycle"].by_key()["color"]
        for j, trace in enumerate(traces):
            ax.plot(trace.t, trace.measured, "-", linewidth=1.1, color=colours[j % len(colours)],
                    label=trace.channel.name)
        _mark_events(ax, data, RUN_CLOCK, label=False)
        ax.set_xlim(*t_range)
        ax.set_xlabel("time since the run started (s)", fontsize=9, labelpad=1)
        ax.set_ylabel(UNIT_LABELS.get(unit, unit), fontsize=9)
        kinds = {e.get("event") for e in data.events}
        marks = "".join(text for present, text in (
            ("replan" in kinds, "; dashed purple: re-plan"),
            (bool(kinds & {"fault", "estop"}), "; red: fault / e-stop")) if present)
        ax.set_title("measured, every channel of the stream" + (f" ({group})" if group else "")
                     + marks,
                     fontsize=9, pad=3, loc="left")
        ax.tick_params(labelsize=8, pad=1)
        ax.grid(True, linewidth=0.3, alpha=0.6)
        ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.005, 0.5), frameon=False,
                  ncol=2 if len(traces) > 4 else 1, handlelength=1.2, columnspacing=0.8)
        fig.canvas.draw()
        rgba = np.asarray(fig.canvas.buffer_rgba())
        self.image = cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGR)
        x0, x1 = ax.get_xlim()
        self._x = (x0, x1, left * WIDTH, right * WIDTH)
        self._y = (int((1 - top) * STRIP_H), int((1 - bottom) * STRIP_H))

    def cursor(self, image: np.ndarray, t_s: float) -> None:
        """The cursor at `t_s` into `image` (the strip's rows of a frame), in place."""
        if self._x is not None:
            x0, x1, p0, p1 = self._x
            x = p0 + (t_s - x0) / (x1 - x0) * (p1 - p0)
            cv2.line(image, (int(round(x)), self._y[0]), (int(round(x)), self._y[1]),
                     (0, 0, 0), 2, cv2.LINE_AA)  # black: red marks faults


# -- rendering ------------------------------------------------------------------------------------

class _VideoFrames:
    """The record's video read forward: `at(t)` the latest frame taken at or before t s."""

    def __init__(self, path: Path, times_s: np.ndarray) -> None:
        self.capture = cv2.VideoCapture(str(path))
        self.times_s = times_s
        self.index = -1
        self.image: np.ndarray | None = None
        ok, first = self.capture.read()
        if not ok:
            raise ConfigError(f"{path} holds no frame OpenCV can read")
        self.index, self.image = 0, first
        self.size = (first.shape[1], first.shape[0])

    def at(self, t_s: float) -> np.ndarray:
        wanted = max(0, int(np.searchsorted(self.times_s, t_s, side="right")) - 1)
        while self.index < wanted:
            ok, image = self.capture.read()
            if not ok:  # the file ends before its table (a crash): keep the last frame
                self.times_s = self.times_s[: self.index + 1]
                break
            self.index, self.image = self.index + 1, image
        assert self.image is not None
        return self.image

    def close(self) -> None:
        self.capture.release()


def render_video(run_dir: str | Path, out: str | Path | None = None, *,
                 fps: float = FPS) -> Rendered:
    """Render the record at `run_dir` into an MP4 at 1280 x 720 (default `RUN/report.mp4`)."""
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / "report.mp4"
    data = read_run(run_dir)
    paths = _agent_paths(data.plan, data.events, data.summary) if data.plan else []
    tracked = _tracked(data.events)
    if not paths and tracked is None:
        raise ConfigError(f"{run_dir.name}: no agents in the plan and no tracked positions: "
                          "nothing to show in a video (`rigctl report RUN` draws its channels)")
    n = len(paths) if paths else tracked[1].shape[1]
    radii = _radii_mm(data.plan, n)
    extra = np.vstack([np.vstack([p, g[None]]) for p, _, g in paths]) if paths else \
        tracked[1].reshape(-1, 2)
    series = read_series(run_dir, VIDEO_SERIES)
    calibration = _calibration(run_dir)
    video: _VideoFrames | None = None
    has_video = (series is not None and len(series.get("t_s", ()))
                 and (run_dir / VIDEO_FILE).is_file())
    if not has_video:
        why = "the workspace drawn from the plan (the record has no video)"
    elif calibration is None:
        why = ("the workspace drawn from the plan (the record's rig.toml has no camera "
               "calibration to put the paths on its video)")
    else:
        why = "the record's video"
    if has_video and calibration is not None:
        video = _VideoFrames(run_dir / VIDEO_FILE, np.asarray(series["t_s"], dtype=float))
        scene_map = _video_map(calibration, video.size, _floor_points(data.plan, extra))
        backdrop = None
    else:
        scene_map, _ = _drawn_map(data.plan.get("workspace") or {}, extra)
        backdrop = _draw_workspace(data.plan.get("workspace") or {}, scene_map, run_dir)
    stream = read_stream(run_dir)
    times = [np.asarray(x, dtype=float) for x in (
        video.times_s if video is not None else None,
        tracked[0] if tracked is not None else None,
        stream["t_s"] if stream is not None else None) if x is not None and len(x)]
    if not times:
        raise ConfigError(f"{run_dir.name}: no video, tracked positions nor stream: no time to show")
    t_start = float(min(t[0] for t in times))
    t_end = float(max(t[-1] for t in times))
    frames_n = int(np.floor((t_end - t_start) * fps)) + 1
    strip = Strip(data, (t_start, t_end))
    panel = _Panel(data, paths, stream, video is not None)
    writer = cv2.VideoWriter(str(out), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*FOURCC), fps,
                             (WIDTH, HEIGHT))
    if not writer.isOpened():
        raise ConfigError(f"OpenCV cannot write {out} ({FOURCC} in MP4)")
    base = np.full((HEIGHT, WIDTH, 3), BACKGROUND, np.uint8)
    base[HEIGHT - STRIP_H:] = strip.image
    base = panel.draw_static(base, _title(data))
    x0 = SCENE[0] + (SCENE[2] - SCENE[0] - scene_map.size[0]) // 2
    y0 = SCENE[1] + (SCENE[3] - SCENE[1] - scene_map.size[1]) // 2
    frame = base.copy()
    try:
        for k in range(frames_n):
            t = t_start + k / fps
            if video is not None:
                c0, r0, c1, r1 = scene_map.crop
                scene = cv2.resize(video.at(t)[r0:r1, c0:c1], scene_map.size,
                                   interpolation=cv2.INTER_AREA)
            else:
                scene = backdrop.copy()
            now = _draw_overlays(scene, scene_map, paths, tracked, radii, t, panel.move_at(t),
                                 drawn=video is None)
            frame[HEIGHT - STRIP_H:] = base[HEIGHT - STRIP_H:]  # the strip without the cursor
            frame[y0:y0 + scene.shape[0], x0:x0 + scene.shape[1]] = scene
            strip.cursor(frame[HEIGHT - STRIP_H:], t)
            panel.draw(frame, t, now)
            writer.write(frame)
    finally:
        writer.release()
        if video is not None:
            video.close()
    return Rendered(out, frames_n, fps, "video" if video is not None else "drawn", why, t_start,
                    t_end)


def _title(data: RunData) -> str:
    name = data.plan.get("name") or "plan"
    return f"{_run_name(data.run_dir, data.plan)}: {name}"


def _draw_overlays(scene, scene_map: SceneMap, paths, tracked, radii, t_s: float, move: int,
                   *, drawn: bool) -> np.ndarray:
    """Planned paths, expected positions, goals, the tracked path up to `t_s` and the agents
    there; returns the agents' positions (n, 2) mm at `t_s` (NaN: not tracked then)."""
    n = len(radii)
    now = np.full((n, 2), np.nan)
    if tracked is not None:
        t_tr, p_tr = tracked
        upto = int(np.searchsorted(t_tr, t_s, side="right"))
        for i in range(min(n, p_tr.shape[1])):
            if upto == 0:
                break
            if upto < len(t_tr):  # between two tracked pictures: where it was in between
                now[i] = [np.interp(t_s, t_tr[upto - 1:upto + 1], p_tr[upto - 1:upto + 1, i, j])
                          for j in range(2)]
            else:
                now[i] = p_tr[upto - 1, i]
    for i, (planned, _, goal) in enumerate(paths):
        colour = COLOURS[i % len(COLOURS)]
        planned_px = scene_map(planned)
        _dashed(scene, planned_px, colour, 2)
        for point in planned_px[1:]:
            cv2.circle(scene, tuple(_fixed(point)), 3 * 16, colour, 1, cv2.LINE_AA, shift=4)
        if 0 <= move < len(planned) - 1:  # where the plan expects it after this move
            ring = max(6.0, radii[i] * scene_map.px_per_mm + 4)
            cv2.circle(scene, tuple(_fixed(planned_px[move + 1])), int(ring * 16), colour, 2,
                       cv2.LINE_AA, shift=4)
        _star(scene, scene_map(goal)[0], colour, 11.0)
    if tracked is not None:
        t_tr, p_tr = tracked
        upto = int(np.searchsorted(t_tr, t_s, side="right"))
        for i in range(min(n, p_tr.shape[1])):
            colour = COLOURS[i % len(COLOURS)]
            trail = np.vstack([p_tr[:upto, i], now[i][None]]) if upto else np.empty((0, 2))
            trail = trail[np.isfinite(trail).all(axis=1)]
            if len(trail) >= 2:
                cv2.polylines(scene, [_fixed(scene_map(trail))], False, colour, 2, cv2.LINE_AA,
                              shift=4)
            if np.isfinite(now[i]).all():
                centre = _fixed(scene_map(now[i])[0])
                r = max(4.0, radii[i] * scene_map.px_per_mm)
                if drawn:  # no picture of the magnet: the disc is it
                    cv2.circle(scene, tuple(centre), int(r * 16), colour, -1, cv2.LINE_AA, shift=4)
                cv2.circle(scene, tuple(centre), int((r + 2) * 16), (0, 0, 0) if drawn else colour,
                           2, cv2.LINE_AA, shift=4)
    return now


class _Panel:
    """The text right of the scene: time, move, re-plans, faults, distances to goal, legend."""

    def __init__(self, data: RunData, paths, stream: dict | None, has_video: bool) -> None:
        self.data, self.paths, self.has_video = data, paths, has_video
        self.stream_t = None if stream is None else np.asarray(stream["t_s"], float)
        self.stream_move = None if stream is None else np.asarray(stream["move"], int)
        streamed = int(self.stream_move.max()) + 1 if self.stream_move is not None and len(
            self.stream_move) else 0
        self.moves = max(streamed, len(data.plan.get("moves") or []))
        self.replans = np.array([e["t"] for e in data.events if e.get("event") == "replan"])
        self.faults = [(e["t"], e.get("device") or e.get("reason") or e["event"])
                       for e in data.events if e.get("event") in ("fault", "estop")]
        self.big, self.body = _font(30, bold=True), _font(18)
        self.small, self.title = _font(15), _font(17, bold=True)

    def move_at(self, t_s: float) -> int:
        if self.stream_t is None or not len(self.stream_t):
            return -1
        k = int(np.searchsorted(self.stream_t, t_s, side="right")) - 1
        return int(self.stream_move[k]) if k >= 0 else -1

    def _last_move(self, t_s: float) -> int:
        if self.stream_t is None:
            return -1
        k = int(np.searchsorted(self.stream_t, t_s, side="right"))
        done = self.stream_move[:k]
        return int(done.max()) if len(done) else -1

    @property
    def dynamic_height(self) -> int:
        """px of the part that changes: time, move, re-plans, a fault, one line per agent."""
        return 14 + 46 + 3 * 28 + 8 + 28 * len(self.paths) + 6

    def draw_static(self, frame: np.ndarray, title: str) -> np.ndarray:
        """The title band and the legend, drawn once into the frame every frame starts from."""
        image = Image.fromarray(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        pen = ImageDraw.Draw(image)
        pen.text((16, 9), _fit(pen, title, self.title, WIDTH - 32), font=self.title, fill=TEXT)
        x, y = PANEL_X, TITLE_H + self.dynamic_height + 4
        pen.text((x, y), "legend", font=self.title, fill=TEXT)
        y += 26
        scene = "camera video" if self.has_video else "workspace drawn from the plan (no video)"
        for line in ("dashed: planned path (start, then after each move)",
                     "small rings: positions the plan expects",
                     "large ring: expected after the current move",
                     "solid line: tracked path so far",
                     "circle: tracked position now (agent's radius)",
                     "star: goal",
                     f"scene: {scene}"):
            pen.text((x, y), _fit(pen, line, self.small, WIDTH - x - 16), font=self.small,
                     fill=TEXT)
            y += 21
        return cv2.cvtColor(np.asarray(image), cv2.COLOR_RGB2BGR)

    def draw(self, frame: np.ndarray, t_s: float, now_mm: np.ndarray) -> None:
        """The changing lines at `t_s` into `frame`, in place (only their box goes through
        Pillow: a whole frame there and back cost more than the rest of the frame)."""
        box_w, box_h = WIDTH - PANEL_X, self.dynamic_height
        image = Image.new("RGB", (box_w, box_h), BACKGROUND)
        pen = ImageDraw.Draw(image)
        x, y = 0, 14
        pen.text((x, y), f"t = {t_s:.2f} s", font=self.big, fill=TEXT)
        y += 46
        move = self.move_at(t_s)
        if move >= 0:
            text = f"move {move + 1} of {self.moves}"
        elif self._last_move(t_s) < 0:
            text = f"before the first move (of {self.moves})"
        else:
            text = f"between moves ({self._last_move(t_s) + 1} of {self.moves} done)"
        pen.text((x, y), text, font=self.body, fill=TEXT)
        y += 28
        replans = int((self.replans <= t_s).sum())
        pen.text((x, y), f"re-plans so far: {replans}", font=self.body, fill=TEXT)
        y += 28
        faults = [what for t, what in self.faults if t <= t_s]
        if faults:
            pen.text((x, y), _fit(pen, f"FAULT: {faults[-1]}", self.body, box_w - 16),
                     font=self.body, fill=(200, 30, 30))
        y += 28 + 8
        for i, (_, _, goal) in enumerate(self.paths):
            rgb = COLOURS[i % len(COLOURS)][::-1]
            pen.rectangle((x, y + 4, x + 14, y + 18), fill=rgb)
            if np.isfinite(now_mm[i]).all():
                dist = float(np.hypot(*(now_mm[i] - goal)))
                text = (f"agent {i}: at ({now_mm[i][0]:.1f}, {now_mm[i][1]:.1f}) mm, "
                        f"{dist:.1f} mm from goal")
            else:
                text = f"agent {i}: not tracked now"
            pen.text((x + 22, y), _fit(pen, text, self.body, box_w - 40), font=self.body,
                     fill=TEXT)
            y += 28
        frame[TITLE_H:TITLE_H + box_h, PANEL_X:] = cv2.cvtColor(np.asarray(image),
                                                              cv2.COLOR_RGB2BGR)


def _fit(pen: ImageDraw.ImageDraw, text: str, font, width_px: float) -> str:
    """`text` shortened with an ellipsis to `width_px` in `font`: nothing runs off the frame."""
    if pen.textlength(text, font=font) <= width_px:
        return text
    while text and pen.textlength(text + " …", font=font) > width_px:
        text = text[:-1]
    return text.rstrip() + " …"
