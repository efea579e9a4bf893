"""The daemon's verbs of the `rigctl` command line: `daemon`, `status`, `hold`, `estop`, `keys`,
`runs`, `report`, and `execute_remote` behind `rigctl execute PLAN --connect ENDPOINT`.

Client verbs find the daemon with `--connect` (default: the loopback command endpoint) and, for a
daemon with CURVE keys, take `--server-key` / `--client-key` or the environment variables
RIGCTL_SERVER_KEY / RIGCTL_CLIENT_KEY. Exit status as everywhere: 0 success, 1 goal not reached,
2 bad input (refused; nothing energised), 3 a fault, an e-stop, or no daemon to talk to.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

from rigctl.apps.daemon.admission import REQUEST_RATE_HZ
from rigctl.core.errors import (
    EXIT_BAD_INPUT,
    EXIT_FAULT,
    EXIT_NOT_REACHED,
    EXIT_OK,
    ConfigError,
    PlanError,
)
from rigctl.core.registry import default_kind, entry_point_names

if TYPE_CHECKING:
    from rigctl.rigs.guardian import Guardian

READY_PREFIX = "READY "

log = logging.getLogger(__name__)


def _positive_rate(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"a rate in Hz > 0, got {text!r}")
    return value


def _client(endpoint: str, server_key: str | None = None, client_key: str | None = None,
            timeout_s: float = 2.0):
    from rigctl.apps.client import Rig

    server_key = server_key or os.environ.get("RIGCTL_SERVER_KEY") or None
    client_key = client_key or os.environ.get("RIGCTL_CLIENT_KEY") or None
    if (server_key is None) != (client_key is None):
        raise ConfigError("CURVE needs both keys: --server-key (the daemon's public key) and "
                          "--client-key (your secret key), or RIGCTL_SERVER_KEY and "
                          "RIGCTL_CLIENT_KEY")
    try:
        return Rig(endpoint, server_key=server_key, client_key=client_key, timeout_s=timeout_s)
    except (OSError, ValueError) as err:  # an unreadable or malformed key file
        raise ConfigError(f"cannot use the CURVE keys: {err}") from None


def _refused_exit(err) -> int:
    print(f"refused: {err}", file=sys.stderr)
    return EXIT_BAD_INPUT if err.code in ("plan_invalid", "limit", "bad_args", "unknown_plan",
                                          "bad_request", "too_large", "bad_json",
                                          "unknown_command") else EXIT_FAULT


# -- rigctl daemon -------------------------------------------------------------------------------
def _cmd_daemon(args: argparse.Namespace) -> int:
    from rigctl.rigs.guardian import Guardian

    # the guardian first: its start overlaps the imports below; left last: if this process dies
    # without a word (SIGKILL) while it owns the rig, the guardian makes it safe (under systemd
    # the unit's ExecStopPost does too)
    with Guardian("rigctl daemon") as guardian:
        return _serve_guarded(args, guardian)


def _serve_guarded(args: argparse.Namespace, guardian: Guardian) -> int:
    from rigctl.apps.daemon.messages import DaemonSettings, is_loopback_endpoint
    from rigctl.apps.daemon.server import Daemon
    from rigctl.core.config import load_rig
    from rigctl.emulators.process import EmulatedBenchProcess
    from rigctl.rigs.doctor import preflight
    from rigctl.rigs.owner import RigLock

    for endpoint in (args.command, args.telemetry, args.events):  # before anything is started
        if endpoint:
            is_loopback_endpoint(endpoint)
    if args.console is not None:  # the web console's options, checked before anything starts
        from rigctl.apps.console.server import check_options

        check_options(args.console, args.console_cert, args.console_key, args.console_plans)
        if (args.server_key is not None) != (args.console_client_key is not None):
            raise ConfigError("--console with CURVE keys needs --console-client-key (an "
                              "operator's .key_secret whose public key is in --allowed-keys)"
                              if args.server_key else
                              "--console-client-key is for a daemon with --server-key")
    # a thread waiting for the GIL (the command thread answering `status`, the stream thread)
    # gets it within 0.1 ms instead of Python's default 5 ms
    sys.setswitchinterval(1e-4)
    with ExitStack() as stack:
        if args.rig is not None:
            if args.bench is not None:
                raise ConfigError("--bench starts an emulated bench; with --rig the rig file "
                                  "says which rig it is: give one of them")
            rig = load_rig(args.rig)
        else:
            kind = args.bench or default_kind()
            tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="rigctl-daemon-bench-"))
            print(f"no --rig given: starting the emulated {kind} bench on loopback "
                  "(nothing real is energised)", file=sys.stderr)
            rig = load_rig(stack.enter_context(EmulatedBenchProcess(kind, Path(tmp) / "bench.toml")))
        settings = _rig_daemon_settings(rig) or DaemonSettings()
        # one owner per rig: refused (exit 2) before anything connects if another process has it
        lock = stack.enter_context(RigLock(rig, "rigctl daemon"))
        # a bench started here is this process's to stop: its rig file names its pid
        guardian.guard(rig, bench_pid=rig.emulation.pid if args.rig is None and rig.emulation is not None else None)
        preflight(rig)  # every device answers and is made safe first, or exit 2 naming it
        guardian.wait_armed()  # before a client can have anything energised
        daemon = Daemon(
            rig,
            command=args.command or settings.command,
            telemetry=args.telemetry or settings.telemetry,
            events=args.events or settings.events,
            runs_dir=args.runs or settings.runs_dir,
            server_key=args.server_key or settings.server_key,
            allowed_keys=args.allowed_keys or settings.allowed_keys,
            realtime_priority=args.realtime,
            currents_hz=args.currents_hz,
            request_rate_hz=args.request_rate,
            camera_frames=args.console is not None,
        )
        endpoints = daemon.start()
        console_lines = ""
        if args.console is not None:
            from rigctl.apps.console.server import Console

            console = Console(rig, command_endpoint=endpoints.command, runs_dir=daemon.runs_dir,
                              clock_origin=daemon.t0, address=args.console,
                              token=os.environ.get("RIGCTL_CONSOLE_TOKEN") or None,
                              cert=args.console_cert, key=args.console_key,
                              plans_dir=args.console_plans, server_key=args.server_key,
                              client_key=args.console_client_key)
            url = console.start()
            stack.callback(console.stop)
            console_lines = (f" console={url} console_token={console.token}",
                             f"\n  console    {url}#token={console.token}  (the token "
                             "controls the rig: keep it to the operators)")
        lock.name_control(endpoints.command)  # where `rigctl estop --rig` finds this daemon
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: daemon.request_shutdown())
        ready_console, human_console = console_lines or ("", "")
        print(f"{READY_PREFIX}command={endpoints.command} telemetry={endpoints.telemetry} "
              f"events={endpoints.events}{ready_console}", flush=True)
        print(f"rigctl daemon for {rig.rig.name!r} ({rig.rig.kind}"
              f"{', emulated' if rig.emulated else ''})\n"
              f"  commands   {endpoints.command}\n  telemetry  {endpoints.telemetry}\n"
              f"  events     {endpoints.events}\n  run records {Path(daemon.runs_dir).resolve()}"
              f"{human_console}", file=sys.stderr, flush=True)
        daemon.serve_forever()
    return EXIT_OK


def _rig_daemon_settings(rig):
    """The rig file's [daemon] table, once RigConfig carries one (see the integrator's note)."""
    from rigctl.core.config import RigConfig

    return rig.daemon if "daemon" in RigConfig.model_fields else None


# -- client verbs --------------------------------------------------------------------------------
def _cmd_status(args: argparse.Namespace) -> int:
    with _client(_owner_endpoint(args), args.server_key, args.client_key) as rig:
        status = rig.status()
    if args.json:
        print(json.dumps(status))
        return EXIT_OK
    print(_status_text(status))
    return EXIT_OK


def _status_text(status: dict) -> str:
    """`rigctl status` for a terminal, from the daemon's `status` or a local run's (the same
    shape, docs/daemon-protocol.md); a key an owner left out is shown as "?" rather than
    failing: an older rigctl may be the one answering."""
    device = status.get("device")
    lines = [f"state: {status.get('state', '?')}" + (
        f" ({device + ': ' if device else ''}{status['reason']})" if status.get("reason") else "")
        + (f"; owner: {status['owner']}" if status.get("owner") else "")]
    rig = status.get("rig") or {}
    lines.append(f"rig: {rig.get('name', '?')} ({rig.get('kind', '?')}"
                 f"{', emulated' if rig.get('emulated') else ''})")
    run = status.get("run")
    if run:
        plan = f" plan {run['plan_id']}" if run.get("plan_id") else ""
        lines.append(f"run: {run.get('id') or run.get('name') or '(starting)'}{plan} sample "
                     f"{run.get('sample', '?')}/{run.get('samples') or '?'} {_step(run)}")
    if status.get("hold"):
        lines.append(f"manual hold: {status['hold']}")
    for item in status.get("devices") or []:
        lines.append(f"  {item.get('name', '?'):<4} {item.get('health', '?'):<8} "
                     f"{item.get('url', '')}  {item.get('detail') or ''}")
    fault = status.get("last_fault")
    if fault:
        lines.append(f"last fault: {fault.get('device') or '-'}: {fault.get('reason')}")
    return "\n".join(lines)


def _cmd_hold(args: argparse.Namespace) -> int:
    from rigctl.apps.client import CommandRefused

    with _client(_owner_endpoint(args), args.server_key, args.client_key, timeout_s=35.0) as rig:
        try:
            if args.release:
                reply = rig.release(args.ramp_s)
            elif args.joints_rad is not None:
                q = args.joints_rad
                reply = rig.hold({"joints_rad": [q[:7], q[7:]]}, args.ramp_s)
            else:
                key = "field_mT" if args.field_mT is not None else "drive"
                reply = rig.hold({key: getattr(args, key)}, args.ramp_s)
        except CommandRefused as err:
            return _refused_exit(err)
    if reply["hold"] is None:
        print("released: ramping to the rest" if reply["released"] else "nothing was held")
    else:
        setpoints = ", ".join(f"{name} {value:g}"
                              for name, value in zip(reply["channels"], reply["setpoints"]))
        print(f"holding {reply['hold']}: {setpoints}")
    return EXIT_OK


def _cmd_load(args: argparse.Namespace) -> int:
    """`rigctl load PLAN`: the daemon checks the plan against its rig and keeps it; prints the
    plan id that `rigctl execute --connect` or a client's `execute` starts."""
    from rigctl.apps.client import CommandRefused

    document = _plan_document(args.plan)
    with _client(_owner_endpoint(args), args.server_key, args.client_key, timeout_s=60.0) as rig:
        try:
            plan_id = rig.load(document)
        except CommandRefused as err:
            return _refused_exit(err)
    print(json.dumps({"plan_id": plan_id}) if args.json else f"loaded: plan id {plan_id}")
    return EXIT_OK


