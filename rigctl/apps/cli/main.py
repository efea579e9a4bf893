"""The `rigctl` command line: execute plans, validate them, plan, and run emulated benches.

Exit status, for every command: 0 success (for `execute`: every agent reached its goal), 1 the
job ran but did not succeed (goal missed, plan not solved), 2 bad input (malformed plan or rig file,
a limit the plan would break; nothing was energised), 3 a device fault stopped the run.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from rigctl.apps.cli.calibrate_field import (
    add_coil_error_flags,
    add_field_flags,
    cmd_calibrate_field,
)
from rigctl.apps.cli.commands import top_parser
from rigctl.apps.cli.daemon import register as register_daemon
from rigctl.apps.cli.execute import (
    _add_mismatch_flags,
    cmd_execute,
    refuse_foreign_bench_flags,
)
from rigctl.apps.cli.faults import register_faults
from rigctl.apps.cli.field import register_field
from rigctl.apps.cli.init import register_init
from rigctl.apps.cli.paths import (
    BadPath,
    coordinates_are_values,
    folder,
    input_file,
    output_file,
)
from rigctl.apps.cli.plan import points_mm
from rigctl.apps.cli.plan import register as register_planners
from rigctl.apps.cli.service import register_service
from rigctl.apps.cli.teleop import register_teleop
from rigctl.apps.cli.view import register_view
from rigctl.apps.study.cli import register as register_study
from rigctl.core.config import load_rig
from rigctl.core.errors import (
    EXIT_BAD_INPUT,
    EXIT_FAULT,
    EXIT_OK,
    ConfigError,
    LimitError,
    PlanError,
    RigError,
    interrupt_name,
)
from rigctl.core.extras import EXTRAS, MissingExtra, need
from rigctl.core.logs import configure as configure_logs
from rigctl.core.registry import entry_point_names

log = logging.getLogger("rigctl")


def _add_bench_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("emulated bench")
    g.add_argument("--world", choices=["rolling", "pair"], default=None,
                   help="six-coil: rolling magnets (seed 000, default) or two interacting agents "
                   "at a liquid surface (seed 002; pair-formation plans pick it themselves)")
    g.add_argument("--firmware", choices=["python", "simavr"], default=None,
                   help="coil-board: emulate the board's firmware in Python (default) or run the "
                   "real AVR firmware in simavr")
    g.add_argument("--truth", metavar="FILE.yaml|NAME", default=None,
                   help="six-coil: the world's true field is this mag_manip MPEM calibration file "
                   "(or a station: helmholtz-triad, octomag-like, navion-like, built as "
                   "--coil-seed says); one supply per coil of it, the rig file draws the coils")


def _cmd_calibrate_camera(args: argparse.Namespace) -> int:
    """Calibrate the rig's camera and write the rig file back with the calibration in it."""
    from rigctl.core.config import dump_rig
    from rigctl.vision.calibration import (
        boundary_corners_mm,
        calibrate_camera,
        floor_corners_mm,
    )

    rig = load_rig(args.rig)
    if rig.camera is None:
        raise ConfigError(f"{args.rig}: the rig has no [camera] table to calibrate")
    options: dict = {}
    if args.plan is not None:
        from rigctl.plans.schema import load_plan
        from rigctl.plans.workspace import Workspace

        plan = load_plan(args.plan)
        if not hasattr(plan.workspace, "boundary"):
            raise ConfigError("an image workspace has no boundary corners: use --markers")
        # the corners the camera sees: the free floor's (a maze's walls hide the boundary's)
        options["corners_mm"] = floor_corners_mm(Workspace.from_spec(plan.workspace),
                                                 len(boundary_corners_mm(plan.workspace.boundary)))
        _show_workspace_to_emulated_camera(rig, plan)
    elif args.markers is not None:
        if args.marker_radius is None:
            raise ConfigError("--markers needs --marker-radius")
        options["markers_mm"] = points_mm([p for p in args.markers.split(";") if p.strip()],
                                          "--markers")
        options["marker_radius_mm"] = args.marker_radius
    else:
        raise ConfigError("give --plan (workspace corners) or --markers 'x,y;x,y;...'")
    calibration = calibrate_camera(rig.camera.url, stamped=rig.camera.stamped,
                                   timeout_s=rig.camera.timeout_s, **options)
    camera = rig.camera.model_copy(update={"calibration": calibration})
    out = Path(args.output or args.rig)
    out.write_text(dump_rig(rig.model_copy(update={"camera": camera})))
    print(f"camera calibrated; written to {out}")
    return EXIT_OK


