"""Helpers of the browser tests: the daemon with its console on an emulated bench, and what
a test asks of a page (selenium's driver; `window.rigctlConsole` is what the page saw)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from rigctl.apps.client import Rig
from rigctl.core.config import dump_rig, load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "plans" / "examples"


class ConsoleDaemon:
    """`rigctl daemon --rig BENCH --console 127.0.0.1:0` with the example plans as its plans
    folder; `url`, `token` and the daemon's endpoints from its READY line."""

    def __init__(self, rig_path: Path, runs: Path, log_path: Path) -> None:
        self.rig_path = rig_path
        self.log = open(log_path, "w")  # noqa: SIM115 - closed by close()
        self.log_path = log_path
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rigctl", "daemon", "--rig", str(rig_path), "--runs", str(runs),
             "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
             "--events", "tcp://127.0.0.1:0", "--console", "127.0.0.1:0",
             "--console-plans", str(EXAMPLES)],
            stdout=subprocess.PIPE, stderr=self.log, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        for line in self.proc.stdout:  # readiness: the READY line, never a sleep
            if line.startswith("READY "):
                self.endpoints = dict(f.split("=", 1) for f in line[6:].split())
                self.url = self.endpoints["console"]
                self.token = self.endpoints["console_token"]
                return
        raise AssertionError(f"daemon did not start: {log_path.read_text()[-3000:]}")

    def client(self) -> Rig:
        return Rig(self.endpoints["command"])

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


PATIENT_REPLY_S = 3.0
"""The devices' reply watchdog on the browser tests' benches: a headless Chromium shares the
machine's cores with the bench, the daemon and the stream, and a 0.25 s watchdog that fires
under that load is not what these tests are about (tests/e2e/test_run_control.py tests it)."""


def bench_daemon(kind: str, tmp_path_factory) -> tuple:
    """A generator body for module fixtures: (daemon, backdoor) on an emulated `kind` bench."""
    folder = tmp_path_factory.mktemp(kind)
    with EmulatedBenchProcess(kind, folder / "bench.toml") as bench_path:
        rig = load_rig(bench_path)
        rig_path = folder / "console-bench.toml"
        rig_path.write_text(dump_rig(rig.model_copy(update={"stream": rig.stream.model_copy(
            update={"reply_timeout_s": max(rig.stream.reply_timeout_s, PATIENT_REPLY_S)})})))
        daemon = ConsoleDaemon(rig_path, folder / "runs", folder / "daemon.log")
        try:
            with BackdoorClient(load_rig(rig_path).emulation.backdoor) as backdoor:
                yield daemon, backdoor
        finally:
            daemon.close()


def js(driver, expression: str):
    return driver.execute_script(f"return {expression};")


def wait_page(driver, expression: str, timeout_s: float, what: str):
    """Until the page's `expression` is truthy; its value. Fails naming `what` and the page's
    state."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = js(driver, expression)
        if value:
            return value
        if time.monotonic() > deadline:
            seen = js(driver, "JSON.stringify({state: rigctlConsole.state, "
                      "reason: document.getElementById('reason').textContent, "
                      "reply: document.getElementById('reply').textContent, "
                      "frames: rigctlConsole.frames})")
            raise AssertionError(f"{what}: not within {timeout_s:g} s; the page: {seen}")
        time.sleep(0.05)


def open_console(browser, daemon: ConsoleDaemon, *, token: bool = True, width: int = 1280,
                 height: int = 800):
    driver = browser(width, height)
    driver.get(daemon.url + (f"#token={daemon.token}" if token else ""))
    wait_page(driver, "window.rigctlConsole && rigctlConsole.connected && rigctlConsole.status",
              30.0, "the page connected and got the daemon's status")
    return driver


def click(driver, element_id: str) -> None:
    driver.find_element("id", element_id).click()


def page_state(driver) -> str:
    return driver.find_element("id", "state").get_attribute("data-state")


def no_horizontal_scroll(driver) -> bool:
    return bool(js(driver, "document.documentElement.scrollWidth <= window.innerWidth"))
