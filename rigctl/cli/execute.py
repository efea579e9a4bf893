"""`rigctl execute PLAN`: run a plan on the emulated bench of its rig kind, or on the rig a rig file
names, and print the summary. Each (plan kind, rig kind) has its runner; the options are shared."""

from __future__ import annotations

import argparse
import sys

from rigctl.emulators.process import rig_for_run
from rigctl.errors import (
    EXIT_BAD_INPUT,
    EXIT_FAULT,
    EXIT_NOT_REACHED,
    EXIT_OK,
    ConfigError,
)
from rigctl.plans.schema import load_plan
from rigctl.run.summary import format_summary, summary_json_line


def _execute_coil_board(plan, args: argparse.Namespace) -> int:
    """A coil-board plan: exit 0 reached, 1 not, 2 bad input, 3 fault."""
    from rigctl.rigs.coil_board.run import CoilBoardRun
    from rigctl.run.summary import exit_code

    out = None if args.quiet else sys.stderr
    if args.open_loop:
        raise ConfigError("--open-loop: a coil-board move ends when the camera sees it done; the "
                          "coil board runs closed loop only")
    if getattr(args, "agnostic", False):
        raise ConfigError("--agnostic is for the depm rig")
    extra: list[str] = []
    if getattr(args, "firmware", None):
        extra += ["--firmware", args.firmware]
    if args.rig is not None and extra:
        raise ConfigError("--firmware chooses the emulated bench that execute starts itself: "
                          "give it to `rigctl emulate coil-board` when using --rig")
    with rig_for_run(args.rig, "coil-board", extra_args=extra, progress_out=out) as rig:
        summary = CoilBoardRun(plan, rig, runs_dir=args.runs, progress_out=out).execute()
    print(format_summary(summary))
    if args.json:
        print(summary_json_line(summary))
    return exit_code(summary)


def _execute_depm(plan, args: argparse.Namespace) -> int:
    """A field-sequence plan on the dual-EPM rig: exit 0 reached, 1 not, 2 refused (nothing
    moved: a plan or an approach that breaks a safety constraint raises SafetyRefusal, a
    LimitError), 3 fault."""
    from rigctl.plans.depm import baseline_of
    from rigctl.rigs.depm.run import FieldSequenceRun
    from rigctl.run.summary import exit_code

    out = None if args.quiet else sys.stderr
    time_scale = float(args.time_scale or 1.0)
    if not time_scale > 0:
        raise ConfigError("--time-scale must be positive")
    if args.agnostic:
        if out is not None:
            print("the magnetic-agnostic baseline: straight joint moves to the plan's end poses",
                  file=out, flush=True)
        plan = baseline_of(plan)
    with rig_for_run(args.rig, "depm", progress_out=out) as rig:
        summary = FieldSequenceRun(plan, rig, runs_dir=args.runs, progress_out=out,
                                   time_scale=time_scale).execute()
    print(format_summary(summary))
    if args.json:
        print(summary_json_line(summary))
    if summary.metrics.get("refused"):  # the approach from where the arms stand: nothing moved
        return EXIT_BAD_INPUT
    return exit_code(summary)


def _execute_pair(plan, args: argparse.Namespace) -> int:
    """A pair-formation plan: exit 0 reached and held, 1 not, 3 fault (bad input raises
    PlanError / LimitError / ConfigError: exit 2 from the CLI)."""
    from rigctl.plans.pair import default_rig
    from rigctl.rigs.six_coil.pair import (
        PairRun,
        PairRunSettings,
        loopback_rig,
        prepare_pair,
    )
    from rigctl.run.summary import exit_code

    out = None if args.quiet else sys.stderr
    settings = PairRunSettings(closed_loop=not args.open_loop)
    if getattr(args, "agnostic", False):
        raise ConfigError("--agnostic is for the depm rig")
    if getattr(args, "world", None) not in (None, "pair"):
        raise ConfigError("a pair-formation plan runs in the pair world (--world pair)")
    if args.rig is not None:
        if _mismatch_args(args):
            raise ConfigError("--slip, --noise, --drift and --seed set up the emulated bench that "
                              "execute starts itself: give them to `rigctl emulate` with --rig")
    else:
        prepare_pair(plan, default_rig(), settings)  # refuse a bad plan before starting a bench
    with rig_for_run(args.rig, "six-coil", extra_args=["--world", "pair", *_mismatch_args(args)],
                     progress_out=out, world=" (pair world)") as rig:
        if args.rig is None:
            rig = loopback_rig(rig)
        summary = PairRun(plan, rig, runs_dir=args.runs, progress_out=out,
                          settings=settings).execute()
    print(format_summary(summary))
    if args.json:
        print(summary_json_line(summary))
    return exit_code(summary)


_MISMATCH_FLAGS = (("slip", "--slip"), ("speed_spread", "--speed-spread"), ("drift", "--drift"),
                   ("noise", "--noise"), ("seed", "--seed"))


def _mismatch_args(args: argparse.Namespace) -> list[str]:
    """The model-mismatch flags given, as `rigctl emulate` arguments."""
    out = []
    for name, flag in _MISMATCH_FLAGS:
        value = getattr(args, name, None)
        if value is not None:
            out += [flag, str(value)]
    if getattr(args, "field_at_robots", False):
        out.append("--field-at-robots")
    return out


def _add_mismatch_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("model mismatch of the emulated world (recorded in the rig file)")
    g.add_argument("--slip", type=float, help="distance per turn x F (e.g. 0.85)")
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
        from rigctl.cli.daemon import execute_remote

        return execute_remote(args.plan, args.connect, json_out=args.json, quiet=args.quiet)
    from rigctl.rigs.six_coil.global_moves import execute_plan
    from rigctl.run.summary import summary_json_line

    plan = load_plan(args.plan)
    runner = _RUNNERS.get((plan.kind, plan.rig))
    if runner is not None:
        # Rigs and plan kinds with their own execution: same flags, summary and exit codes.
        return runner(plan, args)
    out = sys.stderr if not args.quiet else None
    closed_loop = False if args.open_loop else None  # None: whenever the rig has a camera
    mismatch = _mismatch_args(args)
    if args.rig is not None and mismatch:
        raise ConfigError("--slip, --speed-spread, --drift, --noise, --seed and "
                          "--field-at-robots set up the emulated bench that execute starts "
                          "itself: give them to `rigctl emulate` when using --rig")
    with rig_for_run(args.rig, plan.rig, extra_args=mismatch, progress_out=out) as rig:
        summary = execute_plan(plan, rig, runs_dir=args.runs, progress_out=out,
                               closed_loop=closed_loop)
    print(format_summary(summary))
    if args.json:
        print(summary_json_line(summary))
    if summary.faults:
        return EXIT_FAULT
    return EXIT_OK if summary.reached else EXIT_NOT_REACHED


# (plan kind, rig kind) -> its runner; the six-coil global-moves run is `cmd_execute`'s own.
_RUNNERS = {
    ("global-moves", "coil-board"): _execute_coil_board,
    ("field-sequence", "depm"): _execute_depm,
    ("pair-formation", "six-coil"): _execute_pair,
}