def _show_workspace_to_emulated_camera(rig, plan) -> None:
    """On an emulated bench, lay the plan's workspace on the floor its camera sees (a real rig's
    floor has its walls; the emulated one shows nothing until told what is there)."""
    if rig.emulation is None:
        return
    from rigctl.emulators.backdoor import BackdoorClient
    from rigctl.run.agents import portable_workspace

    with BackdoorClient.of(rig.emulation) as backdoor:
        backdoor.request("floor", workspace=portable_workspace(plan))
    print(f"emulated bench: the workspace of {plan.source} laid on its floor",
          file=sys.stderr)


def _cmd_validate(args: argparse.Namespace) -> int:
    """The plan's own checks (schema, geometry, its planner's model), then what the daemon's
    `load` and `rigctl execute` run to refuse a plan on a rig (`rigctl.rigs.prepare_run`): on the
    rig of --rig, else on the rig its rig kind runs without one (the emulated bench `rigctl
    execute PLAN` starts), so that validate passes no plan that load or execute refuses."""
    from rigctl.plans.checks import check_plan, simulate
    from rigctl.plans.schema import dump_plan, load_plan
    from rigctl.rigs import prepare_run, rig_kind

    if args.rig is not None and args.simulate:
        raise ConfigError("--rig and --simulate: give one (certify the plan, or fill its states)")
    if args.json and args.rig is None:
        raise ConfigError("--json: the certificate's JSON needs --rig")
    plan = load_plan(args.file)
    if args.simulate:
        plan = simulate(plan)
    check_plan(plan)
    if args.rig is not None:
        return _validate_on_rig(args, plan)
    kind = rig_kind(plan.rig)
    if kind.bench_rig is None:  # a rig kind registered without one: its own rules need its rig
        raise ConfigError(f"a {kind.name} plan is checked on a rig: give --rig RIG.toml")
    prepare_run(plan, kind.bench_rig(), runs_dir="runs")
    if args.simulate:
        text = dump_plan(plan)
        if args.output:
            Path(args.output).write_text(text)
        else:
            print(text)
    print(f"OK: {args.file}: {plan.kind} plan for a {plan.rig} rig, {plan.size}; every check "
          f"passed on the emulated {plan.rig} bench (--rig RIG.toml: on yours)",
          file=sys.stderr if args.simulate and not args.output else sys.stdout)
    return EXIT_OK


def _validate_on_rig(args: argparse.Namespace, plan) -> int:
    """`validate PLAN --rig RIG`: the run that `execute` would build, with no I/O, and its
    pre-flight certificate (every check, its margin); exit 2 if refused."""
    from rigctl.rigs import prepare_run
    from rigctl.run.certificate import CertificateRefused

    rig = load_rig(args.rig)
    try:
        certificate = prepare_run(plan, rig, runs_dir="runs").certificate
    except CertificateRefused as refused:
        _show_certificate(args, refused.certificate)
        raise
    _show_certificate(args, certificate)
    return EXIT_OK


def _show_certificate(args: argparse.Namespace, certificate) -> None:
    if args.json:
        print(json.dumps(certificate.as_dict()))
    else:
        print("\n".join(certificate.lines()))


def _cmd_schema(args: argparse.Namespace) -> int:
    if args.what == "plan":
        from rigctl.plans.schema import plan_json_schema

        schema = plan_json_schema()
    else:
        from rigctl.core.config import rig_json_schema

        schema = rig_json_schema()
    print(json.dumps(schema, indent=2))
    return EXIT_OK


