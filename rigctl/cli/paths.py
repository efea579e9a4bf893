"""Paths as the command line takes them, checked where they come in (argparse `type=`), so that a
bad one is one line naming it and exit 2 before anything is done, never a traceback from deep
inside a command: a file to read exists, is a file, can be read, is not empty and (for text) is
UTF-8; a file to write has a folder to go in; a folder is not a file.

Coordinates as options take them (`--start -8,-6`, `--markers '-5,0;5,0'`) are values, not
options: `coordinates_are_values(parser)` tells argparse so.
"""

from __future__ import annotations

import argparse
import os
import re
from collections.abc import Callable
from pathlib import Path

from rigctl.errors import RigError


class BadPath(RigError):
    """A path argument that cannot be used. Not a ValueError, so that argparse lets it through
    (it would make a usage message of it) to `rigctl.cli.main`, which prints it as bad input."""


def _describe(what: str) -> str:
    return f"{what} " if what else ""


def input_file(what: str, *, text: bool = True) -> Callable[[str], str]:
    """An argparse type: a file to read (`what`: "plan", "rig file", ...); UTF-8 text unless
    `text` is false. Returns the path as given."""

    def check(value: str) -> str:
        path = Path(value)
        if not path.exists():
            raise BadPath(f"{_describe(what)}{value}: no such file")
        if path.is_dir():
            raise BadPath(f"{value}: is a folder, not a {what or 'file'}")
        try:
            data = path.read_bytes()
        except OSError as err:
            raise BadPath(f"{_describe(what)}{value}: cannot read: {err.strerror}") from None
        if not data.strip():
            raise BadPath(f"{value}: empty file, not a {what or 'file'}")
        if text:
            try:
                data.decode("utf-8")
            except UnicodeDecodeError:
                raise BadPath(f"{value}: not a {what}: not UTF-8 text (an image or other binary "
                              "file?)") from None
        return value

    return check


def output_file(what: str) -> Callable[[str], str]:
    """An argparse type: a file to write (`what` names it); its folder exists and is writable."""

    def check(value: str) -> str:
        path = Path(value)
        if path.is_dir():
            raise BadPath(f"{value}: is a folder; give the {what} file to write")
        folder = path.resolve().parent
        if not folder.is_dir():
            raise BadPath(f"{value}: cannot write the {what}: folder {folder} does not exist")
        if not os.access(folder, os.W_OK):
            raise BadPath(f"{value}: cannot write the {what}: folder {folder} is not writable")
        return value

    return check


def folder(what: str, *, write: bool = False) -> Callable[[str], str]:
    """An argparse type: a folder (`what` names it). It may be missing when `write` (it is made
    then) if the folder it would go in exists; it must be writable when `write`."""

    def check(value: str) -> str:
        path = Path(value)
        if path.exists() and not path.is_dir():
            raise BadPath(f"{value}: is a file, not a folder of {what}")
        if not write:
            if not path.is_dir():
                raise BadPath(f"{value}: no such folder of {what}")
            return value
        existing = path if path.is_dir() else path.resolve().parent
        if not existing.is_dir():
            raise BadPath(f"{value}: cannot make the folder of {what}: {existing} does not exist")
        if not os.access(existing, os.W_OK):
            raise BadPath(f"{value}: the folder of {what} {existing} is not writable")
        return value

    return check


# a value such as "-8,-6", "-8.5,6,1" or "-5,0;5,0" (argparse itself knows "-8" and "-.5" only)
_NUMBERS = re.compile(r"^-\.?\d[\d.eE+-]*([,;]\s*[-+]?\.?\d[\d.eE+-]*)*[;]?$")


def coordinates_are_values(parser: argparse.ArgumentParser) -> None:
    """Let `parser` take "-8,-6" (and "-8") as an option's value, as `--start=-8,-6` already is.
    argparse has no public switch for it: this sets the pattern it tells numbers by."""
    parser._negative_number_matcher = _NUMBERS
