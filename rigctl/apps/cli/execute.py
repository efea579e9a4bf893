"""`rigctl execute PLAN`: run a plan on the emulated bench of its rig kind, or on the rig a rig file
names, and print the summary. One path for every rig: the registry's builder for the plan's kind
makes the run; the options a rig does not take are refused by name."""

from __future__ import annotations

import argparse
import contextlib
import functools
import inspect
import sys
from typing import TYPE_CHECKING

from rigctl.core.errors import ConfigError, abort_on_sigterm, shielded_from_interrupts, take_interrupt

if TYPE_CHECKING:
    from rigctl.core.config import RigConfig
    from rigctl.rigs.guardian import Guardian

# run options: CLI flag -> the builder's keyword (a builder takes only those it names)
_RUN_FLAGS = {"--open-loop": "closed_loop", "--agnostic": "agnostic", "--time-scale": "time_scale"}
# emulated-bench options (`rigctl emulate` flags): CLI flag -> the keywords of a bench's
# constructor, one of which takes it
_BENCH_FLAGS = {**dict.fromkeys(("--slip", "--speed-spread", "--drift", "--noise",
                                 "--field-at-robots"), ("mismatch",)),
                "--seed": ("seed", "mismatch"), "--world": ("world",), "--firmware": ("firmware",),
                "--coil-error": ("coil_errors",), "--coil-seed": ("coil_errors",),
                "--truth": ("truth",), "--probe-noise": ("probe_noise_mT",)}


def refuse_foreign(flags: list[str], table: dict, target, where: str) -> None:
    """Refuse by name (ConfigError) each of `flags` whose keyword in `table` the callable `target`
    does not take; `where` says what was asked ("a global-moves run on a depm rig")."""
    takes = set(inspect.signature(target).parameters)
    for flag in flags:
        wanted = table[flag]
        if takes.isdisjoint((wanted,) if isinstance(wanted, str) else wanted):
            raise ConfigError(f"{flag}: not an option of {where}")


def refuse_foreign_bench_flags(args: argparse.Namespace, kind: str, where: str) -> None:
    """The emulated-bench flags given that the bench of rig kind `kind` does not take, refused."""
    flags = [arg for arg in _bench_args(args) if arg in _BENCH_FLAGS]
    if flags:  # the bench's module (OpenCV, the world models) only imported to check them
        from rigctl.emulators.base import bench_class

        refuse_foreign(flags, _BENCH_FLAGS, bench_class(kind), where)


def _run_options(args: argparse.Namespace) -> dict:
    given = {"--open-loop": False if args.open_loop else None,
             "--agnostic": True if args.agnostic else None, "--time-scale": args.time_scale}
    return {flag: value for flag, value in given.items() if value is not None}


def _bench_args(args: argparse.Namespace) -> list[str]:
    """The emulated bench's flags given (model mismatch, world, firmware) as `rigctl emulate`
    arguments."""
    out = []
    for flag in _BENCH_FLAGS:
        value = getattr(args, flag[2:].replace("-", "_"), None)
        if value is True:
            out.append(flag)
        elif value is not None and value is not False:
            out += [flag, str(value)]
    return out


def _add_mismatch_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("model mismatch of the emulated world (recorded in the rig file)")
    g.add_argument("--slip", type=float, help="distance per turn x F (e.g. 0.85); --world pair: the "
                   "agents' speed under a force x F (the liquid 1/F times as viscous)")
    g.add_argument("--speed-spread", type=float,
                   help="each robot's distance per turn x (1 + s_i), s_i ~ N(0, F)")
    g.add_argument("--drift", type=float, metavar="MM_PER_S",
                   help="slow steady drift, direction drawn from --seed")
    g.add_argument("--noise", type=float, metavar="MM",
                   help="position jitter per turn while touching a wall or another robot")
    g.add_argument("--seed", type=int, help="seed of the spread, drift direction and jitter")
    g.add_argument("--field-at-robots", action="store_true",
                   help="each robot feels the coils' field at its own position (not uniform)")


