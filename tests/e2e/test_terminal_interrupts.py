"""Ctrl-C as a terminal sends it: SIGINT to every process of the foreground process group, not to
`rigctl` alone (issue 35, item 3). Each command is started in a session of its own, as a shell
starts a foreground job, and the group is signalled with `os.killpg` once the command's output
(or its run record) says it is running.

What the user sees is asserted: the exit status, one line on stderr, the run record's summary
(aborted, and safe: confirmed by every device), and that nothing the command started is left
running afterwards: neither its process group nor any process that descended from it (those that
rigctl now starts in sessions of their own, out of the terminal's reach, are not in the group).

Before the fix, a Ctrl-C to the group during a coil-board run ended "FAULT: coil board: not
confirmed safe when the run stopped (check it by hand)": the emulated bench died with the same
keystroke, before the run could make the board safe.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from rigctl.client import Rig
from rigctl.record import read_events
from rigctl.testing import wait_for

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "plans" / "examples"
PLANS = {"six-coil": "fig4-quick.json", "coil-board": "coilboard-disk.json", "depm": "depm-plan.json"}
START_S = 120.0  # a command's start-up on a loaded two-core machine (imports, benches, numba)
END_S = 60.0  # from the Ctrl-C to the command's exit
GONE_S = 10.0  # from its exit to every process it started gone


def _started_at(pid: int) -> str | None:
    """The process's start time (clock ticks since boot), None if it is gone or a zombie: with
    the pid, what tells a process from a later one given the same pid."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return None if fields[0] in "ZX" else fields[19]


