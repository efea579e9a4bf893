"""Recorded runs in the browser: the routes of the run viewer (`static/viewer.html`), mounted in
the daemon's console and served alone by `rigctl view RUN`.

A record (`rigctl.core.record`) is read once per change of its files and served as one compact
JSON document (`record_document`): the channels decimated to what a plot of the whole run can
show (`MAX_PLOT_POINTS` per channel, the minimum and the maximum of each time bucket, so a spike
stays visible), the events, the tracked positions, the video's frame-time table, the scene's
geometry (the plan in the camera's pixels through the record's calibration, or in mm when the
scene is drawn) and, on an arms rig (depm), the arms' joint origins at sampled instants
(`ArmsSketch`, the live console's own kinematics) from the recorded joints.

The video: the recorder writes Motion-JPEG in AVI (`rigctl.vision.video`: readable after a
crash), which no browser's `<video>` plays. Every frame of it is a whole JPEG, so the viewer asks
for the frame it wants by its index (`/records/RUN/frames/K.jpg`, the chunk's bytes as they are
in the file, found by walking the AVI's chunks: `avi_frames`, which also reads a file a crash cut
off) and the page shows the frame whose time on the record's clock is nearest the scrubbed time:
a seek is one small request, however long the run. The file itself is served whole with HTTP
Range support (`/records/RUN/video`: aiohttp's `FileResponse`) for a player or a download.

Who may read: the mounting server's `allowed(request)` (the console: loopback host names and, off
loopback, the token, which the page sends as `Authorization: Bearer`); the page itself holds no
data and is served to anyone, as the console's. A run is named by its folder's name under the
runs folder, never a path.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import struct
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.apps.console.scene import CameraScene, plan_paths_mm, shape_polygon_mm

log = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
MAX_PLOT_POINTS = 1600  # per channel: a min and a max for each of 800 buckets (a plot's width)
ARMS_SAMPLES = 1200  # arm poses over the whole record (a seek between two shows the nearer)
MAX_EVENTS = 3000  # events listed (the high-rate ones, `tracked` and `agents`, are positions)
CACHED_RECORDS = 4
VIDEO_FILES = ("video.avi", "video.mp4")  # served at /records/ID/video; shown: video.avi
_RUN_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,254}$")
_POSITION_EVENTS = {"tracked", "agents"}


# -- the video's frames ----------------------------------------------------------------------------

def avi_frames(path: str | Path) -> list[tuple[int, int]]:
    """(offset, size) in bytes of each video frame's data in the AVI at `path`, in order: the
    `##dc`/`##db` chunks of its `movi` lists (OpenDML's `AVIX` parts included). The chunks are
    walked, not the index: a file whose writer was killed has no index, and its last chunk may be
    cut off (it is left out)."""
    frames: list[tuple[int, int]] = []
    with open(path, "rb") as f:
        end = f.seek(0, 2)

        def walk(start: int, stop: int) -> None:
            at = start
            while at + 8 <= stop:
                f.seek(at)
                head = f.read(12)
                tag, size = head[:4], struct.unpack("<I", head[4:8])[0]
                body = at + 8
                if tag in (b"RIFF", b"LIST") and len(head) == 12 and \
                        head[8:12] in (b"AVI ", b"AVIX", b"movi", b"rec "):
                    # a writer killed mid-run leaves a list's size as it wrote it at the
                    # start (0): such a list runs to the end of the file
                    list_end = body + size if 4 <= size and body + size <= end else end
                    walk(body + 4, list_end)
                    if list_end == end:
                        return
                elif tag[2:] in (b"dc", b"db") and tag[:2].isdigit():
                    if body + size > end:
                        return  # cut off by a crash
                    frames.append((body, size))
                at = body + size + (size & 1)  # chunks are padded to an even size

        walk(0, end)
    return frames


def read_frame(path: str | Path, offset: int, size: int) -> bytes:
    with open(path, "rb") as f:
        f.seek(offset)
        return f.read(size)


# -- the record as one document ---------------------------------------------------------------------

def decimate(t: np.ndarray, y: np.ndarray, max_points: int = MAX_PLOT_POINTS
             ) -> tuple[np.ndarray, np.ndarray]:
    """At most `max_points` of the series (t, y), t sorted: each of max_points/2 equal time
    buckets gives its lowest and its highest sample (NaN only where a bucket has nothing else),
    in time order, so a plot of the whole run keeps every peak a full plot would show. Shorter
    series come back as they are."""
    n = len(t)
    if n <= max_points:
        return t, y
    buckets = max_points // 2
    span = max(float(t[-1] - t[0]), 1e-12)
    bucket = np.minimum(((t - t[0]) / span * buckets).astype(np.int64), buckets - 1)
    order = np.lexsort((y, bucket))  # by bucket, then by value, NaN last
    starts = np.flatnonzero(np.diff(bucket[order], prepend=-1))
    finite = np.add.reduceat(np.isfinite(y[order]).astype(np.int64), starts)
    low = order[starts]
    high = order[starts + np.maximum(finite, 1) - 1]
    keep = np.unique(np.concatenate([low, high]))  # indices, so in time order
    return t[keep], y[keep]


def _numbers(values: Any, digits: int = 5) -> list:
    """A JSON-ready list with NaN as null, rounded to `digits` decimals (small documents)."""
    array = np.round(np.asarray(values, dtype=float), digits)
    if np.isfinite(array).all():
        return array.tolist()
    return [None if not np.isfinite(v) else v for v in array.tolist()] if array.ndim == 1 else \
        [_numbers(row, digits) for row in array]


def _json_safe(value: Any) -> Any:
    """`value` with NaN and infinities as None (a browser's JSON.parse refuses NaN), anything
    JSON has no type for as its text."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if value is None or isinstance(value, (str, int, bool)):
        return value
    if hasattr(value, "tolist"):
        return _json_safe(value.tolist())
    return str(value)


class _RecordedCamera(CameraScene):
    """The console's camera scene with the record's calibration instead of a live rig's."""

    def __init__(self, calibration) -> None:
        self.calibration = calibration


def _record_rig(run_dir: Path):
    """The record's rig file snapshot, None if it has none or it no longer loads here."""
    from rigctl.core.config import load_rig
    from rigctl.core.errors import ConfigError

    if not (run_dir / "rig.toml").is_file():
        return None
    try:
        return load_rig(run_dir / "rig.toml")
    except (ConfigError, ValueError) as err:
        log.info("viewer: %s/rig.toml does not load here (%s): no arms from it", run_dir.name, err)
        return None


def _arms(run_dir: Path, data, rig) -> dict | None:
    """The arms at sampled instants from the recorded joints, for an "arms" rig kind: {"t",
    "frames": [{"arms": [{"name", "points_mm" (9, 3)}], ...}], "keep_out_mm", "epm_radius_mm"}."""
    from rigctl.apps.console.scene import ArmsSketch
    from rigctl.core.errors import ConfigError
    from rigctl.core.registry import rig_kind

    if rig is None:
        return None
    try:  # as the live console chooses its scene (server.console_scene)
        kind = rig_kind(rig.rig.kind)
    except ConfigError:
        return None
    if kind.scene != "arms" or kind.scene_of is None:
        return None
    sketch = ArmsSketch(kind.scene_of(rig))
    if not sketch.available:
        return None
    joints = [tr for tr in data.traces if tr.channel.unit == "rad"]
    if len(joints) != 7 * len(sketch.arms) or not len(joints[0].t):
        return None
    t = np.asarray(joints[0].t, dtype=float)
    q = np.column_stack([np.asarray(tr.measured, dtype=float) for tr in joints])
    pick = np.unique(np.linspace(0, len(t) - 1, min(len(t), ARMS_SAMPLES)).round().astype(int))
    frames = []
    for k in pick:
        row = np.where(np.isfinite(q[k]), q[k], 0.0)  # as the live console: an unread joint at 0
        frames.append(sketch.of_joints(row.tolist())["arms"])
    return {"t": _numbers(t[pick], 4), "frames": frames, "keep_out_mm": sketch.keep_out_mm,
            "epm_radius_mm": sketch.epm_radius_mm}


def _plots(traces: list) -> list[dict]:
    """One plot per channel group and unit: each channel's measured series (what the device
    reported), decimated, with its limits."""
    from rigctl.apps.report import UNIT_LABELS

    groups: dict[tuple[str, str], list] = {}
    for trace in traces:
        groups.setdefault((trace.channel.group or "", trace.channel.unit), []).append(trace)
    plots = []
    for (group, unit), members in groups.items():
        channels = []
        for trace in members:
            t, y = decimate(np.asarray(trace.t, dtype=float),
                            np.asarray(trace.measured, dtype=float))
            c = trace.channel
            channels.append({"name": c.name, "unit": c.unit, "low": c.low, "high": c.high,
                             "measured": {"t": _numbers(t, 4), "y": _numbers(y)}})
        label = UNIT_LABELS.get(unit, unit)
        plots.append({"title": f"{group}: {label}" if group else label, "unit": unit,
                      "y_label": label, "channels": channels})
    return plots


def record_document(run_dir: str | Path) -> dict:
    """The record at `run_dir` as the viewer draws it (see the module's docstring); times are s
    since the run started (the record's clock), positions mm, scene geometry px or mm."""
    from rigctl.apps.report import _agent_paths, read_run
    from rigctl.apps.report_video import _calibration, _radii_mm, _tracked
    from rigctl.core.record import read_series, read_stream
    from rigctl.vision.video import VIDEO_FILE, VIDEO_SERIES

    run_dir = Path(run_dir)
    stream = read_stream(run_dir)  # once: a 10-minute record has 120 Parquet parts
    data = read_run(run_dir, stream)
    plan = data.plan
    rig = _record_rig(run_dir)

    plots = _plots(data.traces)
    moves = []
    if stream is not None and len(stream.get("t_s", ())):
        move = np.asarray(stream["move"], dtype=int)
        changes = np.flatnonzero(np.diff(move, prepend=move[0] - 1))
        moves = [[round(float(stream["t_s"][k]), 4), int(move[k])] for k in changes]

    paths = _agent_paths(plan, data.events, data.summary) if plan else []
    tracked = _tracked(data.events)
    n_agents = len(paths) if paths else (tracked[1].shape[1] if tracked is not None else 0)
    radii = _radii_mm(plan, n_agents) if n_agents else np.empty(0)

    video_file = run_dir / VIDEO_FILE  # the recorder's (an MP4 beside it is served, not shown)
    series = read_series(run_dir, VIDEO_SERIES)
    video = None
    if video_file.is_file() and series is not None and len(series.get("t_s", ())):
        frames_t = np.asarray(series["t_s"], dtype=float)
        # a crash: the file or the table may be the longer; frames beyond either are not shown
        count = min(len(avi_frames(video_file)), len(frames_t))
        video = {"file": video_file.name, "frames": count, "t_s": _numbers(frames_t[:count], 6)}
    calibration = _calibration(run_dir)
    arms = _arms(run_dir, data, rig)

    workspace = plan.get("workspace") or {}
    to_scene = None
    if arms is not None:
        scene: dict[str, Any] = {"kind": "arms",
                                 "why": "the arms from their recorded joints (no camera)"}
    elif video is not None and calibration is not None:
        camera = _RecordedCamera(calibration)
        scene = {"kind": "camera", "why": "the record's video", **camera.of_plan(plan),
                 "resolution": calibration.resolution}
        to_scene = camera.to_px
    elif video is not None:  # the pictures, but nothing to put the plan's mm on them with
        scene = {"kind": "camera", "why": "the record's video (its rig.toml has no camera "
                 "calibration: no overlays)", "boundary": [], "obstacles": [], "paths": [],
                 "goals": [], "radii_px": [], "resolution": None}
        to_scene = None
    else:
        why = "the record has no video"
        scene = {"kind": "drawn", "why": f"drawn from the plan and the tracked positions ({why})",
                 "boundary": [], "obstacles": [], "paths": plan_paths_mm(plan) or [],
                 "goals": [a["goal"][:2] for a in plan.get("agents") or []
                           if isinstance(a, dict) and a.get("goal")]}
        if "boundary" in workspace:
            scene["boundary"] = shape_polygon_mm(workspace["boundary"])
            scene["obstacles"] = [shape_polygon_mm(s) for s in workspace.get("obstacles", [])]

        def to_scene(points):
            return np.round(np.asarray(points, dtype=float).reshape(-1, 2), 3).tolist()
    if scene["kind"] == "drawn" and paths and not scene["paths"]:  # a pair: its planned states
        scene["paths"] = [np.round(p, 3).tolist() for p, _, _ in paths]
        scene["goals"] = [np.round(g, 3).tolist() for _, _, g in paths]
    scene["goals_mm"] = [np.round(g, 3).tolist() for _, _, g in paths]
    agents = None
    if tracked is not None:
        t_tr, p_tr = tracked
        agents = {"t": _numbers(t_tr, 4), "mm": _numbers(p_tr.reshape(len(t_tr), -1), 3),
                  "n": int(p_tr.shape[1]), "radii_mm": _numbers(radii, 3)}
        if to_scene is not None and scene["kind"] in ("camera", "drawn"):
            flat = p_tr.reshape(-1, 2)
            scene_points = np.full_like(flat, np.nan)
            ok = np.isfinite(flat).all(axis=1)
            if ok.any():
                scene_points[ok] = np.asarray(to_scene(flat[ok]), dtype=float)
            agents["scene"] = _numbers(scene_points.reshape(len(t_tr), -1), 2)
            if scene["kind"] == "camera":  # each agent's radius in px where it started
                agents["radii_scene"] = scene.get("radii_px") or []
            else:
                agents["radii_scene"] = _numbers(radii, 3)

    events = [e for e in data.events if e.get("event") not in _POSITION_EVENTS][:MAX_EVENTS]
    times = [np.asarray(x, dtype=float) for x in (
        np.asarray(video["t_s"], dtype=float) if video else None,
        tracked[0] if tracked is not None else None,
        stream["t_s"] if stream is not None else None,
        [e["t"] for e in data.events if isinstance(e.get("t"), (int, float))]) if x is not None
        and len(x)]
    t_start = float(min(x.min() for x in times)) if times else 0.0
    t_end = float(max(x.max() for x in times)) if times else 0.0
    summary = data.summary or {}
    return {"id": run_dir.name, "plan": plan.get("name"), "rig": data.rig,
            "rig_name": rig.rig.name if rig is not None else None,
            "finished": data.summary is not None, "reached": summary.get("reached"),
            "t_start_s": round(t_start, 4), "t_end_s": round(t_end, 4),
            "plots": plots, "moves": moves, "n_moves": len(plan.get("moves") or []) or
            1 + max((m for _, m in moves), default=-1),
            "events": _json_safe(events), "video": video,
            "scene": scene, "agents": agents, "arms": arms}


def _document_json(document: dict) -> bytes:
    """Compact JSON; the series are NaN-free already (`_numbers`), and a NaN anywhere else (an
    event's field) costs one pass over the whole (0.15 s for 10 minutes) rather than the page."""
    try:
        return json.dumps(document, separators=(",", ":"), allow_nan=False).encode()
    except ValueError:
        return json.dumps(_json_safe(document), separators=(",", ":"), allow_nan=False).encode()


# -- the routes ---------------------------------------------------------------------------------

class Records:
    """The records under `runs_dir`, read on demand and kept while their files do not change
    (the handlers' executor threads share the caches: a lock around each look-up and store)."""

    def __init__(self, runs_dir: str | Path) -> None:
        self.runs_dir = Path(runs_dir)
        self._lock = threading.Lock()
        self._documents: OrderedDict[str, tuple[tuple, bytes]] = OrderedDict()
        self._frames: OrderedDict[str, tuple[tuple, list[tuple[int, int]]]] = OrderedDict()

    def run_dir(self, run: str) -> Path | None:
        if not _RUN_ID.match(run) or run in (".", ".."):
            return None
        path = self.runs_dir / run
        return path if (path / "events.jsonl").is_file() else None

    @staticmethod
    def _stamp(run_dir: Path) -> tuple:
        """What changes when a record grows: its files' sizes and times (a running record)."""
        return tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns)
                     for p in sorted(run_dir.iterdir()) if p.is_file())

    def _cached(self, cache: OrderedDict, key: str, stamp: tuple, make: Callable[[], Any]) -> Any:
        with self._lock:
            hit = cache.get(key)
            if hit is not None and hit[0] == stamp:
                cache.move_to_end(key)
                return hit[1]
        value = make()  # outside the lock: two pages asking at once read it twice, harmlessly
        with self._lock:
            cache[key] = (stamp, value)
            while len(cache) > CACHED_RECORDS:
                cache.popitem(last=False)
        return value

    def document(self, run_dir: Path) -> bytes:
        return self._cached(self._documents, run_dir.name, self._stamp(run_dir),
                            lambda: _document_json(record_document(run_dir)))

    def frames(self, run_dir: Path, video: Path) -> list[tuple[int, int]]:
        stat = video.stat()
        return self._cached(self._frames, run_dir.name, (stat.st_size, stat.st_mtime_ns),
                            lambda: avi_frames(video))

    def listing(self, limit: int = 200) -> list[dict]:
        from rigctl.core.record import list_runs

        runs = list_runs(self.runs_dir, limit=limit)
        for run in runs:
            folder = self.runs_dir / run["id"]
            run["video"] = any((folder / name).is_file() for name in VIDEO_FILES)
        return runs


