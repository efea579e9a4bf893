"""Benchmark: the daemon under load on every rig, as the issue asks. Prints one JSON object.

For each rig kind asked for (`--rig`, default all three), its emulated bench runs in a process of
its own, `rigctl daemon` in another (the six coils streamed at 1 kHz, the coil board and the arms
at their own rates), and this process is the operator. It submits a plan that streams longer
than it measures (a back-and-forth on the six coils, the wall-contact example on the board, the
eight-component field sequence on the arms), measures for `--seconds`, aborts the run, and
takes, per rig:
- the `status` round trip over tcp loopback (p50, p99, max, microseconds), 100 requests a second
  from this process (nothing else in it), each followed by a bare REQ/REP echo of the same size
  to a process that does nothing else: the floor on this machine under the same load, so that a
  slow figure can be told from a slow machine; the p99 difference (the issue: within 0.25 ms).
  Also both with the daemon idle, and which threads ran at SCHED_FIFO (`--realtime`, as the
  systemd unit gives it);
- telemetry delivered to 1 and to 10 subscribers: cycles per second per subscriber in the
  `actuators` messages, against the cycles the stream ran per second in the same span (the
  daemon's `stream` messages), samples the daemon dropped, and lost `actuators` / `state` /
  `fault` messages (sequence gaps);
- e-stop, once the devices really drive (current, board output, joint speed): request received
  by the daemon -> seen by the stream thread -> every device told (the run record's
  `estop_zeroed` event, which the one engine writes on every rig; in ms and in stream periods),
  request sent -> reply, and request sent -> the emulated devices physically safe, read from the
  bench's backdoor `truth` as fast as it answers: every coil current under 0.05 A (set by the
  coils' L/R, not by rigctl), every SyRen output zero, both arms at rest (every joint speed zero);
  then the same e-stop against a local `rigctl execute` of the same plan on the same rig (its
  control endpoint found through the rig's lock), and, with nothing owning the rig, `rigctl estop
  --rig` as a process reaching every device directly (its wall time, and the direct make-safe
  of every device timed in this process: what that command does once Python has started);
- six coils only: the stream's late share while 20 clients (in 4 processes) ask `status` as fast
  as they are answered, next to the same run without them (the issue: within 1 point). The
  supplies' emulator runs at SCHED_FIFO 45 (`--emulator-realtime`), above the daemon: real supplies
  answer from processors of their own, and at normal priority the emulator's answers waited for
  the daemon's realtime command thread, which measured that thread against the emulator instead.

    python bench/daemon.py                          # every rig, about 35 s each
    python bench/daemon.py --rig depm --seconds 1   # one rig, quickly
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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Self

import numpy as np

from rigctl.apps.client import Rig, Telemetry
from rigctl.apps.daemon.admission import REQUEST_RATE_HZ
from rigctl.core.config import RigConfig, dump_rig, load_rig
from rigctl.core.record import read_events
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess

EXAMPLES = Path(__file__).resolve().parents[1] / "plans" / "examples"


def back_and_forth_plan(moves: int) -> dict:
    """One rolling magnet going 10 mm (one turn, about 0.7 s) right and back, `moves` times."""
    return {
        "schema": "rigctl.plan/1", "kind": "global-moves", "rig": "six-coil", "name": "bench",
        "workspace": {"boundary": {"rect": [-100, -100, 200, 200]}},
        "agents": [{"start": [0.0, 0.0], "goal": [0.0, 0.0], "radius": 3.0}],
        "moves": [[10.0, 0.0] if k % 2 == 0 else [-10.0, 0.0] for k in range(moves)],
    }


@dataclass(frozen=True)
class RigBench:
    """What differs per rig: its plan (streaming for at least the seconds given), its stream
    settings for the benchmark, and, from the backdoor's `truth`, whether its devices drive
    something (an e-stop before that measures nothing) and whether they are physically safe."""

    plan: Callable[[float], dict]
    tune: Callable[[RigConfig], RigConfig]
    driving: Callable[[dict], bool]
    safe: Callable[[dict], bool]
    safe_means: str


def six_coil_rig(rig: RigConfig) -> RigConfig:
    # 1 kHz; a watchdog that tolerates a loaded machine, as bench/closed_loop.py: this measures
    # latency, and a run faulted by a 0.25 s scheduling gap would measure nothing; open loop (no
    # camera): this measures the daemon itself, the camera loop's own latency is bench/tracker.py's
    return rig.model_copy(update={"camera": None, "stream": rig.stream.model_copy(
        update={"rate_hz": 1000.0, "reply_timeout_s": 1.0})})


def arm_speeds(truth: dict) -> np.ndarray:
    return np.abs([arm["qd"] for arm in truth["arms"].values()])


RIGS = {
    "six-coil": RigBench(
        plan=lambda seconds: back_and_forth_plan(int(seconds / 0.5) + 4),
        tune=six_coil_rig,
        driving=lambda t: max(abs(c) for c in t["currents_A"].values()) > 1.0,
        safe=lambda t: all(abs(c) < 0.05 for c in t["currents_A"].values()),
        safe_means="every emulated coil current under 0.05 A"),
    # the wall-contact example (about 25 s: its moves end when the camera sees them done)
    "coil-board": RigBench(
        plan=lambda _: json.loads((EXAMPLES / "coilboard-disk.json").read_text()),
        tune=lambda rig: rig,  # its runs close the loop through the camera: they need it
        driving=lambda t: any(t["outputs"]),
        safe=lambda t: not any(t["outputs"]),
        safe_means="every SyRen output zero"),
    # the eight-component sequence (about 105 s)
    "depm": RigBench(
        plan=lambda _: json.loads((EXAMPLES / "depm-plan.json").read_text()),
        tune=lambda rig: rig,
        driving=lambda t: arm_speeds(t).max() > 0.01,
        safe=lambda t: not arm_speeds(t).any(),
        safe_means="both arms at rest: every joint speed zero"),
}


def start_daemon(rig_path: Path, runs: Path, log_path: Path, realtime: int = 0,
                 request_rate: float | None = None) -> tuple[subprocess.Popen, dict]:
    cmd = [sys.executable, "-m", "rigctl", "daemon", "--rig", str(rig_path), "--runs", str(runs),
           "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
           "--events", "tcp://127.0.0.1:0"]
    if request_rate is not None:
        cmd += ["--request-rate", str(request_rate)]
    if realtime:
        cmd += ["--realtime", str(realtime)]
    with open(log_path, "w") as log:  # the child keeps its own copy of the descriptor
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    for line in proc.stdout:
        if line.startswith("READY "):
            return proc, dict(field.split("=", 1) for field in line[6:].split())
    raise RuntimeError(f"the daemon did not start: {log_path.read_text()[-2000:]}")


class Subscriber(threading.Thread):
    """One telemetry subscriber: when each `actuators` message came and how many cycles it
    carried, and the daemon's `stream` figures (cycles run, samples dropped) as they came."""

    def __init__(self, endpoints: dict, stop: threading.Event) -> None:
        super().__init__(daemon=True)
        self.feed = Telemetry(endpoints["telemetry"], endpoints["events"],
                              ["actuators", "stream", "state", "fault"])
        self.stop_event = stop
        self.arrivals: list[tuple[float, int]] = []  # (time received, cycles in the message)
        self.stream: list[tuple[float, int, int]] = []  # (time received, cycles, dropped)

    def run(self) -> None:
        while not self.stop_event.is_set():
            msg = self.feed.receive(timeout_s=0.2)
            if msg is None:
                continue
            if msg.topic == "actuators":
                self.arrivals.append((time.monotonic(), len(msg.samples)))
            elif msg.topic == "stream":
                self.stream.append((time.monotonic(), msg.cycles, msg.dropped_samples))

    def rates(self, window: tuple[float, float]) -> tuple[float, float, int]:
        """Within `window`, between the first and the last `stream` message in it: the cycles
        the stream ran per second, those delivered here per second, samples the daemon dropped."""
        inside = [m for m in self.stream if window[0] <= m[0] <= window[1]]
        if len(inside) < 2:
            raise RuntimeError(f"{len(inside)} `stream` message(s) in {window[1] - window[0]:.2f} s "
                               "(10 a second while streaming): measure longer (--seconds)")
        (t0, cycles0, dropped0), (t1, cycles1, dropped1) = inside[0], inside[-1]
        delivered = sum(n for t, n in self.arrivals if t0 < t <= t1)
        return (cycles1 - cycles0) / (t1 - t0), delivered / (t1 - t0), dropped1 - dropped0


