"""A run's summary: what each agent ended at, the faults, the stream's timing; as text and JSON."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any


@dataclass
class AgentResult:
    """One agent at the end: where it is (`final`, None if unknown), its goal, the error in
    `unit` (mm, or body lengths for a pair), and ground truth's error on an emulated bench."""

    final: list[float] | None
    goal: list[float]
    error_mm: float | None
    truth_error_mm: float | None = None  # closed loop on an emulator: ground truth's error too
    unit: str = "mm"

    def as_dict(self) -> dict[str, Any]:
        out = {"final": self.final, "goal": self.goal, f"error_{self.unit}": self.error_mm}
        if self.truth_error_mm is not None:
            out[f"truth_error_{self.unit}"] = self.truth_error_mm
        return out


@dataclass
class RunSummary:
    """The summary of any run on any rig: one shape, the rig's own figures in `metrics`
    (Table 1 for the dual-EPM rig, tracking RMS for pairs, moves for the coil board), and the
    lines a person reads about them in `details` (text only)."""

    reached: bool
    agents: list[AgentResult]
    run: str
    duration_s: float
    positions_from: str
    tolerance_mm: float | None
    faults: list[dict[str, Any]] = field(default_factory=list)
    stream: dict[str, Any] | None = None
    replans: int = 0
    tracking: dict[str, Any] | None = None  # closed loop: tracked vs ground truth, lost frames
    safe: bool = True  # every device confirmed its safe state at the end
    unsafe_devices: list[str] = field(default_factory=list)  # ... all but these
    metrics: dict[str, Any] = field(default_factory=dict)
    state: str | None = None
    rig_kind: str | None = None
    plan_kind: str | None = None
    tolerance_unit: str = "mm"
    details: list[str] = field(default_factory=list)
    refused: str | None = None  # refused before anything was energised (exit 2), and why

    def as_dict(self) -> dict[str, Any]:
        return {
            "reached": self.reached,
            "state": self.state,
            "safe": self.safe,
            "unsafe_devices": self.unsafe_devices,
            "rig": self.rig_kind,
            "plan_kind": self.plan_kind,
            "agents": [a.as_dict() for a in self.agents],
            "run": self.run,
            "duration_s": round(self.duration_s, 3),
            "positions_from": self.positions_from,
            "tolerance_mm" if self.tolerance_unit == "mm" else f"tolerance_{self.tolerance_unit}":
                self.tolerance_mm,
            "replans": self.replans,
            "tracking": self.tracking,
            "faults": self.faults,
            "stream": self.stream,
            "metrics": self.metrics,
            "details": self.details,
            "refused": self.refused,
        }


def summary_from_dict(data: dict[str, Any]) -> RunSummary:
    """The summary a record or the daemon gave as JSON (`RunSummary.as_dict`), as a RunSummary."""
    unit = next((k[len("tolerance_"):] for k in data if k.startswith("tolerance_")), "mm")
    agents = []
    for a in data.get("agents", []):
        agents.append(AgentResult(a.get("final"), a.get("goal"), a.get(f"error_{unit}"),
                                  a.get(f"truth_error_{unit}"), unit))
    return RunSummary(
        reached=bool(data.get("reached")), agents=agents, run=data.get("run", ""),
        duration_s=float(data.get("duration_s") or 0.0),
        positions_from=data.get("positions_from", "unknown"),
        tolerance_mm=data.get(f"tolerance_{unit}"), faults=data.get("faults") or [],
        stream=data.get("stream"), replans=data.get("replans") or 0, tracking=data.get("tracking"),
        safe=data.get("safe", True), unsafe_devices=data.get("unsafe_devices") or [],
        metrics=data.get("metrics") or {}, state=data.get("state"), rig_kind=data.get("rig"),
        plan_kind=data.get("plan_kind"), tolerance_unit=unit, details=data.get("details") or [],
        refused=data.get("refused"))


