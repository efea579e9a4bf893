"""One run-control suite for the three rigs, on their emulated benches (each in its own process):
pause at the end of a step and pause now, resume, abort, e-stop, a device fault mid-run, and lost
sensing (the camera frozen; the Hall board stalled) -> suspended -> running again. Once through
the daemon (`rigctl daemon`, the `Rig` client) and once through `rigctl execute --rig` (the same
requests to the control endpoint its rig lock names; SIGINT and SIGTERM: an abort with one line,
exit 3, a finished record). The coil board runs through the daemon on both its
Python firmware emulator and the real firmware in simavr.

Physical safety is read from each emulator's ground truth, not from rigctl: supply currents under
50 mA, the SyRen outputs the board's wire carries at zero, the arms' joint speeds at rest.

One bench per rig kind serves the module's tests of that kind (starting a bench and a daemon was
3-9 s of every test's 6-35, at load 5-10), and one daemon on it serves the daemon's tests: each
test's run is loaded and placed anew (the run places its agents through the backdoor), and after
each test the run is ended, the bench's faults restored and the daemon reset, then every device
read safe from the bench's ground truth, so that no test starts on what the one before left
(`rig_on_bench`). A kind's tests are one xdist group (one worker, one bench); the rest spread.
The tests that need a bench of their own (SIGINT or SIGTERM to a `rigctl execute` that started
its bench; an e-stop with no owner) start one.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from rigctl.apps.client import DaemonUnreachable, Rig
from rigctl.apps.testing import descendants, wait_for
from rigctl.core.config import load_rig
from rigctl.core.record import read_events
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.rigs.owner import holder_of

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "plans" / "examples"


def six_coil_safe(truth: dict, but: str | None = None) -> bool:
    return all(abs(a) < 0.05 for name, a in truth["currents_A"].items() if name != but)


def coil_board_safe(truth: dict, but: str | None = None) -> bool:
    return all(v == 0 for v in truth["outputs"])


def depm_safe(truth: dict, but: str | None = None) -> bool:
    return all(max(abs(v) for v in arm["qd"]) < 1e-3 for name, arm in truth["arms"].items())


def six_coil_active(truth: dict) -> bool:
    return max(abs(a) for a in truth["currents_A"].values()) > 0.5


def coil_board_active(truth: dict) -> bool:
    return any(v != 0 for v in truth["outputs"])


def depm_active(truth: dict) -> bool:
    return any(max(abs(v) for v in arm["qd"]) > 1e-3 for arm in truth["arms"].values())


@dataclass
class RigCase:
    kind: str
    plan: str
    safe: object
    active: object
    fault: dict  # a backdoor request that breaks one device for good
    fault_device: str
    suspend: dict  # a backdoor request that takes the run's sensing away ...
    restore: dict  # ... and one that gives it back
    bench_args: list[str] = field(default_factory=list)
    # what the fault makes of the run: a device that fails ends it (faulted); a camera whose link
    # drops for good is reopened every second while the run is suspended (docs/safety.md)
    fault_state: str = "faulted"


CASES = {
    "six-coil": RigCase("six-coil", "fig4-two-magnets.json", six_coil_safe, six_coil_active,
                        {"cmd": "fault", "device": "x+", "kind": "drop_link"}, "x+",
                        {"cmd": "camera", "kind": "freeze"}, {"cmd": "camera", "kind": "restore"}),
    "coil-board": RigCase("coil-board", "coilboard-disk.json", coil_board_safe, coil_board_active,
                          {"cmd": "fault", "device": "board", "kind": "unplug"}, "coil board",
                          {"cmd": "camera", "kind": "freeze"},
                          {"cmd": "camera", "kind": "restore"}),
    "coil-board-simavr": RigCase("coil-board", "coilboard-disk.json", coil_board_safe,
                                 coil_board_active,
                                 {"cmd": "camera", "kind": "drop_link"}, "camera",
                                 {"cmd": "camera", "kind": "freeze"},
                                 {"cmd": "camera", "kind": "restore"},
                                 bench_args=["--firmware", "simavr"], fault_state="suspended"),
    "depm": RigCase("depm", "depm-plan.json", depm_safe, depm_active,
                    {"cmd": "fault", "device": "left", "kind": "drop_link"}, "left",
                    {"cmd": "fault", "device": "hall", "kind": "stall"},
                    {"cmd": "fault", "device": "hall", "kind": "restore"}),
}


class Daemon:
    def __init__(self, rig_path: Path, runs: Path, log_path: Path) -> None:
        self.log = open(log_path, "w")
        self.log_path = log_path
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rigctl", "daemon", "--rig", str(rig_path), "--runs", str(runs),
             "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
             "--events", "tcp://127.0.0.1:0"],
            stdout=subprocess.PIPE, stderr=self.log, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        for line in self.proc.stdout:  # readiness: the READY line
            if line.startswith("READY "):
                self.endpoints = dict(f.split("=", 1) for f in line[6:].split())
                return
        raise AssertionError(f"daemon did not start: {log_path.read_text()[-3000:]}")

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc.stdout.close()
        self.log.close()


RUN_ACTIVE = ("running", "paused", "suspended")  # the daemon's states while a run is on


def healing(case: RigCase) -> list[dict]:
    """The backdoor requests that undo what the case's tests break: its fault and lost sensing."""
    fault = dict(case.fault, kind="restore")
    return [fault, dict(case.restore)]


