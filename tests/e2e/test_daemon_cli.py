"""`rigctl daemon` end to end as a subprocess, the emulated bench in its own process: the CLI verbs
on top of the client, SIGTERM mid-run (ramps down, exit 0), a crash mid-run leaving a readable run
record and a report, and the systemd units through `systemd-analyze verify` where it exists."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.client import Rig
from rigctl.apps.testing import plan_pair, wait_for
from rigctl.core.config import load_rig
from rigctl.core.record import read_events, read_stream
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "plans" / "examples"


def rigctl_cmd() -> list[str]:
    """The `rigctl` command, as a user runs it."""
    return [sys.executable, "-m", "rigctl"]


class DaemonProcess:
    def __init__(self, rig_path: Path, runs: Path, log_path: Path) -> None:
        self.runs = runs
        self.log = open(log_path, "w")
        self.log_path = log_path
        self.proc = subprocess.Popen(
            [*rigctl_cmd(), "daemon", "--rig", str(rig_path), "--runs", str(runs),
             "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
             "--events", "tcp://127.0.0.1:0"],
            stdout=subprocess.PIPE, stderr=self.log, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        for line in self.proc.stdout:  # readiness: the READY line, never a sleep
            if line.startswith("READY "):
                self.endpoints = dict(f.split("=", 1) for f in line[6:].split())
                return
        raise AssertionError(f"daemon did not start: {log_path.read_text()[-3000:]}")

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()
        self.log.close()


@pytest.fixture
def bench(tmp_path):
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml") as rig_path:
        yield rig_path


@pytest.fixture
def daemon(bench, tmp_path):
    d = DaemonProcess(bench, tmp_path / "runs", tmp_path / "daemon.log")
    yield d
    d.close()


def run_cli(*args, cwd):
    return subprocess.run([*rigctl_cmd(), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=120)


def bench_currents(rig_path: Path) -> dict:
    with BackdoorClient(load_rig(rig_path).emulation.backdoor) as backdoor:
        return backdoor.request("truth")["currents_A"]


def test_status_execute_remote_and_estop_verbs(daemon, tmp_path):
    command = daemon.endpoints["command"]
    status = run_cli("status", "--connect", command, cwd=tmp_path)
    assert status.returncode == 0, status.stderr
    assert "state: idle" in status.stdout and "x+" in status.stdout

    from rigctl.apps.cli.daemon import execute_remote

    code = execute_remote(EXAMPLES / "fig4-quick.json", command, json_out=True, quiet=True)
    assert code == 0
    runs = run_cli("runs", "--runs", str(tmp_path / "runs"), cwd=tmp_path)
    assert runs.returncode == 0 and "reached" in runs.stdout

    estop = run_cli("estop", "--connect", command, cwd=tmp_path)
    assert estop.returncode == 0 and "estopped" in estop.stdout
    with Rig(command) as rig:
        assert rig.status()["state"] == "estopped"
        assert rig.reset()["state"] == "idle"
    unreachable = run_cli("status", "--connect", "tcp://127.0.0.1:1", cwd=tmp_path)
    assert unreachable.returncode == 3 and "no reply" in unreachable.stderr


def test_sigterm_mid_run_ramps_down_and_exits_0(daemon, bench):
    # generous timeouts: CI shares 2 cores, and a loaded machine makes the plan's load (realize,
    # allocate) and the run's start (devices, camera) take seconds
    with Rig(daemon.endpoints["command"], timeout_s=30.0) as rig:
        rig.execute(rig.load(json.loads((EXAMPLES / "fig4-two-magnets.json").read_text())))
        rig.wait_state("running", timeout_s=60.0)
        deadline = time.monotonic() + 60
        while max(abs(a) for a in bench_currents(bench).values()) < 1.0:
            assert time.monotonic() < deadline, "no current in the coils within 60 s"
    daemon.proc.send_signal(signal.SIGTERM)
    assert daemon.proc.wait(timeout=20) == 0
    # ramped to zero before the outputs went off: at most the last step of the ramp is left to
    # decay through R (tau = L/R = 20 ms)
    deadline = time.monotonic() + 0.5
    while not all(abs(a) < 0.05 for a in bench_currents(bench).values()):
        assert time.monotonic() < deadline, bench_currents(bench)
    events = read_events(next((daemon.runs).iterdir()))
    assert [e["state"] for e in events if e["event"] == "state"][-1] == "aborted"


def test_a_crash_mid_run_leaves_a_readable_record_and_a_report(daemon, bench, tmp_path):
    with Rig(daemon.endpoints["command"], timeout_s=30.0) as rig:
        rig.execute(rig.load(json.loads((EXAMPLES / "fig4-two-magnets.json").read_text())))
        rig.wait_state("running", timeout_s=60.0)
        deadline = time.monotonic() + 60  # generous: CI shares 2 cores
        while True:  # past the first Parquet part (5 s of cycles), then crash
            run = rig.status()["run"]
            if run and run["sample"] > 0 and list((tmp_path / "runs").glob("*/stream/part-*")):
                break
            assert time.monotonic() < deadline, "no Parquet part within 60 s"
            time.sleep(0.05)
    daemon.proc.kill()  # no ramp, no summary: a crash
    daemon.proc.wait()
    run_dir = next((tmp_path / "runs").iterdir())
    assert not (run_dir / "summary.json").exists()
    data = read_stream(run_dir)
    journal_rows = sum(1 for _ in open(run_dir / "stream.csv")) - 1
    assert data["source"] == "parquet+journal"
    assert len(data["t_s"]) >= journal_rows - 1  # at most the line being written is lost
    assert (data["sample"][1:] >= data["sample"][:-1]).all()
    events = read_events(run_dir)
    assert events[0]["event"] == "prepared" and any(e["event"] == "energised" for e in events)
    report = run_cli("report", str(run_dir), "-o", str(tmp_path / "crash.png"), cwd=tmp_path)
    assert report.returncode == 0, report.stderr
    png = (tmp_path / "crash.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


def test_keys_new_and_allow(tmp_path):
    made = run_cli("keys", "new", "alice", "--dir", str(tmp_path / "keys"), cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    assert (tmp_path / "keys" / "alice.key").is_file()
    assert oct((tmp_path / "keys" / "alice.key_secret").stat().st_mode & 0o777) == "0o600"
    again = run_cli("keys", "new", "alice", "--dir", str(tmp_path / "keys"), cwd=tmp_path)
    assert again.returncode == 2 and "already exists" in again.stderr
    allowed = run_cli("keys", "allow", str(tmp_path / "keys" / "alice.key"), "--dir",
                      str(tmp_path / "allowed"), cwd=tmp_path)
    assert allowed.returncode == 0 and (tmp_path / "allowed" / "alice.key").is_file()
    secret = run_cli("keys", "allow", str(tmp_path / "keys" / "alice.key_secret"), "--dir",
                     str(tmp_path / "allowed"), cwd=tmp_path)
    assert secret.returncode == 2 and not (tmp_path / "allowed" / "alice.key_secret").exists()


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
@pytest.mark.parametrize("unit", ["rigctl.service", "rigctl-bench@.service"])
def test_systemd_units_verify(unit, tmp_path):
    # the units name the documented install's interpreter; verify them with this one in its place
    here = tmp_path / unit
    here.write_text((ROOT / "systemd" / unit).read_text().replace(
        "/opt/rigctl/venv/bin/python3", f"{sys.prefix}/bin/python3"))
    result = subprocess.run(["systemd-analyze", "verify", str(here)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    text = (ROOT / "systemd" / unit).read_text()
    if unit == "rigctl.service":
        for key in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "User=rigctl",
                    "ProtectSystem=strict", "LimitRTPRIO="):
            assert key in text


def test_a_pair_plan_submitted_to_a_daemon_on_the_pair_bench(tmp_path):
    """The operator's path for seed 002: `rigctl emulate six-coil --world pair`, `rigctl daemon
    --rig`, then `rigctl execute PLAN --connect`: the pair run's own summary comes back."""
    plan = plan_pair(tmp_path, goal="8.8,7.3,2.3,40", hold_s=0.5)
    with EmulatedBenchProcess("six-coil", tmp_path / "pair-bench.toml",
                              extra_args=["--world", "pair"]) as rig_path:
        d = DaemonProcess(rig_path, tmp_path / "runs", tmp_path / "daemon.log")
        try:
            result = run_cli("execute", str(plan), "--connect", d.endpoints["command"], "--json",
                             cwd=tmp_path)
        finally:
            d.close()
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["reached"] is True and summary["tolerance_bl"] > 0
    assert summary["metrics"]["mode"] == "closed loop"
    run_dir = Path(summary["run"])
    assert run_dir.parent == tmp_path / "runs"
    # the report draws both agents, planned from the plan's states and measured from the camera
    report = run_cli("report", str(run_dir), "-o", str(tmp_path / "pair.png"), cwd=tmp_path)
    assert report.returncode == 0, report.stderr
    assert (tmp_path / "pair.png").stat().st_size > 10_000
    from rigctl.apps.report import _agent_paths

    source = json.loads(plan.read_text())
    start, body = source["start"], source["agents"]["body_diameter_mm"]
    half = 0.5 * start["r_bl"] * body * np.array([np.cos(np.radians(start["phi_deg"])),
                                                    np.sin(np.radians(start["phi_deg"]))])
    paths = _agent_paths(source, read_events(run_dir), summary)
    centre = np.array([start["x_mm"], start["y_mm"]])
    np.testing.assert_allclose(paths[0][0][0], centre - half, atol=1e-9)
    np.testing.assert_allclose(paths[1][0][0], centre + half, atol=1e-9)
    assert len(paths[0][1]) > 10  # tracked frames
    np.testing.assert_allclose(paths[0][1][0], centre - half, atol=0.5 * body)


def test_the_daemon_zeroes_a_supply_left_energised_before_it_serves(bench, tmp_path):
    """A process killed mid-run leaves a Kepco BOP at its last setpoint (it has no link watchdog):
    the daemon makes every device safe when it starts, before its READY line."""
    from rigctl.core.transport import open_transport
    from rigctl.drivers.kepco_bop import KepcoBop

    coil = load_rig(bench).coils[0]
    bop = KepcoBop(open_transport(coil.url), name=coil.name)
    bop.configure()
    bop.output(True)
    bop.set_current(2.0)
    bop.close()  # gone without a word, as a SIGKILLed stream process
    wait_for(lambda: abs(bench_currents(bench)[coil.name] - 2.0) < 0.05, 5.0, "2 A in the coil")
    d = DaemonProcess(bench, tmp_path / "runs", tmp_path / "daemon.log")
    try:
        # READY came after the make-safe; what remains is the coil's L/R decay
        wait_for(lambda: max(abs(a) for a in bench_currents(bench).values()) < 0.05, 1.0,
                 "every coil under 50 mA")
    finally:
        d.close()


def test_a_wrong_port_is_refused_before_anything_is_energised(bench, tmp_path):
    rig = load_rig(bench)
    text = bench.read_text().replace(rig.coils[2].url, "tcp://127.0.0.1:1")
    broken = tmp_path / "broken.toml"
    broken.write_text(text)
    for command in (["execute", str(EXAMPLES / "fig4-quick.json"), "--rig", str(broken),
                     "--runs", str(tmp_path / "runs")],
                    ["daemon", "--rig", str(broken), "--runs", str(tmp_path / "runs"),
                     "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
                     "--events", "tcp://127.0.0.1:0"]):
        done = run_cli(*command, cwd=tmp_path)
        assert done.returncode == 2, done.stderr
        lines = done.stderr.strip().splitlines()  # the daemon also logs (INFO) what it opened
        assert lines[-1].startswith(f"error: {rig.coils[2].name} (tcp://127.0.0.1:1)"), done.stderr
        assert command[0] == "daemon" or len(lines) == 1, done.stderr
        assert not (tmp_path / "runs").exists()  # no run record: nothing started
    assert max(abs(a) for a in bench_currents(bench).values()) < 0.05
