"""Benchmark: the full fault campaign (`rigctl faults` without `--quick`). Prints one JSON object.

Every fault each emulated bench's backdoor offers (one device per class: the six supplies are one)
and SIGKILL / SIGSTOP of the daemon's stream process, at every phase of a short run (before
energising, mid-move, paused, suspended, ramping down) through the daemon, and every bench fault
mid-move through a local `rigctl execute`, on every rig (`rigctl.apps.faults`). Per rig: the cells, how
many failed, the count per outcome, the worst time from a fault to every device safe among the
cells the fault stopped (read from the emulator: coil currents under 50 mA, SyRen outputs 0, arms
at rest) and which cell it was, the worst time from the run's decision to stop to every device's
commands turned toward safe (the record's `stopping` event) against the stream period, and the
records complete / readable; then every failed cell in full.

    python bench/faults.py                                   # every rig: about 40 minutes
    python bench/faults.py --rig depm                        # one rig
    python bench/faults.py --rig six-coil --cell daemon/x+:stall/moving   # one cell
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from rigctl.apps.faults import as_json, parse_cell, profiled_kinds, run_campaign


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", choices=[*profiled_kinds(), "all"], default="all")
    parser.add_argument("--cell", action="append", metavar="PATH/DEVICE:KIND/PHASE",
                        help="only this cell (repeatable), e.g. daemon/x+:stall/moving")
    parser.add_argument("--all-devices", action="store_true",
                        help="every device, not one per class")
    parser.add_argument("--cells-out", metavar="FILE",
                        help="also append each cell, as it is done, to FILE (JSON lines)")
    parser.add_argument("--hold", type=float, default=1.5,
                        help="seconds each fault is held before it is cleared (default 1.5)")
    args = parser.parse_args()
    for name in args.cell or []:
        try:
            parse_cell(name)
        except ValueError as err:
            parser.error(str(err))
    started = time.monotonic()
    load_before = round(os.getloadavg()[0], 2)
    def save(cell) -> None:
        if args.cells_out:
            with open(args.cells_out, "a") as out:
                out.write(json.dumps(cell.as_dict()) + "\n")

    cells = run_campaign(profiled_kinds() if args.rig == "all" else [args.rig], quick=False,
                         progress=sys.stderr, hold_s=args.hold, all_devices=args.all_devices,
                         only=args.cell, on_cell=save)
    document = as_json(cells)
    print(json.dumps({
        "ok": document["ok"], "figures": document["figures"],
        "safe_means": document["safe_means"], "hold_s": args.hold,
        "minutes": round((time.monotonic() - started) / 60.0, 1),
        "load_average_1min_before": load_before,
        "load_average_1min_after": round(os.getloadavg()[0], 2),
        "failed": [c for c in document["cells"] if not c["ok"] and c["outcome"] != "n/a"],
        "cells": document["cells"],
    }, indent=2))


if __name__ == "__main__":
    main()
