"""The `rigctl` command line: one module per group of commands (`main` holds the parser)."""

from rigctl.apps.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
