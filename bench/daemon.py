"""Benchmark: the daemon under load, as the issue asks. Prints one JSON object.

The emulated six-coil bench runs in its own process, `rigctl daemon` in another (stream at
1 kHz), and this process is the operator: it submits a plan of back-and-forth rolling moves and
measures, while the plan streams,
- the `status` round trip over tcp loopback (p50, p99, max, microseconds), 100 requests a second
  from this process (nothing else in it), each followed by a bare REQ/REP echo of the same size
  to a process that does nothing else: the floor on this machine under the same load, so that a
  slow figure can be told from a slow machine. Also both with the daemon idle, and which threads
  ran at SCHED_FIFO (`--realtime`, as the systemd unit gives it);
- telemetry delivered to 1 and to 10 subscribers: `currents` messages per second per subscriber,
  against the stream rate, and lost `state` / `fault` messages (sequence gaps);
- e-stop latency: request received by the daemon -> seen by the stream thread -> every supply
  told zero and switched off (from the run record's `estop_zeroed` event, in stream periods too),
  request sent -> reply, and request sent -> every measured
  current under 0.05 A on the emulated supplies (set by the coils' L/R, not by rigctl).

    python bench/daemon.py               # about a minute
    python bench/daemon.py --moves 8     # quicker
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess

from rigctl.client import Rig, Telemetry
from rigctl.config import dump_rig, load_rig
from rigctl.record import read_events

RATE_HZ = 1000.0


def back_and_forth_plan(moves: int) -> dict:
    """One rolling magnet going 10 mm (one turn) right and back, `moves` times."""
    return {
        "schema": "rigctl.plan/1", "kind": "global-moves", "rig": "six-coil", "name": "bench",
        "workspace": {"boundary": {"rect": [-100, -100, 200, 200]}},
        "agents": [{"start": [0.0, 0.0], "goal": [0.0, 0.0], "radius": 3.0}],
        "moves": [[10.0, 0.0] if k % 2 == 0 else [-10.0, 0.0] for k in range(moves)],
    }


def start_daemon(rig_path: Path, runs: Path, log_path: Path,
                 realtime: int = 0) -> tuple[subprocess.Popen, dict]:
    cmd = [sys.executable, "-m", "rigctl", "daemon", "--rig", str(rig_path), "--runs", str(runs),
           "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
           "--events", "tcp://127.0.0.1:0"]
    if realtime:
        cmd += ["--realtime", str(realtime)]
    log = open(log_path, "w")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    for line in proc.stdout:
        if line.startswith("READY "):
            return proc, dict(field.split("=", 1) for field in line[6:].split())
    raise RuntimeError(f"the daemon did not start: {log_path.read_text()[-2000:]}")


class Subscriber(threading.Thread):
    def __init__(self, endpoints: dict, stop: threading.Event) -> None:
        super().__init__(daemon=True)
        self.feed = Telemetry(endpoints["telemetry"], endpoints["events"],
                              ["actuators", "state", "fault"])
        self.stop_event = stop
        self.arrivals: list[tuple[float, int]] = []  # (time received, cycles in the message)

    def run(self) -> None:
        while not self.stop_event.is_set():
            msg = self.feed.receive(timeout_s=0.2)
            if msg is not None and msg.topic == "actuators":
                self.arrivals.append((time.monotonic(), len(msg.samples)))
        self.feed.close()


def delivered_rate(subscribers: list[Subscriber], window: tuple[float, float],
                   stream: dict) -> dict:
    """Cycles delivered per second to each subscriber, against the cycles the stream ran."""
    span = window[1] - window[0]
    rates = [sum(n for t, n in s.arrivals if window[0] <= t <= window[1]) / span
             for s in subscribers]
    lost = {topic: sum(s.feed.lost.get(topic, 0) for s in subscribers) for topic in
            ("actuators", "state", "fault")}
    return {"subscribers": len(subscribers),
            "stream_cycles_per_s": round(stream["cycles_per_s"], 1),
            "stream_late_share": round(stream["late_share"], 4),
            "delivered_cycles_per_s_min": round(min(rates), 1),
            "delivered_cycles_per_s_mean": round(float(np.mean(rates)), 1),
            "lost_messages": lost}


def renice(pid: int, nice: int) -> None:
    """Every thread of process `pid` to `nice` (Linux: a nice value is a thread's)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        os.setpriority(os.PRIO_PROCESS, int(task.name), nice)


def realtime_threads(pid: int) -> list[str]:
    """Threads of process `pid` and its children at SCHED_FIFO: "process/thread name"."""
    found = []
    children = Path(f"/proc/{pid}/task/{pid}/children")
    pids = [pid, *map(int, children.read_text().split())] if children.exists() else [pid]
    for p in pids:
        for task in Path(f"/proc/{p}/task").iterdir():
            try:
                stat = (task / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()
            if fields[38] == "1":  # policy (field 41 of stat): 1 is SCHED_FIFO
                found.append(f"{p}/{(task / 'comm').read_text().strip()}")
    return found


def timed_run(rig: Rig, plan_id: str, n_subscribers: int, endpoints: dict,
              echo: BareEcho | None = None) -> dict:
    """One run of the plan with `n_subscribers` telemetry subscribers in this process, or (with
    `echo`, and no subscriber here, whose decoding would hold this process's GIL) an operator
    script polling `status` 100 times a second, each followed by a bare echo round trip (the floor
    under the same load). What was measured, and the stream."""
    stop = threading.Event()
    subscribers = [Subscriber(endpoints, stop) for _ in range(n_subscribers)]
    for s in subscribers:
        s.start()
    time.sleep(0.5)  # let the subscriptions reach the publisher (a PUB drops before that)
    rig.execute(plan_id)
    rig.wait_state("running")
    time.sleep(0.5)
    realtime = realtime_threads(rig.ping()["pid"])
    start = time.monotonic()
    rtts: dict[str, list[float]] = {"status": [], "bare": []}
    while rig.status()["state"] in ("running", "paused"):
        if echo is not None:  # `status` and the bare echo in turn, 200 requests a second
            for name, call in (("status", rig.status), ("bare", echo.call)):
                t0 = time.perf_counter()
                call()
                rtts[name].append(time.perf_counter() - t0)
                time.sleep(max(0.0, 0.005 - (time.perf_counter() - t0)))
        else:
            time.sleep(0.05)
    end = time.monotonic() - 0.2
    stop.set()
    for s in subscribers:
        s.join()
    while rig.status()["run"] is not None:
        time.sleep(0.05)
    summary = rig.run(Path(rig.status()["last_run"]["run"]).name)["summary"]
    if summary["stream"] is None or summary["faults"]:
        raise RuntimeError(f"the benchmark's run did not stream cleanly: {summary['faults']}")
    stream = dict(summary["stream"])
    stream["cycles_per_s"] = stream["cycles"] / summary["duration_s"]
    if echo is not None:
        return {**microseconds(rtts["status"]), "bare_echo": microseconds(rtts["bare"]),
                "stream_late_share": round(stream["late_share"], 4), "realtime_threads": realtime}
    return delivered_rate(subscribers, (start, end), stream)


def round_trips(call, seconds: float = 4.0, rate_hz: float = 200.0) -> dict:
    """`call()` round trips at `rate_hz` for `seconds`: p50, p99, max in microseconds."""
    rtts = []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        call()
        rtts.append(time.perf_counter() - t0)
        time.sleep(max(0.0, 1.0 / rate_hz - (time.perf_counter() - t0)))
    return microseconds(rtts)


def microseconds(seconds: list[float]) -> dict:
    us = np.asarray(seconds) * 1e6
    return {"samples": len(us), "p50_us": round(float(np.percentile(us, 50)), 1),
            "p99_us": round(float(np.percentile(us, 99)), 1), "max_us": round(float(us.max()), 1)}


BARE_REP = """
import sys, zmq
sock = zmq.Context().socket(zmq.REP)
port = sock.bind_to_random_port("tcp://127.0.0.1")
print(port, flush=True)
while True:
    sock.send(sock.recv())
"""


class BareEcho:
    """The floor: a REQ/REP echo of a status-sized reply over tcp loopback, served by another
    process that does nothing else; `call()` is one round trip."""

    def __enter__(self) -> "BareEcho":
        import zmq

        self.server = subprocess.Popen([sys.executable, "-c", BARE_REP], stdout=subprocess.PIPE,
                                       text=True)
        port = int(self.server.stdout.readline())
        self.sock = zmq.Context.instance().socket(zmq.REQ)
        self.sock.connect(f"tcp://127.0.0.1:{port}")
        for _ in range(100):
            self.call()
        return self

    def call(self) -> None:
        self.sock.send(b"x" * 700)
        self.sock.recv()

    def __exit__(self, *exc: object) -> None:
        self.sock.close(linger=0)
        self.server.kill()
        self.server.wait()


def estop_latency(rig: Rig, plan_id: str, backdoor_url: str, runs: Path) -> dict:
    rig.execute(plan_id)
    rig.wait_state("running")
    time.sleep(1.0)
    with BackdoorClient(backdoor_url) as backdoor:
        t0 = time.perf_counter()
        rig.estop()
        reply_s = time.perf_counter() - t0
        while True:
            currents = backdoor.request("truth")["currents_A"].values()
            if all(abs(c) < 0.05 for c in currents):
                break
        below_s = time.perf_counter() - t0
    status = rig.status()
    while status["run"] is not None:
        status = rig.status()
    run_dir = max((p for p in runs.iterdir() if p.is_dir()), key=lambda p: p.name)
    zeroed = [e for e in read_events(run_dir) if e["event"] == "estop_zeroed"]
    rig.reset()
    result = {"request_to_reply_us": round(reply_s * 1e6, 1),
              "request_to_measured_below_50mA_ms": round(below_s * 1e3, 1)}
    if zeroed:
        seen, done = zeroed[0]["seen_after_request_s"], zeroed[0]["after_request_s"]
        result["received_to_stream_thread_us"] = round(seen * 1e6, 1)
        result["received_to_all_drivers_zeroed_and_off_us"] = round(done * 1e6, 1)
        result["received_to_all_drivers_zeroed_and_off_periods"] = round(done * RATE_HZ, 2)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--moves", type=int, default=16, help="moves per plan (about 0.7 s each)")
    parser.add_argument("--emulator-nice", type=int, default=0, metavar="N",
                        help="run the emulated devices at this nice value (default 0). They stand "
                             "in for hardware with processors of its own; on two cores their CPU "
                             "is a load a real rig does not put on the control computer")
    parser.add_argument("--realtime", type=int, default=40, metavar="PRIO",
                        help="the daemon's --realtime, as systemd/rigctl.service gives it (default "
                             "40; 0: normal scheduling). Where not permitted the daemon streams at "
                             "normal priority and says so in its log")
    args = parser.parse_args()
    load_before = round(os.getloadavg()[0], 2)  # other work on the machine skews every figure
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-daemon-") as tmp:
        tmp = Path(tmp)
        with EmulatedBenchProcess("six-coil", tmp / "bench.toml") as rig_path:
            rig = load_rig(rig_path)
            renice(rig.emulation.pid, args.emulator_nice)
            # open loop (no camera): this measures the daemon itself; the camera loop's own
            # latency is bench/tracker.py's
            # a watchdog that tolerates a loaded machine, as bench/closed_loop.py: this measures
            # latency, and a run faulted by a 0.25 s scheduling gap would measure nothing
            fast = rig.model_copy(update={
                "stream": rig.stream.model_copy(update={"rate_hz": RATE_HZ,
                                                        "reply_timeout_s": 1.0}),
                "camera": None})
            (tmp / "rig-1khz.toml").write_text(dump_rig(fast))
            runs = tmp / "runs"
            proc, endpoints = start_daemon(tmp / "rig-1khz.toml", runs, tmp / "daemon.log",
                                           args.realtime)
            try:
                with Rig(endpoints["command"], timeout_s=5.0) as client:
                    plan_id = client.load(back_and_forth_plan(args.moves))
                    with BareEcho() as echo:
                        bare = round_trips(echo.call)
                        idle = round_trips(client.status)
                        status_rtt = timed_run(client, plan_id, 0, endpoints, echo)
                    one = timed_run(client, plan_id, 1, endpoints)
                    ten = timed_run(client, plan_id, 10, endpoints)
                    estop = estop_latency(client, plan_id, rig.emulation.backdoor, runs)
            finally:
                proc.terminate()
                proc.wait(timeout=30)

    print(json.dumps({
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_average_1min_before": load_before,
                    "load_average_1min_after": round(os.getloadavg()[0], 2)},
        "stream_rate_hz": RATE_HZ,
        "emulator_nice": args.emulator_nice,
        "idle": {"status_round_trip": idle, "bare_echo": bare},
        "status_round_trip_while_running": status_rtt,
        "telemetry_1_subscriber": one,
        "telemetry_10_subscribers": ten,
        "estop": estop,
    }, indent=2))


if __name__ == "__main__":
    main()
