"""`rigctl report RUN`: one PNG per run record, planned against measured, for every rig.

The figure is made of the panels the record has data for, and only those (what is missing is
said in a line of text at the bottom, never shown as an empty panel):

- **paths** (camera rigs: six-coil global moves and pairs, the coil board): the workspace
  (boundary and obstacles from the plan), each agent's planned path (dashed: its start, then where
  the plan expects it after every move; a pair's from the plan's formation states) and its
  measured path (solid: the `tracked` events the tracking loop writes, else a pair run's `track`
  events, else the daemon's `agents` samples, else an old coil-board record's per-move positions;
  then the summary's final position), start (square) and goal (star) marked;
- **actuators**: one small panel per channel group of the record's `channels.json` (the six
  supplies, the coil board, each arm), commanded dashed over measured solid in the same colour,
  the channels' limits as grey horizontal lines, the y axis in the channels' unit;
- **field and gradients** (dual-EPM rig): the Hall board's estimate of U (the `field` series;
  old records: `field.csv`) against the requests of the plan's segments (dashed steps), fields in
  one panel and gradients in another, each hold shaded and named;
- **stream timing**: each cycle's period error, when the record has it;
- **identified model** (camera rigs): the closed loop's estimates over time (the `identification`
  series, `rigctl.physics.identify`), one panel per unit (a rolling gain, a heading bias, a drift, the
  coil board's non-uniformity rates), each estimate with its +-1 standard deviation shaded.

What a rig kind draws its own way comes from its `RigKind.report` (`rigctl.rigs.base.ReportHooks`):
its channel groups' titles, the channels of its records from before channels had units, and any
panel only it has; the report names no rig kind.

Faults and e-stops (red) and re-plans (purple) are marked on every time axis. The title names the
run (its start time and plan) and states the verdict. The dual-EPM rig's panels run on the plan's
clock (its emulated bench may run K times faster than real time); the run's own events are put on
that clock through the events that carry both (`t`, `t_plan_s`).

`build_figure` draws a record into a matplotlib Figure (tests inspect its axes; the artists
carry gids: "planned i", "measured i", "limit", "fault", "replan"); `render_report` saves it.
The report reads only the record, so it works on a run cut off by a crash too.
"""

from __future__ import annotations

import json
import logging
import re
import textwrap
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import patches  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from rigctl.core.channels import Channel  # noqa: E402
from rigctl.core.errors import ConfigError  # noqa: E402
from rigctl.core.record import _read_journal, read_events, read_series, read_stream  # noqa: E402
from rigctl.rigs.base import ReportHooks  # noqa: E402
from rigctl.run.certificate import read_certificate, summary_line  # noqa: E402

log = logging.getLogger(__name__)

UNIT_LABELS = {
    "A": "current (A)",
    "drive": "SyRen drive (-127..127)",
    "rad": "joint angle (rad)",
    "mT": "field (mT)",
    "mT/m": "gradient (mT/m)",
}
FIELD_COMPONENTS = ("Bx", "By", "Bz")
GRADIENT_COMPONENTS = ("dBx/dx", "dBx/dy", "dBx/dz", "dBy/dy", "dBy/dz")
FAULT_EVENTS = ("fault", "estop")
FAULT_COLOUR = "red"
REPLAN_COLOUR = "tab:purple"
RUN_CLOCK, PLAN_CLOCK = "run", "plan"


def find_run(run: str | Path, runs_dir: str | Path = "runs") -> Path:
    """A run given as a path, as a run id inside `runs_dir`, as the start of one (a unique
    prefix), or as `latest` (the newest there)."""
    for candidate in (Path(run), Path(runs_dir) / str(run)):
        if (candidate / "events.jsonl").is_file():
            return candidate
    root = Path(runs_dir)
    ids = sorted(p.name for p in root.iterdir() if (p / "events.jsonl").is_file()) \
        if root.is_dir() else []
    found = ids[-1:] if str(run) == "latest" else [i for i in ids if i.startswith(str(run))]
    if len(found) == 1:
        return root / found[0]
    if found:
        raise ConfigError(f"run {run!r} is the start of {len(found)} runs in {root}: "
                          f"{', '.join(found[:3])}{', ...' if len(found) > 3 else ''}; give more")
    raise ConfigError(f"no run record at {run} (nor in {root}: `rigctl runs --runs {root}` lists "
                      "them)")


# -- reading the record ---------------------------------------------------------------------------

@dataclass
class Trace:
    """One actuator channel over time: commanded and measured, on `clock`."""

    channel: Channel
    t: np.ndarray
    commanded: np.ndarray
    measured: np.ndarray
    clock: str = RUN_CLOCK


