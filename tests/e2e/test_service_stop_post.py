"""The unit's `ExecStopPost=` makes the rig safe after the service died by SIGKILL (issue 15 item 2).

A Kepco BOP has no link watchdog: with the daemon and its stream process both killed mid-run (the
OOM killer, `systemctl kill -s KILL`), the emulated supplies hold their current. The unit's stop-
post command line, taken from `systemd/rigctl.service` and run as systemd runs it (no owner's
lock left, the kernel dropped it with the processes), must bring every supply's output, read from
the emulator's ground truth, under 50 mA; how long after the command's start is printed (about
1 s on a loaded 2-core machine, most of it the interpreter's start and imports).
"""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

from rigctl.apps.cli.service import DEFAULT_VENV
from rigctl.apps.client import Rig
from rigctl.apps.testing import descendants, wait_for
from rigctl.core.config import load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "systemd" / "rigctl.service"
UNIT_RIG = "/etc/rigctl/rig.toml"
SAFE_A = 0.05


def stop_post_command(rig_path: Path) -> list[str]:
    """The unit's ExecStopPost= command line, the unit's rig file replaced by `rig_path`."""
    (line,) = [v for k, _, v in (raw.partition("=") for raw in UNIT.read_text().splitlines())
               if k.strip() == "ExecStopPost"]
    argv = shlex.split(line.strip().lstrip("-@:+!"))  # systemd's prefixes, if any
    assert UNIT_RIG in argv, argv
    assert argv[0] == f"{DEFAULT_VENV}/bin/python3", argv  # the documented install's interpreter
    return [sys.executable] + [str(rig_path) if a == UNIT_RIG else a for a in argv[1:]]


def test_the_units_stop_post_makes_every_supply_safe_after_a_sigkill(tmp_path):
    env = {**os.environ, "RIGCTL_LOCK_DIR": str(tmp_path / "locks"), "PYTHONUNBUFFERED": "1"}
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml") as rig_path, \
            BackdoorClient(load_rig(rig_path).emulation.backdoor) as backdoor:
        def currents() -> dict[str, float]:
            return backdoor.request("truth")["currents_A"]

        with open(tmp_path / "daemon.log", "w") as log:
            daemon = subprocess.Popen(
                [sys.executable, "-m", "rigctl", "daemon", "--rig", str(rig_path), "--runs",
                 str(tmp_path / "runs"), "--command", "tcp://127.0.0.1:0", "--telemetry",
                 "tcp://127.0.0.1:0", "--events", "tcp://127.0.0.1:0"],
                stdout=subprocess.PIPE, stderr=log, text=True, env=env)
        try:
            ready = next((line for line in daemon.stdout if line.startswith("READY ")), None)
            assert ready, (tmp_path / "daemon.log").read_text()[-3000:]
            command = dict(f.split("=", 1) for f in ready[6:].split())["command"]
            plan = json.loads((ROOT / "plans" / "examples" / "fig4-two-magnets.json").read_text())
            with Rig(command) as rig:
                rig.execute(rig.load(plan))
            wait_for(lambda: max(map(abs, currents().values())) > 0.5, 60, "the coils to carry current")

            # stopped first, so that neither sees the other die and ramps the supplies down
            pids = [daemon.pid, *descendants(daemon.pid)]
            assert len(pids) > 1, "no stream process below the daemon"
            for sig in (signal.SIGSTOP, signal.SIGKILL):
                for pid in pids:
                    os.kill(pid, sig)
            daemon.wait(10)
            held = currents()
            assert max(map(abs, held.values())) > 0.5, held  # nothing else made the rig safe

            started = time.monotonic()
            stop_post = subprocess.Popen(stop_post_command(rig_path), env=env, text=True,
                                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
            wait_for(lambda: all(abs(a) < SAFE_A for a in currents().values()), 10,
                     "every supply under 50 mA")
            seconds = time.monotonic() - started
            out, _ = stop_post.communicate(timeout=30)
            assert stop_post.returncode == 0, out
            assert "every device made safe directly" in out, out
            # the time is a figure, not an assertion (a shared machine's load is in it)
            print(f"stop-post: every supply under {SAFE_A * 1e3:.0f} mA {seconds:.2f} s after "
                  f"its start (from {max(map(abs, held.values())):.2f} A)")
        finally:
            if daemon.poll() is None:
                daemon.kill()
                daemon.wait()
            daemon.stdout.close()