def _descendants(pid: int) -> dict[int, str]:
    """Every living process descended from `pid` (children of every thread), with its start."""
    found: dict[int, str] = {}
    todo = [pid]
    while todo:
        parent = todo.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            try:
                children = [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                continue
            for child in children:
                started = _started_at(child)
                if started is not None and child not in found:
                    found[child] = started
                    todo.append(child)
    return found


def _command(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ").strip()
    except OSError:
        return "?"


class Session:
    """`rigctl ARGS` in a session of its own (its process group: a shell's foreground job), its
    stdout and stderr read line by line as they come."""

    def __init__(self, *args: str, cwd: Path) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rigctl", *args], cwd=cwd, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True, start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1", "RIGCTL_LOCK_DIR": str(cwd / "locks")})
        self.pgid = self.proc.pid  # the session's leader: its group is its pid
        self.out: list[str] = []
        self.err: list[str] = []
        self._arrived = threading.Condition()
        self._readers = [threading.Thread(target=self._read, args=(stream, lines), daemon=True)
                         for stream, lines in ((self.proc.stdout, self.out),
                                               (self.proc.stderr, self.err))]
        for reader in self._readers:
            reader.start()
        self.started: dict[int, str] = {}  # every process it had started when interrupted
        self.commands: dict[int, str] = {}  # ... and their command lines

    def _read(self, stream, lines: list[str]) -> None:
        for line in stream:
            with self._arrived:
                lines.append(line.rstrip("\n"))
                self._arrived.notify_all()
        with self._arrived:
            self._arrived.notify_all()

    def wait_line(self, lines: list[str], wanted: Callable[[str], bool], what: str,
                  timeout_s: float = START_S) -> str:
        """The first line of `lines` (self.out or self.err) that is `wanted`, as it arrives."""
        found: list[str] = []

        def arrived() -> bool:
            found[:] = [line for line in lines if wanted(line)][:1]
            return bool(found) or self.proc.poll() is not None and not any(
                r.is_alive() for r in self._readers)

        with self._arrived:
            self._arrived.wait_for(arrived, timeout_s)
        assert found, f"no {what} from rigctl {self.proc.args[3:]}: {self.text()}"
        return found[0]

    def ctrl_c(self) -> None:
        """SIGINT to the whole group, as the terminal's Ctrl-C; what it had started is noted."""
        if not self.started:
            self.started = _descendants(self.proc.pid)
            self.commands = {pid: _command(pid) for pid in self.started}
        os.killpg(self.pgid, signal.SIGINT)

    def finish(self) -> int:
        code = self.proc.wait(END_S)
        for reader in self._readers:
            reader.join(END_S)
        return code

    def text(self) -> str:
        return "\n".join(["-- stdout", *self.out, "-- stderr", *self.err])

    def assert_nothing_left(self) -> None:
        """No process of its group, and none it had started (in a session of its own), still
        running a bounded while after it exited."""
        def group_gone() -> bool:
            try:
                os.killpg(self.pgid, 0)
            except ProcessLookupError:
                return True
            return False

        wait_for(group_gone, GONE_S, f"every process of group {self.pgid} to end")
        wait_for(lambda: all(_started_at(pid) != started for pid, started in self.started.items()),
                 GONE_S, f"every process rigctl started to end: {self._left()}")

    def _left(self) -> list[str]:
        return [self.commands[pid] for pid, started in self.started.items()
                if _started_at(pid) == started]

    def kill(self) -> None:
        """Clean-up after a failed test: nothing of it survives the test."""
        for pid, started in {**self.started, **_descendants(self.proc.pid)}.items():
            if _started_at(pid) == started:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        try:
            os.killpg(self.pgid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait()


@pytest.fixture
def session(tmp_path):
    """Start `rigctl ARGS` in a session of its own in tmp_path; killed after the test if left."""
    started: list[Session] = []

    def start(*args: str) -> Session:
        started.append(Session(*args, cwd=tmp_path))
        return started[-1]

    yield start
    for s in started:
        s.kill()
        for stream in (s.proc.stdout, s.proc.stderr):
            stream.close()


def _events(run_dir: Path) -> list[dict]:
    return read_events(run_dir) if (run_dir / "events.jsonl").exists() else []


def _energised(runs: Path) -> Callable[[], bool]:
    """The run's record (the command's output on disk) says its devices are energised: the run
    is streaming."""
    return lambda: any(e.get("event") == "energised" for d in runs.glob("*") for e in _events(d))


def _summary(runs: Path) -> dict:
    records = sorted(runs.glob("*/summary.json"))
    assert len(records) == 1, records
    return json.loads(records[0].read_text())


def assert_aborted_safely(s: Session, runs: Path, code: int, by: str = "Ctrl-C") -> dict:
    """What the user must see after a Ctrl-C ended a run: exit 3, one line saying aborted on
    stderr, no traceback, no fault and no "check it by hand", the record aborted and safe."""
    summary = _summary(runs)
    assert summary["state"] == "aborted" and summary["safe"] is True, summary
    assert [f["kind"] for f in summary["faults"]] == ["Abort"] and by in \
        summary["faults"][0]["reason"], summary["faults"]
    assert code == 3, s.text()
    everything = s.out + s.err
    assert not any("Traceback" in line or "by hand" in line or line.startswith("FAULT")
                   for line in everything), s.text()
    said = [line for line in s.err if "aborted" in line]
    assert len(said) == 1 and by in said[0], s.text()
    return summary


@pytest.mark.parametrize("kind", list(PLANS))
def test_ctrl_c_to_execute_aborts_with_every_device_safe_and_leaves_nothing_running(
        kind, session, tmp_path):
    runs = tmp_path / "runs"
    s = session("execute", str(EXAMPLES / PLANS[kind]), "--runs", str(runs))
    wait_for(_energised(runs), START_S, "the run to energise")
    s.ctrl_c()
    assert_aborted_safely(s, runs, s.finish())
    assert any(f"emulate {kind}" in command for command in s.commands.values()), s.commands
    s.assert_nothing_left()  # its emulated bench (a session of its own) among them


def test_a_second_ctrl_c_during_the_wind_down_still_ends_safe_with_the_summary(session, tmp_path):
    runs = tmp_path / "runs"
    s = session("execute", str(EXAMPLES / PLANS["coil-board"]), "--runs", str(runs))
    wait_for(_energised(runs), START_S, "the run to energise")
    s.ctrl_c()
    # the line comes as the run starts to wind down (the ramp, the last look, the record's end)
    s.wait_line(s.err, lambda line: "aborted by Ctrl-C" in line, "line saying aborted", END_S)
    s.ctrl_c()  # the operator presses again, impatient
    assert_aborted_safely(s, runs, s.finish())
    assert any("interrupted again" in line for line in s.err), s.text()  # noted, not raised
    assert any(line.startswith("run record: ") for line in s.out), s.text()  # the summary
    s.assert_nothing_left()


EMULATED = {"six-coil": [], "coil-board": ["--firmware", "simavr"], "depm": []}


@pytest.mark.parametrize("kind", list(EMULATED))
def test_ctrl_c_to_emulate_stops_the_bench_and_everything_it_started(kind, session, tmp_path):
    if EMULATED[kind]:
        from rigctl.emulators.coilboard.simavr import missing_tools

        if missing_tools():
            pytest.skip(f"the firmware in simavr needs {', '.join(missing_tools())}")
    s = session("emulate", kind, "--rig-out", str(tmp_path / "bench.toml"), *EMULATED[kind])
    s.wait_line(s.out, lambda line: line.startswith("READY "), "READY line")
    s.ctrl_c()
    code = s.finish()
    assert code == 0 and not any("Traceback" in line for line in s.err), s.text()
    if EMULATED[kind]:  # the firmware's harness (a session of its own) was running, and is gone
        assert any("harness" in command for command in s.commands.values()), s.commands
    s.assert_nothing_left()


@pytest.mark.parametrize("kind", list(PLANS))
def test_ctrl_c_to_the_daemon_mid_run_ramps_down_and_exits_cleanly(kind, session, tmp_path):
    runs = tmp_path / "runs"
    s = session("daemon", "--bench", kind, "--runs", str(runs), "--command", "tcp://127.0.0.1:0",
                "--telemetry", "tcp://127.0.0.1:0", "--events", "tcp://127.0.0.1:0")
    ready = s.wait_line(s.out, lambda line: line.startswith("READY "), "READY line")
    endpoints = dict(field.split("=", 1) for field in ready.split()[1:])
    with Rig(endpoints["command"], timeout_s=10.0) as rig:
        rig.execute(rig.load(json.loads((EXAMPLES / PLANS[kind]).read_text())))
        wait_for(_energised(runs), START_S, "the run to energise")
        assert rig.status()["state"] == "running"
        s.ctrl_c()
        code = s.finish()
    assert code == 0 and not any("Traceback" in line or "by hand" in line for line in s.err), \
        s.text()
    summary = _summary(runs)
    assert summary["state"] == "aborted" and summary["safe"] is True, summary
    assert any("emulate" in command for command in s.commands.values()), s.commands
    assert any("runhost" in command for command in s.commands.values()), s.commands
    s.assert_nothing_left()  # the bench and the stream process, each in a session of its own


def test_ctrl_c_to_a_local_study_stops_its_workers_and_the_runs_they_started(session, tmp_path):
    """One rig kind (the coil board, the shortest start): a run's stop is the same on every rig,
    and a study's own part (its workers, the cases' runs and benches) does not depend on it."""
    spec = tmp_path / "spec.toml"
    spec.write_text(f'name = "ctrl-c"\n[run]\ncommand = "execute"\n'
                    f'args = {{ plan = "{EXAMPLES / PLANS["coil-board"]}" }}\n')
    out = tmp_path / "study"
    s = session("study", str(spec), "--workers", "2", "--out", str(out))
    runs = out / "cases"
    wait_for(lambda: any(_energised(case / "runs")() for case in runs.glob("*")), START_S,
             "the case's run to energise")
    s.ctrl_c()
    code = s.finish()
    assert code == 3, s.text()
    said = [line for line in s.err if "interrupted" in line]
    assert len(said) == 1 and not any("Traceback" in line for line in s.err), s.text()
    # the case's run (`rigctl execute --rig`, a session of its own) was stopped by the study as
    # SIGTERM stops it, before its bench: aborted, every device safe
    (case,) = runs.glob("*")
    summary = _summary(case / "runs")
    assert summary["state"] == "aborted" and summary["safe"] is True, summary
    assert "SIGTERM" in summary["faults"][0]["reason"], summary["faults"]
    assert sum("distributed" in c or "multiprocessing" in c for c in s.commands.values()) >= 2, \
        s.commands  # both Dask workers were running
    assert any("emulate" in command for command in s.commands.values()), s.commands
    s.assert_nothing_left()


def test_ctrl_c_to_the_fault_campaign_stops_its_daemon_and_bench(session, tmp_path):
    """One rig kind (the coil board): the campaign's own part (its daemon and bench, each now in a
    session of its own, stopped by the campaign) does not depend on the rig."""
    keep = tmp_path / "campaign"
    s = session("faults", "--rig", "coil-board", "--quick", "--keep", str(keep))
    runs = keep / "coil-board" / "runs"
    wait_for(_energised(runs), START_S, "the campaign's first run to energise")
    s.ctrl_c()
    code = s.finish()
    assert code == 3, s.text()
    said = [line for line in s.err if "interrupted" in line]
    assert len(said) == 1 and "Ctrl-C" in said[0], s.text()
    assert not any("Traceback" in line for line in s.err), s.text()
    # the daemon was stopped as SIGTERM stops it (its run ramped down, its record finished)
    # before the bench it runs on
    summary = _summary(runs)
    assert summary["state"] in ("aborted", "faulted") and summary["safe"] is True, summary
    assert any(" daemon " in command for command in s.commands.values()), s.commands
    assert any("emulate" in command for command in s.commands.values()), s.commands
    s.assert_nothing_left()