@dataclass
class RunData:
    """What the report draws, read from a record (any rig, old or new layout)."""

    run_dir: Path
    plan: dict
    events: list[dict]
    summary: dict | None
    traces: list[Trace] = field(default_factory=list)
    period_error: tuple[np.ndarray, np.ndarray] | None = None  # (t run s, error s)
    fields: dict | None = None  # "t" (plan s) and one array per U component, "units"
    to_plan: Callable[[np.ndarray], np.ndarray] | None = None  # run clock -> plan clock
    to_run: Callable[[np.ndarray], np.ndarray] | None = None
    time_scale: float = 1.0

    @property
    def rig(self) -> str | None:
        return (self.summary or {}).get("rig") or self.plan.get("rig")


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def read_run(run_dir: str | Path, stream: dict | None = None) -> RunData:
    """Everything the report draws from the record at `run_dir` (its `read_stream` if the caller
    has read it already)."""
    run_dir = Path(run_dir)
    data = RunData(run_dir, _read_json(run_dir / "plan.json") or {}, read_events(run_dir),
                   _read_json(run_dir / "summary.json"))
    data.to_plan, data.to_run, data.time_scale = _plan_clock(data.events)
    stream = read_stream(run_dir) if stream is None else stream
    if stream is not None and len(stream.get("t_s", ())):
        data.traces = _stream_traces(stream, data)
        error = stream.get("period_error_s")
        if error is not None and np.isfinite(error).any():
            data.period_error = (stream["t_s"], np.asarray(error, dtype=float))
    if not data.traces and (run_dir / "joints.csv").is_file():
        data.traces = _old_joint_traces(run_dir / "joints.csv")
    data.fields = _read_fields(run_dir)
    return data


def _plan_clock(events: list[dict]):
    """The run clock (`t` of the events) to the plan's clock and back, from the events that carry
    both (`t_plan_s`: the dual-EPM run's segments); with one such event only, the bench's time
    scale gives the slope. (None, None, scale) when the record has none."""
    scale = next((float(e["time_scale"]) for e in events if e.get("time_scale")), 1.0)
    pairs = np.array([(e["t"], e["t_plan_s"]) for e in events
                      if "t_plan_s" in e and "t" in e], dtype=float).reshape(-1, 2)
    if len(np.unique(pairs[:, 0])) >= 2:
        slope, offset = np.polyfit(pairs[:, 0], pairs[:, 1], 1)
    elif len(pairs):
        slope, offset = scale, pairs[0, 1] - scale * pairs[0, 0]
    else:
        return None, None, scale
    return (lambda t: offset + slope * np.asarray(t, dtype=float),
            lambda tp: (np.asarray(tp, dtype=float) - offset) / slope, scale)


def report_hooks(rig: str | None) -> ReportHooks:
    """What the record's rig kind draws its own way (`RigKind.report`); the defaults for a record
    of a kind not installed here (its panels then take the generic titles)."""
    from rigctl.core.registry import kinds

    kind = kinds().get(rig) if rig else None
    return kind.report if kind is not None else ReportHooks()


def _stream_traces(stream: dict, data: RunData) -> list[Trace]:
    traces = []
    channels: list[Channel] = stream["channels"]
    # a record from before channels had units and groups: as its rig kind meant them (the
    # columns keep the names and units they were written with)
    old_channels = report_hooks(data.rig).old_channels
    meant = old_channels(channels, data.run_dir) if old_channels is not None else channels
    for written, channel in zip(channels, meant, strict=True):
        cmd, meas = stream.get(written.column("cmd")), stream.get(written.column("meas"))
        if cmd is None or meas is None:
            continue
        traces.append(Trace(channel, stream["t_s"], np.asarray(cmd, float), np.asarray(meas, float)))
    return traces


def _old_joint_traces(path: Path) -> list[Trace]:
    """A dual-EPM record from before channels: `joints.csv` (plan s, cmd/meas_<arm>_q<j> rad)."""
    from rigctl.physics.kinematics import LBR_IIWA_14_R820

    header, rows = _read_journal(path)
    if not rows:
        return []
    table = np.asarray(rows, dtype=float)
    col = {name: j for j, name in enumerate(header)}
    traces = []
    for name in header:
        m = re.fullmatch(r"cmd_(.+)_q(\d+)", name)
        if not m or f"meas_{m[1]}_q{m[2]}" not in col:
            continue
        arm, j = m[1], int(m[2])
        low, high = LBR_IIWA_14_R820.joint_limits_rad[j - 1]
        channel = Channel(f"{arm}_q{j}", "rad", low, high, arm)
        traces.append(Trace(channel, table[:, col["t_s"]], table[:, col[name]],
                            table[:, col[f"meas_{arm}_q{j}"]], clock=PLAN_CLOCK))
    return traces


