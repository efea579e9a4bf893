"""Paths as the command line takes them, checked where they come in (argparse `type=`), so that a
bad one is one line naming it and exit 2 before anything is done, never a traceback from deep
inside a command: a file to read exists, is a file, can be read, is not empty and (for text) is
UTF-8; a file to write has a writable folder to go in; a folder is not a file.

`coordinates_are_values(parser)` makes "-8,-6" an option's value, not an option.
"""

from __future__ import annotations

import argparse
import os
import re
from collections.abc import Callable
from pathlib import Path

from rigctl.core.errors import RigError


class BadPath(RigError):
    """A path argument that cannot be used. Not a ValueError, so that argparse lets it through
    (it would make a usage message of it) to `rigctl.apps.cli.main`, which prints it as bad input."""


def input_file(what: str, *, text: bool = True) -> Callable[[str], str]:
    """An argparse type: a file to read (`what`: "plan", "rig file", ...), UTF-8 unless `text`
    is false."""

    def check(value: str) -> str:
        path = Path(value)
        if not path.exists():
            raise BadPath(f"{what} {value}: no such file")
        if path.is_dir():
            raise BadPath(f"{value}: is a folder, not a {what}")
        try:
            data = path.read_bytes()
        except OSError as err:
            raise BadPath(f"{what} {value}: cannot read: {err.strerror}") from None
        if not data.strip():
            raise BadPath(f"{value}: empty file, not a {what}")
        if text:
            try:
                data.decode("utf-8")
            except UnicodeDecodeError:
                raise BadPath(f"{value}: not a {what}: not UTF-8 text (an image or other binary "
                              "file?)") from None
        return value

    return check


def output_file(what: str) -> Callable[[str], str]:
    """An argparse type: a file to write (`what` names it)."""

    def check(value: str) -> str:
        path = Path(value)
        if path.is_dir():
            raise BadPath(f"{value}: is a folder; give the {what} file to write")
        _writable(value, path.resolve().parent, f"write the {what}")
        return value

    return check


def folder(what: str, *, write: bool = False) -> Callable[[str], str]:
    """An argparse type: a folder of `what`; with `write` it may be missing (it is made then)."""

    def check(value: str) -> str:
        path = Path(value)
        if path.exists() and not path.is_dir():
            raise BadPath(f"{value}: is a file, not a folder of {what}")
        if write:
            _writable(value, path if path.is_dir() else path.resolve().parent,
                      f"write the {what} there")
        elif not path.is_dir():
            raise BadPath(f"{value}: no such folder of {what}")
        return value

    return check


def _writable(value: str, where: Path, doing: str) -> None:
    if not where.is_dir():
        raise BadPath(f"{value}: cannot {doing}: folder {where} does not exist")
    if not os.access(where, os.W_OK):
        raise BadPath(f"{value}: cannot {doing}: folder {where} is not writable")


# "-8,-6", "-8.5,6,1" or "-5,0;5,0" (argparse itself takes only "-8" and "-.5" for numbers)
_NUMBERS = re.compile(r"^-\.?\d[\d.eE+-]*([,;]\s*[-+]?\.?\d[\d.eE+-]*)*;?$")


def coordinates_are_values(parser: argparse.ArgumentParser) -> None:
    """Let `parser` take "-8,-6" as an option's value, as it takes `--start=-8,-6`. argparse has
    no public switch for it: this sets the pattern it tells negative numbers by."""
    parser._negative_number_matcher = _NUMBERS
