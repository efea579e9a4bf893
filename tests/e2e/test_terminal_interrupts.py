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

from rigctl.apps.client import Rig
from rigctl.apps.testing import wait_for
from rigctl.core.record import read_events

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

    def __init__(self, *args: str, cwd: Path, again_on: str | None = None) -> None:
        self.again_on = again_on  # Ctrl-C again the moment a stderr line says this
        self.again_late = False
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
            if self.again_on is not None and self.again_on in line:
                self.again_on = None
                # a loaded machine may run this thread only after the command has ended (its
                # zombie keeps the group): that press came too late to be noted
                self.again_late = _ended(self.proc.pid)
                os.killpg(self.pgid, signal.SIGINT)  # the operator presses again, impatient
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

    def start(*args: str, again_on: str | None = None) -> Session:
        started.append(Session(*args, cwd=tmp_path, again_on=again_on))
        return started[-1]

    yield start
    for s in started:
        s.kill()
        for stream in (s.proc.stdout, s.proc.stderr):
            stream.close()


def _ended(pid: int) -> bool:
    """Whether process `pid` has exited (a zombie not yet waited for, or gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in "ZX"
    except (OSError, IndexError):
        return True


def _events(run_dir: Path) -> list[dict]:
    return read_events(run_dir) if (run_dir / "events.jsonl").exists() else []


def _energised(runs: Path) -> Callable[[], bool]:
    """The run's record (the command's output on disk) says its devices are energised: the run
    is streaming."""
    return lambda: any(e.get("event") == "energised" for d in runs.glob("*") for e in _events(d))


def _summary(runs: Path, s: Session | None = None) -> dict:
    records = sorted(runs.glob("*/summary.json"))
    assert len(records) == 1, (sorted(runs.glob("*/*")), [
        [e for e in _events(d) if e.get("event") != "tracked"][-8:] for d in runs.glob("*")],
        s and s.text())
    return json.loads(records[0].read_text())


def assert_aborted_safely(s: Session, runs: Path, code: int, by: str = "Ctrl-C") -> dict:
    """What the user must see after a Ctrl-C ended a run: exit 3, one line saying aborted on
    stderr, no traceback, no fault and no "check it by hand", the record aborted and safe."""
    summary = _summary(runs, s)
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


def ctrl_c_each_once_ready(sessions: dict[str, tuple[Session, Callable[[], bool]]]) -> None:
    """Ctrl-C to each session's group as soon as its predicate holds (its run streams): side by
    side, one run may be streaming (and soon done) while another still starts."""
    waiting = dict(sessions)

    def signalled_every_one() -> bool:
        for name, (s, streaming) in list(waiting.items()):
            if streaming():
                s.ctrl_c()
                del waiting[name]
        return not waiting

    wait_for(signalled_every_one, START_S, f"the runs of {', '.join(waiting)} to energise")


def test_ctrl_c_to_execute_aborts_with_every_device_safe_and_leaves_nothing_running(
        session, tmp_path):
    """Each rig, and the coil board once more with Ctrl-C pressed twice (again as the run says it
    aborted: during its wind-down), side by side (each its own command, session and bench)."""
    runs = {kind: tmp_path / kind for kind in [*PLANS, "twice"]}
    sessions = {kind: session("execute", str(EXAMPLES / plan), "--runs", str(runs[kind]))
                for kind, plan in PLANS.items()}
    sessions["twice"] = session("execute", str(EXAMPLES / PLANS["coil-board"]), "--runs",
                                str(runs["twice"]), again_on="aborted by Ctrl-C")
    ctrl_c_each_once_ready({kind: (s, _energised(runs[kind])) for kind, s in sessions.items()})
    for kind, s in sessions.items():
        assert_aborted_safely(s, runs[kind], s.finish())
        bench = "coil-board" if kind == "twice" else kind
        assert any(f"emulate {bench}" in c for c in s.commands.values()), (kind, s.commands)
        s.assert_nothing_left()  # its emulated bench (a session of its own) among them
    twice = sessions["twice"]
    assert twice.again_on is None, twice.text()  # pressed again ...
    assert twice.again_late or any("interrupted again" in line for line in twice.err), \
        twice.text()  # ... noted, up to the summary
    assert any(line.startswith("run record: ") for line in twice.out), twice.text()  # summary


def test_ctrl_c_to_emulate_stops_the_bench_and_everything_it_started(session, tmp_path):
    """Each rig's bench side by side; the coil board's runs its firmware in simavr (the harness,
    a session of its own, which the bench stops)."""
    from rigctl.emulators.coilboard.simavr import missing_tools

    emulated = {"six-coil": [], "coil-board": [] if missing_tools() else ["--firmware", "simavr"],
                "depm": []}
    sessions = {kind: session("emulate", kind, "--rig-out", str(tmp_path / f"{kind}.toml"), *extra)
                for kind, extra in emulated.items()}
    for s in sessions.values():
        s.wait_line(s.out, lambda line: line.startswith("READY "), "READY line")
        s.ctrl_c()
    for kind, s in sessions.items():
        code = s.finish()
        assert code == 0 and not any("Traceback" in line for line in s.err), s.text()
        if emulated[kind]:
            assert any("harness" in c for c in s.commands.values()), s.commands
        s.assert_nothing_left()


def test_ctrl_c_to_the_daemon_mid_run_ramps_down_and_exits_cleanly(session, tmp_path):
    """A daemon of each rig side by side, each running a plan it was given through the client."""
    runs = {kind: tmp_path / kind for kind in PLANS}
    sessions = {kind: session("daemon", "--bench", kind, "--runs", str(runs[kind]), "--command",
                              "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0", "--events",
                              "tcp://127.0.0.1:0")
                for kind in PLANS}
    for kind, s in sessions.items():
        ready = s.wait_line(s.out, lambda line: line.startswith("READY "), "READY line")
        endpoints = dict(field.split("=", 1) for field in ready.split()[1:])
        with Rig(endpoints["command"], timeout_s=10.0) as rig:
            rig.execute(rig.load(json.loads((EXAMPLES / PLANS[kind]).read_text())))
    ctrl_c_each_once_ready({kind: (s, _energised(runs[kind])) for kind, s in sessions.items()})
    for kind, s in sessions.items():
        code = s.finish()
        assert code == 0 and not any("Traceback" in line or "by hand" in line
                                     for line in s.err), s.text()
        summary = _summary(runs[kind], s)
        assert summary["state"] == "aborted" and summary["safe"] is True, (kind, summary)
        assert any("emulate" in c for c in s.commands.values()), (kind, s.commands)
        assert any("runhost" in c for c in s.commands.values()), (kind, s.commands)
        s.assert_nothing_left()  # the bench and the stream process, each a session of its own


def test_ctrl_c_to_a_local_study_and_to_the_fault_campaign_stops_all_they_started(session,
                                                                                   tmp_path):
    """Side by side, each on one rig kind (the coil board, the shortest start): a run's stop is
    the same on every rig, and their own parts (a study's workers and its cases' runs and
    benches; the campaign's daemon and bench) do not depend on it."""
    spec = tmp_path / "spec.toml"
    spec.write_text(f'name = "ctrl-c"\n[run]\ncommand = "execute"\n'
                    f'args = {{ plan = "{EXAMPLES / PLANS["coil-board"]}" }}\n')
    cases = tmp_path / "study" / "cases"
    study = session("study", str(spec), "--workers", "2", "--out", str(cases.parent))
    keep = tmp_path / "campaign"
    # one cell that keeps its run going: a camera frozen 30 s suspends it (a stalled board, the
    # quick cell, faulted the run 0.3 s after it drove: on a loaded CI the Ctrl-C came after)
    campaign = session("faults", "--rig", "coil-board", "--cell", "daemon/camera:freeze/moving",
                       "--hold", "30", "--keep", str(keep))
    campaign_runs = keep / "coil-board" / "runs"

    def suspended() -> bool:
        return any('"suspend"' in events.read_text()
                   for events in campaign_runs.glob("*/events.jsonl"))

    # the study as soon as its first case drives; the campaign once its run is suspended
    ctrl_c_each_once_ready({
        "study": (study, lambda: any(_energised(case / "runs")() for case in cases.glob("*"))),
        "campaign": (campaign, suspended)})

    for s in (study, campaign):
        code = s.finish()
        said = [line for line in s.err if "interrupted" in line]
        assert code == 3 and len(said) == 1, s.text()
        assert not any("Traceback" in line for line in s.err), s.text()
        assert any("emulate" in c for c in s.commands.values()), s.commands
        s.assert_nothing_left()
    # the case's run (`rigctl execute --rig`, a session of its own) was stopped by the study as
    # SIGTERM stops it, before its bench: aborted, every device safe
    (case,) = cases.glob("*")
    summary = _summary(case / "runs")
    assert summary["state"] == "aborted" and summary["safe"] is True, summary
    assert [f["kind"] for f in summary["faults"]] == ["Abort"] and "SIGTERM" in \
        summary["faults"][0]["reason"], summary["faults"]
    assert sum("spawn_main" in c for c in study.commands.values()) == 2, study.commands  # workers
    # the campaign stopped its daemon as SIGTERM stops it (the run ramped down, its record
    # finished), then the bench it runs on
    summary = _summary(campaign_runs, campaign)
    assert summary["state"] == "aborted" and summary["safe"] is True, summary
    # and nothing of the bench went away under it (before, the bench died with the keystroke:
    # "connection closed" by its backdoor, as the run was placing its particles)
    assert [f["kind"] for f in summary["faults"]] == ["Abort"], summary["faults"]
    assert any(" daemon " in c for c in campaign.commands.values()), campaign.commands