def _read_fields(run_dir: Path) -> dict | None:
    """The Hall board's U estimate: the `field` series, else an old record's `field.csv`."""
    series = read_series(run_dir, "field")
    if series is None and (run_dir / "field.csv").is_file():
        header, rows = _read_journal(run_dir / "field.csv")
        table = np.asarray(rows, dtype=float).reshape(-1, len(header))
        series = {c: table[:, j] for j, c in enumerate(header)}
        series["t_plan_s"] = series.pop("t_s", np.empty(0))
        series["units"] = {}
    if series is None or not len(series.get("t_plan_s", ())):
        return None
    units = series.get("units") or {}
    out: dict[str, Any] = {"t": series["t_plan_s"], "units": {}}
    for component in (*FIELD_COMPONENTS, *GRADIENT_COMPONENTS):
        column = f"U_{component}"
        if column in series:
            out[component] = series[column]
            default = "mT" if component in FIELD_COMPONENTS else "mT/m"
            out["units"][component] = units.get(column, default)
    return out


# -- paths ----------------------------------------------------------------------------------------

def _draw_shape(ax, shape: dict, *, obstacle: bool) -> None:
    style = dict(facecolor="0.8" if obstacle else "none", edgecolor="0.35", linewidth=1.0)
    if "rect" in shape:
        x, y, w, h = shape["rect"]
        ax.add_patch(patches.Rectangle((x, y), w, h, **style))
    elif "polygon" in shape:
        ax.add_patch(patches.Polygon(np.asarray(shape["polygon"]), closed=True, **style))
    elif "disk" in shape:
        cx, cy, r = shape["disk"]
        ax.add_patch(patches.Circle((cx, cy), r, **style))


def _draw_workspace(ax, workspace: dict, plan_dir: Path) -> None:
    if "image" in workspace:
        try:
            image = plt.imread(plan_dir / workspace["image"])
        except (OSError, ValueError, SyntaxError):
            log.warning("workspace image %s not found beside the record", workspace["image"])
            return
        scale = float(workspace.get("mm_per_px", 1.0))
        ox, oy = workspace.get("origin", [0.0, 0.0])
        h, w = image.shape[:2]
        ax.imshow(image, cmap="gray", extent=(ox, ox + w * scale, oy, oy + h * scale))
        return
    _draw_shape(ax, workspace.get("boundary", {}), obstacle=False)
    for obstacle in workspace.get("obstacles", []):
        _draw_shape(ax, obstacle, obstacle=True)


def _tracked_positions(events: list[dict]) -> np.ndarray | None:
    """(frames, agents, 2) mm from the `tracked` events, a lost agent's point NaN."""
    frames = []
    for e in events:
        if e.get("event") != "tracked" or not e.get("positions_mm"):
            continue
        p = np.array(e["positions_mm"], dtype=float).reshape(-1, 2)
        lost = np.asarray(e.get("lost") or [False] * len(p), dtype=bool)
        p[lost[:len(p)]] = np.nan
        frames.append(p)
    if not frames or len({len(p) for p in frames}) != 1:
        return None
    return np.array(frames)


def _final_positions(summary: dict | None, n: int) -> list[np.ndarray | None]:
    agents = (summary or {}).get("agents") or []
    finals: list[np.ndarray | None] = []
    for i in range(n):
        a = agents[i] if i < len(agents) else {}
        final = a.get("final", a.get("final_mm"))
        finals.append(None if final is None else np.array(final, dtype=float)[:2])
    return finals


def _measured_source(events: list[dict]) -> str:
    names = {e.get("event") for e in events}
    for name, text in (("tracked", "camera, tracked events"), ("track", "camera, pair run"),
                       ("agents", "daemon samples"), ("move", "camera, after each move")):
        if name in names:
            return text
    return "final positions only"


def _agent_paths(plan: dict, events: list[dict],
                 summary: dict | None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per agent: the planned path (k, 2) mm from the start, the measured one (m, 2) mm, and the
    goal (2,) mm.

    Global moves (six-coil, coil board): the start, then the positions the plan expects after
    each move. A pair formation change (seed 002): both agents from the plan's states (centre,
    separation, heading) at the start, after each segment and at the goal. Measured: the tracking
    loop's `tracked` events, else the pair run's `track` events, else the daemon's `agents`
    samples, else the positions an old coil-board run logged after each move; then the
    summary's final position."""
    samples: list = []  # per frame, each agent's position (mm), when no `tracked` events fit
    if plan.get("kind") == "pair-formation":
        from rigctl.plans.pair import agent_positions

        body = plan["agents"]["body_diameter_mm"]
        states = [plan["start"], *(plan.get("expected") or []), plan["goal"]]
        both = agent_positions(np.array([[s["x_mm"] / body, s["y_mm"] / body, s["r_bl"],
                                          np.radians(s["phi_deg"])] for s in states])) * body
        planned = [both[:, i] for i in range(2)]
        goals = [p[-1] for p in planned]
        track = np.array([e["q"] for e in events if e.get("event") == "track"], dtype=float)
        if track.size:
            samples = list(agent_positions(track) * body)
    else:
        agents = plan.get("agents") or []
        if not isinstance(agents, list):
            return []
        expected = plan.get("expected") or []
        planned = [np.array([a["start"]] + [step[i] for step in expected if len(step) > i],
                            dtype=float) for i, a in enumerate(agents)]
        goals = [np.array(a["goal"], dtype=float) for a in agents]
    tracked = _tracked_positions(events)
    if tracked is not None and tracked.shape[1] == len(planned):
        samples = list(tracked)
    if not samples:
        samples = [e["tracked"] for e in events if e.get("event") == "agents" and e.get("tracked")]
    if not samples:  # an old coil-board record: where the camera saw them after each move
        samples = [e["measured"] for e in events if e.get("event") == "move" and e.get("measured")]
    finals = _final_positions(summary, len(planned))
    paths = []
    for i, (path, goal, final) in enumerate(zip(planned, goals, finals)):
        measured = np.array([s[i] for s in samples if len(s) > i], dtype=float).reshape(-1, 2)
        if final is not None:
            measured = np.vstack([measured, final[None, :]])
        paths.append((path, measured, goal))
    return paths


