"""`rigctl study SPEC.toml` (run a study's cases on Dask) and `rigctl study report FOLDER` (PNG).

Exit status: 0 every case ran ok (a planner that did not solve, a run that missed its goal, are
results: ok), 1 some cases could not run (their rows say why), 2 a bad spec or option (nothing
ran), 3 interrupted (the cases finished so far are in the table; the same command resumes).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from rigctl.core.errors import EXIT_FAULT, EXIT_NOT_REACHED, EXIT_OK, ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `study` to the top-level subparsers (sets func(args) -> int)."""
    p = subparsers.add_parser(
        "study", help="sweeps and campaigns: planner or emulated-run cases on Dask, one Parquet table",
        description="Run every case of a study spec (TOML: the command each case runs, a product "
        "or list of parameters, seeds; docs/studies.md) on a Dask LocalCluster (one worker per "
        "core) or a lab's Dask scheduler, writing one row per finished case to "
        "OUT/results.parquet. Cases already in the table are not run again: re-run the same "
        "command to resume a stopped study. `rigctl study report OUT` draws success and error "
        "against each parameter to PNG. Exit 0 all cases ran ok, 1 some could not run, 2 bad "
        "spec, 3 interrupted.",
    )
    p.add_argument("spec", metavar="SPEC.toml|report",
                   help="the study spec, or `report` followed by a study's results folder")
    p.add_argument("folder", nargs="?", metavar="FOLDER",
                   help="with `report`: the study's results folder")
    p.add_argument("-o", "--out", metavar="PATH",
                   help="the results folder (default ./study-NAME), or with `report` the PNG "
                   "(default FOLDER/report.png)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N",
                       help="local Dask workers, one process each (default: one per core)")
    where.add_argument("--scheduler", metavar="tcp://HOST:8786",
                       help="a running Dask scheduler (its workers need rigctl and the spec's "
                       "files at the same paths)")
    where.add_argument("--serial", action="store_true",
                       help="run the cases one after another in this process (no Dask)")
    p.add_argument("--retry-failed", action="store_true",
                   help="also run again the cases in the table that did not run ok")
    p.add_argument("--json", action="store_true", help="end with one JSON object on stdout")
    p.set_defaults(func=cmd_study)


def cmd_study(args: argparse.Namespace) -> int:
    if args.spec == "report":
        return _cmd_report(args)
    if args.folder is not None:
        raise ConfigError(f"{args.folder}: one spec per study (a folder only follows `report`)")
    from rigctl.apps.study.cases import parse_planner
    from rigctl.apps.study.execution import run_study
    from rigctl.apps.study.spec import load_spec, options_argv

    spec = load_spec(args.spec)
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: at least 1, got {args.workers}")
    if args.scheduler is not None and not re.fullmatch(r"(tcp|tls)://[^\s:/]+:\d+", args.scheduler):
        raise ConfigError(f"--scheduler {args.scheduler}: expected tcp://HOST:PORT")
    if spec.command != "execute":  # every case's options checked by the planner's parser first
        for case in spec.cases:
            try:
                parse_planner(spec.command.split() + options_argv(case.options, spec.folder)
                              + ["-o", "/dev/null"] * (spec.command not in ("plan coverage",
                                                                            "plan reachable")))
            except ValueError as err:
                raise ConfigError(f"{args.spec}: case {case.parameters} seed {case.seed}: "
                                  f"{err}") from None
    out = Path(args.out) if args.out else Path(f"study-{spec.name}")
    try:
        outcome = run_study(spec, out, workers=args.workers, scheduler=args.scheduler,
                            serial=args.serial, retry_failed=args.retry_failed)
    except KeyboardInterrupt:
        print(f"study {spec.name}: interrupted; the cases finished are in {out / 'results.parquet'}"
              "; the same command resumes", file=sys.stderr)
        return EXIT_FAULT
    except OSError as err:  # a scheduler that does not answer
        raise ConfigError(f"--scheduler {args.scheduler}: {err}") from None
    print(f"study {spec.name}: {outcome.ran} cases run in {outcome.wall_s:.1f} s "
          f"({outcome.skipped} already done, {outcome.not_ok} not ok) -> "
          f"{out / 'results.parquet'}", file=sys.stderr)
    if args.json:
        print(json.dumps({"study": spec.name, "table": str(out / "results.parquet"),
                          "cases": outcome.cases, "skipped": outcome.skipped, "ran": outcome.ran,
                          "not_ok": outcome.not_ok, "wall_s": round(outcome.wall_s, 3),
                          "workers": outcome.workers, "dashboard": outcome.dashboard}))
    return EXIT_OK if outcome.not_ok == 0 else EXIT_NOT_REACHED


def _cmd_report(args: argparse.Namespace) -> int:
    from rigctl.apps.study.report import report

    if args.folder is None:
        raise ConfigError("report: name the study's results folder: rigctl study report FOLDER")
    folder = Path(args.folder)
    if not folder.is_dir():
        raise ConfigError(f"{folder}: no such results folder")
    png = Path(args.out) if args.out else folder / "report.png"
    if png.suffix.lower() != ".png":
        raise ConfigError(f"--out {png}: the report is a PNG (name it .png)")
    drawn = report(folder, png)
    print(f"study report: {drawn['cases_ok']} cases -> {png}", file=sys.stderr)
    if args.json:
        print(json.dumps(drawn))
    return EXIT_OK
