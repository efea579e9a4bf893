"""Benchmark: the operator console (`rigctl daemon --console`) in headless Chromium, on the
emulated six-coil bench. Prints one JSON object.

- frame captured -> overlay drawn: the browser's own clock (`performance.timeOrigin +
  performance.now()` when the frame and its overlays are on the canvas) against the camera's
  capture time (the emulated camera stamps it; the console puts it on the wall clock, which the
  browser reads too, on this machine), for every frame the page drew during a closed-loop run at
  the camera's rate; p50 / p99 / max ms (the issue: p99 under 100 ms);
- E-STOP click -> every supply commanded to 0 A: the page's click (its wall clock) -> the run
  record's `estop_zeroed.told_unix` (this machine's wall clock: every supply told 0 A and off), and
  the page's click -> the reply (the daemon replies once the stream process has written 0 A and
  output off to every supply: an upper bound), next to one stream period plus the page's own
  WebSocket round trip (a request the console answers itself); the run record's `estop_zeroed`
  (daemon received -> every supply told) and the bench's truth (every coil under 0.05 A, set by
  L/R) beside it;
- ten pages watching vs none: the same plan run `--repeats` times each way, alternately; the
  stream's late share (its `stream` telemetry) and `status` p99 (this process asks 50 times a
  second), with the spread between runs of the same kind as the run-to-run noise; once with ten
  Chromium tabs, at SCHED_IDLE by default (`--pages-at idle`: pages on other computers, as a lab
  watches; they load the daemon with their sockets but take no core from the rig; `--pages-at
  normal` puts their decoding and drawing on the rig's own cores), once with ten plain WebSocket
  clients in one process (the console's own cost).
The daemon streams at SCHED_FIFO 40 (`--realtime`, as systemd/rigctl.service runs it); the bench's
emulator and the pages at normal priority (`--emulator-realtime PRIO` puts the emulator above the
daemon, as supplies with their own processors are, but its one thread renders the camera too).

    python bench/console.py                 # about 3 minutes
    python bench/console.py --quick         # one short run of each
    python bench/console.py --smoke         # the smallest run of each (the test suite's)
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from daemon import make_emulator_realtime  # bench/daemon.py

from rigctl.apps.client import Rig
from rigctl.core.config import dump_rig, load_rig
from rigctl.core.record import read_events
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess

EXAMPLES = Path(__file__).resolve().parents[1] / "plans" / "examples"
CHROMIUM = os.environ.get("RIGCTL_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("RIGCTL_CHROMEDRIVER", "/usr/bin/chromedriver")


class ConsoleDaemon:
    def __init__(self, rig_path: Path, runs: Path, log_path: Path, realtime: int = 0) -> None:
        self.log = open(log_path, "w")  # noqa: SIM115 - closed by close()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rigctl", "daemon", "--rig", str(rig_path), "--runs", str(runs),
             "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
             "--events", "tcp://127.0.0.1:0", "--console", "127.0.0.1:0",
             *(["--realtime", str(realtime)] if realtime else [])],
            stdout=subprocess.PIPE, stderr=self.log, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        for line in self.proc.stdout:
            if line.startswith("READY "):
                self.endpoints = dict(f.split("=", 1) for f in line[6:].split())
                return
        raise RuntimeError(f"the daemon did not start: {log_path.read_text()[-2000:]}")

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


def chromium(width: int = 1280, height: int = 800, idle: bool = False):
    """Headless Chromium; `idle`: the driver, the browser and every process it starts at
    SCHED_IDLE (they inherit it), so that they run only on CPU nothing else on this machine wants:
    pages on other computers, as a lab's operators watch, which load the daemon with their
    requests and sockets but not the rig's cores with their decoding and drawing."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                f"--window-size={width},{height}"):
        options.add_argument(arg)
    popen = {"preexec_fn": _sched_idle} if idle else {}
    return webdriver.Chrome(service=Service(CHROMEDRIVER, popen_kw=popen), options=options)


def _sched_idle() -> None:
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def wait_js(driver, expression: str, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while True:
        value = driver.execute_script(f"return {expression};")
        if value:
            return value
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what}: not within {timeout_s:g} s")
        time.sleep(0.02)


def open_page(driver, endpoints: dict, token: bool = True) -> None:
    driver.get(endpoints["console"] + (f"#token={endpoints['console_token']}" if token else ""))
    wait_js(driver, "window.rigctlConsole && rigctlConsole.connected && rigctlConsole.status",
            30.0, "the page connected")


def percentiles(values: list[float], digits: int = 2) -> dict:
    a = np.asarray(values, dtype=float)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "p50": round(float(np.percentile(a, 50)), digits),
            "p99": round(float(np.percentile(a, 99)), digits), "max": round(float(a.max()), digits)}


