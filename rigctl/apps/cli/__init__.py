"""The `rigctl` command line: one module per group of commands (`main` holds the parser).

`main` here answers `rigctl --version` before the parser and the commands' modules are imported
(they take half a second to load); everything else goes to `rigctl.apps.cli.main`."""

import sys


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args == ["--version"]:
        import rigctl

        print(f"rigctl {rigctl.__version__}")
        return 0
    from rigctl.apps.cli.main import main as run

    return run(argv)


def build_parser():
    from rigctl.apps.cli.main import build_parser as build

    return build()


__all__ = ["build_parser", "main"]
