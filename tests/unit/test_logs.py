"""Log lines: a time on a terminal; the journal's priority prefix, and no time, under systemd."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
import tempfile

import pytest

from rigctl.core.logs import formatter

# sd-daemon(3): the syslog priorities
PRIORITIES = {logging.DEBUG: "<7>", logging.INFO: "<6>", logging.WARNING: "<4>",
              logging.ERROR: "<3>", logging.CRITICAL: "<2>"}


def _record(level: int, message: str = "supply %s off", exc_info=None) -> logging.LogRecord:
    return logging.LogRecord("rigctl.apps.daemon", level, __file__, 1, message, ("A",), exc_info)


@pytest.mark.parametrize("level", list(PRIORITIES))
def test_journal_lines_start_with_their_priority_and_carry_no_time(level):
    line = formatter(journal=True).format(_record(level))
    name = logging.getLevelName(level)
    assert line == f"{PRIORITIES[level]}{name} rigctl.apps.daemon: supply A off"


@pytest.mark.parametrize("level", list(PRIORITIES))
def test_terminal_lines_start_with_their_time_and_no_priority(level):
    line = formatter(journal=False).format(_record(level))
    assert re.fullmatch(rf"\d{{4}}-\d\d-\d\d \d\d:\d\d:\d\d,\d{{3}} {logging.getLevelName(level)} "
                        r"rigctl\.apps\.daemon: supply A off", line), line


def test_every_line_of_a_traceback_keeps_the_priority_in_the_journal():
    try:
        raise ValueError("bad reply")
    except ValueError:
        record = _record(logging.ERROR, "supply %s failed", exc_info=sys.exc_info())
    lines = formatter(journal=True).format(record).splitlines()
    assert len(lines) > 3
    assert all(line.startswith("<3>") for line in lines), lines
    assert lines[-1] == "<3>ValueError: bad reply"


LOG_ONE_WARNING = ("import logging; from rigctl.core.logs import configure; configure(False, True); "
                   "logging.getLogger('rigctl.x').warning('hot')")


def _stderr_of_configured_process(journal: bool) -> str:
    """A process that configures logging and warns once, its stderr a file (as the journal's
    stream would be a socket); $JOURNAL_STREAM names that file, or another one."""
    with tempfile.TemporaryFile("w+") as err, tempfile.TemporaryFile() as elsewhere:
        st = os.fstat((err if journal else elsewhere).fileno())
        env = dict(os.environ, JOURNAL_STREAM=f"{st.st_dev}:{st.st_ino}")
        subprocess.run([sys.executable, "-c", LOG_ONE_WARNING], stderr=err, env=env, check=True)
        err.seek(0)
        return err.read()


def test_configure_picks_the_journal_format_only_when_stderr_is_the_journal_stream():
    assert _stderr_of_configured_process(journal=True) == "<4>WARNING rigctl.x: hot\n"
    # a process that inherited $JOURNAL_STREAM but writes elsewhere (a terminal, a file) keeps times
    assert re.fullmatch(r"\d{4}-\d\d-\d\d [\d:,]+ WARNING rigctl\.x: hot\n",
                        _stderr_of_configured_process(journal=False))