@pytest.fixture(scope="module",
                params=[pytest.param(name, marks=pytest.mark.xdist_group(f"run_control-{name}"))
                        for name in CASES])
def case(request) -> RigCase:
    """A rig kind's case; its tests are one xdist group, so one worker starts its bench once."""
    return CASES[request.param]


@pytest.fixture(scope="module")
def bench(case, tmp_path_factory):
    """(rig file, backdoor) of the case's emulated bench, shared by the module's tests of it."""
    folder = tmp_path_factory.mktemp("bench")
    with EmulatedBenchProcess(case.kind, folder / "bench.toml",
                              extra_args=case.bench_args) as rig_path:
        with BackdoorClient(load_rig(rig_path).emulation.backdoor) as backdoor:
            yield rig_path, backdoor


class SharedDaemon:
    """A `rigctl daemon` on the shared bench, and a `Rig` client of it; started again if a test
    left it past reach (the next test then starts on a fresh one, as it did before)."""

    def __init__(self, rig_path: Path, folder: Path) -> None:
        self.rig_path, self.folder, self.starts = rig_path, folder, 0
        self._start()

    def _start(self) -> None:
        self.starts += 1
        self.daemon = Daemon(self.rig_path, self.folder / "runs",
                             self.folder / f"daemon-{self.starts}.log")
        self.rig = Rig(self.daemon.endpoints["command"])

    def restart(self) -> None:
        self.close()
        self._start()

    def close(self) -> None:
        self.rig.close()
        self.daemon.close()


@pytest.fixture(scope="module", params=["daemon", "execute"])
def owner(bench, request, tmp_path_factory):
    """Who runs the plan on the shared bench: a daemon shared by the module's daemon tests of the
    case, or (None) a `rigctl execute` of each test's own. pytest runs a kind's daemon tests
    together (a parameter of module scope): the daemon is up for them only, never while an
    `execute` test needs the rig's lock."""
    if request.param == "execute":
        yield None
        return
    shared = SharedDaemon(bench[0], tmp_path_factory.mktemp("daemon"))
    try:
        yield shared
    finally:
        shared.close()


def heal(case: RigCase, backdoor: BackdoorClient) -> None:
    for request in healing(case):
        request = dict(request)
        backdoor.request(request.pop("cmd"), **request)


def settle_daemon(shared: SharedDaemon, case: RigCase, backdoor: BackdoorClient) -> None:
    """The daemon idle with no run, after whatever the test did: the bench's faults restored,
    a run still on aborted, a fault or an e-stop reset, every device confirmed safe."""
    heal(case, backdoor)
    rig = shared.rig
    if rig.status()["state"] in RUN_ACTIVE:
        rig.abort()
    wait_for(lambda: rig.status()["run"] is None, 60, "the test's run to end")
    if rig.status()["state"] != "idle":
        rig.reset()
    wait_state(rig, "idle", timeout_s=10)
    # a device a run could not confirm safe (its link was down) is made safe by the daemon once
    # it answers again; until then the daemon starts no run (`_require_safe`)
    wait_for(lambda: all(d["health"] != "unsafe" for d in rig.status()["devices"]), 30,
             "the daemon to confirm every device safe")


