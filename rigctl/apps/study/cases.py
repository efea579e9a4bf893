"""Running one case of a study, wherever a worker runs it: a planner in this process, exactly as
`rigctl plan ...` runs it (the same parser, so the same checks and defaults); an emulated run as
`rigctl execute --rig` in a child process, on a bench of its own (`rigctl emulate`, another child)
that serves on ports the kernel picks, so cases side by side never share a device.

`run_case` returns the case's row: its figures (the command's JSON), `success` and `error` as the
spec names them, its wall time and the folder it wrote (the plan, or the run record). A case that
fails (bad input, a fault) is a row too, with `status` and the message: a study goes on.

A run's two children are in sessions of their own, out of reach of the terminal's Ctrl-C (which
would have stopped the bench with the same keystroke as the run on it, the run then unable to
make it safe). The study stops them when it is interrupted: `stop_cases` in each worker (and an
exception in a serial study) ends each run as SIGTERM does, an abort recorded, then its bench.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import io
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rigctl.apps.study.spec import BENCH_OPTIONS, Case, options_argv
from rigctl.core.children import end_child

if TYPE_CHECKING:
    from rigctl.core.config import Emulation

EXECUTE_TIMEOUT_S = 600.0


@functools.cache
def planner_parser() -> argparse.ArgumentParser:
    """`rigctl plan ...`'s own parser (rigctl.apps.cli.plan), under a bare top level. Built once
    per process (parsing leaves it as it was): building it took about 20 ms, most of a small
    case (`bench/study.py`'s tiny cases)."""
    from rigctl.apps.cli.plan import register

    parser = argparse.ArgumentParser(prog="rigctl")
    register(parser.add_subparsers(dest="command", required=True))
    return parser


def parse_planner(argv: list[str]) -> argparse.Namespace:
    """The namespace of a planner command line; ValueError with argparse's own line if it is bad."""
    from rigctl.apps.cli.paths import BadPath

    parser = planner_parser()
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            return parser.parse_args(argv)
    except SystemExit:
        lines = [line for line in err.getvalue().splitlines() if line.strip()]
        raise ValueError(lines[-1] if lines else f"cannot parse {' '.join(argv)}") from None
    except BadPath as err:  # a path the option's type refuses
        raise ValueError(str(err)) from None


def run_case(command: str, folder: str, case: Case, out_root: str, success: str | None,
             error: str | None) -> dict[str, Any]:
    """Run one case; its row for the results table (see the module docstring)."""
    out = Path(out_root) / "cases" / case.id
    out.mkdir(parents=True, exist_ok=True)
    started_s = time.time()  # epoch: comparable across the workers of one machine
    started, cpu = time.perf_counter(), time.process_time()
    try:
        if command == "execute":
            status, figures, record = _execute(case, Path(folder), out)
        else:
            status, figures, record = _plan(command, case, Path(folder), out)
        message = figures.pop("_message", None)
    except Exception as err:  # noqa: BLE001 - one case's failure is its row, never the study's end
        status, figures, record, message = "error", {}, str(out), f"{type(err).__name__}: {err}"
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    return {
        "case_id": case.id, "seed": case.seed, "parameters": case.parameters, "status": status,
        "message": message, "success": _flag(figures.get(success)) if success else None,
        "error": _number(figures.get(error)) if error else None, "figures": figures,
        "wall_s": wall, "cpu_s": cpu, "started_s": started_s, "record": record,
        "worker": f"{os.uname().nodename}:{os.getpid()}",
    }


def _flag(value: Any) -> bool | None:
    return None if value is None else bool(value)


def _number(value: Any) -> float | None:
    try:
        return None if value is None else float(value)
    except (TypeError, ValueError):
        return None


# ---------------------------------------------------------------- planners, in process


def _plan(command: str, case: Case, folder: Path, out: Path) -> tuple[str, dict, str]:
    from rigctl.core.errors import RigError

    argv = command.split() + options_argv(case.options, folder) + ["--json", "-o", str(out / "plan.json")]
    if command in ("plan coverage", "plan reachable"):
        argv = argv[:-2]  # these write no plan
    try:
        args = parse_planner(argv)
    except ValueError as err:
        return "bad_input", {"_message": str(err)}, str(out)
    stdout, stderr = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = args.func(args)
    except RigError as err:
        return "bad_input", {"_message": str(err)}, str(out)
    (out / "planner.log").write_text(stderr.getvalue())
    lines = [line for line in stdout.getvalue().splitlines() if line.startswith("{")]
    figures = json.loads(lines[-1]) if lines else {}
    figures["exit_code"] = code
    return "ok" if code in (0, 1) else "failed", figures, str(out / "plan.json") \
        if (out / "plan.json").exists() else str(out)


# ---------------------------------------------------------------- emulated runs, in children


class CasesStopped(Exception):
    """The study this case belongs to is stopping (`stop_cases`): its run was not started."""


class _RunningCases:
    """The emulated runs of this process's cases (`rigctl execute` children, by the study's
    results folder), and how many cases still hold a bench; a study's cases stop together."""

    changed = threading.Condition()
    runs: dict[str, set[subprocess.Popen]] = {}
    benches: dict[str, int] = {}
    stopping: set[str] = set()

    @classmethod
    @contextlib.contextmanager
    def case(cls, study: str) -> Iterator[None]:
        with cls.changed:
            cls.benches[study] = cls.benches.get(study, 0) + 1
        try:
            yield
        finally:
            with cls.changed:
                cls.benches[study] -= 1
                cls.changed.notify_all()

    @classmethod
    def start(cls, study: str, argv: list[str], **popen: Any) -> subprocess.Popen:
        """`argv` started in a session of its own, unless the study is stopping (CasesStopped)."""
        with cls.changed:
            if study in cls.stopping:
                raise CasesStopped("the study was interrupted before this case's run started")
            proc = subprocess.Popen(argv, start_new_session=True, **popen)
            cls.runs.setdefault(study, set()).add(proc)
            return proc

    @classmethod
    def done(cls, study: str, proc: subprocess.Popen) -> None:
        with cls.changed:
            cls.runs.get(study, set()).discard(proc)


def stop_cases(out_root: str, timeout_s: float = 60.0) -> int:
    """Stop the emulated runs of the study writing to `out_root` that this process runs (SIGTERM:
    each aborts, ramps down and records its end; its case then stops its bench), start no new
    one, and wait (at most `timeout_s`) until every case of the study has let its bench go.
    Run in each worker by an interrupted study (`run_study`, its cases cancelled first); the
    number of runs stopped. The same study may run again in this process afterwards (a lab's
    worker, the study resumed)."""
    with _RunningCases.changed:
        _RunningCases.stopping.add(out_root)
        runs = list(_RunningCases.runs.get(out_root, ()))
    try:
        for proc in runs:
            if proc.poll() is None:
                proc.terminate()
        with _RunningCases.changed:
            _RunningCases.changed.wait_for(lambda: not _RunningCases.benches.get(out_root),
                                           timeout_s)
    finally:
        with _RunningCases.changed:
            _RunningCases.stopping.discard(out_root)
    return len(runs)


def _execute(case: Case, folder: Path, out: Path) -> tuple[str, dict, str]:
    """A bench of the plan's rig kind in a child (`rigctl emulate`, its own ephemeral ports), the
    rig file's overrides applied, `rigctl execute --rig` in another child; the fault, if any,
    injected through the bench's backdoor once the run record shows its event."""
    from rigctl.core.config import dump_rig, load_rig
    from rigctl.core.errors import shielded_from_interrupts
    from rigctl.emulators.backdoor import BackdoorClient
    from rigctl.emulators.process import EmulatedBenchProcess
    from rigctl.plans.schema import load_plan
    from rigctl.run.agents import portable_workspace

    options = case.options
    plan_path = (folder / str(options["plan"])).resolve()
    plan = load_plan(plan_path)
    kind = plan.rig
    bench_flags = options_argv({k: options[k] for k in BENCH_OPTIONS if k in options}, folder)
    if options.get("seed") is not None:
        bench_flags += ["--seed", str(options["seed"])]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.setdefault("RIGCTL_LOCK_DIR", str(out.parent.parent / "locks"))
    Path(env["RIGCTL_LOCK_DIR"]).mkdir(parents=True, exist_ok=True)
    study = str(out.parent.parent)
    with _RunningCases.case(study), \
            EmulatedBenchProcess(kind, out / "bench.toml", extra_args=bench_flags) as bench_rig:
        rig = load_rig(bench_rig)
        overrides = {k[len("rig."):]: v for k, v in options.items() if k.startswith("rig.")}
        rig_path = out / "rig.toml"
        rig_path.write_text(dump_rig(_override(rig, overrides)) if overrides else bench_rig.read_text())
        if plan.kind == "global-moves":
            # a fresh bench builds its world at the first `place` (seconds on a loaded machine,
            # past the run's own 5 s backdoor timeout): built here, before the run, with time
            with BackdoorClient.of(rig.emulation, timeout_s=120.0) as backdoor:
                backdoor.request("place", workspace=portable_workspace(plan),
                                 agents=[{"position": a.start, "radius": a.radius}
                                         for a in plan.agents])
        requests = list(options.get("backdoor", []))
        if options.get("speed") is not None:
            requests.append({"cmd": "speed", "factor": float(options["speed"])})
        if requests:
            with BackdoorClient.of(rig.emulation) as backdoor:
                for request in requests:
                    backdoor.request(**request)
        runs = out / "runs"
        argv = [sys.executable, "-m", "rigctl", "execute", str(plan_path), "--rig", str(rig_path),
                "--runs", str(runs), "--json", "-q"] + (["--open-loop"] if options.get("open-loop") else [])
        with open(out / "execute.log", "w") as log:
            proc = _RunningCases.start(study, argv, stdout=subprocess.PIPE, stderr=log, text=True,
                                       env=env)
            try:
                fault = options.get("fault")
                injected = _inject(fault, rig.emulation, runs, proc) if fault else None
                try:
                    stdout, _ = proc.communicate(timeout=EXECUTE_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    proc.terminate()  # SIGTERM: execute aborts the run as Ctrl-C does, recorded
                    stdout, _ = proc.communicate(timeout=30)
            finally:  # interrupted (a serial study's Ctrl-C): the run ends before its bench,
                with shielded_from_interrupts():  # a second Ctrl-C meanwhile noted, not raised
                    end_child(proc)
                _RunningCases.done(study, proc)
    lines = [line for line in stdout.splitlines() if line.startswith("{")]
    summary = json.loads(lines[-1]) if lines else {}
    if "error" in summary:
        return "bad_input" if proc.returncode == 2 else "failed", \
            {"exit_code": proc.returncode, "_message": summary["error"].get("message")}, str(out)
    errors = [a.get("truth_error_mm", a.get("error_mm")) for a in summary.get("agents", [])]
    errors = [e for e in errors if e is not None]
    figures = {
        "exit_code": proc.returncode, "reached": summary.get("reached"),
        "state": summary.get("state"), "error_mm": max(errors) if errors else None,
        "replans": summary.get("replans"), "duration_s": summary.get("duration_s"),
        "faults": len(summary.get("faults") or []), "safe": summary.get("safe"),
        "fault_injected_at_s": injected,
    }
    for name, value in (summary.get("metrics") or {}).items():  # the rig's own scalar figures
        if isinstance(value, (bool, int, float, str)):
            figures[f"metric_{name}"] = value
    if summary.get("faults"):
        figures["_message"] = "; ".join(str(f.get("reason")) for f in summary["faults"])[:500]
    return "ok" if proc.returncode in (0, 1, 3) else "failed", figures, summary.get("run") or str(out)


def _override(rig, overrides: dict[str, Any]):
    """The rig with `SECTION.KEY` values replaced (checked by the rig file's own model)."""
    from rigctl.core.config import parse_rig
    from rigctl.core.errors import ConfigError

    data = rig.model_dump(mode="json")
    for dotted, value in overrides.items():
        *path, key = dotted.split(".")
        node = data
        for part in path:
            if not isinstance(node.get(part), dict):
                raise ConfigError(f"rig.{dotted}: the rig file has no table {part!r}")
            node = node[part]
        if key not in node:
            raise ConfigError(f"rig.{dotted}: the rig file has no key {key!r}")
        node[key] = value
    return parse_rig(data, "rig")


def _inject(fault: dict, emulation: Emulation, runs: Path,
            proc: subprocess.Popen) -> float | None:
    """Wait for `fault.at_event` (default "energised") in the run record's events, then
    `after_s`, then send the fault; the seconds into the record it went in (None: the run ended
    before the event)."""
    from rigctl.emulators.backdoor import BackdoorClient

    event, after_s = fault.get("at_event", "energised"), float(fault.get("after_s", 0.0))
    seen_at = None
    while proc.poll() is None and seen_at is None:
        for events in runs.glob("*/events.jsonl"):
            for line in events.read_text().splitlines():
                with contextlib.suppress(ValueError):
                    entry = json.loads(line)
                    if entry.get("event") == event:
                        seen_at = float(entry.get("t", 0.0))
                        break
        if seen_at is None:
            time.sleep(0.05)  # the record is a file another process appends to: polled
    if seen_at is None:
        return None
    deadline = time.monotonic() + after_s
    while proc.poll() is None and time.monotonic() < deadline:
        time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))
    if proc.poll() is not None:
        return None
    request = {k: v for k, v in fault.items() if k in ("n", "robot")}
    with BackdoorClient.of(emulation) as backdoor:
        backdoor.request("fault", device=fault["device"], kind=fault["kind"], **request)
    return round(seen_at + after_s, 3)
