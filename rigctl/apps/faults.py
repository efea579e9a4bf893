"""The fault campaign (`rigctl faults`): every fault an emulated bench's backdoor can inject, at each
phase of a short run, on each rig, through the daemon and the local `rigctl execute`, with what
became of the run and of the devices.

For each rig kind its emulated bench is started in a process of its own (as `rigctl emulate`
does) and asked which faults it has: the backdoor's `fault` command names its devices and, per
device, its fault kinds when asked for one it lacks. Devices with the same kinds (the six supplies)
are one class; one device stands for each class. The daemon's own faults join them: SIGKILL and
SIGSTOP of its stream process (a supply's `stall` is the hung driver). Each fault is injected at
each phase of a run of a short plan of that rig: before energising (injected, then `execute`),
mid-move, paused (at the end of a move), suspended (the camera frozen first, on rigs with one) and
ramping down (`abort`, then the fault). A fault is held for `hold_s` and then cleared (its
backdoor `restore`, `unstall` or `replug`; SIGCONT), and the run is watched to its end.

Per cell: the outcome (completed, suspended and resumed, paused and resumed, faulted, e-stopped,
aborted, refused), the device and reason the run reported, the time from the fault to every device
safe read from the emulator's truth, never from rigctl (every coil current under 50 mA, every
SyRen output 0, both arms at rest), and whether the run record is complete (summary written) and
readable (its events, ending in a terminal state or a fault, and its stream, read by
`rigctl.core.record`). A cell passes when its outcome is named, every device ended safe and its record,
if a run began, is intact.

What differs per rig kind (its short plan, when its devices drive and when they are safe, what
suspends a run, the quick subset) is the kind's own `FaultProfile` (`rigctl.rigs.faults`), asked of
the registry: a kind with none is refused by name, and the campaign names no kind itself.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Self, TextIO

from rigctl.apps.client import CommandRefused, Rig
from rigctl.core.children import end_child
from rigctl.core.config import dump_rig, load_rig
from rigctl.core.errors import (
    ConfigError,
    DeviceError,
    DeviceTimeout,
    Disconnected,
    RigError,
    on_interrupt_signal,
)
from rigctl.core.record import describe_run, read_events, read_stream
from rigctl.core.registry import kinds, rig_kind
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.rigs.base import RigKind
from rigctl.rigs.faults import POLL_S, STREAM_PROCESS, Fault, FaultProfile, wait_until

PHASES = ("before", "moving", "paused", "suspended", "ramping")
"""before energising, mid-move, paused, suspended, ramping down."""
OUTCOMES = ("completed", "suspended and resumed", "paused and resumed", "faulted", "e-stopped",
            "aborted", "refused")
CLEARING_KINDS = {"restore", "unstall", "replug"}  # backdoor kinds that end a fault, not faults
TERMINAL = {"done", "aborted", "faulted", "estopped"}
ACTIVE = {"running", "paused", "suspended"}
BACKDOOR_TIMEOUT_S = 10.0  # a loaded machine: the bench's answers took over 5 s


@dataclass
class Cell:
    rig: str
    path: str  # "daemon" or "execute"
    fault: str
    phase: str
    outcome: str | None = None
    device: str | None = None
    reason: str | None = None
    fault_to_stop_s: float | None = None  # the run seen stopped (or paused/suspended) after it
    fault_to_safe_s: float | None = None  # every device safe in the emulator's truth, for good
    stop_to_safe_s: float | None = None  # from the run seen stopped (10-20 ms resolution)
    # from the run's decision to stop (its loop's last cycle, or the error that ended it) to every
    # device's commands turned toward safe (the record's `stopping`), against one stream period
    decision_to_stopping_s: float | None = None
    stream_period_s: float | None = None
    safe: bool = False
    safe_before_clear: bool | None = None  # safe before the fault was cleared (a link restored)
    record: str = "none"  # complete / readable / incomplete / lost / none (no run began)
    run: str | None = None
    note: str = ""

    @property
    def ok(self) -> bool:
        return (self.outcome in OUTCOMES and self.safe
                and self.record in ("complete", "readable", "none") and "phase not reached"
                not in self.note)

    def as_dict(self) -> dict:
        return {**asdict(self), "ok": self.ok}


# -- the rigs ----------------------------------------------------------------------------------


def fault_profile(kind: RigKind) -> FaultProfile:
    """The kind's profile for the campaign; ConfigError in one line for a kind that has none."""
    if kind.faults is None:
        raise ConfigError(f"rig kind {kind.name!r} has no fault profile: `rigctl faults` runs "
                          f"{', '.join(profiled_kinds()) or 'no installed kind'}")
    return kind.faults()


