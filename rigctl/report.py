"""`rigctl report RUN`: one PNG per run record, planned against measured.

Left: the workspace (boundary and obstacles from the plan), each agent's planned path (its start,
then where the plan expects it after every move, dashed) and its measured path (the `agents`
events of the run's log, solid), start and goal marked. Right: every coil's current over time,
commanded (dashed) and measured (solid) in the same colour, with the fault (if any) marked.
The report reads only the record, so it works on a run cut off by a crash too.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import patches  # noqa: E402

from rigctl.errors import ConfigError  # noqa: E402
from rigctl.record import read_events, read_stream  # noqa: E402

log = logging.getLogger(__name__)


def find_run(run: str | Path, runs_dir: str | Path = "runs") -> Path:
    """A run given as a path, or as a run id inside `runs_dir`."""
    for candidate in (Path(run), Path(runs_dir) / str(run)):
        if (candidate / "events.jsonl").is_file():
            return candidate
    raise ConfigError(f"no run record at {run} (nor {Path(runs_dir) / str(run)})")


def _draw_shape(ax, shape: dict, *, obstacle: bool) -> None:
    style = dict(facecolor="0.75" if obstacle else "none", edgecolor="0.3", linewidth=1.0)
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


def _agent_paths(plan: dict, events: list[dict],
                 summary: dict | None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per agent: the planned path (k, 2) mm from the start, the measured one (m, 2) mm, and the
    goal (2,) mm.

    Global moves: the positions the plan expects after each move; measured, the `agents` events
    (the daemon's samples of an emulated bench) and the summary's final position. A pair formation
    change (seed 002): both agents from the plan's states (centre, separation, heading) at the start,
    after each segment and at the goal; measured, the closed loop's `track` events, else `agents`."""
    tracked = [e["tracked"] for e in events if e.get("event") == "agents" and e.get("tracked")]
    if plan.get("kind") == "pair-formation":
        from rigctl.plans.pair import agent_positions

        body = plan["agents"]["body_diameter_mm"]
        states = [plan["start"], *(plan.get("expected") or []), plan["goal"]]
        planned = agent_positions(np.array([[s["x_mm"] / body, s["y_mm"] / body, s["r_bl"],
                                             np.radians(s["phi_deg"])] for s in states])) * body
        track = np.array([e["q"] for e in events if e.get("event") == "track"], dtype=float)
        measured = (agent_positions(track) * body if track.size
                    else np.array([t for t in tracked if len(t) == 2], dtype=float).reshape(-1, 2, 2))
        return [(planned[:, i], measured[:, i], planned[-1, i]) for i in range(2)]
    expected = plan.get("expected") or []
    paths = []
    for i, agent in enumerate(plan.get("agents", [])):
        planned = np.array([agent["start"]] + [step[i] for step in expected], dtype=float)
        measured = np.array([t[i] for t in tracked if len(t) > i], dtype=float).reshape(-1, 2)
        if summary and summary.get("agents") and summary["agents"][i].get("final"):
            final = np.array(summary["agents"][i]["final"], dtype=float)[None, :2]
            measured = np.vstack([measured, final])
        paths.append((planned, measured, np.array(agent["goal"], dtype=float)))
    return paths


def render_report(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Draw the run at `run_dir` into a PNG (default `RUN/report.png`); returns its path."""
    run_dir = Path(run_dir)
    out = Path(out) if out is not None else run_dir / "report.png"
    plan = json.loads((run_dir / "plan.json").read_text()) if (run_dir / "plan.json").is_file() else {}
    events = read_events(run_dir)
    stream = read_stream(run_dir)
    summary_path = run_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None

    fig, (ax_path, ax_current) = plt.subplots(1, 2, figsize=(13, 5.5),
                                              gridspec_kw={"width_ratios": [1, 1.3]})
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]

    # -- paths ------------------------------------------------------------------------------------
    _draw_workspace(ax_path, plan.get("workspace", {}), run_dir)
    paths = _agent_paths(plan, events, summary)
    for i, (planned, measured, goal) in enumerate(paths):
        colour = colours[i % len(colours)]
        ax_path.plot(planned[:, 0], planned[:, 1], "--o", color=colour, markersize=3,
                     linewidth=1.0, label=f"agent {i} planned")
        if measured.size:
            ax_path.plot(measured[:, 0], measured[:, 1], "-", color=colour, linewidth=1.8,
                         label=f"agent {i} measured")
        ax_path.plot(*planned[0], "s", color=colour, markersize=7)
        ax_path.plot(*goal, "*", color=colour, markersize=12)
    ax_path.set_aspect("equal", adjustable="datalim")
    ax_path.autoscale_view()
    ax_path.set_xlabel("x (mm)")
    ax_path.set_ylabel("y (mm)")
    ax_path.set_title("paths: planned (dashed) and measured (solid)")
    if paths:
        ax_path.legend(fontsize=7, loc="best")

    # -- currents ---------------------------------------------------------------------------------
    if stream is not None and stream["t_s"].size:
        t = stream["t_s"]
        for j, name in enumerate(stream["coils"]):
            colour = colours[j % len(colours)]
            ax_current.plot(t, stream[f"cmd_{name}_A"], "--", color=colour, linewidth=0.9)
            ax_current.plot(t, stream[f"meas_{name}_A"], "-", color=colour, linewidth=1.2,
                            label=name)
        ax_current.legend(fontsize=7, ncol=3, loc="upper right", title="coil")
    else:
        ax_current.text(0.5, 0.5, "no stream data in this record", ha="center",
                        transform=ax_current.transAxes)
    for fault in (e for e in events if e.get("event") == "fault"):
        ax_current.axvline(fault["t"], color="red", linewidth=1.0)
        ax_current.text(fault["t"], ax_current.get_ylim()[1], f" fault: {fault.get('device')}",
                        color="red", va="top", fontsize=8)
    ax_current.set_xlabel("time since the run started (s)")
    ax_current.set_ylabel("current (A)")
    ax_current.set_title("coil currents: commanded (dashed) and measured (solid)")

    if summary is None:
        verdict = "did not finish (no summary: crashed or still running)"
    elif summary.get("faults"):
        verdict = "stopped: " + "; ".join(f["reason"] for f in summary["faults"])
    else:
        verdict = "goal reached" if summary.get("reached") else "goal not reached"
    fig.suptitle(f"{run_dir.name}: {plan.get('name') or 'plan'} — {verdict}", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