def delivered_rate(subscribers: list[Subscriber], window: tuple[float, float],
                   stream: dict) -> dict:
    """Cycles delivered per second to each subscriber, against the cycles the stream ran in the
    same span, and the messages lost (sequence gaps)."""
    ran, delivered, dropped = zip(*(s.rates(window) for s in subscribers))
    lost = {topic: sum(s.feed.lost.get(topic, 0) for s in subscribers) for topic in
            ("actuators", "state", "fault")}
    return {"subscribers": len(subscribers), **stream,
            "stream_cycles_per_s_while_measured": round(float(np.mean(ran)), 1),
            "delivered_cycles_per_s_min": round(min(delivered), 1),
            "delivered_cycles_per_s_mean": round(float(np.mean(delivered)), 1),
            "samples_dropped_by_the_daemon": max(dropped),
            "lost_messages": lost}


def renice(pid: int, nice: int) -> None:
    """Every thread of process `pid` to `nice` (Linux: a nice value is a thread's)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        os.setpriority(os.PRIO_PROCESS, int(task.name), nice)


def make_emulator_realtime(pid: int, priority: int) -> int | None:
    """Every thread of process `pid` to SCHED_FIFO `priority` (threads it starts later inherit
    it from the thread that starts them); the priority, or None where not permitted."""
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            os.sched_setscheduler(int(task.name), os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return None
    return priority


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


def start_streaming(rig: Rig, plan_id: str, timeout_s: float = 60.0) -> None:
    """Execute the plan and wait until its stream has started (devices connected, energised,
    cycles running: the arms' and the board's start-up comes before)."""
    rig.execute(plan_id)
    deadline = time.monotonic() + timeout_s
    while True:
        status = rig.status()
        if status["state"] == "running" and (status["run"] or {}).get("sample", 0) > 0:
            return
        if time.monotonic() > deadline or status["state"] not in ("idle", "running"):
            raise RuntimeError(f"the benchmark's run did not start streaming: {status}")
        time.sleep(0.02)


def end_run(rig: Rig, stop: Callable[[], object]) -> tuple[dict, list[dict]]:
    """Stop the run (`stop`: abort or e-stop), wait until it is over; its summary and events."""
    stop()
    while rig.status()["run"] is not None:
        time.sleep(0.02)
    run_dir = Path(rig.status()["last_run"]["run"])
    return rig.run(run_dir.name)["summary"], read_events(run_dir)


def stream_figures(summary: dict, events: list[dict]) -> dict:
    """The stream's rate and timing from the run's summary, or why the run measured nothing."""
    faults = [f for f in summary["faults"] if f["kind"] not in ("Abort", "EStop")]
    if summary["stream"] is None or faults:
        raise RuntimeError(f"the benchmark's run did not stream cleanly: {faults}")
    t = {e["event"]: e["t"] for e in events if e["event"] in ("energised", "stream_stats")}
    stream = summary["stream"]
    return {"stream_rate_hz": stream["rate_hz"],
            "stream_cycles_per_s": round(stream["cycles"] / (t["stream_stats"] - t["energised"]), 1),
            "stream_late_share": round(stream["late_share"], 4)}


def timed_run(rig: Rig, plan_id: str, seconds: float, endpoints: dict,
              n_subscribers: int = 0, echo: BareEcho | None = None) -> dict:
    """One run of the plan for `seconds`, then aborted, with `n_subscribers` telemetry
    subscribers in this process, or (with `echo`, and no subscriber here, whose decoding would
    hold this process's GIL) an operator script polling `status` 100 times a second, each
    followed by a bare echo round trip (the floor under the same load). What was measured, and
    the stream."""
    stop = threading.Event()
    subscribers = [Subscriber(endpoints, stop) for _ in range(n_subscribers)]
    for s in subscribers:
        s.start()
    time.sleep(0.5)  # let the subscriptions reach the publisher (a PUB drops before that)
    start_streaming(rig, plan_id)
    start = time.monotonic()  # telemetry counts from here; round trips once the stream settled
    time.sleep(0.3)
    realtime = realtime_threads(rig.ping()["pid"])
    figures = {} if echo is None else round_trips(rig, echo, seconds)
    time.sleep(max(0.0, start + 0.3 + seconds - time.monotonic()))
    end = time.monotonic()
    stop.set()
    for s in subscribers:
        s.join()
        s.feed.close()
    stream = stream_figures(*end_run(rig, rig.abort))
    if echo is not None:
        return {**figures, **stream, "realtime_threads": realtime}
    return delivered_rate(subscribers, (start, end), stream)


def round_trips(rig: Rig, echo: BareEcho, seconds: float) -> dict:
    """`status` and the bare echo in turn for `seconds`, 200 requests a second (each waits for
    the other: the same load on both); both, and the p99 gap."""
    rtts: dict[str, list[float]] = {"status": [], "bare": []}
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        for name, call in (("status", rig.status), ("bare", echo.call)):
            t0 = time.perf_counter()
            call()
            rtts[name].append(time.perf_counter() - t0)
            time.sleep(max(0.0, 0.005 - (time.perf_counter() - t0)))
    status_us, bare_us = microseconds(rtts["status"]), microseconds(rtts["bare"])
    gap_ms = (status_us["p99_us"] - bare_us["p99_us"]) / 1e3
    return {"status_round_trip": status_us, "bare_echo": bare_us,
            "p99_difference_ms": round(gap_ms, 3), "within_0_25_ms": gap_ms <= 0.25}


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

    def __enter__(self) -> Self:
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


def estop_latency(rig: Rig, plan_id: str, bench: RigBench, backdoor_url: str) -> dict:
    """E-stop once the devices drive: from the run record, and from the bench's ground truth."""
    start_streaming(rig, plan_id)
    with BackdoorClient(backdoor_url) as backdoor:
        deadline = time.monotonic() + 20.0
        while not bench.driving(backdoor.request("truth")):
            if time.monotonic() > deadline:
                raise RuntimeError("the benchmark's run never drove its devices")
            time.sleep(0.01)
        t0 = time.perf_counter()
        rig.estop()
        reply_s = time.perf_counter() - t0
        polls = 0
        while not bench.safe(backdoor.request("truth")):
            polls += 1
        safe_s = time.perf_counter() - t0
    summary, events = end_run(rig, lambda: None)
    rig.reset()
    zeroed = next(e for e in events if e["event"] == "estop_zeroed")
    rate = summary["stream"]["rate_hz"]
    seen, told = zeroed["seen_after_request_s"], zeroed["after_request_s"]
    return {"stream_rate_hz": rate,
            "received_to_stream_thread_ms": round(seen * 1e3, 3),
            "received_to_stream_thread_periods": round(seen * rate, 3),
            "received_to_every_device_told_ms": round(told * 1e3, 3),
            "received_to_every_device_told_periods": round(told * rate, 3),
            "every_device_told_within_one_period": told * rate <= 1.0,
            "told_from_the_thread_that_took_it": zeroed["direct"],
            "request_to_reply_ms": round(reply_s * 1e3, 3),
            "request_to_physically_safe_ms": round(safe_s * 1e3, 1),
            "physically_safe_means": bench.safe_means,
            "truth_polls_until_safe": polls,
            "safe_confirmed_in_record": summary["safe"]}


def local_estop_latency(rig_path: Path, plan: dict, bench: RigBench, tmp: Path) -> dict:
    """The same e-stop against a local `rigctl execute` on the same rig (found through its lock,
    the same client request); then, with nothing owning the rig, `rigctl estop --rig` as a
    process reaching every device directly."""
    from rigctl.rigs.owner import holder_of

    rig = load_rig(rig_path)
    (tmp / "local-plan.json").write_text(json.dumps(plan))
    run = subprocess.Popen([sys.executable, "-m", "rigctl", "execute", str(tmp / "local-plan.json"),
                            "--rig", str(rig_path), "--runs", str(tmp / "local-runs"), "--json",
                            "-q"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        with BackdoorClient(rig.emulation.backdoor) as backdoor:
            deadline = time.monotonic() + 60.0
            while (holder_of(rig) is None or not holder_of(rig).control
                   or not bench.driving(backdoor.request("truth"))):
                if time.monotonic() > deadline or run.poll() is not None:
                    raise RuntimeError("the local run never drove its devices")
                time.sleep(0.01)
            with Rig(holder_of(rig).control, timeout_s=5.0) as owner:
                t0 = time.perf_counter()
                owner.estop()
                reply_s = time.perf_counter() - t0
                while not bench.safe(backdoor.request("truth")):
                    pass
                safe_s = time.perf_counter() - t0
        summary = json.loads(run.communicate(timeout=60)[0])
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
    zeroed = next(e for e in read_events(Path(summary["run"])) if e["event"] == "estop_zeroed")
    t0 = time.perf_counter()
    direct = subprocess.run([sys.executable, "-m", "rigctl", "estop", "--rig", str(rig_path)],
                            capture_output=True, text=True, timeout=60)
    direct_s = time.perf_counter() - t0
    from rigctl.rigs import rig_kind

    t0 = time.perf_counter()  # what that process does once it has started: every device reached
    unreached = [name for name, err in rig_kind(rig.rig.kind).make_safe(rig).items() if err]
    make_safe_s = time.perf_counter() - t0
    return {"local_run": {
                "received_to_every_device_told_ms": round(zeroed["after_request_s"] * 1e3, 3),
                "request_to_reply_ms": round(reply_s * 1e3, 3),
                "request_to_physically_safe_ms": round(safe_s * 1e3, 1),
                "safe_confirmed_in_record": summary["safe"]},
            "no_owner_direct": {
                "exit_code": direct.returncode,
                "devices_reached": sum(line.split()[-1:] == ["safe"]
                                       for line in direct.stdout.splitlines()),
                "process_wall_ms": round(direct_s * 1e3, 1),
                "every_device_made_safe_in_process_ms": round(make_safe_s * 1e3, 1),
                "unreached_in_process": unreached}}


FLOOD = """
import json, sys, threading, time, zmq
endpoint, clients, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
answered = [0] * clients
def client(i):
    sock = zmq.Context.instance().socket(zmq.REQ)
    sock.connect(endpoint)
    request = json.dumps({"id": f"flood-{i}", "cmd": "status"}).encode()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        sock.send(request)
        sock.recv()
        answered[i] += 1
    sock.close(linger=0)
threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
for t in threads: t.start()
for t in threads: t.join()
print(sum(answered))
"""


def flood(rig: Rig, plan_id: str, seconds: float, endpoint: str, clients: int = 20,
          processes: int = 4) -> dict:
    """The stream's late share while `clients` operator scripts (in `processes` processes, so
    that this one's GIL is not the limit) ask `status` as fast as they are answered, next to the
    same run without them, in turn."""
    figures = {}
    for name, n in (("without_flood", 0), ("with_flood", clients)):
        start_streaming(rig, plan_id)
        procs = [subprocess.Popen([sys.executable, "-c", FLOOD, endpoint, str(n // processes),
                                   str(seconds)], stdout=subprocess.PIPE, text=True)
                 for _ in range(processes if n else 0)]
        time.sleep(seconds)
        answered = sum(int(p.communicate(timeout=60)[0] or 0) for p in procs)
        figures[name] = {**stream_figures(*end_run(rig, rig.abort)),
                         "status_requests_answered_per_s": round(answered / seconds, 1)}
    gap = figures["with_flood"]["stream_late_share"] - figures["without_flood"]["stream_late_share"]
    return {**figures, "clients": clients, "late_share_difference_points": round(100 * gap, 2),
            "within_1_point": abs(gap) <= 0.01}


def bench_rig(kind: str, args: argparse.Namespace, tmp: Path) -> dict:
    """Every figure for one rig kind: its bench and its daemon started, measured, stopped."""
    bench = RIGS[kind]
    tmp = tmp / kind
    tmp.mkdir()
    with EmulatedBenchProcess(kind, tmp / "bench.toml") as rig_path:
        rig = load_rig(rig_path)
        renice(rig.emulation.pid, args.emulator_nice)
        # the six-coil supplies' emulator only: the coil board's simavr spins a core whatever
        # it simulates, and at SCHED_FIFO it would take that core from everything else
        emulator_realtime = (make_emulator_realtime(rig.emulation.pid, args.emulator_realtime)
                             if args.emulator_realtime and kind == "six-coil" else None)
        (tmp / "rig.toml").write_text(dump_rig(bench.tune(rig)))
        runs = tmp / "runs"
        proc, endpoints = start_daemon(tmp / "rig.toml", runs, tmp / "daemon.log", args.realtime,
                                      args.request_rate)
        try:
            with Rig(endpoints["command"], timeout_s=5.0) as client:
                plan_id = client.load(bench.plan(args.seconds + 2.0))
                with BareEcho() as echo:
                    idle = round_trips(client, echo, args.seconds)
                    streaming = timed_run(client, plan_id, args.seconds, endpoints, echo=echo)
                one = timed_run(client, plan_id, args.seconds, endpoints, 1)
                ten = timed_run(client, plan_id, args.seconds, endpoints, 10)
                estop = estop_latency(client, plan_id, bench, rig.emulation.backdoor)
                flooded = flood(client, plan_id, args.seconds, endpoints["command"]) \
                    if kind == "six-coil" else None
        except Exception:
            print((tmp / "daemon.log").read_text()[-3000:], file=sys.stderr)
            raise
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        estop.update(local_estop_latency(tmp / "rig.toml", bench.plan(args.seconds + 2.0), bench,
                                         tmp))
    return {"idle": idle, "while_streaming": streaming, "telemetry_1_subscriber": one,
            "telemetry_10_subscribers": ten, "estop": estop, "status_flood": flooded,
            "emulator_realtime_priority": emulator_realtime}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", choices=[*RIGS, "all"], default="all")
    parser.add_argument("--seconds", type=float, default=5.0,
                        help="each measurement's length (idle round trips, streaming round trips, "
                             "1 and 10 subscribers); default 5, about 35 s per rig; at most about "
                             "20 (the coil board's plan lasts about 25 s)")
    parser.add_argument("--emulator-nice", type=int, default=0, metavar="N",
                        help="run the emulated devices at this nice value (default 0). They stand "
                             "in for hardware with processors of its own; on two cores their CPU "
                             "is a load a real rig does not put on the control computer")
    parser.add_argument("--emulator-realtime", type=int, default=45, metavar="PRIO",
                        help="run the emulated devices at SCHED_FIFO priority PRIO where "
                             "permitted (default 45, above the daemon's: nothing on this computer "
                             "delays a real device's answers; 0: normal scheduling). The six-coil "
                             "supplies' emulator only")
    parser.add_argument("--realtime", type=int, default=40, metavar="PRIO",
                        help="the daemon's --realtime, as systemd/rigctl.service gives it (default "
                             "40; 0: normal scheduling). Where not permitted the daemon streams at "
                             "normal priority and says so in its log")
    parser.add_argument("--request-rate", type=float, default=None, metavar="HZ",
                        help="the daemon's --request-rate: queries answered per second over all "
                             "clients (default: the daemon's own)")
    args = parser.parse_args()
    if not args.seconds > 0:
        parser.error(f"--seconds must be > 0, got {args.seconds}")
    load_before = round(os.getloadavg()[0], 2)  # other work on the machine skews every figure
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-daemon-") as tmp:
        rigs = {kind: bench_rig(kind, args, Path(tmp))
                for kind in (RIGS if args.rig == "all" else [args.rig])}
    print(json.dumps({
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_average_1min_before": load_before,
                    "load_average_1min_after": round(os.getloadavg()[0], 2)},
        "seconds_per_measurement": args.seconds, "emulator_nice": args.emulator_nice,
        "request_rate_hz": args.request_rate or REQUEST_RATE_HZ,
        "rigs": rigs,
    }, indent=2))


if __name__ == "__main__":
    main()