def _draw_paths(ax, data: RunData, paths) -> None:
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    _draw_workspace(ax, data.plan.get("workspace", {}), data.run_dir)
    for i, (planned, measured, goal) in enumerate(paths):
        colour = colours[i % len(colours)]
        # measured wide and pale under the planned dashes: both show where they coincide
        if len(measured):
            ax.plot(measured[:, 0], measured[:, 1], "-", color=colour, linewidth=2.6, alpha=0.45,
                    marker="o" if len(measured) <= 3 else None, markersize=4,
                    label=f"agent {i} measured", gid=f"measured {i}")
        ax.plot(planned[:, 0], planned[:, 1], "--o", color=colour, markersize=3, linewidth=1.0,
                label=f"agent {i} planned", gid=f"planned {i}")
        ax.plot(*planned[0], "s", color=colour, markersize=7, markeredgecolor="k",
                markeredgewidth=0.5)
        ax.plot(*goal, "*", color=colour, markersize=13, markeredgecolor="k", markeredgewidth=0.5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    source = (_measured_source(data.events) if any(len(m) for _, m, _ in paths)
              else "none recorded")
    ax.set_title(f"paths: planned (dashed), measured (solid; {source})", fontsize=9)
    handles, labels = ax.get_legend_handles_labels()
    handles += [Line2D([], [], color="0.4", marker="s", linestyle="none"),
                Line2D([], [], color="0.4", marker="*", markersize=10, linestyle="none")]
    labels += ["start", "goal"]
    ax.legend(handles, labels, fontsize=7, loc="best", framealpha=0.8)


# -- time panels ----------------------------------------------------------------------------------

@dataclass
class TimePanel:
    gid: str
    clock: str  # the clock of its x axis
    draw: Callable[[Any], None]
    weight: float = 1.0  # its share of the column's height


def _group_title(group: str, unit: str, hooks: ReportHooks) -> str:
    """A channel group's panel title: the rig kind's own name for it, else the group's name (amps
    in no group: coil currents; an arm's joint angles: its joints)."""
    if group in hooks.group_titles:
        name = hooks.group_titles[group]
    elif not group and unit == "A":
        name = "coil currents"
    elif unit == "rad":
        name = f"{group} arm joints"
    else:
        name = group or "actuators"
    return f"{name}: commanded (dashed), measured (solid)"


def _actuator_panels(data: RunData, clock: str) -> list[TimePanel]:
    groups: dict[str, list[Trace]] = {}
    for trace in data.traces:
        groups.setdefault(trace.channel.group, []).append(trace)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    hooks = report_hooks(data.rig)
    panels = []
    for group, traces in groups.items():
        t_axis, axis_clock = _on_clock(data, traces[0].t, traces[0].clock, clock)
        units = sorted({t.channel.unit for t in traces})

        def draw(ax, traces=traces, t_axis=t_axis, units=units, group=group):
            for j, same in enumerate(_same_commands(traces)):
                colour = colours[j % len(colours)]
                names = []
                for trace in same:
                    name = trace.channel.name
                    if group and name.startswith(f"{group}_"):
                        name = name[len(group) + 1:]  # "left_q3" in the "left" panel: "q3"
                    names.append(name)
                    # measured wide and pale under the commanded dashes: both stay visible where
                    # they coincide (a supply that follows its setpoint)
                    ax.plot(t_axis, trace.measured, "-", color=colour, linewidth=2.2, alpha=0.45,
                            gid=f"measured {trace.channel.name}")
                ax.plot(t_axis, same[0].commanded, "--", color=colour, linewidth=0.8,
                        gid=f"commanded {' '.join(t.channel.name for t in same)}")
                ax.plot([], [], "-", color=colour, linewidth=2.2, alpha=0.6, label=" = ".join(names))
            limits = sorted({v for t in traces for v in (t.channel.low, t.channel.high)
                             if v is not None})
            for value in limits:
                ax.axhline(value, color="0.45", linewidth=0.9, linestyle=(0, (1, 1.5)),
                           gid="limit")
            if limits:
                ax.plot([], [], color="0.45", linewidth=0.9, linestyle=(0, (1, 1.5)),
                        label="limits")
            unit = units[0] if len(units) == 1 else ", ".join(units)
            ax.set_ylabel(UNIT_LABELS.get(unit, unit), fontsize=8)
            ax.set_title(_group_title(group, unit, hooks), fontsize=9)
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.02), borderaxespad=0.2,
                      handlelength=1.5, frameon=False)

        panels.append(TimePanel(f"actuators:{group or units[0]}", axis_clock, draw, 1.6))
    return panels