def format_summary(summary: RunSummary) -> str:
    """The summary as a person reads it: where the record is, timing, each agent, the rig's own
    figures, faults, whether every device is safe, the verdict."""
    # an abort (the operator's, Ctrl-C, a limit of time) is how the run ended, not a fault
    aborts = [f for f in summary.faults if f.get("kind") == "Abort"]
    faults = [f for f in summary.faults if f.get("kind") != "Abort"]
    ended = f"; ended {summary.state}" if summary.state else ""
    if aborts and summary.state == "aborted":
        ended += f": {aborts[0]['reason']}"
    lines = [f"run record: {summary.run}", f"duration: {summary.duration_s:.1f} s{ended}"]
    if summary.stream:
        s = summary.stream
        e = s["period_error_us"]
        skipped = f", skipped {s['skipped_cycles']}" if s.get("skipped_cycles") else ""
        lines.append(
            f"stream: {s['cycles']} cycles at {s['rate_hz']:g} Hz; period error p50 {e['p50']:.0f} us,"
            f" p99 {e['p99']:.0f} us, max {e['max']:.0f} us; late {s['late_cycles']}"
            f" ({100 * s['late_share']:.1f} %){skipped}"
        )
    if summary.tracking is not None or summary.replans:
        t = summary.tracking or {}
        lines.append(f"camera: {t.get('frames', '?')} frames ({t.get('lost_frames', '?')} lost); "
                     f"{summary.replans} re-plans")
    lines += summary.details
    unit, tol = summary.tolerance_unit, summary.tolerance_mm
    if summary.agents:
        lines.append(f"positions from: {summary.positions_from}")
        lines.append(f"agent  final (mm)            goal (mm)             error ({unit})")
    for i, a in enumerate(summary.agents):
        final = "unknown" if a.final is None else f"({a.final[0]:.2f}, {a.final[1]:.2f})"
        goal = f"({a.goal[0]:.2f}, {a.goal[1]:.2f})"
        if a.error_mm is None:
            verdict, err = "", "?"
        else:
            verdict = "ok" if tol is not None and a.error_mm <= tol else "MISSED"
            err = f"{a.error_mm:.3f}"
        lines.append(f"{i:>5}  {final:<20}  {goal:<20}  {err:>8}  {verdict}")
    for f in aborts if summary.state != "aborted" else []:  # an abort that did not end it
        lines.append(f"aborted: {f['reason']}")
    for f in faults:
        lines.append(f"FAULT: {f['reason']}")
    if not faults:
        lines.append("faults: none")
    if summary.safe:
        lines.append("safe: every device confirmed off")
    else:
        lines.append("NOT CONFIRMED SAFE: " + ", ".join(summary.unsafe_devices)
                     + " (check by hand)")
    if tol is None:
        lines.append("DONE" if summary.reached else "NOT DONE")
    else:
        lines.append(f"REACHED: every agent within {tol:g} {unit} of its goal" if summary.reached
                     else f"NOT REACHED (tolerance {tol:g} {unit})")
    return "\n".join(lines)


def exit_code(summary: RunSummary) -> int:
    """The README's exit status of a finished run: 3 a fault, an abort, an e-stop or a device not
    confirmed safe; 2 refused before anything was energised; 1 the goal was not reached; 0 it
    was."""
    from rigctl.core.errors import EXIT_BAD_INPUT, EXIT_FAULT, EXIT_NOT_REACHED, EXIT_OK

    if not summary.safe:
        return EXIT_FAULT
    if summary.refused:
        return EXIT_BAD_INPUT
    if summary.faults:
        return EXIT_FAULT
    return EXIT_OK if summary.reached else EXIT_NOT_REACHED


def print_summary(summary: RunSummary, json_out: bool = False) -> None:
    """The summary as `rigctl execute` prints it: the text on stdout; with `json_out` the text on
    stderr and stdout holds the one JSON document and nothing else."""
    import sys

    print(format_summary(summary), file=sys.stderr if json_out else sys.stdout)
    if json_out:
        print(summary_json_line(summary), flush=True)


def summary_json_line(summary: RunSummary | Any) -> str:
    """Any run's summary (anything with `as_dict`) as the one JSON line `--json` prints."""
    return json.dumps(summary.as_dict(), separators=(",", ":"))