def energised(backdoor) -> bool:
    return max(abs(a) for a in backdoor.request("truth")["currents_A"].values()) > 0.5


def safe(truth: dict) -> bool:
    return all(abs(a) < 0.05 for a in truth["currents_A"].values())


def settle(rig: Rig) -> None:
    state = rig.status()["state"]
    if state in ("running", "paused", "suspended"):
        rig.abort()
        state = rig.wait_state("idle", "faulted", "estopped", timeout_s=60)["state"]
    if state in ("faulted", "estopped"):
        deadline = time.monotonic() + 60
        while rig.status().get("run") is not None:  # still stopping: reset would be `busy`
            if time.monotonic() > deadline:
                raise RuntimeError("the run did not stop within 60 s")
            time.sleep(0.05)
        rig.reset()
    rig.wait_state("idle", timeout_s=60)


def start_streaming(rig: Rig, backdoor, plan: dict, attempts: int = 3) -> None:
    """Load and execute `plan` until the supplies carry current; a run that faulted first (a
    watchdog on a loaded machine) is reset and started again, at most `attempts` times."""
    for attempt in range(attempts):
        rig.execute(rig.load(plan))
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            if energised(backdoor):
                return
            status = rig.status()
            if status["state"] in ("faulted", "estopped", "idle"):
                break
            time.sleep(0.02)
        print(f"the run did not stream (attempt {attempt + 1}): {status['state']} "
              f"{status.get('device')}: {status.get('reason')}", file=sys.stderr)
        settle(rig)
    raise RuntimeError(f"the run never energised the supplies in {attempts} attempts")


def frame_latency(rig: Rig, driver, backdoor, plan: dict, seconds: float,
                  camera_fps: float | None) -> dict:
    """A closed-loop run with one page open: every frame the page drew, capture -> drawn."""
    start_streaming(rig, backdoor, plan)
    driver.execute_script("rigctlConsole.frameLatenciesMs.length = 0; "
                          "rigctlConsole.frameReceivedMs.length = 0; rigctlConsole.frames = 0;")
    t0 = time.monotonic()
    time.sleep(seconds)
    span = time.monotonic() - t0
    latencies = driver.execute_script("return rigctlConsole.frameLatenciesMs.slice();")
    received = driver.execute_script("return rigctlConsole.frameReceivedMs.slice();")
    frames = driver.execute_script("return rigctlConsole.frames;")
    settle(rig)
    return {"frames_drawn": frames, "drawn_per_s": round(frames / span, 1),
            "camera_fps": camera_fps, "capture_to_drawn_ms": percentiles(latencies),
            "capture_to_received_by_the_page_ms": percentiles(received),
            "p99_under_100_ms": bool(latencies) and float(np.percentile(latencies, 99)) < 100.0}


def estop_latency(rig: Rig, driver, backdoor, plan: dict, runs: Path, rate_hz: float) -> dict:
    rtts = []
    for _ in range(20):  # the page's own round trip: a request the console answers itself
        rtts.append(driver.execute_async_script(
            "const done = arguments[arguments.length - 1]; const t = performance.now();"
            "rigctlConsole.request('plans').then(() => done(performance.now() - t));"))
    start_streaming(rig, backdoor, plan)
    before = driver.execute_script("return rigctlConsole.estops.length;")
    driver.find_element("id", "estop").click()
    clicked_unix = driver.execute_script(f"return rigctlConsole.estops[{before}].clicked_ms;") / 1e3
    polls = 0
    while not safe(backdoor.request("truth")):
        polls += 1
    safe_unix = time.time()
    entry = wait_js(driver, f"rigctlConsole.estops[{before}].replied_ms && "
                    f"rigctlConsole.estops[{before}]", 10.0, "the e-stop's reply")
    last = rig.wait_state("estopped", timeout_s=10)
    settle(rig)
    run_id = (rig.status().get("last_run") or last.get("last_run") or {}).get("run")
    zeroed = None
    if run_id:
        zeroed = next((e for e in read_events(Path(run_id)) if e["event"] == "estop_zeroed"), None)
    period_ms = 1e3 / rate_hz
    click_to_reply = entry["replied_ms"] - entry["clicked_ms"]
    # the goal's figure: the click (the page's wall clock) to every supply told 0 A and off (the
    # run record's wall clock, this machine's, so the same clock)
    click_to_told = (1e3 * zeroed["told_unix"] - entry["clicked_ms"]
                     if zeroed and "told_unix" in zeroed else None)
    rtt = float(np.median(rtts))
    return {"ok": entry["ok"], "stream_period_ms": round(period_ms, 3),
            "page_round_trip_ms": percentiles(rtts, 3),
            "click_to_every_supply_told_ms": (None if click_to_told is None
                                              else round(click_to_told, 2)),
            "within_one_period_plus_round_trip": (click_to_told is not None
                                                  and click_to_told <= period_ms + rtt),
            "click_to_reply_ms": round(click_to_reply, 2),
            "click_to_reply_means": "the daemon replies once the stream process said every supply "
                                    "was written 0 A and off",
            "daemon_received_to_every_supply_told_ms": (
                round(zeroed["after_request_s"] * 1e3, 3) if zeroed else None),
            "click_to_coils_under_50_mA_ms": round((safe_unix - clicked_unix) * 1e3, 1),
            "truth_polls_until_safe": polls}


