"""A rig kind from outside rigctl (examples/rigctl-grbl-spinner), installed with pip and run as a
user runs rigctl (issue 36 item 3): `rigctl emulate grbl-spinner`, `init`, `doctor`, `execute` of
a short plan, the daemon (load, pause, resume, e-stop) with its console's page, and `faults`.

The package is installed with `pip install --no-deps --target DIR` once for the module and found
through PYTHONPATH by every rigctl process (importlib.metadata reads entry points from sys.path):
the test environment itself stays as it was for the other tests. One bench and one daemon serve
the module's tests. What is checked of the rotor comes from the emulator's truth (the GRBL model's
angle and rate), not from rigctl."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rigctl.apps.client import Rig
from rigctl.apps.testing import run_rigctl, wait_for
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "examples" / "rigctl-grbl-spinner"
KIND = "grbl-spinner"


def spin_plan(*segments: tuple[float, float], name: str = "e2e spin") -> dict:
    return {"schema": "rigctl.plan/1", "kind": "spin-sequence", "rig": KIND, "name": name,
            "segments": [{"rate_hz": r, "duration_s": d} for r, d in segments],
            "tolerance_hz": 0.1}


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The example package pip-installed into a folder of its own, on every child's PYTHONPATH."""
    target = tmp_path_factory.mktemp("site")
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                           "--disable-pip-version-check", "--target", str(target), str(PACKAGE)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (target / "rigctl_grbl_spinner").is_dir()
    with pytest.MonkeyPatch.context() as patch:
        path = os.environ.get("PYTHONPATH")
        patch.setenv("PYTHONPATH", str(target) + (os.pathsep + path if path else ""))
        yield target


@pytest.fixture(scope="module")
def bench(installed, tmp_path_factory):
    """`rigctl emulate grbl-spinner`: its rig file and a backdoor to its truth."""
    folder = tmp_path_factory.mktemp("bench")
    with EmulatedBenchProcess(KIND, folder / "bench.toml") as rig_path, \
            BackdoorClient(load_rig_in_child(rig_path)["backdoor"]) as backdoor:
        yield rig_path, backdoor