def cmd_execute(args: argparse.Namespace) -> int:
    if args.connect:
        from rigctl.apps.cli.daemon import execute_remote

        return execute_remote(args.plan, args.connect, json_out=args.json, quiet=args.quiet)
    from rigctl.core.priority import favour
    from rigctl.rigs.guardian import Guardian

    # this process streams, tracks and re-plans: ahead of ordinary work where the machine permits
    # it, before any thread or process (the guardian, the bench) starts and inherits it
    restore = favour("run", pass_on=True)  # given back at the end: `main` may be called in a longer process
    try:
        # the guardian first: its start overlaps the imports below; it is left last, so a SIGKILL
        # at any point from the lock to the bench's stop leaves it to make the rig safe, stop the
        # bench
        with Guardian("rigctl execute") as guardian:
            return _execute_guarded(args, guardian)
    finally:
        restore()


def _execute_guarded(args: argparse.Namespace, guardian: Guardian) -> int:
    # here, not at the top: every other command (`estop` first) starts without these imports
    from rigctl.apps.daemon.local import LocalControl
    from rigctl.emulators.process import bench_for_run
    from rigctl.plans.schema import load_plan
    from rigctl.rigs import rig_kind
    from rigctl.rigs.doctor import preflight
    from rigctl.rigs.owner import RigLock
    from rigctl.run.engine import INTERRUPTED_AGAIN
    from rigctl.run.summary import exit_code, print_summary

    plan = load_plan(args.plan)
    kind = rig_kind(plan.rig)
    build = kind.builder(plan.kind)
    where = f"a {plan.kind} run on a {kind.name} rig"
    given_options = _run_options(args)
    refuse_foreign(list(given_options), _RUN_FLAGS, build, where)
    options = {_RUN_FLAGS[flag]: value for flag, value in given_options.items()}
    refuse_foreign_bench_flags(args, kind.name, where)
    given, implied = _bench_args(args), kind.bench_args(plan)
    if args.rig is not None and given:
        raise ConfigError(f"{' '.join(given)}: these set up the emulated bench that execute starts "
                          f"itself; give them to `rigctl emulate {kind.name}` when using --rig")
    for flag, value in zip(implied[::2], implied[1::2]):
        if flag in given and given[given.index(flag) + 1] != value:
            raise ConfigError(f"a {plan.kind} plan runs with {flag} {value}")
    bench = given + implied
    world = f" ({bench[bench.index('--world') + 1]} world)" if "--world" in bench else ""
    out = None if args.quiet else sys.stderr
    build_on = functools.partial(build, plan, runs_dir=args.runs, progress_out=out, **options)
    if args.rig is not None:  # the pre-flight certificate refuses before any device is opened
        from rigctl.core.config import load_rig

        rig = load_rig(args.rig)
        run = build_on(rig)
        where_it_runs: contextlib.AbstractContextManager[RigConfig] = contextlib.nullcontext(rig)
    else:
        # the bench's own rig file (its links' addresses, its world) is known only once it is up:
        # the run is built on that; a plan the bench's rig refuses is refused before it starts
        run = None
        if kind.bench_rig is not None:
            build(plan, kind.bench_rig(), runs_dir=args.runs, **options)
        where_it_runs = bench_for_run(kind.name, extra_args=bench, progress_out=out, world=world)
    abort_on_sigterm()  # SIGTERM ends a run as Ctrl-C does: an abort, recorded and summarised
    with contextlib.ExitStack() as after_run:
        with where_it_runs as rig, RigLock(rig, "rigctl execute") as lock:  # one owner
            # a bench started here is this process's to stop: its rig file names its pid
            guardian.guard(rig, bench_pid=rig.emulation.pid if args.rig is None and rig.emulation is not None else None)
            preflight(rig)  # every device answers and is made safe, or exit 2 naming it
            if run is None:
                run = build_on(rig)
            guardian.wait_armed()  # nothing is energised unguarded
            with LocalControl(run) as control:
                lock.name_control(control.endpoint)  # where `rigctl estop --rig` and the rest find it
                summary = run.execute()
                # from here to the summary (the bench stopped, the lock let go), a Ctrl-C is noted,
                # not raised: raised, it would lose the summary and say nothing was running
                after_run.enter_context(shielded_from_interrupts())
        print_summary(summary, args.json)
    if take_interrupt() is not None:
        print(f"  {INTERRUPTED_AGAIN}", file=sys.stderr, flush=True)
    return exit_code(summary)
