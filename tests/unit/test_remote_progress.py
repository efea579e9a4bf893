"""`rigctl execute PLAN --connect`: the progress of a run on a daemon is shown as a local `rigctl
execute` shows it (`rigctl.run.progress.Progress`): off a terminal a line per move (or segment) out
of how many and the planned time, a paused run said so, nothing more after the run ends. The
daemon's answers are scripted `status` replies of the shape docs/daemon-protocol.md gives."""

import io
import re

import pytest

from rigctl.apps.cli import daemon as daemon_cli

pytestmark = pytest.mark.quick

LINE = re.compile(r"^  (\S.*?) +([\d.]+) s / ([\d.]+) s planned$")


class ScriptedDaemon:
    """Answers `status` with the replies given, in order; the last one again once they run out."""

    def __init__(self, replies: list[dict]) -> None:
        self.replies = replies
        self.asked = 0

    def status(self) -> dict:
        self.asked += 1
        return self.replies[min(self.asked, len(self.replies)) - 1]


def running(move: int, unit: str, count: int, state: str = "running") -> dict:
    return {"state": state, "run": {"sample": 100 * (move + 1), "move": move, unit: count,
                                    "duration_s": 6.0}}


IDLE = {"state": "idle", "run": None, "last_run": {"run": "runs/x"}}


@pytest.fixture(autouse=True)
def no_wait(monkeypatch):
    monkeypatch.setattr(daemon_cli.time, "sleep", lambda s: None)  # the replies are scripted


def lines(out: io.StringIO) -> list[tuple[str, float]]:
    found = [LINE.match(line) for line in out.getvalue().splitlines()]
    assert all(found), out.getvalue()
    return [(m[1], float(m[3])) for m in found]


def test_a_line_per_move_with_the_planned_time():
    daemon = ScriptedDaemon([running(-1, "moves", 3), running(0, "moves", 3), running(0, "moves", 3),
                             running(1, "moves", 3), running(2, "moves", 3), IDLE])
    out = io.StringIO()
    status = daemon_cli._follow(daemon, out, {"moves": 3, "samples": 600, "duration_s": 6.0})
    assert status is IDLE
    assert lines(out) == [("move 1/3", 6.0), ("move 2/3", 6.0), ("move 3/3", 6.0)]


def test_segments_are_counted_as_segments_and_a_pause_is_said():
    # a dEPM run's `execute` reply names no sample count: progress must not depend on one
    daemon = ScriptedDaemon([running(0, "segments", 2), running(1, "segments", 2, "paused"),
                             running(1, "segments", 2), IDLE])
    out = io.StringIO()
    daemon_cli._follow(daemon, out, {"segments": 2, "duration_s": 6.0})
    assert lines(out) == [("segment 1/2", 6.0), ("segment 2/2 paused", 6.0)]


def test_quiet_shows_nothing():
    daemon = ScriptedDaemon([running(0, "moves", 1), IDLE])
    assert daemon_cli._follow(daemon, None, {"moves": 1, "duration_s": 6.0}) is IDLE