def stream_and_status(rig: Rig, plan: dict, pages: int, seconds: float) -> dict:
    """One run of `plan` (aborted after `seconds` of streaming) with `pages` pages open; over the
    streaming window: the stream's late share (its `stream` telemetry: late cycles / cycles) and
    `status` round trips from this process, 50 a second."""
    telemetry = rig.telemetry(["stream"])
    rig.execute(rig.load(plan))
    first = None
    deadline = time.monotonic() + 60
    while first is None:  # the stream has begun (the camera found the magnets, the supplies on)
        msg = telemetry.receive(timeout_s=1.0)
        if msg is not None and msg.cycles > 0:
            first = msg
        if time.monotonic() > deadline:
            raise RuntimeError("the run never streamed")
    rtts, last = [], first
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        t0 = time.perf_counter()
        rig.status()
        rtts.append((time.perf_counter() - t0) * 1e6)
        msg = telemetry.receive(timeout_s=0.0)
        while msg is not None:
            last = msg if msg.cycles >= last.cycles else last
            msg = telemetry.receive(timeout_s=0.0)
        time.sleep(0.02)
    telemetry.close()
    settle(rig)
    cycles = last.cycles - first.cycles
    late = (last.late_cycles - first.late_cycles) / cycles if cycles > 0 else None
    return {"pages": pages, "late_share": None if late is None else round(late, 5),
            "cycles": cycles, "status_us": percentiles(rtts, 1)}