def profiled_kinds() -> list[str]:
    """The installed rig kinds that have a fault profile, by name."""
    return [name for name, kind in kinds().items() if kind.faults is not None]


def rig_profile(name: str) -> FaultProfile:
    """The fault profile of the installed rig kind `name` (ConfigError naming the installed kinds
    for an unknown one, or the kinds with a profile for one without)."""
    return fault_profile(rig_kind(name))


# the arguments a kind needs, and what ends it (default: "restore")
KIND_ARGS: dict[str, dict] = {"corrupt": {"n": 3}, "drop_frames": {"n": 30}, "skip": {"n": 20},
                              "occlude": {"robot": 0}, "stall_joint": {"joint": 3}}
KIND_CLEAR = {"stall_joint": "unstall", "unplug": "replug"}


def _listed(message: str, after: str) -> list[str]:
    """The comma-separated names that follow `after` in a backdoor error."""
    found = re.search(re.escape(after) + r"\s*(.*)$", message)
    if found is None:
        raise RigError(f"the bench's backdoor did not list them: {message}", device="bench backdoor")
    return [name.strip() for name in found.group(1).split(",") if name.strip()]


def bench_faults(backdoor: Any) -> dict[str, list[str]]:
    """Every device of the bench and its fault kinds, as its backdoor names them (clearing kinds
    left out): it lists its devices when asked for one it lacks, a device's kinds likewise."""
    if "fault" not in backdoor.request("help")["commands"]:
        return {}
    try:
        backdoor.request("fault", device="?", kind="?")
    except DeviceError as err:
        devices = _listed(str(err), "the bench has")
    else:
        raise RigError("the backdoor took a fault on device '?'", device="bench backdoor")
    kinds = {}
    for device in devices:
        try:
            backdoor.request("fault", device=device, kind="?")
        except DeviceError as err:
            kinds[device] = [k for k in _listed(str(err), "; use") if k not in CLEARING_KINDS]
    return kinds


def campaign_faults(kinds: dict[str, list[str]], *, all_devices: bool = False) -> list[Fault]:
    """One device per class (the same kinds) unless `all_devices`, each of its kinds; then the
    daemon's own: SIGKILL and SIGSTOP of its stream process."""
    seen: set[tuple[str, ...]] = set()
    faults = []
    for device, names in kinds.items():
        if not all_devices and tuple(names) in seen:
            continue
        seen.add(tuple(names))
        faults += [Fault(device, kind, tuple(KIND_ARGS.get(kind, {}).items()),
                         KIND_CLEAR.get(kind, "restore")) for kind in names]
    return faults + [Fault(STREAM_PROCESS, "sigkill", clear=None),
                     Fault(STREAM_PROCESS, "sigstop", clear="SIGCONT")]


# -- helpers -----------------------------------------------------------------------------------


def stream_process_pid(daemon_pid: int) -> int | None:
    """The daemon's stream process (`rigctl.apps.daemon.runhost`), found in /proc."""
    for task in Path(f"/proc/{daemon_pid}/task").iterdir():
        with contextlib.suppress(OSError):
            for child in map(int, (task / "children").read_text().split()):
                with contextlib.suppress(OSError):
                    if b"runhost" in Path(f"/proc/{child}/cmdline").read_bytes():
                        return child
    return None


def check_record(run_dir: Path | None) -> tuple[str, str | None]:
    """(complete / readable / incomplete / lost, run id) of a run record, read by the loaders
    `rigctl report` uses: complete when its summary is written and everything reads; readable
    when the summary is missing but the events end in a terminal state or a fault and the stream
    reads; incomplete otherwise; lost when there is no record."""
    if run_dir is None or not (run_dir / "events.jsonl").is_file():
        return "lost", None
    try:
        described = describe_run(run_dir)
        events = read_events(run_dir)
        streamed = any(e.get("event") == "energised" for e in events)
        if streamed and read_stream(run_dir) is None:
            return "incomplete", run_dir.name
    except (OSError, ValueError, KeyError, TypeError) as err:  # ValueError: bad JSON, Parquet
        return f"incomplete ({type(err).__name__}: {err})", run_dir.name
    if described["finished"] and (run_dir / "plan.json").is_file():
        return "complete", run_dir.name
    ends = any(e.get("event") == "fault" or (e.get("event") == "state" and e.get("state") in
                                              TERMINAL) for e in events)
    return ("readable" if ends else "incomplete"), run_dir.name


