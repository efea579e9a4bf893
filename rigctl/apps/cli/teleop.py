"""`rigctl teleop-save RUN -o PLAN.json`: a teleoperation session's record written out as a plan
that replays it (`rigctl.apps.teleop_save`); what the plan differs in, one line each on stderr."""

from __future__ import annotations

import argparse
import json
import sys

from rigctl.apps.cli.paths import input_file, output_file
from rigctl.core.errors import EXIT_OK, ConfigError


def _cmd_teleop_save(args: argparse.Namespace) -> int:
    from rigctl.apps.report import find_run
    from rigctl.apps.teleop_save import teleop_plan
    from rigctl.plans.schema import dump_plan

    workspace = None
    if args.workspace is not None:
        try:
            data = json.loads(open(args.workspace).read())
        except (OSError, ValueError) as err:
            raise ConfigError(f"--workspace {args.workspace}: not a readable JSON file ({err})") \
                from None
        workspace = data.get("workspace", data) if isinstance(data, dict) else None
        if not isinstance(workspace, dict):
            raise ConfigError(f"--workspace {args.workspace}: no workspace in it")
    plan, notes = teleop_plan(find_run(args.run, args.runs), workspace=workspace,
                              radius_mm=args.radius)
    with open(args.output, "w") as out:
        out.write(dump_plan(plan))
    print(f"wrote {args.output}: a {plan.kind} plan for a {plan.rig} rig, {plan.size}")
    for note in notes:
        print(f"  differs: {note}", file=sys.stderr)
    return EXIT_OK


def register_teleop(sub) -> None:
    p = sub.add_parser(
        "teleop-save", help="write a teleoperation session out as a plan that replays it",
        description="The moves of a steering session (rigctl daemon's teleop: its record's "
        "inputs) as a global-moves plan of the rig's kind, the agents starting where they were "
        "first tracked and aiming where they were last; docs/teleoperation.md says what a plan "
        "cannot replay exactly.")
    p.add_argument("run", help="the session's run record folder, a run id inside --runs, or "
                   "`latest`")
    p.add_argument("--runs", default="runs", help="run records folder (default ./runs)")
    p.add_argument("-o", "--output", required=True, type=output_file("plan"),
                   help="the plan file to write")
    p.add_argument("--workspace", type=input_file("workspace"), metavar="FILE.json",
                   help="the plan's workspace: a plan file's, or a workspace document (default: "
                   "the box of the tracked positions grown by 50 mm, no obstacles)")
    p.add_argument("--radius", type=float, metavar="MM",
                   help="the agents' radius (default: the rig file's magnets')")
    p.set_defaults(func=_cmd_teleop_save)
