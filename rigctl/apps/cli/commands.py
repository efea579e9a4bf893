"""The `rigctl` top level without its commands' modules: the parser's own options, description
and epilog (one definition, used by the full parser in `rigctl.apps.cli.main` too) and the list of
commands with their one-line help, so that `rigctl --help`, `--version` and `rigctl` alone are
answered in a few tens of milliseconds instead of the half second the commands' modules (numpy,
pydantic, OpenCV, the planners) take to import.

`command_word(argv)` is the word argv gives as its command, if any; only when there is none does
`rigctl.apps.cli` skip building the full parser, and then `summary_parser()` answers: an argv
without a command ends in the top level's help, its version or its usage error, which need nothing
but the names and lines below. Any word, even one missing here, goes to the full parser, so a
command added without its line here still runs. `COMMANDS` repeats the `help=` of each command's
`add_parser` in the order they are added; tests/unit/test_cli_summary.py compares the two parsers'
help and errors, so a command added, renamed or re-worded without its line here fails there.
"""

from __future__ import annotations

import argparse

DESCRIPTION = ("Run magnetic micro-robot rigs: execute plans on real or emulated hardware, "
               "validate and write plans, start emulated benches.")
EPILOG = ("Exit status: 0 success, 1 goal not reached / not solved, 2 bad input (nothing "
          "energised), 3 device fault. Start with: rigctl execute "
          "plans/examples/fig4-two-magnets.json")

# each command's one line in `rigctl --help`, in the order the full parser adds them
COMMANDS = {
    "execute": "run a plan on a rig (the emulated bench unless --rig names one)",
    "validate": "check a plan file; name what is wrong",
    "schema": "print the JSON Schema of a plan or a rig file",
    "emulate": "start an emulated bench and write the rig file for it",
    "calibrate": "calibrate a device of a rig (the camera, the coils' field)",
    "plan": "write plans with a planner (rrt) or measure a tree (coverage)",
    "daemon": "run the long-lived service: ZeroMQ commands and telemetry",
    "status": "ask a running daemon (or a rig's owner) for its state, run and devices",
    "hold": "hold the rig at a manual setpoint (a field, drive values, a pose), or release",
    "load": "give a plan to a running daemon, checked against its rig (prints its id)",
    "estop": "emergency stop: every output of the rig to zero at once",
    "doctor": "reach every device of a rig without energising anything",
    "pause": "pause the run at the end of the step it drives (--now: at once)",
    "resume": "resume a paused run",
    "abort": "end the run: ramp down cleanly",
    "reset": "after an e-stop or a fault: back to idle (the daemon)",
    "watch": "a live view of the rig: state, channels, stream timing, agents, faults",
    "keys": "CURVE keys for the daemon and its operators",
    "runs": "list run records (local folder, or a daemon's with --connect)",
    "report": "draw a run: planned vs measured paths, currents (PNG)",
    "init": "write a commented rig file for a real rig (the seed papers' hardware)",
    "faults": "fault campaign: every emulated fault at every run phase, on every rig",
    "study": "sweeps and campaigns: planner or emulated-run cases on Dask, one Parquet table",
    "service": "install the daemon as a systemd service (unit and system user)",
    "field": "the field (mT) and gradient an electromagnet rig makes at a point, or the currents "
             "for a wanted field",
    "teleop-save": "write a teleoperation session out as a plan that replays it",
    "view": "open a run record in the browser: video, overlays, channels, events",
}


class _Version(argparse.Action):
    """`--version`: the installed package's version, read (importlib.metadata) only when asked."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS,
                 help: str = "show program's version number and exit") -> None:
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0,
                         help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: str | None = None) -> None:
        import rigctl

        print(f"rigctl {rigctl.__version__}")
        parser.exit()


def top_parser() -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    """The top-level parser and its (empty) COMMAND subparsers."""
    parser = argparse.ArgumentParser(prog="rigctl", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    return parser, sub


def summary_parser() -> argparse.ArgumentParser:
    """The top level with each command's line and nothing of it: for an argv naming none."""
    parser, sub = top_parser()
    for name, line in COMMANDS.items():
        sub.add_parser(name, help=line)
    return parser


def command_word(argv: list[str]) -> str | None:
    """The word argv gives as its command, known or not (the top level's options take no value:
    the first word that is not an option), None if it gives none."""
    for i, word in enumerate(argv):
        if word == "--":
            return argv[i + 1] if i + 1 < len(argv) else None
        if not word.startswith("-") or word == "-":
            return word
    return None