def stop_latency(events: list[dict]) -> tuple[float | None, float | None]:
    """(seconds from the run's decision to stop to every device's commands turned toward safe,
    the run's stream period) from its record's `stopping` and `prepared` events; None for what
    the record does not hold (no run streamed, or its process was killed before it stopped)."""
    stopping = next((e for e in events if e.get("event") == "stopping"), None)
    prepared = next((e for e in events if e.get("event") == "prepared"), None)
    rate = (prepared or {}).get("rate_hz")
    return (None if stopping is None else stopping.get("after_decision_s"),
            1.0 / rate if rate else None)


def outcome_of(events: list[dict], summary: dict | None) -> tuple[str | None, str | None, str | None]:
    """(outcome, device, reason) of a run from its record."""
    states = [e["state"] for e in events if e.get("event") == "state"]
    faults = [e for e in events if e.get("event") == "fault"]
    final = (summary or {}).get("state") or (states[-1] if states else None)
    reported = [f for f in (summary or {}).get("faults") or []
                if f.get("kind") not in ("Abort", "EStop")]
    first = reported[0] if reported else (faults[0] if faults else {})
    device, reason = first.get("device"), first.get("reason")
    if summary is not None and summary.get("refused"):
        return "refused", device, summary["refused"]
    if final == "estopped":
        return "e-stopped", device, reason
    # a device fault during an abort's ramp ends the run "aborted" in the record (the abort
    # wins in RunControl._end_state) while the daemon says faulted: the fault is the outcome
    if final == "faulted" or reported or faults:
        return "faulted", device, reason
    if final == "aborted":
        return "aborted", device, reason
    if final == "done":
        for held in ("suspended", "paused"):
            if any(a == held and b == "running" for a, b in itertools.pairwise(states)):
                return f"{held} and resumed", device, reason
        return "completed", device, reason
    return None, device, reason


# -- one rig's campaign ------------------------------------------------------------------------


