"""`rigctl --help` and the commands' own `--help`, as a user runs them, print what the whole
parser (`build_parser`, every command's module loaded: the way `--help` was answered before issue
38's fast top level) formats for them."""

from __future__ import annotations

import argparse

import pytest

from rigctl.apps.cli.main import build_parser
from rigctl.apps.testing import run_rigctl


def parser_for(words: list[str]) -> argparse.ArgumentParser:
    parser = build_parser()
    for word in words:
        parser = parser._subparsers._group_actions[0].choices[word]
    return parser


@pytest.mark.parametrize("words", [[], ["emulate"], ["plan", "rrt"], ["estop"]],
                         ids=lambda w: " ".join(w) or "top")
def test_help_is_the_whole_parsers(words, tmp_path, monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")
    done = run_rigctl(*words, "--help", cwd=tmp_path)
    assert done.returncode == 0 and done.stderr == ""
    assert done.stdout == parser_for(words).format_help()