def _cmd_estop(args: argparse.Namespace) -> int:
    if args.rig is not None:
        return _estop_rig(args)
    with _client(args.connect, args.server_key, args.client_key, timeout_s=1.0) as rig:
        reply = rig.estop()
    print(f"EMERGENCY STOP: state {reply.get('state')}; "
          f"{reply.get('zeroing') or 'every device told to stop'}")
    return EXIT_OK


def _cmd_doctor(args: argparse.Namespace) -> int:
    from rigctl.core.config import load_rig
    from rigctl.core.priority import computer_notes
    from rigctl.rigs.doctor import probe_rig

    rig = load_rig(args.rig)
    results = probe_rig(rig, timed=True)
    healthy = all(p.ok for p in results)
    computer = computer_notes()
    if args.json:
        print(json.dumps({"rig": rig.rig.kind, "ok": healthy, "computer": computer,
                          "devices": [p.as_dict() for p in results]}))
        return EXIT_OK if healthy else EXIT_FAULT
    print(f"{rig.rig.name} ({rig.rig.kind}): nothing is energised by this check")
    print(f"  {'device':<12} {'kind':<10} {'':<4} {'ms':>6}  detail")
    for p in results:
        print(f"  {p.device:<12} {p.kind:<10} {'ok' if p.ok else 'FAIL':<4} {p.ms:>6.0f}  "
              f"{p.detail}")
    print("every device answered" if healthy else
          "NOT READY: " + ", ".join(p.device for p in results if not p.ok))
    for note in computer:
        print(f"  {note}")
    return EXIT_OK if healthy else EXIT_FAULT