def alive(pid: int) -> bool:
    """Whether process `pid` still runs (a zombie's work is done: whoever reaps it may be late)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def settle_local(local: LocalRun, case: RigCase, backdoor: BackdoorClient) -> None:
    """The test's `rigctl execute` gone, killed if it still runs (as each test's own bench was
    before), and everything it had started with it: its guardian, which makes the shared bench
    safe on seeing its owner gone, has done so and exited before the next test starts."""
    heal(case, backdoor)
    proc = local.proc
    if proc is not None and proc.poll() is None:
        below = descendants(proc.pid)  # once it is dead, its guardian is no longer below it
        proc.kill()
        proc.wait()
        wait_for(lambda: not any(map(alive, below)), 30,
                 "the killed run's guardian and children to exit")
    local.close()


@pytest.fixture
def rig_on_bench(case, bench, owner, tmp_path):
    """(case, rig file, a backdoor, the run's control: a Rig client of the shared daemon on the
    shared bench, or a `rigctl execute` on it). After the test, the bench and its owner are as
    the next test needs them: no run, no fault, every device safe."""
    rig_path, backdoor = bench
    if owner is None and case.bench_args:
        pytest.skip("through rigctl execute once per rig kind (the simavr board: the daemon)")
    if owner is None:
        local = LocalRun(case, rig_path, tmp_path / "runs")
        try:
            yield case, rig_path, backdoor, local
        finally:
            settle_local(local, case, backdoor)
    else:
        try:
            yield case, rig_path, backdoor, owner.rig
        finally:
            try:
                settle_daemon(owner, case, backdoor)
            except (AssertionError, DaemonUnreachable, TimeoutError):
                owner.restart()  # past reach: the next test gets a fresh daemon
    wait_for(lambda: case.safe(backdoor.request("truth")), 10, "every device safe after the test")


class LocalRun:
    """`rigctl execute PLAN --rig RIG` driven as the daemon is: through the control endpoint its
    rig lock names (the same requests), while it runs; once its process ended, what its record's
    summary says, in the daemon's terms (a run that ended without a fault leaves the rig idle)."""

    def __init__(self, case: RigCase, rig_path: Path, runs: Path) -> None:
        self.case, self.rig_path, self.runs = case, rig_path, runs
        self.proc: subprocess.Popen | None = None
        self.client: Rig | None = None

    def execute(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rigctl", "execute", str(EXAMPLES / self.case.plan), "--rig",
             str(self.rig_path), "--runs", str(self.runs), "-q"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        rig = load_rig(self.rig_path)
        # the lock is taken first, its control endpoint named once the run is built
        wait_for(lambda: getattr(holder_of(rig), "control", None) is not None, 60,
                 "rigctl execute to own the rig and answer control requests")
        self.client = Rig(holder_of(rig).control, timeout_s=1.0, retries=1)

    def __getattr__(self, name: str):  # pause, resume, abort, estop: the Rig client's own
        if name in ("pause", "resume", "abort", "estop"):
            return getattr(self.client, name)
        raise AttributeError(name)

    def status(self) -> dict:
        if self.proc.poll() is None:
            try:
                return self.client.request("status")
            except DaemonUnreachable:  # its endpoint closes once the summary is written
                if self.proc.poll() is None and not any(self.runs.glob("*/summary.json")):
                    raise
        summary = json.loads(next(self.runs.glob("*/summary.json")).read_text())
        faulted = summary["state"] in ("faulted", "estopped")
        return {"state": summary["state"] if faulted else "idle", "run": None,
                "last_run": summary, "last_fault": (summary["faults"] or [None])[-1]}

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def start(rig: Rig | LocalRun, case: RigCase, backdoor) -> None:
    if isinstance(rig, LocalRun):
        rig.execute()
    else:
        rig.execute(rig.load(json.loads((EXAMPLES / case.plan).read_text())))
    wait_state(rig, "running", timeout_s=60)
    wait_for(lambda: case.active(backdoor.request("truth")), 60, "the actuators to act")


def wait_state(rig: Rig, *states: str, timeout_s: float = 30.0) -> dict:
    status: dict = {}

    def reached() -> bool:
        nonlocal status
        status = rig.status()
        return status["state"] in states

    try:
        wait_for(reached, timeout_s, f"state {' or '.join(states)}")
    except AssertionError as err:  # what it was instead, for the one reading the failure
        raise AssertionError(f"{err}; last status: {status}") from None
    return status


def test_status_lists_every_device_of_the_rig(rig_on_bench):
    case, rig_path, backdoor, rig = rig_on_bench
    if isinstance(rig, LocalRun):  # a local run answers while it runs
        rig.execute()
    names = {d["name"] for d in rig.status()["devices"]}
    loaded = load_rig(rig_path)
    expected = {"six-coil": lambda: {c.name for c in loaded.coils} | {"camera"},
                "coil-board": lambda: {"coil board", "camera"},
                "depm": lambda: set(loaded.depm.arm_names) | {"hall board"}}
    assert names == expected[case.kind]()


def test_pause_resume_pause_now_and_abort(rig_on_bench):
    case, _, backdoor, rig = rig_on_bench
    start(rig, case, backdoor)
    rig.pause(immediate=True)
    wait_state(rig, "paused")
    rig.resume()
    wait_state(rig, "running")
    rig.pause()  # at the end of the step being driven
    wait_state(rig, "paused", timeout_s=90)
    rig.resume()
    wait_state(rig, "running")
    rig.abort()
    status = wait_state(rig, "idle", timeout_s=60)
    assert any(f["kind"] == "Abort" for f in status["last_run"]["faults"])
    wait_for(lambda: case.safe(backdoor.request("truth")), 10, "every device safe")


def test_estop_from_a_running_rig_makes_every_device_safe(rig_on_bench):
    case, _, backdoor, rig = rig_on_bench
    start(rig, case, backdoor)
    reply = rig.estop()
    assert reply["state"] == "estopped" and reply["unreached"] == []
    wait_for(lambda: case.safe(backdoor.request("truth")), 5, "every device safe")
    wait_for(lambda: rig.status()["run"] is None, 30, "the run to end")
    if isinstance(rig, LocalRun):
        assert rig.proc.wait(30) == 3  # the README's exit status of an e-stopped run
        assert rig.status()["last_run"]["state"] == "estopped"
    else:
        assert rig.reset()["state"] == "idle"


def test_a_device_fault_mid_run_names_the_device(rig_on_bench):
    case, _, backdoor, rig = rig_on_bench
    start(rig, case, backdoor)
    fault = dict(case.fault)
    backdoor.request(fault.pop("cmd"), **fault)
    status = wait_state(rig, case.fault_state, timeout_s=60)
    if case.fault_state == "suspended":
        assert "tracking lost" in status["reason"], status  # what the run waits for, named
        return
    assert status["last_fault"]["device"] == case.fault_device, status["last_fault"]
    # every other device was made safe (the broken one cannot be reached)
    wait_for(lambda: case.safe(backdoor.request("truth"), but=case.fault_device), 10,
             "the other devices safe")


def test_lost_sensing_suspends_the_run_and_it_resumes(rig_on_bench):
    case, _, backdoor, rig = rig_on_bench
    start(rig, case, backdoor)
    suspend, restore = dict(case.suspend), dict(case.restore)
    backdoor.request(suspend.pop("cmd"), **suspend)
    status = wait_state(rig, "suspended", timeout_s=30)
    assert status["reason"], status  # what the run waits for, named
    backdoor.request(restore.pop("cmd"), **restore)
    wait_state(rig, "running", timeout_s=30)  # resumed, not ended
    rig.abort()
    wait_state(rig, "idle", timeout_s=60)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("case_name", list(CASES))
def test_a_signal_to_rigctl_execute_aborts_with_one_line_and_a_finished_record(case_name, sig,
                                                                               tmp_path):
    case = CASES[case_name]  # a bench of its own: the one `rigctl execute` starts
    cmd = [sys.executable, "-m", "rigctl", "execute", str(EXAMPLES / case.plan), "--runs",
           str(tmp_path / "runs"), *case.bench_args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, cwd=tmp_path)
    try:
        wait_for(lambda: any(e.get("event") == "energised"
                             for p in (tmp_path / "runs").glob("*/events.jsonl")
                             for e in read_events(p.parent)), 90, "the run to energise")
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 3, err
    assert "Traceback" not in err
    run_dir = next((tmp_path / "runs").iterdir())
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["state"] == "aborted" and summary["safe"] is True
    aborts = [e for e in read_events(run_dir) if e["event"] == "abort"]
    name = "Ctrl-C" if sig == signal.SIGINT else "SIGTERM"
    assert aborts and name in aborts[0]["reason"], aborts
    assert "aborted" in out


def estop_with_rig_file(rig_path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rigctl", "estop", "--rig", str(rig_path)],
                          capture_output=True, text=True, timeout=60)


def test_estop_with_the_rig_file_reaches_the_run_that_owns_the_rig(rig_on_bench):
    case, rig_path, backdoor, rig = rig_on_bench
    start(rig, case, backdoor)
    done = estop_with_rig_file(rig_path)
    assert done.returncode == 0, done.stdout + done.stderr
    owner = "rigctl execute" if isinstance(rig, LocalRun) else "rigctl daemon"
    assert f"EMERGENCY STOP: {owner}, pid" in done.stdout
    wait_for(lambda: case.safe(backdoor.request("truth")), 5, "every device safe")
    if isinstance(rig, LocalRun):
        assert rig.proc.wait(30) == 3
        assert rig.status()["last_run"]["state"] == "estopped"
    else:
        wait_state(rig, "estopped", timeout_s=30)


@pytest.mark.parametrize("kind", ["six-coil", "coil-board", "depm"])
def test_estop_with_the_rig_file_and_no_owner_reaches_every_device_directly(kind, tmp_path):
    from rigctl.rigs import rig_kind

    with EmulatedBenchProcess(kind, tmp_path / "bench.toml") as rig_path:
        rig = load_rig(rig_path)
        supplies = None
        if kind == "six-coil":  # left energised by something that is gone: 2 A on every coil
            from rigctl.rigs.six_coil.supplies import CoilSupplies

            supplies = CoilSupplies.connect(rig)
            supplies.energise()
            supplies.cycle([2.0] * len(rig.coils))
            with BackdoorClient(rig.emulation.backdoor) as backdoor:
                wait_for(lambda: six_coil_active(backdoor.request("truth")), 5, "current")
        try:
            done = estop_with_rig_file(rig_path)
            assert done.returncode == 0, done.stdout + done.stderr
            actuators = [d.name for d in rig_kind(kind).devices(rig)
                         if d.kind in ("supply", "board", "arm")]
            for name in actuators:
                assert any(line.split()[:1] == name.split()[:1] and line.rstrip().endswith("safe")
                           for line in done.stdout.splitlines()), (name, done.stdout)
            if supplies is not None:
                with BackdoorClient(rig.emulation.backdoor) as backdoor:
                    wait_for(lambda: six_coil_safe(backdoor.request("truth")), 5, "0 A")
        finally:
            if supplies is not None:
                supplies.stop(0.0)


def test_the_cli_verbs_control_the_run_that_owns_the_rig(rig_on_bench):
    case, rig_path, backdoor, rig = rig_on_bench
    if case.kind != "six-coil":
        pytest.skip("the verbs are the same requests on every rig (the suite above): once")
    start(rig, case, backdoor)

    def verb(*words: str) -> None:
        done = subprocess.run([sys.executable, "-m", "rigctl", *words, "--rig", str(rig_path)],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stdout + done.stderr

    verb("pause", "--now")
    wait_state(rig, "paused")
    verb("resume")
    wait_state(rig, "running")
    verb("abort")
    status = wait_state(rig, "idle", timeout_s=60)
    assert any(f["kind"] == "Abort" for f in status["last_run"]["faults"])