class RigCampaign:
    """One rig's bench (a process of its own), its daemon, and the cells run against them."""

    def __init__(self, kind: str, folder: Path, *, hold_s: float = 1.5, settle_s: float = 20.0,
                 progress: TextIO | None = None, all_devices: bool = False) -> None:
        self.all_devices = all_devices
        self.kind = kind
        self.profile = rig_profile(kind)
        self.folder = folder
        self.hold_s = hold_s
        self.settle_s = settle_s
        self.progress = progress
        self.env = {**os.environ, "RIGCTL_LOCK_DIR": str(folder / "locks"),
                    "PYTHONUNBUFFERED": "1"}
        self.runs_dir = folder / "runs"
        self.plan_path = folder / "plan.json"
        self.plan_path.write_text(json.dumps(self.profile.plan()))
        self._stack = contextlib.ExitStack()
        self.backdoor: BackdoorClient | None = None
        self.rig_path: Path | None = None
        self.daemon: subprocess.Popen | None = None
        self.client: Rig | None = None
        self.plan_id: str | None = None

    # -- life cycle ----------------------------------------------------------------------------
    def __enter__(self) -> Self:
        try:
            bench_path = self._stack.enter_context(
                EmulatedBenchProcess(self.kind, self.folder / "bench.toml"))
            rig = load_rig(bench_path)
            self.rig_path = self.folder / "rig.toml"
            self.rig_path.write_text(dump_rig(self.profile.tune(rig)))
            self.backdoor = BackdoorClient.of(rig.emulation, timeout_s=BACKDOOR_TIMEOUT_S)
            self._stack.callback(lambda: self.backdoor.close())
            self.faults = campaign_faults(bench_faults(self),
                                          all_devices=self.all_devices)
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_daemon()
        self._stack.close()

    def start_daemon(self) -> None:
        with open(self.folder / "daemon.log", "a") as log:
            self.daemon = subprocess.Popen(
                [sys.executable, "-m", "rigctl", "daemon", "--rig", str(self.rig_path), "--runs",
                 str(self.runs_dir), "--command", "tcp://127.0.0.1:0", "--telemetry",
                 "tcp://127.0.0.1:0", "--events", "tcp://127.0.0.1:0"],
                stdout=subprocess.PIPE, stderr=log, text=True, env=self.env,
                start_new_session=True)  # stopped by `stop_daemon`, not the terminal's Ctrl-C
        assert self.daemon.stdout is not None
        ready = next((line for line in self.daemon.stdout if line.startswith("READY ")), None)
        if ready is None:
            raise RigError("the daemon did not start: " + (self.folder / "daemon.log").read_text()
                           [-2000:], device="daemon")
        command = dict(f.split("=", 1) for f in ready[6:].split())["command"]
        self.client = Rig(command, timeout_s=5.0)
        self.plan_id = self.client.load(json.loads(self.plan_path.read_text()))

    def stop_daemon(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
        if self.daemon is not None:
            end_child(self.daemon)
            if self.daemon.stdout is not None:
                self.daemon.stdout.close()
            self.daemon = None

    def fault(self, label: str) -> Fault:
        found = [f for f in self.faults if f.label == label]
        if not found:
            raise RigError(f"the {self.kind} bench has no fault {label}; it has "
                           f"{', '.join(f.label for f in self.faults)}", device="bench backdoor")
        return found[0]

    # -- the backdoor --------------------------------------------------------------------------
    def request(self, cmd: str, **args: Any) -> dict:
        """A backdoor request; on a timeout or a dropped connection (a loaded machine) the
        connection is opened anew, so that a late reply cannot answer the next request, and the
        request sent again (at most twice). A refusal (DeviceError) is the bench's answer."""
        for attempt in range(3):
            assert self.backdoor is not None
            try:
                return self.backdoor.request(cmd, **args)
            except (DeviceTimeout, Disconnected, ValueError):  # ValueError: a torn reply line
                url, token = self.backdoor.url, self.backdoor.token
                self.backdoor.close()
                self.backdoor = BackdoorClient(url, timeout_s=BACKDOOR_TIMEOUT_S, token=token)
                if attempt == 2:
                    raise
        raise AssertionError("unreachable")

    def truth(self) -> dict:
        return self.request("truth")

    def inject(self, fault: Fault, pid: int | None) -> None:
        if fault.device == STREAM_PROCESS:
            if pid is not None:
                os.kill(pid, signal.SIGKILL if fault.kind == "sigkill" else signal.SIGSTOP)
            return
        self.request("fault", device=fault.device, kind=fault.kind, **dict(fault.args))

    def clear(self, fault: Fault, pid: int | None) -> None:
        if fault.clear is None:
            return
        if fault.clear == "SIGCONT":
            if pid is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGCONT)
            return
        self.request("fault", device=fault.device, kind=fault.clear)

    def clear_all(self) -> None:
        """Every fault the bench has, cleared (its clearing kinds), and the bench reset."""
        for f in self.faults:
            if f.device != STREAM_PROCESS and f.clear is not None:
                self.request("fault", device=f.device, kind=f.clear)
        for device in {f.device for f in self.faults if f.device != STREAM_PROCESS}:
            self.request("fault", device=device, kind="restore")

    # -- the daemon's cells --------------------------------------------------------------------
    def _daemon_ready(self) -> None:
        """The daemon idle, nothing unsafe, every fault cleared, the bench where plans start."""
        assert self.client is not None
        self.clear_all()
        deadline = time.monotonic() + 60.0
        while True:
            status = self.client.status()
            if status["state"] in ("faulted", "estopped") and status["run"] is None:
                with contextlib.suppress(CommandRefused):
                    self.client.reset()
            elif status["state"] == "idle" and status["run"] is None and not any(
                    d["health"] == "unsafe" for d in status["devices"]):
                break
            if time.monotonic() > deadline:
                raise RigError(f"the daemon did not come back to idle: {status}", device="daemon")
            time.sleep(0.05)
        self.profile.reset(self)

    def run_daemon_cell(self, fault: Fault, phase: str) -> Cell:
        cell = Cell(self.kind, "daemon", fault.label, phase)
        if phase == "suspended" and self.profile.suspend_with is None:
            cell.note = "n/a: the rig has no camera, nothing suspends its runs"
            cell.outcome, cell.safe = "n/a", True
            return cell
        if self.daemon is None or self.daemon.poll() is not None:
            self.start_daemon()
        self._daemon_ready()
        assert self.client is not None and self.daemon is not None
        before = set(self.runs_dir.glob("*")) if self.runs_dir.is_dir() else set()
        suspend = self.profile.suspend_with
        t_fault, pid, refused = self._daemon_phase(cell, fault, phase)
        resumed = [False]

        def while_held(now: float, status: dict, truth: dict) -> bool:
            # before energising: the fault stays until the run has met it (it drives, or ended)
            met = phase != "before" or status["state"] not in ACTIVE or self.profile.driving(truth)
            if now - t_fault >= self.hold_s and met and not resumed[0]:
                self.clear(fault, pid)
                if phase == "suspended" and suspend is not None:
                    self.clear(suspend, pid)
                resumed[0] = True
            if resumed[0] and phase == "paused" and status["state"] == "paused":
                with contextlib.suppress(CommandRefused):
                    self.client.resume()
            return resumed[0]

        self._finish(cell, t_fault, *self._watch(t_fault, while_held, self.client.status))
        if not cell.safe:
            cell.note = (cell.note + "; " if cell.note else "") + "daemon says " + ", ".join(
                f"{d['name']} {d['health']}" for d in self.client.status()["devices"])
        new = sorted(set(self.runs_dir.glob("*")) - before) if self.runs_dir.is_dir() else []
        if refused is not None and not new:
            cell.outcome, cell.reason = "refused", f"{refused.code}: {refused.reason}"
            return cell
        self._read_record(cell, new[-1] if new else None)
        return cell

    def _daemon_phase(self, cell: Cell, fault: Fault, phase: str
                      ) -> tuple[float, int | None, CommandRefused | None]:
        """Bring the daemon's run to `phase` and inject `fault` there: (when it was injected, the
        stream process's pid it was injected with, the refusal of a run faulted before it began).
        A phase not reached is said in the cell's note (the time is then now)."""
        assert self.client is not None and self.daemon is not None
        pid = stream_process_pid(self.daemon.pid)
        suspend = self.profile.suspend_with
        refused = t_fault = None
        try:
            if phase == "before":
                self.inject(fault, pid)
                t_fault = time.monotonic()
                try:
                    self.client.execute(self.plan_id)
                except CommandRefused as err:
                    refused = err
            else:
                self.client.execute(self.plan_id)
                wait_until(lambda: self.profile.driving(self.truth()), 60.0, "the devices to drive")
                if phase == "paused":
                    self.client.pause()
                    wait_until(lambda: self.client.status()["state"] == "paused", 60.0, "paused")
                elif phase == "suspended":
                    self.inject(suspend, pid)
                    try:
                        wait_until(lambda: self.client.status()["state"] == "suspended", 10.0,
                                   "suspended")
                    except TimeoutError:
                        cell.note = (f"phase not reached: {suspend.label} did not suspend the "
                                     f"run (state {self.client.status()['state']})")
                elif phase == "ramping":
                    self.client.abort()
                pid = stream_process_pid(self.daemon.pid)
                self.inject(fault, pid)
                t_fault = time.monotonic()
        except (TimeoutError, RigError) as err:
            cell.note = f"phase not reached: {err}"
        return (time.monotonic() if t_fault is None else t_fault), pid, refused

    def _read_record(self, cell: Cell, run_dir: Path | None) -> None:
        """The cell's record check and, from the record, its outcome and stop latency."""
        cell.record, cell.run = check_record(run_dir)
        if run_dir is None:
            return
        summary_path = run_dir / "summary.json"
        summary = json.loads(summary_path.read_text()) if summary_path.is_file() else None
        events = read_events(run_dir)
        cell.outcome, cell.device, cell.reason = outcome_of(events, summary)
        cell.decision_to_stopping_s, cell.stream_period_s = stop_latency(events)

    def _finish(self, cell: Cell, t_fault: float, stop_at: float | None, safe_at: float | None,
                safe_now: bool) -> None:
        """The cell's times from the fault, and, if a device is not safe, what the truth says."""
        cell.fault_to_stop_s = None if stop_at is None else round(stop_at - t_fault, 3)
        cell.fault_to_safe_s = None if safe_at is None else round(safe_at - t_fault, 3)
        if safe_at is not None and stop_at is not None:
            cell.stop_to_safe_s = round(max(0.0, safe_at - stop_at), 3)
        cell.safe = safe_now
        cell.safe_before_clear = safe_at is not None and safe_at - t_fault < self.hold_s
        if not safe_now:
            shown = self.profile.unsafe_detail(self.truth())
            cell.note = (cell.note + "; " if cell.note else "") + f"not safe at the end: {shown}"

    def _watch(self, t_fault: float, on_poll: Callable[[float, dict, dict], bool],
               status: Callable[[], dict | None]) -> tuple[float | None, float | None, bool]:
        """Poll the run's state and the emulator's truth until the run is over, the fault cleared
        (`on_poll` says so, and clears it when it is time) and every device safe, or `settle_s`
        after the clearing at most. (when the run was first seen stopped, held or ended; when
        every device became safe for good; safe at the end)."""
        stop_at = safe_at = None
        cleared_at = None
        while True:
            now = time.monotonic()
            state = status()
            truth = self.truth()
            cleared = on_poll(now, state or {"state": "idle"}, truth)
            running = state is not None and (state.get("run") is not None or
                                             state.get("state") == "running")
            if stop_at is None and (state is None or state.get("state") not in ("running",)):
                stop_at = now
            safe = self.profile.safe(truth)
            if not safe:
                safe_at = None
            elif safe_at is None:
                safe_at = now
            if cleared and cleared_at is None:
                cleared_at = now
            if cleared_at is None and now - t_fault > 60.0 + self.settle_s:
                return stop_at, safe_at, safe  # never met (a bug of the campaign's): say so
            if cleared_at is not None and not running and safe:
                return stop_at, safe_at, True
            if cleared_at is not None and now - cleared_at > self.settle_s + (
                    120.0 if running else 0.0):
                return stop_at, safe_at, safe
            time.sleep(POLL_S)

    # -- the local `rigctl execute` cells ------------------------------------------------------
    def run_execute_cell(self, fault: Fault, phase: str) -> Cell:
        """`rigctl execute PLAN --rig RIG` in a process of its own, the fault injected mid-move
        (the daemon's signals have no meaning here)."""
        cell = Cell(self.kind, "execute", fault.label, phase)
        self.stop_daemon()  # the rig has one owner
        self.clear_all()
        self.profile.reset(self)
        runs = self.folder / "runs-execute"
        before = set(runs.glob("*")) if runs.is_dir() else set()
        out_path = self.folder / "execute.json"
        with open(out_path, "w") as out, open(self.folder / "execute.log", "a") as err:
            proc = subprocess.Popen(
                [sys.executable, "-m", "rigctl", "execute", str(self.plan_path), "--rig",
                 str(self.rig_path), "--json", "-q", "--runs", str(runs)],
                stdout=out, stderr=err, env=self.env,
                start_new_session=True)  # a Ctrl-C of the campaign stops it below, bench alive
        try:
            return self._execute_cell(cell, fault, proc, runs, before, out_path)
        finally:  # the campaign interrupted: the run aborts (ramps down) before the bench stops
            end_child(proc)

    def _execute_cell(self, cell: Cell, fault: Fault, proc: subprocess.Popen, runs: Path,
                      before: set[Path], out_path: Path) -> Cell:
        t_fault = None
        try:
            wait_until(lambda: self.profile.driving(self.truth()) or proc.poll() is not None, 60.0,
                  "the devices to drive")
            if proc.poll() is None:
                self.inject(fault, None)
                t_fault = time.monotonic()
        except TimeoutError as err:
            cell.note = f"phase not reached: {err}"
        if t_fault is None:
            cell.note = cell.note or "phase not reached: the run ended before the devices drove"
            t_fault = time.monotonic()
        cleared = [False]

        def while_held(now: float, _: dict, __: dict) -> bool:
            if now - t_fault >= self.hold_s and not cleared[0]:
                self.clear(fault, None)
                cleared[0] = True
            return cleared[0]

        stop_at, safe_at, safe_now = self._watch(
            t_fault, while_held, lambda: None if proc.poll() is not None else {"state": "running",
                                                                                 "run": "local"})
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            cell.note = (cell.note + "; " if cell.note else "") + "rigctl execute did not end"
        self._finish(cell, t_fault, stop_at, safe_at, safe_now)
        new = sorted(set(runs.glob("*")) - before) if runs.is_dir() else []
        cell.record, cell.run = check_record(new[-1] if new else None)
        summary = None
        with contextlib.suppress(json.JSONDecodeError, OSError):
            summary = json.loads(out_path.read_text())
        if new:
            events = read_events(new[-1])
            cell.outcome, cell.device, cell.reason = outcome_of(events, summary)
            cell.decision_to_stopping_s, cell.stream_period_s = stop_latency(events)
        elif summary is not None and "error" in summary:
            cell.outcome, cell.reason = "refused", str(summary["error"].get("message"))
        cell.note = (cell.note + "; " if cell.note else "") + f"exit {proc.returncode}"
        return cell