def _cmd_control(args: argparse.Namespace) -> int:
    """`rigctl pause [--now] | resume | abort | reset`, to the daemon at --connect or to whichever
    process owns the rig of --rig (a daemon or a `rigctl execute`)."""
    from rigctl.apps.client import CommandRefused

    with _client(_owner_endpoint(args), args.server_key, args.client_key) as rig:
        try:
            if args.verb == "pause":
                reply = rig.pause(immediate=args.now)
            else:
                reply = getattr(rig, args.verb)()
        except CommandRefused as err:
            return _refused_exit(err)
    print(f"{args.verb}: state {reply.get('state')}"
          + (" (pausing at the end of this step)" if reply.get("pending") else ""))
    return EXIT_OK


def _owner_endpoint(args: argparse.Namespace) -> str:
    """--connect, or with --rig the control endpoint of the process that owns the rig (its lock
    names it: a daemon or a `rigctl execute`)."""
    if getattr(args, "rig", None) is None:
        return args.connect
    from rigctl.core.config import load_rig
    from rigctl.rigs.owner import holder_of

    holder = holder_of(load_rig(args.rig))
    if holder is None or not holder.control:
        raise ConfigError(f"{args.rig}: no process owns this rig (nothing is running on it)")
    return holder.control


def _cmd_watch(args: argparse.Namespace) -> int:
    from rigctl.apps.cli.watch import watch

    return watch(_owner_endpoint(args), seconds=args.seconds, interval_s=args.interval,
                 out=sys.stdout, as_json=args.json,
                 client=lambda endpoint: _client(endpoint, args.server_key, args.client_key))


