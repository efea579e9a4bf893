"""`rigctl watch`: the live view of a rig's owner, from its telemetry, against a local `rigctl
execute` (found through the rig's lock) and against the daemon, on the emulated six-coil bench.
What it shows is checked against the rig file (channels, units, rate) and the emulator's ground
truth (the supplies' currents)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from rigctl.apps.client import Rig
from rigctl.apps.testing import wait_for
from rigctl.core.config import load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.rigs.owner import holder_of

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
RIGCTL = [sys.executable, "-m", "rigctl"]


@pytest.fixture
def bench(tmp_path):
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml") as rig_path:
        yield rig_path


def watch(*args) -> tuple[int, dict]:
    done = subprocess.run([*RIGCTL, "watch", *args, "--seconds", "1.5", "--json"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.returncode, json.loads(done.stdout)


def streaming(rig_path: Path) -> bool:
    """The run's stream has begun: the emulated supplies carry current."""
    with BackdoorClient(load_rig(rig_path).emulation.backdoor) as backdoor:
        return max(abs(a) for a in backdoor.request("truth")["currents_A"].values()) > 0.5


def check_view(view: dict, rig_path: Path) -> None:
    rig = load_rig(rig_path)
    assert view["state"] == "running"
    assert [c["name"] for c in view["channels"]] == [c.name for c in rig.coils]
    assert {c["unit"] for c in view["channels"]} == {"A"}
    assert view["stream"]["rate_hz"] == rig.stream.rate_hz and view["stream"]["cycles"] > 0
    limits = {c.name: c.current_limit_A for c in rig.coils}
    assert all(abs(c["commanded"]) <= limits[c["name"]] for c in view["channels"])
    assert any(abs(c["commanded"]) > 0.5 for c in view["channels"])  # the field is on


def test_watch_follows_a_local_run_through_the_rig_lock(bench, tmp_path):
    run = subprocess.Popen([*RIGCTL, "execute", str(EXAMPLES / "fig4-two-magnets.json"), "--rig",
                            str(bench), "--runs", str(tmp_path / "runs"), "-q"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        rig = load_rig(bench)
        wait_for(lambda: (holder_of(rig) or None) is not None and holder_of(rig).control, 30.0,
                 "the local run owns the rig")
        wait_for(lambda: streaming(bench), 30.0, "the stream begun")
        _, view = watch("--rig", str(bench))
        check_view(view, bench)
        assert view["endpoint"] == holder_of(rig).control
        # Ctrl-C is how a watch ends: exit 0, with the last view when stdout is not a terminal
        watching = subprocess.Popen([*RIGCTL, "watch", "--rig", str(bench)],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        wait_for(lambda: watching.poll() is None and streaming(bench), 10.0, "watching")
        import signal
        import time

        # it has started following: its socket to the run is open (its imports are done)
        def connected() -> bool:
            fds = Path(f"/proc/{watching.pid}/fd")
            for fd in os.listdir(fds):
                try:
                    if os.readlink(fds / fd).startswith("socket:"):
                        return True
                except FileNotFoundError:  # closed while we looked
                    continue
            return False

        wait_for(connected, 30.0, "the watch connected")
        time.sleep(1.0)  # it follows for a while (a wait on the process, not on a result)
        watching.send_signal(signal.SIGINT)
        out, err = watching.communicate(timeout=30)
        assert watching.returncode == 0, err
        # the run's live state (a camera frame late on a loaded machine suspends it for a moment)
        assert re.search(r"^state   (running|suspended)\b", out, re.M), out
        assert "interrupted" not in err
    finally:
        run.terminate()
        run.wait(30)
    after = subprocess.run([*RIGCTL, "watch", "--rig", str(bench), "--seconds", "0.5"],
                           capture_output=True, text=True, timeout=60)
    assert after.returncode == 2 and "no process owns this rig" in after.stderr


def test_watch_follows_the_daemon_a_run_and_a_hold(bench, tmp_path):
    from tests.e2e.test_daemon_cli import DaemonProcess

    daemon = DaemonProcess(bench, tmp_path / "runs", tmp_path / "daemon.log")
    try:
        plan = json.loads((EXAMPLES / "fig4-two-magnets.json").read_text())
        with Rig(daemon.endpoints["command"]) as rig, \
                BackdoorClient(load_rig(bench).emulation.backdoor) as backdoor:
            rig.execute(rig.load(plan))
            wait_for(lambda: streaming(bench), 30.0, "the stream begun")
            _, view = watch("--connect", daemon.endpoints["command"])
            check_view(view, bench)
            assert len(view["agents"]["tracked_mm"]) == len(plan["agents"])
            assert view["agents"]["source"] == "emulator ground truth"
            rig.abort()
            if rig.wait_state("idle", "faulted", timeout_s=30.0)["state"] == "faulted":
                rig.reset()  # on a loaded machine the stream process may miss its watchdog
            # a held field: constant currents, so what the view measured is what the emulated
            # supplies carry
            rig.hold({"field_mT": [2.0, 0.0, 1.0]}, ramp_s=0.05)
            def held():
                return backdoor.request("truth")["currents_A"]

            first = held()
            wait_for(lambda: all(abs(a - first[k]) < 1e-3 for k, a in held().items())
                     or first.update(held()), 5.0, "the coils settled")
            _, view = watch("--connect", daemon.endpoints["command"])
            truth = held()
            rig.release()
        assert view["state"] == "running" and view["run"]["kind"] == "hold"
        for channel in view["channels"]:
            assert abs(channel["measured"] - truth[channel["name"]]) < 0.02, (channel, truth)
        assert max(abs(a) for a in truth.values()) > 0.5
    finally:
        daemon.close()
