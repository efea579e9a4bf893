"""`rigctl watch`: a live terminal view of a rig's owner (the daemon, or a `rigctl execute` found
through the rig's lock), refreshed from its telemetry: state and reason, the run and where it is,
each actuator channel commanded and measured, the stream's period error and late share, each
agent's distance from where the plan expects it, and the faults seen.

One `View` folds telemetry messages in; `render` draws it as text (the terminal's screen is
redrawn in place), `as_dict` gives it to `--json`. Ends when the owner stops answering.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
from dataclasses import dataclass, field

from rigctl.core.errors import EXIT_OK, RigError

CLEAR = "\x1b[H\x1b[J"  # cursor home, clear to the end of the screen


@dataclass
class View:
    endpoint: str
    status: dict = field(default_factory=dict)
    channels: list[str] = field(default_factory=list)
    units: list[str] = field(default_factory=list)
    commanded: list[float] = field(default_factory=list)
    measured: list[float] = field(default_factory=list)
    stream: dict | None = None
    agents: dict | None = None
    faults: list[dict] = field(default_factory=list)
    messages: int = 0

    def fold(self, msg) -> None:
        """One telemetry message (a model of rigctl.apps.daemon.messages) into the view."""
        self.messages += 1
        if msg.topic == "state":
            self.status.update(state=msg.state.value, reason=msg.reason, device=msg.device)
        elif msg.topic == "actuators" and msg.commanded:
            self.channels, self.units = msg.channels, msg.units
            self.commanded, self.measured = msg.commanded[-1], msg.measured[-1]
            if self.status.get("run"):
                self.status["run"].update(sample=msg.samples[-1], move=msg.moves[-1])
        elif msg.topic == "stream":
            self.stream = msg.model_dump(exclude={"topic", "seq", "t"})
        elif msg.topic == "agents":
            self.agents = {"move": msg.move, "tracked_mm": msg.tracked_mm,
                           "expected_mm": msg.expected_mm, "source": msg.source,
                           "error_mm": _errors(msg.tracked_mm, msg.expected_mm)}
        elif msg.topic == "fault":
            self.faults = (self.faults + [{"device": msg.device, "reason": msg.reason,
                                           "kind": msg.kind}])[-5:]

    def as_dict(self) -> dict:
        return {"endpoint": self.endpoint, "state": self.status.get("state"),
                "reason": self.status.get("reason"), "run": self.status.get("run"),
                "channels": [{"name": n, "unit": u, "commanded": c, "measured": m}
                             for n, u, c, m in zip(self.channels, self.units, self.commanded,
                                                   self.measured)],
                "stream": self.stream, "agents": self.agents, "faults": self.faults,
                "messages": self.messages}

    def render(self) -> str:
        s = self.status
        rig = s.get("rig")
        lines = [f"rigctl watch: {rig['name']} ({rig['kind']})" if rig else "rigctl watch",
                 f"  {s.get('owner', 'rigctl daemon')} at {self.endpoint}   "
                 f"{time.strftime('%H:%M:%S')}   Ctrl-C to stop watching",
                 "", f"state   {s.get('state', '?')}"
                 + (f"  ({s.get('device') or ''}{': ' if s.get('device') else ''}{s['reason']})"
                    if s.get("reason") else "")]
        run = s.get("run")
        if run:
            lines.append(f"run     {run.get('id') or run.get('name') or run.get('kind', '')}  "
                         f"sample {run.get('sample', '?')}/{run.get('samples', '?')}  move "
                         f"{run.get('move', '?')}")
        if self.stream:
            st = self.stream
            late = 100.0 * st["late_cycles"] / st["cycles"] if st["cycles"] else 0.0
            lines.append(f"stream  {st['rate_hz']:g} Hz, {st['cycles']} cycles; period error p50 "
                         f"{st['period_error_p50_us']:.0f} us, p99 {st['period_error_p99_us']:.0f}"
                         f" us, max {st['period_error_max_us']:.0f} us; late {late:.1f} %")
        if self.channels:
            lines += ["", f"  {'channel':<10} {'commanded':>11} {'measured':>11}  unit"]
            lines += [f"  {n:<10} {c:>11.4g} {m:>11.4g}  {u}" for n, u, c, m in
                      zip(self.channels, self.units, self.commanded, self.measured)]
        if self.agents and self.agents["tracked_mm"]:
            lines += ["", (f"  agents at move {self.agents['move']} ({self.agents['source']}); "
                           "error = distance from where the plan expects it")]
            for i, p in enumerate(self.agents["tracked_mm"]):
                err = self.agents["error_mm"]
                lines.append(f"  {i:>3}  ({p[0]:8.2f}, {p[1]:8.2f}) mm"
                             + (f"   error {err[i]:.2f} mm" if err else ""))
        lines += ["", "faults: " + ("none" if not self.faults else "")]
        lines += [f"  {f['device'] or '-'}: {f['reason']} ({f['kind']})" for f in self.faults]
        return "\n".join(lines)


def _errors(tracked: list | None, expected: list | None) -> list[float] | None:
    if not tracked or not expected or len(tracked) != len(expected):
        return None
    return [round(math.dist(a, b), 4) for a, b in zip(tracked, expected)]


def watch(endpoint: str, *, client, seconds: float | None, interval_s: float, out,
          as_json: bool) -> int:
    """Follow the owner at `endpoint` (a `Rig` client from `client(endpoint)`): redraw every
    `interval_s` on a terminal; with `seconds`, one view (text or JSON) after that long."""
    view = View(endpoint)
    tty = out.isatty() and seconds is None and not as_json
    # Ctrl-C is how a watch ends: nothing to report, nothing stopped. Taken as a flag the loop
    # reads within 0.1 s, not as a KeyboardInterrupt that could land inside a socket's close
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set()) \
        if threading.current_thread() is threading.main_thread() else None
    try:
        _follow(view, client, endpoint, seconds, interval_s, out, tty, stop)
    except KeyboardInterrupt:  # a second Ctrl-C before the handler was in place
        stop.set()
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
    if stop.is_set() and tty:
        return EXIT_OK
    if not tty:
        print(json.dumps(view.as_dict()) if as_json else view.render(), file=out)
    return EXIT_OK


def _follow(view: View, client, endpoint: str, seconds: float | None, interval_s: float, out,
            tty: bool, stop: threading.Event) -> None:
    with client(endpoint) as rig:
        view.status = rig.status()
        with rig.telemetry() as telemetry:
            started = next_draw = time.monotonic()
            while (seconds is None or time.monotonic() - started < seconds) and not stop.is_set():
                msg = telemetry.receive(timeout_s=min(interval_s, 0.1))
                if msg is not None:
                    view.fold(msg)
                now = time.monotonic()
                if now < next_draw:
                    continue
                next_draw = now + interval_s
                try:
                    view.status = {**view.status, **_fresh(rig)}
                except RigError:
                    print("the owner stopped answering: the run is over", file=sys.stderr)
                    break
                if tty:
                    out.write(CLEAR + view.render() + "\n")
                    out.flush()


def _fresh(rig) -> dict:
    """The slow-changing part of the view, from `status` (telemetry's `state` is the fast one)."""
    status = rig.status()
    return {k: status.get(k) for k in ("state", "reason", "device", "run", "rig", "last_fault")}


def register(sub: argparse._SubParsersAction, client_options,
             rig_file) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "watch", help="a live view of the rig: state, channels, stream timing, agents, faults",
        description="Follow the daemon at --connect, or whichever process owns the rig of --rig "
        "(a daemon or a `rigctl execute`), from its telemetry: state and reason, the run, every "
        "actuator channel commanded and measured, the stream's period error and late share, "
        "each agent's error, faults. Redraws in place until Ctrl-C or the owner goes away. "
        "--seconds S prints one view after S seconds (with --json as one JSON document).")
    client_options(p)
    p.add_argument("--rig", type=rig_file, help="the rig file: watch the process that owns it")
    p.add_argument("--seconds", type=float, metavar="S", help="one view after S seconds")
    p.add_argument("--interval", type=float, default=0.5, metavar="S",
                   help="redraw every S seconds (default 0.5)")
    p.add_argument("--json", action="store_true", help="with --seconds: the view as JSON")
    return p
