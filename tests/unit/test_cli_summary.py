"""`rigctl --help`, `rigctl` alone and `--version` are answered by the top level alone
(`rigctl.apps.cli.commands`, issue 38: `--help` within 0.3 s): with the very text and exit status
of the whole parser (`rigctl.apps.cli.main.build_parser`, every command's module loaded: the way
it was answered before), and without importing a command's module. The top level alone also
answers a misspelt command as the whole parser does (its list of commands is the whole parser's),
though the whole parser is the one that answers it."""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys

import pytest

from rigctl.apps.cli.commands import command_word, summary_parser
from rigctl.apps.cli.main import build_parser


@pytest.fixture(scope="module")
def whole():
    return build_parser()


def answer(parser, argv: list[str]) -> tuple[object, str, str]:
    """(exit status, stdout, stderr) of parsing argv."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
            pytest.raises(SystemExit) as end:
        parser.parse_args(argv)
    return end.value.code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("argv", [["--help"], ["-h"], ["-v", "--help"], [], ["-v"], ["nosuch"],
                                  ["--version"], ["-v", "--version"], ["--bogus"], ["-"], ["--"]])
def test_the_top_level_alone_answers_as_the_whole_parser(whole, argv, monkeypatch):
    for columns in ("100", "60"):  # the help is wrapped to the terminal's width
        monkeypatch.setenv("COLUMNS", columns)
        code, out, err = answer(summary_parser(), argv)
        assert (code, out, err) == answer(whole, argv), argv
        assert out or err


def test_the_command_is_the_first_word_that_is_not_an_option():
    for argv in (["--help"], ["-h"], ["-v", "--help"], [], ["-v"], ["--version"], ["--bogus"],
                 ["--"]):
        assert command_word(argv) is None, argv  # the top level alone answers these
    assert command_word(["estop"]) == "estop"
    assert command_word(["-v", "plan", "rrt", "--help"]) == "plan"
    assert command_word(["--", "execute", "p.json"]) == "execute"
    assert command_word(["nosuch", "execute"]) == "nosuch"  # argparse's COMMAND is the first word
    assert command_word(["-"]) == "-"
    assert command_word(["--help", "execute"]) == "execute"  # the whole parser answers it


def test_help_imports_no_command_module():
    code = ("import sys\nfrom rigctl.apps.cli import main\ntry:\n    main(['--help'])\n"
            "except SystemExit:\n    pass\nprint(sorted(m for m in sys.modules if m in "
            "('numpy', 'pydantic', 'cv2', 'rigctl.apps.cli.main', 'rigctl.core.config')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.splitlines()[-1] == "[]"