def _winding_panels(data: RunData, clock: str) -> list[TimePanel]:
    """The live winding model's estimate (`series/winding.csv`), with the windings' limits from
    the certificate (`rigctl.run.certificate`), on the run's clock."""
    series = read_series(data.run_dir, "winding")
    if series is None or not len(series.get("t_s", ())):
        return []
    names = [c for c in series if c not in ("t_s", "units")]
    certificate = read_certificate(data.run_dir) or {}
    limits = sorted({c["limit"] for c in certificate.get("checks", [])
                     if c["check"] == "winding temperature"})
    t_axis, axis_clock = _on_clock(data, np.asarray(series["t_s"]), RUN_CLOCK, clock)

    def draw(ax):
        values = np.concatenate([np.asarray(series[name], float) for name in names])
        low, high = float(np.nanmin(values)), float(np.nanmax(values))
        for name in names:
            ax.plot(t_axis, series[name], linewidth=1.2, label=name)
        # a limit far above a small rise would flatten it: the axis is the data's, and the limit
        # is named in the legend with how far off it is
        span = max(high - low, 1.0)
        near = [v for v in limits if v <= high + 4 * span]
        for value in near:
            ax.axhline(value, color="tab:red", linewidth=0.9, linestyle=(0, (1, 1.5)))
        if near:
            ax.plot([], [], color="tab:red", linewidth=0.9, linestyle=(0, (1, 1.5)),
                    label="limit")
        for value in limits:
            if value not in near:
                ax.plot([], [], color="none", label=f"limit {value:g} °C\n({value - high:.0f} K above)")
        if not near:
            ax.set_ylim(low - 0.1 * span, high + 0.3 * span)
        ax.set_ylabel("winding (°C)", fontsize=8)
        ax.set_title("coil windings: the live thermal model's estimate", fontsize=9)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.02), borderaxespad=0.2,
                  handlelength=1.5, frameon=False)

    return [TimePanel("windings", axis_clock, draw, 1.0)]


def _same_commands(traces: list[Trace]) -> list[list[Trace]]:
    """The traces in sets commanded alike (a coil pair in series for a uniform field): one colour
    and one legend entry each, so a trace is never hidden under its twin in another colour."""
    sets: list[list[Trace]] = []
    for trace in traces:
        scale = 1e-3 * max(1.0, float(np.nanmax(np.abs(trace.commanded), initial=0.0)))
        for same in sets:
            if (same[0].channel.unit == trace.channel.unit
                    and same[0].commanded.shape == trace.commanded.shape
                    and np.allclose(same[0].commanded, trace.commanded, atol=scale, equal_nan=True)):
                same.append(trace)
                break
        else:
            sets.append([trace])
    return sets


def _segment_requests(plan: dict) -> list[dict]:
    return [s for s in plan.get("segments") or [] if "U" in s and "start_s" in s and "end_s" in s]


def _field_panels(data: RunData) -> list[TimePanel]:
    fields = data.fields
    if fields is None:
        return []
    segments = _segment_requests(data.plan)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    panels = []
    for gid, components, title in (("fields", FIELD_COMPONENTS, "field at the workspace centre"),
                                   ("gradients", GRADIENT_COMPONENTS, "field gradient")):
        present = [c for c in components if c in fields]
        if not present:
            continue

        def draw(ax, present=present, title=title, gid=gid):
            from rigctl.physics.magnetics import U_COMPONENTS

            for j, component in enumerate(present):
                colour = colours[j % len(colours)]
                ax.plot(fields["t"], fields[component], "-", color=colour, linewidth=1.0,
                        alpha=0.75, label=component, gid=f"measured {component}")
                if segments:  # what the plan asks for while it holds (the arms arrived)
                    k = U_COMPONENTS.index(component)
                    x, y = [], []
                    for s in segments:
                        x += [s.get("reached_s", s["start_s"]), s["end_s"], np.nan]
                        y += [s["U"][k], s["U"][k], np.nan]
                    ax.plot(x, y, "--", color=colour, linewidth=1.3, gid=f"requested {component}")
            _shade_holds(ax, segments, gid == "fields")
            unit = fields["units"][present[0]]
            ax.set_ylabel(UNIT_LABELS.get(unit, unit), fontsize=8)
            requested = "requested by the plan (dashed), " if segments else ""
            ax.set_title(f"{title}: {requested}measured by the Hall board (solid)", fontsize=9,
                         pad=14 if gid == "fields" and segments else None)
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.02), borderaxespad=0.2,
                      handlelength=1.5, frameon=False)

        panels.append(TimePanel(gid, PLAN_CLOCK, draw, 1.4))
    return panels


