"""Log lines for a terminal and for the systemd journal.

On a terminal every line carries its time. Under systemd, when stderr is the journal's stream
(`$JOURNAL_STREAM` names it), every line starts with its sd-daemon priority instead (`<3>` error,
`<4>` warning, `<6>` info, `<7>` debug) and no time, which the journal adds itself; so
`journalctl -p warning` shows the warnings and errors alone.
"""

from __future__ import annotations

import logging
import os
import sys

_TEXT = "%(levelname)s %(name)s: %(message)s"


def priority(level: int) -> int:
    """The syslog priority of a logging level (sd-daemon(3))."""
    for floor, value in ((logging.CRITICAL, 2), (logging.ERROR, 3), (logging.WARNING, 4),
                         (logging.INFO, 6)):
        if level >= floor:
            return value
    return 7


class JournalFormatter(logging.Formatter):
    """Each line of a record (a traceback's too) prefixed with the record's priority."""

    def __init__(self) -> None:
        super().__init__(_TEXT)

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines())


def formatter(journal: bool) -> logging.Formatter:
    return JournalFormatter() if journal else logging.Formatter("%(asctime)s " + _TEXT)


def stderr_is_journal() -> bool:
    """True when stderr is the stream systemd connected to the journal ($JOURNAL_STREAM is its
    device:inode; a child of the service writing elsewhere inherits the variable, not the stream)."""
    try:
        st = os.fstat(sys.stderr.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    return os.environ.get("JOURNAL_STREAM") == f"{st.st_dev}:{st.st_ino}"


def configure(verbose: bool, service: bool) -> None:
    """Log to stderr: debug with `verbose`, else info for a service, warnings for other commands."""
    handler = logging.StreamHandler()
    handler.setFormatter(formatter(stderr_is_journal()))
    level = logging.DEBUG if verbose else logging.INFO if service else logging.WARNING
    logging.basicConfig(level=level, handlers=[handler])