# -- the campaign ------------------------------------------------------------------------------


def planned_cells(campaign: RigCampaign, *, quick: bool,
                  only: list[str] | None = None) -> list[tuple[str, Fault, str]]:
    """(path, fault, phase) of every cell to run on this rig: those `only` names
    ("daemon/x+:stall/moving"), the quick subset, or every fault at every phase through the
    daemon and each bench fault mid-move through `rigctl execute`."""
    if only is not None:
        chosen = []
        for name in only:
            path, label, phase = parse_cell(name)
            chosen.append((path, campaign.fault(label), phase))
        return chosen
    if quick:
        return [(path, campaign.fault(label), phase) for path, label, phase in campaign.profile.quick]
    cells = [("daemon", f, phase) for f in campaign.faults for phase in PHASES]
    cells += [("execute", f, "moving") for f in campaign.faults if f.device != STREAM_PROCESS]
    return cells


def parse_cell(name: str) -> tuple[str, str, str]:
    """"PATH/DEVICE:KIND/PHASE" -> (path, fault label, phase); ValueError naming what is wrong."""
    parts = name.split("/")
    if len(parts) != 3 or parts[0] not in ("daemon", "execute") or parts[2] not in PHASES \
            or ":" not in parts[1]:
        raise ValueError(f"cell {name!r}: use PATH/DEVICE:KIND/PHASE, PATH daemon or execute, "
                         f"PHASE one of {', '.join(PHASES)} (e.g. daemon/x+:stall/moving)")
    return parts[0], parts[1], parts[2]