def _estop_rig(args: argparse.Namespace) -> int:
    """`rigctl estop --rig RIG.toml`: the rig's owner (daemon or local run, as its lock names it)
    stops; if none answers, every device of the rig is made safe directly."""
    from rigctl.apps.client import Rig
    from rigctl.core.config import load_rig
    from rigctl.core.errors import RigError
    from rigctl.rigs import rig_kind
    from rigctl.rigs.owner import holder_of

    rig = load_rig(args.rig)
    holder = holder_of(rig)
    if holder is not None and holder.control:
        try:
            with Rig(holder.control, timeout_s=0.3, retries=0) as owner:
                reply = owner.estop()
            unreached = reply.get("unreached") or []
            print(f"EMERGENCY STOP: {holder.describe()} took it; state {reply['state']}"
                  + (f"; NOT REACHED: {', '.join(unreached)}" if unreached else
                     f"; {reply.get('zeroing') or 'every device told to stop'}"))
            return EXIT_FAULT if unreached else EXIT_OK
        except RigError as err:
            print(f"{holder.describe()} did not answer ({err}): making every device safe "
                  "directly", file=sys.stderr)
    result = rig_kind(rig.rig.kind).make_safe(rig)
    for name, why in result.items():
        print(f"  {name:<12} {'safe' if why is None else 'NOT REACHED: ' + why}")
    reached = all(why is None for why in result.values())
    print("EMERGENCY STOP: " + ("every device made safe directly" if reached else
                                "some devices could not be reached: check them by hand"))
    return EXIT_OK if reached else EXIT_FAULT


def _cmd_keys(args: argparse.Namespace) -> int:
    from rigctl.apps.daemon.keys import allow, load_public, new_keypair

    if args.keys_command == "new":
        public, secret = new_keypair(args.dir, args.name)
        print(f"public key (give this file to the daemon's allow-list): {public}")
        print(f"secret key (keep it; mode 0600): {secret}")
        print(f"key: {load_public(public).decode()}")
    else:
        target = allow(args.public_key, args.dir)
        print(f"allowed: {target}")
    return EXIT_OK