def websocket_watchers(url: str, n: int) -> None:
    """`n` WebSocket clients of the console reading everything it sends, in this process, until
    killed: the console's own cost of pages, without a browser's decoding and drawing."""
    import asyncio

    import aiohttp

    async def one(session) -> None:
        async with session.ws_connect(url.replace("http", "ws", 1) + "ws",
                                      origin=url.rstrip("/")) as ws:
            await ws.send_str(json.dumps({"type": "hello", "token": ""}))
            async for _ in ws:
                pass

    async def run() -> None:
        async with aiohttp.ClientSession() as session:
            await asyncio.gather(*(one(session) for _ in range(n)))

    asyncio.run(run())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=15.0, help="per measured run")
    parser.add_argument("--repeats", type=int, default=2, help="runs with 0 and with 10 pages each")
    parser.add_argument("--pages", type=int, default=10)
    parser.add_argument("--quick", action="store_true", help="one short run of each")
    parser.add_argument("--smoke", action="store_true",
                        help="the smallest run of every stage, for the test suite: its figures "
                             "mean nothing (half-second runs, one watching page)")
    parser.add_argument("--realtime", type=int, default=40, metavar="PRIO",
                        help="the daemon's --realtime, as systemd/rigctl.service gives it "
                             "(default 40; 0: normal scheduling)")
    parser.add_argument("--emulator-realtime", type=int, default=0, metavar="PRIO",
                        help="the bench's emulator at SCHED_FIFO PRIO, e.g. 45, above the daemon "
                             "(default 0: normal scheduling: its one thread also renders the "
                             "camera's frames, which at SCHED_FIFO starve the page: frame p99 "
                             "365-439 ms against 88-134 ms, measured)")
    parser.add_argument("--pages-at", choices=("idle", "normal"), default="idle",
                        help="the ten watching tabs' scheduling: idle (default: SCHED_IDLE, pages on "
                             "other computers, as in a lab) or normal (on the rig's own cores)")
    parser.add_argument("--watchers-of", metavar="URL", help=argparse.SUPPRESS)  # (internal)
    args = parser.parse_args()
    if args.watchers_of:
        websocket_watchers(args.watchers_of, args.pages)
        return
    if args.quick:
        args.seconds, args.repeats, args.pages = 2.0, 1, 2
    if args.smoke:
        args.seconds, args.repeats, args.pages = 0.5, 1, 1
    plan = json.loads((EXAMPLES / "fig4-two-magnets.json").read_text())
    out: dict = {"bench": "console", "rig": "six-coil", "seconds": args.seconds,
                 "pages_at": args.pages_at,
                 "cpus": os.cpu_count(), "load_average_1min_before": round(os.getloadavg()[0], 2)}
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-console-") as tmp_name:
        tmp = Path(tmp_name)
        with EmulatedBenchProcess("six-coil", tmp / "bench.toml") as rig_path:
            rig_file = load_rig(rig_path)
            # a browser shares these two cores: the devices' watchdog as in the browser tests
            patient = tmp / "console-bench.toml"
            patient.write_text(dump_rig(rig_file.model_copy(update={"stream": rig_file.stream.model_copy(
                update={"reply_timeout_s": max(rig_file.stream.reply_timeout_s, 3.0)})})))
            # as deployed: the daemon's stream at SCHED_FIFO (systemd/rigctl.service); the pages
            # at normal priority (on a lab's network they are other machines)
            out["emulator_realtime_priority"] = (
                make_emulator_realtime(rig_file.emulation.pid, args.emulator_realtime)
                if args.emulator_realtime else None)
            daemon = ConsoleDaemon(patient, tmp / "runs", tmp / "daemon.log", args.realtime)
            out["daemon_realtime"] = args.realtime
            drivers = []
            try:
                with Rig(daemon.endpoints["command"], timeout_s=5.0) as rig, \
                        BackdoorClient(rig_file.emulation.backdoor) as backdoor:
                    driver = chromium()
                    drivers.append(driver)
                    open_page(driver, daemon.endpoints)
                    out["frames"] = frame_latency(rig, driver, backdoor, plan, args.seconds,
                                                  rig_file.camera.fps if rig_file.camera else None)
                    out["estop"] = estop_latency(rig, driver, backdoor, plan, tmp / "runs",
                                                 rig_file.stream.rate_hz)
                    driver.quit()
                    drivers.clear()
                    runs: dict[int, list] = {0: [], args.pages: []}
                    watchers = None
                    for _ in range(args.repeats):
                        for pages in (0, args.pages):
                            if pages and watchers is None:
                                watchers = chromium(idle=args.pages_at == "idle")
                                drivers.append(watchers)
                                open_page(watchers, daemon.endpoints, token=False)
                                for _ in range(pages - 1):
                                    watchers.switch_to.new_window("tab")
                                    open_page(watchers, daemon.endpoints, token=False)
                            if not pages and watchers is not None:
                                watchers.quit()
                                drivers.remove(watchers)
                                watchers = None
                            runs[pages].append(stream_and_status(rig, plan, pages, args.seconds))
                    if watchers is not None:  # the last run had the pages open
                        watchers.quit()
                        drivers.remove(watchers)
                    out["pages"] = summarise_pages(runs, args.pages)
                    # the same without a browser: the console's own cost of the pages' sockets
                    runs = {0: [], args.pages: []}
                    for _ in range(args.repeats):
                        for pages in (0, args.pages):
                            clients = None
                            if pages:
                                clients = subprocess.Popen(
                                    [sys.executable, __file__, "--watchers-of",
                                     daemon.endpoints["console"], "--pages", str(pages)])
                            try:
                                runs[pages].append(stream_and_status(rig, plan, pages,
                                                                     args.seconds))
                            finally:
                                if clients is not None:
                                    clients.kill()
                                    clients.wait()
                    out["websocket_watchers"] = summarise_pages(runs, args.pages)
            finally:
                for driver in drivers:
                    driver.quit()
                daemon.close()
    out["load_average_1min_after"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


def summarise_pages(runs: dict[int, list], pages: int) -> dict:
    def figure(run: dict, key: str):
        return run["late_share"] if key == "late_share" else run["status_us"].get("p99")

    result: dict = {"runs": runs}
    for key in ("late_share", "status_p99_us"):
        none = [figure(r, key) for r in runs[0] if figure(r, key) is not None]
        some = [figure(r, key) for r in runs[pages] if figure(r, key) is not None]
        if not none or not some:
            continue
        noise = max(np.ptp(none) if len(none) > 1 else 0.0, np.ptp(some) if len(some) > 1 else 0.0)
        diff = float(np.mean(some) - np.mean(none))
        result[key] = {"none": round(float(np.mean(none)), 5), f"{pages}_pages": round(float(np.mean(some)), 5),
                       "difference": round(diff, 5), "run_to_run_noise": round(float(noise), 5),
                       "within_noise": bool(abs(diff) <= noise) if len(none) > 1 else None}
    return result


if __name__ == "__main__":
    main()