def add_record_routes(app, runs_dir: str | Path, allowed: Callable[[Any], bool]) -> Records:
    """Mount the viewer on an aiohttp `app`: `/viewer` (the page, `?run=ID`), `/records` (the
    list), `/records/{run}/data.json`, `/records/{run}/frames/{k}.jpg`, `/records/{run}/video`.
    `allowed(request)` says who may read (False: 403)."""
    routes = _Routes(Records(runs_dir), allowed)
    app.router.add_get("/viewer", routes.page)
    app.router.add_get("/records", routes.listing)
    app.router.add_get("/records/{run}/data.json", routes.document)
    app.router.add_get(r"/records/{run}/frames/{k:\d+}.jpg", routes.frame)
    app.router.add_get("/records/{run}/video", routes.video)
    return routes.records


class _Routes:
    """The viewer's handlers; the slow parts (reading a record, a file) in the loop's executor."""

    def __init__(self, records: Records, allowed: Callable[[Any], bool]) -> None:
        self.records, self.allowed = records, allowed

    def _guard(self, request) -> None:
        from aiohttp import web

        if not self.allowed(request):
            raise web.HTTPForbidden(text="refused: not allowed to read the run records here")

    def _run(self, request) -> Path:
        from aiohttp import web

        self._guard(request)
        run = request.match_info["run"]
        run_dir = self.records.run_dir(run)
        if run_dir is None:
            raise web.HTTPNotFound(text=f"no run record {run!r}")
        return run_dir

    @staticmethod
    async def _off_loop(function, *args):
        return await asyncio.get_running_loop().run_in_executor(None, function, *args)

    async def page(self, request):
        from aiohttp import web

        # the page holds no data (as the console's own page): off loopback it comes without the
        # token, which it then sends with every request for the record (Authorization: Bearer)
        return web.FileResponse(STATIC / "viewer.html")

    async def listing(self, request):
        from aiohttp import web

        self._guard(request)
        return web.json_response(await self._off_loop(self.records.listing))

    async def document(self, request):
        from aiohttp import web

        run_dir = self._run(request)
        try:
            body = await self._off_loop(self.records.document, run_dir)
        except Exception as err:  # a record this reader cannot make sense of: say so, once
            log.exception("viewer: cannot read %s", run_dir)
            raise web.HTTPUnprocessableEntity(text=f"{run_dir.name}: cannot be read ({err})"
                                              ) from None
        return web.Response(body=body, content_type="application/json")

    async def frame(self, request):
        from aiohttp import web

        run_dir = self._run(request)
        video = run_dir / "video.avi"
        k = int(request.match_info["k"])  # digits, by the route
        if not video.is_file():
            raise web.HTTPNotFound(text=f"{run_dir.name} has no video.avi")
        frames = await self._off_loop(self.records.frames, run_dir, video)
        if not 0 <= k < len(frames):
            raise web.HTTPNotFound(text=f"{run_dir.name}: no frame {k} (0..{len(frames) - 1})")
        body = await self._off_loop(read_frame, video, *frames[k])
        return web.Response(body=body, content_type="image/jpeg")

    async def video(self, request):
        from aiohttp import web

        run_dir = self._run(request)
        for name in VIDEO_FILES:
            if (run_dir / name).is_file():
                return web.FileResponse(run_dir / name)  # a Range request: 206 with the part
        raise web.HTTPNotFound(text=f"{run_dir.name} has no video")