def _shade_holds(ax, segments: list[dict], named: bool) -> None:
    """Each segment's hold (arms arrived) shaded, its name at the top of the fields panel."""
    for k, s in enumerate(segments):
        start = s.get("reached_s", s["start_s"])
        ax.axvspan(start, s["end_s"], color="0.93" if k % 2 else "0.88", zorder=0, linewidth=0)
        if named:
            ax.text(0.5 * (start + s["end_s"]), 1.01, s.get("name", ""), fontsize=7,
                    ha="center", va="bottom", transform=ax.get_xaxis_transform(), clip_on=False)


def _period_panel(data: RunData, clock: str) -> list[TimePanel]:
    if data.period_error is None:
        return []
    t, error = data.period_error
    t_axis, axis_clock = _on_clock(data, t, RUN_CLOCK, clock)

    def draw(ax):
        ax.plot(t_axis, error * 1e3, "-", color="0.3", linewidth=0.7)
        ax.set_ylabel("period error (ms)", fontsize=8)
        ax.set_title("stream: each cycle's start minus when it was due", fontsize=9)

    return [TimePanel("period", axis_clock, draw)]


IDENTIFIED_LABELS = {"1": "gain (moved / commanded)", "deg": "heading bias (deg)",
                     "mm/s": "drift (mm/s)", "1/mm": "rate (1/mm)"}
# estimates whose unit alone does not say what they are (the coil board's is a ratio too)
IDENTIFIED_COLUMN_LABELS = {"mobility_diff": "mobility difference\n(m1 - m0) / mean m"}


def _identification_panels(data: RunData, clock: str) -> list[TimePanel]:
    """The `identification` series: per unit, every estimate (column P, or P_i for agent i) over
    run time with P_std shaded once `moves_used_i` says a move was used (before that it is the
    prior, drawn thin); counters (unit "count") and std columns are not drawn as lines."""
    series = read_series(data.run_dir, "identification")
    if series is None or len(series.get("t_s", ())) == 0:
        return []
    units = series["units"]
    t_axis, axis_clock = _on_clock(data, series["t_s"], RUN_CLOCK, clock)
    by_unit: dict[str, list[str]] = {}
    for column, unit in units.items():
        if column != "t_s" and unit != "count" and not column.endswith("_std"):
            by_unit.setdefault(unit, []).append(column)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    panels = []
    for unit, columns in by_unit.items():
        def draw(ax, columns=columns, unit=unit):
            for j, column in enumerate(columns):
                colour = colours[j % len(colours)]
                name, _, agent = column.rpartition("_")
                # the unit is the axis's: "drift_x_mm_s" is "drift x" in the legend
                bare = name.removesuffix("_mm_s").removesuffix("_deg").replace("_", " ")
                # an agent's column has its own move count: P_i, or P_name (the pair's centroid)
                named = f"moves_used_{agent}" in series
                label = (f"{bare}, agent {agent}" if agent.isdigit() else f"{bare}, {agent}"
                         if named else column.replace("_", " "))
                used = series.get(f"moves_used_{agent}", series.get("moves_used"))
                known = np.ones(len(t_axis), bool) if used is None else used > 0
                value = series[column]
                # agents on equal estimates would hide each other: each its own dash
                style = ("-", "--", "-.", (0, (5, 1, 1, 1)))[int(agent) % 4] \
                    if agent.isdigit() else "-"
                ax.step(t_axis, np.where(known, value, np.nan), where="post", color=colour,
                        linewidth=2.0 if style == "-" else 1.4, linestyle=style, label=label,
                        gid=f"identified {column}")
                ax.step(t_axis, np.where(known, np.nan, value), where="post", color=colour,
                        linewidth=0.7, linestyle=":", gid=f"prior {column}")
                std = series.get(f"{column}_std")
                if std is not None:
                    ax.fill_between(t_axis, value - std, value + std, where=known, step="post",
                                    color=colour, alpha=0.25, linewidth=0)
            ax.set_ylabel(IDENTIFIED_COLUMN_LABELS.get(columns[0], IDENTIFIED_LABELS.get(unit, unit))
                          if len(columns) == 1 else IDENTIFIED_LABELS.get(unit, unit), fontsize=8)
            ax.set_title("identified from tracking: estimate (dotted: prior, no move used yet), "
                         "+-1 std shaded", fontsize=9)
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.02),
                      borderaxespad=0.2, handlelength=1.5, frameon=False)

        panels.append(TimePanel(f"identified:{unit}", axis_clock, draw))
    return panels


