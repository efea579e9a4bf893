"""The `rigctl` command line: one module per group of commands (`main` holds the parser).

`main` here answers an argv that gives no command (`rigctl --help`, `rigctl --version`, `rigctl`
alone) from `commands`, the top level alone, before the commands' modules are imported (they take
half a second to load); everything else goes to `rigctl.apps.cli.main`."""

import sys


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    from rigctl.apps.cli.commands import command_word, summary_parser

    if command_word(args) is None:
        try:
            summary_parser().parse_args(args)
        except SystemExit as end:  # help, version or a usage error, printed: its exit status
            return end.code if isinstance(end.code, int) else 1
    from rigctl.apps.cli.main import main as run

    return run(argv)


def build_parser():
    from rigctl.apps.cli.main import build_parser as build

    return build()


__all__ = ["build_parser", "main"]