def load_rig_in_child(rig_path: Path) -> dict:
    """The bench's rig file read as rigctl reads it, in a process that has the package (this
    one may not import it: it is not installed here)."""
    code = ("import json, sys; from rigctl.core.config import load_rig; r = load_rig(sys.argv[1]); "
            "print(json.dumps({'kind': r.rig.kind, 'backdoor': r.emulation.backdoor, "
            "'url': r.grbl.url}))")
    done = subprocess.run([sys.executable, "-c", code, str(rig_path)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def rate(backdoor) -> float:
    return backdoor.request("truth")["rate_hz"]


def test_the_installed_kind_is_listed_and_its_rig_file_written(installed, tmp_path):
    help_text = run_rigctl("emulate", "--help", cwd=tmp_path).stdout
    assert KIND in help_text
    out = tmp_path / "spinner.toml"
    done = run_rigctl("init", KIND, "-o", str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert 'kind = "grbl-spinner"' in out.read_text() and "$120=7200" in out.read_text()


def test_doctor_asks_the_emulated_controller_for_its_status(bench, tmp_path):
    rig_path, backdoor = bench
    done = run_rigctl("doctor", "--rig", str(rig_path), "--json", cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    (probe,) = json.loads(done.stdout)["devices"]
    assert probe["device"] == "grbl" and probe["ok"] and probe["detail"].startswith("Idle, MPos X")
    assert backdoor.request("truth")["lines"] == 0  # read-only: a `?`, no line sent


def test_execute_spins_at_the_plans_rates(bench, tmp_path):
    rig_path, backdoor = bench
    plan = tmp_path / "spin.json"
    plan.write_text(json.dumps(spin_plan((2.0, 0.8), (-1.0, 0.7))))
    checked = run_rigctl("validate", str(plan), "--rig", str(rig_path), cwd=tmp_path)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    angle0 = backdoor.request("truth")["angle_deg"]
    done = run_rigctl("execute", str(plan), "--rig", str(rig_path), "--json",
                      "--runs", str(tmp_path / "runs"), cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    summary = json.loads(done.stdout)
    assert summary["reached"] and summary["safe"] and summary["state"] == "done"
    measured = [s["measured_hz"] for s in summary["metrics"]["segments"]]
    assert measured == pytest.approx([2.0, -1.0], abs=0.1)
    truth = backdoor.request("truth")
    assert truth["rate_hz"] == 0.0 and truth["state"] == "Idle"
    # the rotor's own angle is what the controller's reports add up to
    turns = (truth["angle_deg"] - angle0) / 360.0
    assert turns == pytest.approx(summary["metrics"]["turns_measured"], abs=0.1)


def test_a_plan_beyond_the_rigs_max_rate_is_refused_before_anything_starts(installed, tmp_path):
    plan = tmp_path / "fast.json"
    plan.write_text(json.dumps(spin_plan((7.5, 2.0))))
    done = run_rigctl("execute", str(plan), cwd=tmp_path)
    assert done.returncode == 2
    assert "rotation rate of segment 1: 7.5 Hz (limit 5" in done.stderr
    assert "Traceback" not in done.stderr


@pytest.fixture(scope="module")
def daemon(bench, tmp_path_factory):
    """`rigctl daemon --rig BENCH --console 127.0.0.1:0` on the module's bench."""
    rig_path, backdoor = bench
    folder = tmp_path_factory.mktemp("daemon")
    log = open(folder / "daemon.log", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "rigctl", "daemon", "--rig", str(rig_path), "--runs",
         str(folder / "runs"), "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
         "--events", "tcp://127.0.0.1:0", "--console", "127.0.0.1:0"],
        stdout=subprocess.PIPE, stderr=log, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        endpoints = None
        for line in proc.stdout:
            if line.startswith("READY "):
                endpoints = dict(f.split("=", 1) for f in line[6:].split())
                break
        assert endpoints is not None, (folder / "daemon.log").read_text()[-3000:]
        with Rig(endpoints["command"], timeout_s=10.0) as rig:
            yield rig, endpoints, backdoor
    finally:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        log.close()


def test_the_daemon_pauses_resumes_and_e_stops_the_spinner(daemon):
    rig, _, backdoor = daemon
    rig.execute(rig.load(spin_plan((2.0, 30.0), name="daemon spin")))
    rig.wait_state("running", timeout_s=30)
    try:
        wait_for(lambda: abs(rate(backdoor) - 2.0) < 0.05, 10, "the rotor at 2 turns/s")
    except AssertionError:
        raise AssertionError(f"{rig.status()} {backdoor.request('truth')}") from None
    rig.pause(immediate=True)
    rig.wait_state("paused")
    wait_for(lambda: rate(backdoor) == 0.0, 5, "the rotor at rest while paused")
    rig.resume()
    rig.wait_state("running")
    wait_for(lambda: abs(rate(backdoor) - 2.0) < 0.05, 10, "the rotor at 2 turns/s again")
    reply = rig.estop()
    assert reply["state"] == "estopped" and reply["unreached"] == []
    wait_for(lambda: rate(backdoor) == 0.0, 1.0, "the rotor stopped by the e-stop")
    assert backdoor.request("truth")["state"] == "Alarm"  # GRBL: reset while in motion
    wait_for(lambda: rig.status()["run"] is None, 30, "the run to end")
    rig.reset()


def test_the_console_serves_its_page_and_the_kinds_status(daemon):
    _, endpoints, _ = daemon
    url, token = endpoints["console"], endpoints["console_token"]

    async def look() -> tuple[int, str, dict]:
        import aiohttp

        async with aiohttp.ClientSession() as session:
            async with session.get(url) as page:
                body = await page.text()
            async with session.ws_connect(url + "ws", headers={"Origin": url.rstrip("/")}) as ws:
                await ws.send_str(json.dumps({"token": token}))
                async for message in ws:
                    data = json.loads(message.data)
                    if data.get("topic") == "console.status":
                        return page.status, body, data["status"]
        raise AssertionError("no status from the console")

    status_code, body, status = asyncio.run(asyncio.wait_for(look(), 20))
    assert status_code == 200 and "<html" in body.lower()
    assert status["rig"]["kind"] == KIND
    assert [d["name"] for d in status["devices"]] == ["grbl"]


def test_the_fault_campaigns_quick_cells_leave_the_rotor_safe(installed, tmp_path):
    done = run_rigctl("faults", "--rig", KIND, "--quick", "--json", cwd=tmp_path, timeout_s=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    cells = json.loads(done.stdout)["cells"]
    assert cells and all(c["ok"] and c["safe"] for c in cells)