def _cmd_runs(args: argparse.Namespace) -> int:
    if args.connect:
        with _client(args.connect, args.server_key, args.client_key) as rig:
            runs = rig.runs(limit=args.limit)
        where = args.connect
    else:
        from rigctl.apps.cli.paths import folder
        from rigctl.core.record import list_runs

        where = folder("run records")(args.runs)  # read here: with --connect no folder is needed
        runs = list_runs(where, limit=args.limit)
    if args.json:
        print(json.dumps(runs))
        return EXIT_OK
    if not runs:
        print(f"no runs in {where}")
        return EXIT_OK
    width = max(len(run["id"]) for run in runs)
    print(f"{'RUN':<{width}}  {'RESULT':<10} {'TIME (s)':>8}  PLAN")
    for run in runs:
        if not run["finished"]:
            verdict = "UNFINISHED"
        elif run.get("faults"):
            verdict = "FAULT"
        else:
            verdict = "reached" if run.get("reached") else "missed"
        duration = run.get("duration_s")
        seconds = "" if duration is None else f"{duration:.1f}"
        print(f"{run['id']:<{width}}  {verdict:<10} {seconds:>8}  {run.get('plan') or ''}")
    return EXIT_OK


def _cmd_report(args: argparse.Namespace) -> int:
    from rigctl.apps.report import find_run, render_report
    from rigctl.run.certificate import read_certificate

    run = find_run(args.run, args.runs)
    if args.video is not None:
        from rigctl.apps.report_video import HEIGHT, WIDTH, render_video

        # --video alone: True (argparse would pass a string const through the type check)
        rendered = render_video(run, args.video if isinstance(args.video, str) else None)
        print(rendered.path)
        print(f"{rendered.frames} frames at {rendered.fps:g} frames/s, {WIDTH}x{HEIGHT}, "
              f"{rendered.t_start_s:.2f}-{rendered.t_end_s:.2f} s of the run; scene: "
              f"{rendered.why}")
        return EXIT_OK
    out = render_report(run, args.output)
    print(out)
    certificate = read_certificate(run)
    if certificate is None:
        print("no pre-flight certificate in this record")
    else:  # every check the run was allowed against, refused ones first
        checks = sorted(certificate.get("checks") or [], key=lambda c: c["passed"])
        print(f"pre-flight certificate: {'passed' if certificate.get('passed') else 'REFUSED'}: "
              f"{len(checks)} checks, rig file sha256 {certificate.get('rig_hash')}, issued "
              f"{certificate.get('issued')}")
        for c in checks:
            print(f"  {'ok' if c['passed'] else 'REFUSED'}: {c['check']} of {c['subject']}: "
                  f"{c['value']:.4g} {c['unit']} (limit {c['limit']:.4g}, margin "
                  f"{c['margin']:+.4g})" + (f"; {c['detail']}" if c.get("detail") else ""))
    return EXIT_OK