def run_campaign(rigs: list[str], *, quick: bool, folder: Path | None = None,
                 progress: TextIO | None = sys.stderr, hold_s: float = 1.5,
                 all_devices: bool = False, only: list[str] | None = None,
                 on_cell: Callable[[Cell], None] | None = None) -> list[Cell]:
    """Every rig's cells, each rig's on a bench and daemon of its own (`only`: just these
    cells, "PATH/DEVICE:KIND/PHASE", on every rig given); `on_cell` is handed each cell done."""
    cells: list[Cell] = []
    # SIGTERM ends the campaign as Ctrl-C does: every bench and daemon it started is stopped
    previous = signal.signal(signal.SIGTERM, on_interrupt_signal) \
        if threading.current_thread() is threading.main_thread() else None
    try:
        return _run_rigs(rigs, cells, quick=quick, folder=folder, progress=progress,
                         hold_s=hold_s, all_devices=all_devices, only=only, on_cell=on_cell)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _run_rigs(rigs: list[str], cells: list[Cell], *, quick: bool, folder: Path | None,
              progress: TextIO | None, hold_s: float, all_devices: bool, only: list[str] | None,
              on_cell: Callable[[Cell], None] | None) -> list[Cell]:
    with contextlib.ExitStack() as stack:
        root = folder or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="rigctl-faults-")))
        for kind in rigs:
            rig_folder = root / kind
            rig_folder.mkdir(parents=True, exist_ok=True)
            _say(progress, f"{kind}: starting its emulated bench")
            with RigCampaign(kind, rig_folder, hold_s=hold_s, progress=progress,
                             all_devices=all_devices) as campaign:
                todo = planned_cells(campaign, quick=quick, only=only)
                # the daemon's cells first, then the local runs' (the rig has one owner)
                todo.sort(key=lambda c: c[0] != "daemon")
                for index, (path, fault, phase) in enumerate(todo, 1):
                    run = campaign.run_daemon_cell if path == "daemon" else campaign.run_execute_cell
                    for attempt in (1, 2):
                        try:
                            cell = run(fault, phase)
                        except Exception as err:  # noqa: BLE001 - one cell's error is its own
                            cell = Cell(kind, path, fault.label, phase,
                                        note=f"campaign error: {type(err).__name__}: {err}")
                            campaign.stop_daemon()  # start afresh for the next cell
                        # the campaign's own precondition failed (the run ended before the
                        # phase, the bench did not answer): once more, then it counts
                        if "phase not reached" not in cell.note and "campaign error" not in \
                                cell.note:
                            break
                        if attempt == 1:
                            _say(progress, f"  {path} {fault.label} @ {phase}: {cell.note}; "
                                 "once more")
                    if attempt == 2:
                        cell.note += " (second attempt)"
                    cells.append(cell)
                    if on_cell is not None:
                        on_cell(cell)
                    _say(progress, f"[{kind} {index}/{len(todo)}] {path} {fault.label} @ {phase}: "
                         f"{describe(cell)}")
    return cells