def _on_clock(data: RunData, t: np.ndarray, clock: str, wanted: str) -> tuple[np.ndarray, str]:
    """Times `t` on `clock` moved to the `wanted` clock where the record says how; else as they
    are (the panel then says which clock its axis is)."""
    if clock == wanted:
        return t, clock
    convert = data.to_plan if wanted == PLAN_CLOCK else data.to_run
    return (convert(t), wanted) if convert is not None else (t, clock)


def _mark_events(ax, data: RunData, clock: str, *, label: bool) -> None:
    """Faults and e-stops (red, solid) and re-plans (purple, dashed) on a time axis."""
    for kind, colour, style, gid in ((FAULT_EVENTS, FAULT_COLOUR, "-", "fault"),
                                     (("replan",), REPLAN_COLOUR, "--", "replan")):
        marks = [e for e in data.events if e.get("event") in kind and "t" in e]
        if not marks:
            continue
        times = np.array([e["t"] for e in marks], dtype=float)
        if clock == PLAN_CLOCK:
            if data.to_plan is None:
                continue
            times = data.to_plan(times)
        for e, t in zip(marks, times):
            ax.axvline(t, color=colour, linewidth=1.1 if gid == "fault" else 0.8,
                       linestyle=style, alpha=0.9, gid=gid, zorder=5)
            if label and gid == "fault":
                what = "e-stop" if e["event"] == "estop" else f"fault: {e.get('device') or 'run'}"
                # inside the panel along the line: clear of the titles and the segment names
                ax.text(t, 0.97, f"{what} ", color=colour, fontsize=7, va="top", ha="right",
                        rotation=90, transform=ax.get_xaxis_transform(), clip_on=True)


def _clock_label(data: RunData, clock: str) -> str:
    if clock == PLAN_CLOCK:
        faster = f"; the bench ran {data.time_scale:g}x faster" if data.time_scale != 1 else ""
        return f"plan time (s{faster})"
    return "time since the run started (s)"


# -- title ----------------------------------------------------------------------------------------

def _verdict(summary: dict | None) -> tuple[str, str]:
    """The verdict line and its colour."""
    if summary is None:
        return "did not finish (no summary: crashed or still running)", "tab:red"
    parts, colour = [], "tab:green"
    faults = summary.get("faults") or []
    if faults:
        parts.append("stopped: " + "; ".join(str(f.get("reason")) for f in faults))
        colour = "tab:red"
    elif summary.get("reached"):
        parts.append("goal reached")
    else:
        parts.append("goal NOT reached")
        colour = "tab:orange"
    if summary.get("state"):
        parts.append(f"state {summary['state']}")
    if summary.get("replans"):
        parts.append(f"{summary['replans']} re-plans")
    if summary.get("safe") is True and "unsafe_devices" in summary:
        parts.append("every device confirmed safe")
    if summary.get("safe") is False:
        parts.append("NOT CONFIRMED SAFE: " + ", ".join(summary.get("unsafe_devices") or ["?"]))
        colour = "tab:red"
    return " · ".join(parts), colour


def _run_name(run_dir: Path, plan: dict) -> str:
    """The run id is `<UTC stamp>-<plan name>`: the stamp made readable, the plan by its name."""
    m = re.match(r"(\d{4})(\d\d)(\d\d)T(\d\d)(\d\d)(\d\d)", run_dir.name)
    when = f"{m[1]}-{m[2]}-{m[3]} {m[4]}:{m[5]}:{m[6]} UTC" if m else run_dir.name
    return f"run of {when}" + (f" ({plan['rig']})" if plan.get("rig") else "")


def _title_lines(data: RunData, notes: list[str], width_chars: int) -> list[tuple[str, dict]]:
    """The band above the panels: the run and its plan (wrapped, at most two lines), the verdict
    in its colour, and what the record lacks; each line with its text style."""
    verdict, colour = _verdict(data.summary)
    name = data.plan.get("name") or "plan"
    head = textwrap.shorten(f"{_run_name(data.run_dir, data.plan)}: {name}", width=2 * width_chars,
                            placeholder=" …")
    lines: list[tuple[str, dict[str, Any]]] = [(line, {"fontsize": 10.5})
                                               for line in textwrap.wrap(head, width_chars)]
    lines.append((textwrap.shorten(verdict, width=width_chars, placeholder=" …"),
                  {"fontsize": 10, "color": colour, "fontweight": "bold"}))
    lines.append((textwrap.shorten(summary_line(read_certificate(data.run_dir)),
                                   width=int(1.2 * width_chars), placeholder=" …"),
                  {"fontsize": 8.5, "color": "0.25"}))
    if notes:
        lines.append((textwrap.shorten("not in this record: " + "; ".join(notes),
                                       width=int(1.3 * width_chars), placeholder=" …"),
                      {"fontsize": 8, "color": "0.35"}))
    return lines