# -- rigctl execute PLAN --connect ENDPOINT -------------------------------------------------------
def _plan_document(plan_path: str | Path) -> dict:
    """A plan file as the JSON document a daemon's `load` takes."""
    try:
        return json.loads(Path(plan_path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise PlanError(f"{plan_path}: not a readable JSON plan ({err})") from None


def execute_remote(plan_path: str | Path, endpoint: str, *, json_out: bool = False,
                   quiet: bool = False, server_key: str | None = None,
                   client_key: str | None = None) -> int:
    """Submit a plan to a running daemon, follow its progress, print the summary.

    Returns the exit status (0 reached, 1 not reached, 2 refused, 3 fault / e-stop / no daemon).
    """
    from rigctl.apps.client import CommandRefused

    plan = _plan_document(plan_path)
    out = None if quiet else sys.stderr
    with _client(endpoint, server_key, client_key) as rig:
        try:
            loaded = rig.load(plan)
            started = rig.execute(loaded)
        except CommandRefused as err:
            return _refused_exit(err)
        if out:
            steps = (f"{started['moves']} moves" if "moves" in started
                     else f"{started.get('segments')} segments")
            print(f"submitted to {endpoint}: plan {loaded}, {steps}, "
                  f"{started['duration_s']:.1f} s", file=out)
        status = _follow(rig, out, started)
        last = status.get("last_run") or {}
        run_id = Path(last["run"]).name if last.get("run") else None
        summary = rig.run(run_id).get("summary") if run_id else None
    if summary is None:
        print(f"the run ended in state {status['state']} without a summary", file=sys.stderr)
        return EXIT_FAULT
    result = _print_summary(summary, json_out)
    if result.faults:
        return EXIT_FAULT
    return EXIT_OK if result.reached else EXIT_NOT_REACHED


def _print_summary(summary: dict, json_out: bool):
    """The run's summary as `rigctl execute` prints it; returns it."""
    from rigctl.run.summary import print_summary, summary_from_dict

    result = summary_from_dict(summary)
    print_summary(result, json_out)
    return result


def _step(run: dict) -> str:
    """Where a run is: "move 3/8" for global moves, "segment 2/6" for a pair formation change."""
    unit = "move" if "moves" in run else "segment"
    move = run.get("move")
    return f"{unit} {move + 1 if isinstance(move, int) else '?'}/{run.get(unit + 's', '?')}"


def _follow(rig, out, started: dict) -> dict:
    """Poll `status` until the run is over, showing its progress as a local `rigctl execute` does
    (`rigctl.run.progress.Progress`), timed from when the daemon started it."""
    from rigctl.run.progress import Progress

    t0 = time.monotonic()
    progress = Progress(out, int(started.get("moves") or started.get("segments") or 0),
                        float(started.get("duration_s") or 0.0))  # 0: a duration not known
    while True:
        status = rig.status()
        run = status.get("run")
        if run is None and status["state"] not in ("running", "paused", "suspended"):
            break
        if run is not None:
            move = run["move"] if isinstance(run.get("move"), int) else -1
            # a pair or dEPM run counts segments; one paused or suspended says so
            what = _step(run) if "segments" in run else None
            if status["state"] != "running":
                what = f"{_step(run)} {status['state']}"
            progress.update(move, time.monotonic() - t0, what)
        time.sleep(0.2)
    progress.done()
    return status


# -- registration --------------------------------------------------------------------------------
def _client_options(p: argparse.ArgumentParser) -> None:
    from rigctl.apps.daemon.messages import DEFAULT_COMMAND_ENDPOINT

    p.add_argument("--connect", default=DEFAULT_COMMAND_ENDPOINT,
                   help=f"the daemon's command endpoint (default {DEFAULT_COMMAND_ENDPOINT})")
    p.add_argument("--server-key", help="the daemon's public key file (CURVE)")
    p.add_argument("--client-key", help="your secret key file (CURVE)")


def register(sub: argparse._SubParsersAction) -> None:
    from rigctl.apps.cli.paths import input_file, output_file
    from rigctl.apps.daemon.messages import (
        DEFAULT_COMMAND_ENDPOINT,
        DEFAULT_EVENTS_ENDPOINT,
        DEFAULT_TELEMETRY_ENDPOINT,
    )

    p = sub.add_parser(
        "daemon", help="run the long-lived service: ZeroMQ commands and telemetry",
        description="Own the rig's devices and serve commands (JSON over ZeroMQ, see "
        "docs/daemon-protocol.md) and telemetry. Without --rig it starts the emulated six-coil "
        "bench. Binds loopback unless told otherwise; anything else needs CURVE keys. Prints "
        "`READY command=... telemetry=... events=...` when serving. SIGTERM ramps down and exits 0.")
    p.add_argument("--rig", type=input_file("rig file"),
                   help="rig file (TOML) of any rig kind; default: an emulated bench")
    p.add_argument("--bench", choices=entry_point_names(),
                   help="without --rig: which emulated bench to start (default six-coil)")
    p.add_argument("--command", help=f"command endpoint (default {DEFAULT_COMMAND_ENDPOINT})")
    p.add_argument("--telemetry", help=f"telemetry (data) endpoint (default {DEFAULT_TELEMETRY_ENDPOINT})")
    p.add_argument("--events", help=f"telemetry events endpoint (default {DEFAULT_EVENTS_ENDPOINT})")
    p.add_argument("--runs", help="directory for run records (default ./runs)")
    p.add_argument("--server-key", help="the daemon's CURVE secret key file (.key_secret)")
    p.add_argument("--allowed-keys", help="folder of operators' public keys allowed in")
    p.add_argument("--realtime", type=int, metavar="PRIO",
                   help="run the stream thread at SCHED_FIFO priority PRIO where permitted")
    p.add_argument("--currents-hz", type=float, default=0.0,
                   help="publish `currents` at most this often (default 0: every stream cycle)")
    p.add_argument("--request-rate", type=_positive_rate, default=REQUEST_RATE_HZ,
                   metavar="HZ",
                   help="answer at most HZ queries (status, ping, runs, run) a second over all "
                        f"clients, in arrival order; the rest wait (default {REQUEST_RATE_HZ:g}). "
                        "Control commands (e-stop, abort, pause, ...) never wait")
    console = p.add_argument_group(
        "web console", "a live page of the rig with its controls (docs/console.md)")
    console.add_argument("--console", nargs="?", const="127.0.0.1:7820", metavar="ADDRESS",
                         help="serve the operator console on HOST:PORT (default 127.0.0.1:7820; "
                         "port 0 picks one); watching needs no key on loopback, controlling "
                         "needs the token printed at start-up (or RIGCTL_CONSOLE_TOKEN); beyond "
                         "loopback it needs TLS")
    console.add_argument("--console-cert", type=input_file("TLS certificate"),
                         help="TLS certificate chain (PEM) for the console")
    console.add_argument("--console-key", type=input_file("TLS key"),
                         help="the certificate's private key (PEM)")
    console.add_argument("--console-plans", help="a folder of plans (*.json) the page can load")
    console.add_argument("--console-client-key", type=input_file("client key"),
                         help="with CURVE keys: the console's own operator .key_secret (its "
                         ".key in --allowed-keys)")
    p.set_defaults(func=_cmd_daemon)

    p = sub.add_parser("status", help="ask a running daemon (or a rig's owner) for its state, "
                       "run and devices")
    _client_options(p)
    p.add_argument("--rig", type=input_file("rig file"),
                   help="the rig file: ask the process that owns it")
    p.add_argument("--json", action="store_true", help="print the raw status as JSON")
    p.set_defaults(func=_cmd_status)

    p = sub.add_parser(
        "hold", help="hold the rig at a manual setpoint (a field, drive values, a pose), or release",
        description="Ask a running daemon to hold the rig's actuators: ramp straight from what is "
        "held now to the target over --ramp-s, then hold it until released; again while holding "
        "retargets. Every limit is checked before anything moves (refused: exit 2). --release "
        "ramps the supplies or the board to zero and ends the hold; the arms stay where they are.")
    _client_options(p)
    p.add_argument("--rig", type=input_file("rig file"),
                   help="the rig file: ask the process that owns it (a `rigctl "
                   "execute` is running a plan and refuses)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--field-mT", nargs=3, type=float, metavar=("BX", "BY", "BZ"),
                      help="six-coil: the field at the workspace centre, mT (0 0 0 releases)")
    what.add_argument("--drive", nargs="+", type=float, metavar="V",
                      help="coil board: one SyRen drive value per coil, whole units within "
                      "+-max_command, in the rig file's coil order")
    what.add_argument("--joints-rad", nargs=14, type=float, metavar="Q",
                      help="depm: both arms' joints q1..q7, rad, the first arm's then the second's")
    what.add_argument("--release", action="store_true", help="end the hold (ramp to the rest)")
    p.add_argument("--ramp-s", type=float, default=0.1,
                   help="the ramp's duration, s (default 0.1; the arms need their joints' speed "
                   "limits respected: the refusal says how long)")
    p.set_defaults(func=_cmd_hold)

    p = sub.add_parser(
        "load", help="give a plan to a running daemon, checked against its rig (prints its id)",
        description="Send a plan to the daemon: it is parsed, checked against every limit of the "
        "daemon's rig and kept; the printed plan id is what a client's `execute` starts. Refused "
        "(exit 2) with the field or limit named.")
    _client_options(p)
    p.add_argument("plan", type=input_file("plan"), help="plan file (JSON)")
    p.add_argument("--rig", type=input_file("rig file"),
                   help="the rig file: the process that owns it")
    p.add_argument("--json", action="store_true", help='print {"plan_id": ...}')
    p.set_defaults(func=_cmd_load)

    p = sub.add_parser(
        "estop", help="emergency stop: every output of the rig to zero at once",
        description="Stop the rig now: supplies to 0 A and output off, board outputs to zero, "
        "arms stopped where they are. With --rig, whichever process owns the rig (a daemon or a "
        "`rigctl execute`) is told; if none answers, every device is made safe directly and "
        "each one is named. Without --rig, the daemon at --connect. Exit 0 when every device "
        "was reached, 3 otherwise.")
    _client_options(p)
    p.add_argument("--rig", type=input_file("rig file"),
                   help="the rig file: reach its owner, or else its devices directly")
    p.set_defaults(func=_cmd_estop)

    p = sub.add_parser(
        "doctor", help="reach every device of a rig without energising anything",
        description="Check a rig before a run: every supply's *IDN? and error queue, the coil "
        "board's handshake and outputs, each arm's joints, a Hall board sample, a camera frame. "
        "Nothing is switched on. Exit 0 when every device answered, 3 otherwise, 2 for a bad "
        "rig file.")
    p.add_argument("--rig", required=True, type=input_file("rig file"), help="the rig file (TOML)")
    p.add_argument("--json", action="store_true", help="print the table as one JSON document")
    p.set_defaults(func=_cmd_doctor)

    verbs = {"pause": "pause the run at the end of the step it drives (--now: at once)",
             "resume": "resume a paused run", "abort": "end the run: ramp down cleanly",
             "reset": "after an e-stop or a fault: back to idle (the daemon)"}
    for verb, text in verbs.items():
        p = sub.add_parser(verb, help=text, description=text[0].upper() + text[1:] + ". To the "
                           "daemon at --connect, or with --rig to whichever process owns the rig "
                           "(a daemon or a `rigctl execute`).")
        _client_options(p)
        p.add_argument("--rig", type=input_file("rig file"),
                       help="the rig file: reach the process that owns it")
        if verb == "pause":
            p.add_argument("--now", action="store_true",
                           help="pause at once (the field ramps down; the arms brake)")
        p.set_defaults(func=_cmd_control, verb=verb)

    from rigctl.apps.cli.watch import register as register_watch

    register_watch(sub, _client_options, input_file("rig file")).set_defaults(func=_cmd_watch)

    p = sub.add_parser("keys", help="CURVE keys for the daemon and its operators")
    keys_sub = p.add_subparsers(dest="keys_command", required=True)
    k = keys_sub.add_parser("new", help="make a key pair NAME.key / NAME.key_secret")
    k.add_argument("name")
    k.add_argument("--dir", default=".", help="where to write the pair (default: here)")
    k = keys_sub.add_parser("allow", help="add an operator's public key to an allow-list folder")
    k.add_argument("public_key")
    k.add_argument("--dir", required=True, help="the allow-list folder (the daemon's --allowed-keys)")
    p.set_defaults(func=_cmd_keys)

    p = sub.add_parser("runs", help="list run records (local folder, or a daemon's with --connect)")
    p.add_argument("--runs", default="runs", help="run records folder (default ./runs)")
    p.add_argument("--connect", help="ask this daemon instead of reading the folder")
    p.add_argument("--server-key")
    p.add_argument("--client-key")
    p.add_argument("--limit", type=int, default=20)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_runs)

    p = sub.add_parser("report", help="draw a run: planned vs measured paths, currents (PNG)")
    p.add_argument("run", help="run record folder, a run id inside --runs (or its start), or "
                   "`latest`")
    p.add_argument("--runs", default="runs", help="run records folder (default ./runs)")
    p.add_argument("-o", "--output", type=output_file("report"),
                   help="PNG to write (default RUN/report.png)")
    p.add_argument("--video", nargs="?", const=True, type=output_file("video"), metavar="OUT",
                   help="render an MP4 (1280x720) instead: the run's video with the planned, "
                   "expected and tracked paths, goals, time, move and the channels "
                   "(default RUN/report.mp4)")
    p.set_defaults(func=_cmd_report)