def _say(out: TextIO | None, line: str) -> None:
    if out is not None:
        print(line, file=out, flush=True)


def describe(cell: Cell) -> str:
    safe = (f"safe {cell.fault_to_safe_s:.2f} s" if cell.safe and cell.fault_to_safe_s is not None
            else "safe" if cell.safe else "NOT SAFE")
    text = f"{cell.outcome or 'no outcome'}, {safe}, record {cell.record}"
    if cell.device or cell.reason:
        text += f" ({cell.device or '-'}: {(cell.reason or '')[:90]})"
    if cell.note:
        text += f" [{cell.note}]"
    return text


# -- reporting ---------------------------------------------------------------------------------

SHORT = {"completed": "done", "suspended and resumed": "susp+res", "paused and resumed":
         "paused+res", "faulted": "FAULT", "e-stopped": "ESTOP", "aborted": "abort",
         "refused": "refused", "n/a": "n/a"}


def matrix(cells: list[Cell]) -> str:
    """The campaign as a table per rig and path: a row per fault, a column per phase, each cell
    the outcome and the seconds from the fault to every device safe ('!' marks a failed cell);
    then every failed cell in full."""
    lines = []
    width = 12
    for (rig, path) in dict.fromkeys((c.rig, c.path) for c in cells):
        group = [c for c in cells if (c.rig, c.path) == (rig, path)]
        lines.append(f"{rig} via {'the daemon' if path == 'daemon' else 'rigctl execute'} "
                     f"(outcome, seconds from the fault to every device safe)")
        phases = [p for p in PHASES if any(c.phase == p for c in group)]
        lines.append(f"  {'fault':<24}" + "".join(f"{p:<{width + 6}}" for p in phases))
        for label in dict.fromkeys(c.fault for c in group):
            row = f"  {label:<24}"
            for phase in phases:
                found = [c for c in group if c.fault == label and c.phase == phase]
                if not found:
                    row += f"{'':<{width + 6}}"
                    continue
                c = found[0]
                text = SHORT.get(c.outcome or "", "none")
                if c.outcome != "n/a":
                    text += f" {c.fault_to_safe_s:.2f}" if c.fault_to_safe_s is not None else " -"
                row += f"{('' if c.ok or c.outcome == 'n/a' else '!') + text:<{width + 6}}"
            lines.append(row.rstrip())
        lines.append("")
    for rig, figs in figures(cells).items():
        worst, period = figs["worst_decision_to_stopping_s"], figs["stream_period_s"]
        if worst is not None and period is not None:
            lines.append(f"{rig}: decision to stop -> commands toward safe: worst "
                         f"{worst * 1e3:.2f} ms ({figs['worst_stopping_cell']}), one stream "
                         f"period {period * 1e3:.1f} ms: {'within' if worst <= period else 'OVER'}")
    failed = [c for c in cells if not c.ok and c.outcome != "n/a"]
    lines.append(f"{len(cells)} cells, {len(failed)} failed (a failed cell: no named outcome, a "
                 "device not safe at the end, a record lost or unreadable, or its phase not reached)")
    for c in failed:
        lines.append(f"  ! {c.rig} {c.path} {c.fault} @ {c.phase}: {describe(c)}")
    return "\n".join(lines)