LINE_IN = 0.21  # height of a title line (inches)


# -- the figure -----------------------------------------------------------------------------------

def build_figure(run_dir: str | Path) -> Figure:
    """The report of the record at `run_dir` as a Figure (not saved)."""
    data = read_run(run_dir)
    is_field_run = data.fields is not None or data.plan.get("kind") == "field-sequence"
    clock = PLAN_CLOCK if is_field_run else RUN_CLOCK
    paths = _agent_paths(data.plan, data.events, data.summary) if data.plan else []
    left: list[TimePanel] = _field_panels(data)
    own_panels = report_hooks(data.rig).panels  # what only this rig kind draws
    right: list[TimePanel] = (_actuator_panels(data, clock) + _winding_panels(data, clock)
                              + _period_panel(data, clock) + _identification_panels(data, clock)
                              + (own_panels(data) if own_panels is not None else []))
    notes = _missing(data, paths, is_field_run)
    if not paths and not left:  # one column of time panels
        left, right = right, []
    if paths and left:
        right = left + right
        left = []

    n_rows = max(len(left) + (1 if paths else 0), len(right), 1)
    height = max(6.0, 2.3 * n_rows + 1.4)
    columns = [c for c in ((["paths"] if paths else left), right) if c]
    title = _title_lines(data, notes, width_chars=125 if columns != [["paths"]] else 75)
    band_in = LINE_IN * len(title) + 0.12
    width = 9.0 if columns == [["paths"]] else 15.0  # a workspace alone needs no wide page
    fig = plt.figure(figsize=(width, height + band_in), layout="constrained")
    band, body = fig.subfigures(2, 1, height_ratios=[band_in, height])
    widths = [1.0, 1.25] if paths and right else [1.0] * len(columns)
    if columns:
        _draw_columns(body, data, columns, widths)
    else:
        body.text(0.5, 0.5, "nothing to draw: the record has no stream, no field series and no "
                  "agents", ha="center", va="center", fontsize=11, color="0.35")
    _marks_legend(band, data)
    for i, (text, style) in enumerate(title):
        band.text(0.5, 1.0 - (0.06 + LINE_IN * (i + 0.5)) / band_in, text, ha="center",
                  va="center", **style)
    return fig


def _draw_columns(body, data: RunData, columns: list, widths: list[float]) -> None:
    outer = body.add_gridspec(1, len(columns), width_ratios=widths)
    shared: dict[str, Any] = {}
    for c, column in enumerate(columns):
        if column == ["paths"]:
            ax = body.add_subplot(outer[0, c])
            ax.set_gid("paths")
            _draw_paths(ax, data, _agent_paths(data.plan, data.events, data.summary))
            continue
        grid = outer[0, c].subgridspec(len(column), 1, height_ratios=[p.weight for p in column])
        for r, panel in enumerate(column):
            ax = body.add_subplot(grid[r, 0], sharex=shared.get(panel.clock))
            shared.setdefault(panel.clock, ax)
            ax.set_gid(panel.gid)
            panel.draw(ax)
            _mark_events(ax, data, panel.clock, label=(r == 0))
            ax.tick_params(labelsize=8)
            ax.grid(True, linewidth=0.3, alpha=0.5)
            below = column[r + 1].clock if r + 1 < len(column) else None
            if below != panel.clock:
                ax.set_xlabel(_clock_label(data, panel.clock), fontsize=8)


def _marks_legend(band, data: RunData) -> None:
    kinds = {e.get("event") for e in data.events}
    handles = []
    if kinds & set(FAULT_EVENTS):
        handles.append(Line2D([], [], color=FAULT_COLOUR, label="fault / e-stop"))
    if "replan" in kinds:
        handles.append(Line2D([], [], color=REPLAN_COLOUR, linestyle="--", label="re-plan"))
    if handles:
        band.legend(handles=handles, loc="lower right", fontsize=8, ncol=len(handles),
                    frameon=False)


def _missing(data: RunData, paths, is_field_run: bool) -> list[str]:
    notes = []
    if not data.traces:
        notes.append("no actuator stream")
    if is_field_run and data.fields is None:
        notes.append("no field series")
    if data.fields is not None and not _segment_requests(data.plan):
        notes.append("no segment requests in the plan")
    if not is_field_run and not paths:
        notes.append("no agents in the plan (no paths)")
    elif paths and not any(len(m) for _, m, _ in paths):
        notes.append("no measured positions")
    elif paths and all(len(m) <= 1 for _, m, _ in paths):
        notes.append("no tracked positions (measured: final positions only)")
    if data.traces and data.period_error is None:
        notes.append("no stream timing")
    return notes


def render_report(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Draw the run at `run_dir` into a PNG (default `RUN/report.png`); returns its path."""
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / "report.png"
    fig = build_figure(run_dir)
    try:
        fig.savefig(out, dpi=110)
    finally:
        plt.close(fig)
    return out
