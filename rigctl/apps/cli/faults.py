"""`rigctl faults [--rig KIND] [--quick | --cell CELL ...] [--json] [-o OUT]`: the fault campaign (`rigctl.apps.faults`)
on the emulated benches, a matrix of what became of every run and every device. The rig kinds
are the installed ones that have a fault profile (the registry's); `--rig` names one of them."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rigctl.apps.cli.paths import folder, output_file
from rigctl.core.errors import EXIT_NOT_REACHED, EXIT_OK, ConfigError


def _cmd_faults(args: argparse.Namespace) -> int:
    from rigctl.apps.faults import (
        as_json,
        every_cell_ok,
        matrix,
        parse_cell,
        profiled_kinds,
        rig_profile,
        run_campaign,
    )

    if not 0 < args.hold <= 60:
        raise ConfigError(f"--hold must be > 0 and at most 60 s, got {args.hold:g}")
    if args.rig is not None:
        rig_profile(args.rig)  # a kind not installed, or with no profile: refused in one line
    for name in args.cell or ():
        try:
            parse_cell(name)
        except ValueError as err:
            raise ConfigError(f"--cell {err}") from None
    rigs = profiled_kinds() if args.rig is None else [args.rig]
    if not rigs:
        raise ConfigError("no installed rig kind has a fault profile")
    scope = "chosen cells" if args.cell else "quick" if args.quick else "full"
    print(f"fault campaign ({scope}) on the emulated "
          f"{', '.join(rigs)} bench{'es' if len(rigs) > 1 else ''}: nothing real is energised",
          file=sys.stderr, flush=True)
    keep = None
    if args.keep is not None:
        keep = Path(args.keep)
        keep.mkdir(parents=True, exist_ok=True)
    cells = run_campaign(rigs, quick=args.quick, progress=sys.stderr, hold_s=args.hold,
                         all_devices=args.all_devices, folder=keep, only=args.cell)
    document = as_json(cells)
    if args.output is not None:
        Path(args.output).write_text(json.dumps(document, indent=2) + "\n")
    if args.json:
        print(json.dumps(document, indent=2))
    else:
        print(matrix(cells))
    return EXIT_OK if every_cell_ok(cells) else EXIT_NOT_REACHED


def register_faults(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "faults", help="fault campaign: every emulated fault at every run phase, on every rig",
        description="Start each rig's emulated bench and a daemon for it, run a short plan, and "
        "inject every fault the bench's backdoor offers (and SIGKILL / SIGSTOP of the daemon's "
        "stream process) before energising, mid-move, paused, suspended and ramping down; some "
        "also against a local `rigctl execute`. Prints a matrix: the run's outcome, the seconds "
        "from the fault to every device safe (read from the emulator, as the rig kind's fault "
        "profile says: every coil current under 50 mA, every motor driver output 0, the arms at "
        "rest), and failed cells in full. Exit 0 when every cell "
        "ended in a named outcome with every device safe and its run record intact, else 1. "
        "Nothing real is energised.")
    p.add_argument("--rig", metavar="KIND",
                   help="one rig kind (default: every installed kind with a fault profile)")
    p.add_argument("--quick", action="store_true",
                   help="a small representative subset (about 2-3 minutes; what CI runs)")
    p.add_argument("--cell", action="append", metavar="PATH/DEVICE:KIND/PHASE",
                   help="only this cell (repeatable), as the matrix names it: PATH daemon or "
                   "execute, PHASE one of before, moving, paused, suspended, ramping; "
                   "e.g. daemon/board:stall/moving to run a failed cell again")
    p.add_argument("--all-devices", action="store_true",
                   help="every device, not one per class (the six supplies are one class)")
    p.add_argument("--hold", type=float, default=1.5, metavar="S",
                   help="seconds each fault is held before it is cleared (default 1.5)")
    p.add_argument("--keep", type=folder("campaign files", write=True), metavar="DIR",
                   help="keep each rig's rig file, daemon log and run records in DIR/RIG (default: "
                   "a temporary folder, removed)")
    p.add_argument("--json", action="store_true", help="print the campaign as JSON only")
    p.add_argument("-o", "--output", type=output_file("campaign JSON"),
                   help="also write the campaign's JSON here")
    p.set_defaults(func=_cmd_faults)