def figures(cells: list[Cell]) -> dict:
    """Per rig: the cells, how many failed, the count per outcome and the worst time from a
    fault to every device safe (the cells that stopped the run: not those it rode out)."""
    out: dict[str, dict] = {}
    for rig in dict.fromkeys(c.rig for c in cells):
        group = [c for c in cells if c.rig == rig and c.outcome != "n/a"]
        stopped = [c for c in group if c.outcome in ("faulted", "e-stopped", "aborted")
                   and c.fault_to_safe_s is not None]
        worst = max(stopped, key=lambda c: c.fault_to_safe_s or 0.0, default=None)  # None filtered
        timed = [c for c in group if c.decision_to_stopping_s is not None]
        slowest = max(timed, key=lambda c: c.decision_to_stopping_s or 0.0, default=None)  # as above
        periods = {c.stream_period_s for c in timed if c.stream_period_s is not None}
        counts: dict[str, int] = {}
        for c in group:
            counts[c.outcome or "none"] = counts.get(c.outcome or "none", 0) + 1
        out[rig] = {"cells": len(group), "failed": sum(not c.ok for c in group),
                    "outcomes": counts,
                    "worst_fault_to_safe_s": None if worst is None else worst.fault_to_safe_s,
                    "worst_cell": None if worst is None else f"{worst.path} {worst.fault} @ "
                    f"{worst.phase}",
                    "worst_decision_to_stopping_s": None if slowest is None
                    else slowest.decision_to_stopping_s,
                    "worst_stopping_cell": None if slowest is None else f"{slowest.path} "
                    f"{slowest.fault} @ {slowest.phase}",
                    "stream_period_s": min(periods) if periods else None,
                    "stopping_timed": len(timed),
                    "records": {r: sum(c.record == r for c in group)
                                for r in dict.fromkeys(c.record for c in group)}}
    return out


def every_cell_ok(cells: list[Cell]) -> bool:
    return all(c.ok or c.outcome == "n/a" for c in cells)


def as_json(cells: list[Cell]) -> dict:
    """The campaign as one JSON document: ok, the figures per rig, what "safe" means per rig,
    every cell."""
    return {"ok": every_cell_ok(cells), "figures": figures(cells),
            "safe_means": {k: rig_profile(k).safe_means for k in dict.fromkeys(c.rig for c in cells)},
            "cells": [c.as_dict() for c in cells]}