def _cmd_emulate(args: argparse.Namespace) -> int:
    from rigctl.emulators.base import bench_class

    refuse_foreign_bench_flags(args, args.kind, f"the emulated {args.kind} bench")
    # devices answer within 0.1 ms of a request even while another thread of the bench is busy
    # in Python (the camera rendering a frame, the world stepping): a real device has no GIL
    sys.setswitchinterval(1e-4)
    return bench_class(args.kind).emulate_cli(args)


def build_parser() -> argparse.ArgumentParser:
    """The whole parser: every command's (`commands.summary_parser` is its top level alone)."""
    parser, sub = top_parser()

    p = sub.add_parser(
        "execute", help="run a plan on a rig (the emulated bench unless --rig names one)",
        description="Run a plan. Without --rig, an emulated bench of the plan's rig kind is started "
        "on loopback, so nothing real can be energised. Every limit is checked before anything is "
        "switched on. Prints progress, a summary, and writes a run record directory.",
    )
    p.add_argument("plan", type=input_file("plan"), help="plan file (JSON, see `rigctl schema plan`)")
    p.add_argument("--rig", type=input_file("rig file"),
                   help="rig file (TOML) for real hardware or one written by `rigctl emulate`")
    p.add_argument("--connect", metavar="ENDPOINT",
                   help="submit to a running `rigctl daemon` (e.g. tcp://127.0.0.1:5555) and follow it")
    p.add_argument("--json", action="store_true", help="end the output with one JSON line")
    p.add_argument("--runs", default="runs", type=folder("run records", write=True),
                   help="directory for run records (default: ./runs)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.add_argument("--open-loop", action="store_true",
                   help="do not close the loop with the rig's camera (default: closed loop "
                   "whenever the rig has a camera); depm: no Hall correction at the holds")
    p.add_argument("--agnostic", action="store_true",
                   help="depm rig: run the magnetic-agnostic baseline (straight joint-space moves)")
    p.add_argument("--time-scale", type=float, metavar="K",
                   help="depm emulated bench only: run its clock K times faster than real time")
    _add_mismatch_flags(p)
    add_coil_error_flags(p)
    _add_bench_flags(p)
    p.set_defaults(func=cmd_execute)

    p = sub.add_parser("validate", help="check a plan file; name what is wrong",
                       description="Check a plan against the schema and the workspace (agents in free "
                       "space, expected states consistent with the moves), then as `execute` and "
                       "the daemon's `load` check it on a rig (the rig kind's rules, every limit): "
                       "on --rig, else on the emulated bench of the plan's rig kind. Exit 2 if not "
                       "valid (docs/plans.md).")
    p.add_argument("file", type=input_file("plan"))
    p.add_argument("--simulate", action="store_true",
                   help="fill `expected` from the model and print the plan (or write it with -o)")
    p.add_argument("-o", "--output", type=output_file("plan"),
                   help="with --simulate: write the completed plan here")
    p.add_argument("--rig", type=input_file("rig file"),
                   help="also run the pre-flight on this rig: every limit (currents, voltages, "
                   "field, coil heating, links, arms, exposure) on the whole plan, nothing opened; "
                   "prints the certificate, exit 2 if refused (docs/certificate.md)")
    p.add_argument("--json", action="store_true", help="with --rig: the certificate as JSON")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("schema", help="print the JSON Schema of a plan or a rig file")
    p.add_argument("what", choices=["plan", "rig"])
    p.set_defaults(func=_cmd_schema)

    p = sub.add_parser("emulate", help="start an emulated bench and write the rig file for it",
                       description="Serve every device of the rig kind on its real protocol on "
                       "loopback, write a rig file pointing at them, run until interrupted.")
    p.add_argument("kind", choices=entry_point_names(), help="rig kind (the installed ones)")
    p.add_argument("--rig-out", default="bench.toml", type=output_file("rig file"),
                   help="where to write the rig file")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (default loopback); beyond loopback the backdoor "
                   "takes only the token written in the rig file (mode 0600)")
    _add_mismatch_flags(p)
    add_coil_error_flags(p)
    _add_bench_flags(p)
    p.set_defaults(func=_cmd_emulate)

    p = sub.add_parser("calibrate", help="calibrate a device of a rig (the camera, the coils' field)",
                       description="camera: map the camera's pixels to workspace mm from the "
                       "workspace's corners (a plan names them) or from dark round markers at known "
                       "places, and store the calibration in the rig file. field (six-coil): drive "
                       "current patterns, read the Hall probe, fit mag_manip's MPEM (--model mpem, "
                       "the default; its file: -o, default RIG-field.yaml) or each coil's loop "
                       "(--model loops), and name a calibration in the rig file; the allocator then "
                       "uses it.")
    p.add_argument("what", choices=["camera", "field"])
    p.add_argument("--rig", required=True, type=input_file("rig file"),
                   help="rig file with a [camera] table (camera) or a [field_probe] (field)")
    p.add_argument("--plan", type=input_file("plan"),
                   help="a plan whose workspace boundary the camera sees (corners)")
    p.add_argument("--markers", help="known marker centres, 'x,y;x,y;...' in mm")
    p.add_argument("--marker-radius", type=float, help="the markers' radius in mm")
    p.add_argument("-o", "--output", type=output_file("output file"),
                   help="camera: write the calibrated rig file here (default: --rig); field: the "
                   "calibration file")
    add_field_flags(p)
    coordinates_are_values(p)
    p.set_defaults(func=lambda args: (cmd_calibrate_field if args.what == "field"
                                      else _cmd_calibrate_camera)(args))

    register_planners(sub)
    register_daemon(sub)
    register_init(sub)
    register_faults(sub)
    register_study(sub)
    register_service(sub)
    register_field(sub)
    register_teleop(sub)
    register_view(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()  # imports what the commands need: Ctrl-C may come meanwhile
    except KeyboardInterrupt:
        print("interrupted while starting: nothing is running", file=sys.stderr)
        return EXIT_FAULT
    try:
        args = parser.parse_args(argv)
    except BadPath as err:  # before anything is done: one line (and the JSON error with --json)
        argv = sys.argv[1:] if argv is None else argv
        return _failed(argparse.Namespace(json="--json" in argv), "bad_input", f"error: {err}",
                       EXIT_BAD_INPUT)
    # a service's log is its record of what happened (state changes, loads, which threads run
    # at realtime priority): the daemon logs INFO; interactive commands only warnings
    configure_logs(args.verbose, service=args.func.__name__ == "_cmd_daemon")
    try:
        _need_extras(args)
        return args.func(args)
    except ModuleNotFoundError as err:  # an optional part reached by a path _need_extras missed
        if err.name not in EXTRAS:
            raise
        return _failed(args, "bad_input", f"error: {MissingExtra('this command', err.name)}",
                       EXIT_BAD_INPUT)
    except (PlanError, ConfigError, LimitError, BadPath) as err:
        return _failed(args, "bad_input", f"error: {err}", EXIT_BAD_INPUT)
    except RigError as err:
        return _failed(args, "fault", f"fault: {err}", EXIT_FAULT)
    except KeyboardInterrupt as interrupt:  # outside a run (a run ends as an abort, summarised)
        return _failed(args, "interrupted",
                       f"interrupted ({interrupt_name(interrupt)}): nothing is running", EXIT_FAULT)


def _need_extras(args: argparse.Namespace) -> None:
    """Refuse, before anything starts, a command whose optional part is not installed."""
    if args.func.__module__.startswith("rigctl.apps.study"):
        need("distributed", "rigctl study")
    if args.func.__name__ == "_cmd_daemon" and getattr(args, "console", None):
        need("aiohttp", "the console (rigctl daemon --console)")


def _failed(args: argparse.Namespace, code: str, line: str, status: int) -> int:
    """One line on stderr; with --json also the error as the one JSON document on stdout."""
    print(line, file=sys.stderr)
    if getattr(args, "json", False):
        print(json.dumps({"error": {"code": code, "message": line.split(": ", 1)[-1]}}))
    return status


if __name__ == "__main__":
    sys.exit(main())
