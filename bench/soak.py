"""Benchmark: a soak of the daemon on the emulated six-coil bench. Prints one JSON object.

The bench runs in a process of its own, `rigctl daemon` in another (streaming at 1 kHz, open loop:
this measures the daemon, not the camera), and this process is the operator: it runs a short plan
(one magnet 10 mm right and back, `--moves` times) back to back for `--minutes` (default 60,
the issue's hour) and samples, every `--interval` seconds, of the daemon and of its stream
process, between two runs: the resident set (VmRSS, MB), open file descriptors (/proc/PID/fd)
and threads. It
reports each figure's slope over time (least squares, per hour; for the stream process, over the
longest stretch of one process: the daemon replaces one that dies or hangs) after a warm-up (the first
`--warmup-minutes`, default the lesser of 2 min and a fifth of the run: the first runs import,
compile and fill caches), the first and last value, the runs done, any run that did not end
cleanly, and every sample. The issue's goal: no growth in descriptors or threads, RSS under
5 MB per hour.

    python bench/soak.py                          # one hour
    python bench/soak.py --minutes 10             # a shorter soak
    python bench/soak.py --minutes 0.5 --interval 1   # a smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rigctl.apps.client import CommandRefused, Rig
from rigctl.core.config import dump_rig, load_rig
from rigctl.emulators.process import EmulatedBenchProcess

FIGURES = ("rss_MB", "fds", "threads")


def back_and_forth_plan(moves: int) -> dict:
    """One rolling magnet 10 mm (one turn) right and back, `moves` moves in all."""
    return {
        "schema": "rigctl.plan/1", "kind": "global-moves", "rig": "six-coil", "name": "soak",
        "workspace": {"boundary": {"rect": [-100, -100, 200, 200]}},
        "agents": [{"start": [0.0, 0.0], "goal": [0.0, 0.0], "radius": 3.0}],
        "moves": [[10.0, 0.0] if k % 2 == 0 else [-10.0, 0.0] for k in range(moves)],
    }


def process_figures(pid: int) -> dict | None:
    """RSS (MB), open descriptors and threads of process `pid` (None once it is gone)."""
    try:
        status = dict(line.split(":", 1) for line in
                      Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (FileNotFoundError, ProcessLookupError):
        return None
    return {"rss_MB": round(int(status["VmRSS"].split()[0]) / 1024, 2), "fds": fds,
            "threads": int(status["Threads"])}


def stream_process(daemon_pid: int) -> int | None:
    """The daemon's stream process (`rigctl.apps.daemon.runhost`), from /proc."""
    for task in Path(f"/proc/{daemon_pid}/task").iterdir():
        try:
            children = (task / "children").read_text().split()
        except OSError:
            continue
        for child in map(int, children):
            try:
                cmdline = Path(f"/proc/{child}/cmdline").read_bytes()
            except OSError:
                continue
            if b"runhost" in cmdline:
                return child
    return None


def slope_per_hour(t_s: list[float], values: list[float]) -> float | None:
    """Least-squares slope of `values` over `t_s`, per hour (None with fewer than 3 samples)."""
    if len(t_s) < 3 or max(t_s) - min(t_s) <= 0:
        return None
    return round(float(np.polyfit(np.asarray(t_s) / 3600.0, np.asarray(values, float), 1)[0]), 3)


class Sampler:
    """Samples both processes between two runs (the daemon idle: the same point of every cycle,
    so that a run's own threads and sockets do not show as growth), at most every `interval_s`."""

    def __init__(self, daemon_pid: int, interval_s: float) -> None:
        self.daemon_pid = daemon_pid
        self.interval_s = interval_s
        self.t0 = time.monotonic()
        self.last = -float("inf")
        self.samples: list[dict] = []
        self.stream_pids: set[int] = set()

    def sample(self, runs: int, *, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self.last < self.interval_s:
            return
        self.last = now
        stream_pid = stream_process(self.daemon_pid)
        daemon = process_figures(self.daemon_pid)
        stream = process_figures(stream_pid) if stream_pid is not None else None
        if stream_pid is not None:
            self.stream_pids.add(stream_pid)
        self.samples.append({"t_s": round(now - self.t0, 2), "runs": runs,
                             "daemon": daemon, "stream": stream, "stream_pid": stream_pid})


def summarise(samples: list[dict], warmup_s: float, which: str) -> dict:
    """First, last, min, max and the slope per hour of each figure of `which` ("daemon" or
    "stream") after the warm-up. The stream process is replaced when one dies or hangs (the
    daemon kills a silent one): its slope is that of the longest stretch of one process, the
    others' samples are not one process's growth."""
    kept = [s for s in samples if s["t_s"] >= warmup_s and s[which] is not None]
    if which == "stream" and kept:
        stretches: dict[int, list[dict]] = {}
        for s in kept:
            stretches.setdefault(s["stream_pid"], []).append(s)
        kept = max(stretches.values(), key=len)
    out: dict = {"samples": len(kept),
                 "span_s": round(kept[-1]["t_s"] - kept[0]["t_s"], 1) if kept else 0.0}
    for figure in FIGURES:
        t = [s["t_s"] for s in kept]
        v = [s[which][figure] for s in kept]
        out[figure] = {"first": v[0] if v else None, "last": v[-1] if v else None,
                       "min": min(v) if v else None, "max": max(v) if v else None,
                       "slope_per_h": slope_per_hour(t, v)}
    return out


def start_daemon(rig_path: Path, runs: Path, log_path: Path) -> tuple[subprocess.Popen, dict]:
    cmd = [sys.executable, "-m", "rigctl", "daemon", "--rig", str(rig_path), "--runs", str(runs),
           "--command", "tcp://127.0.0.1:0", "--telemetry", "tcp://127.0.0.1:0",
           "--events", "tcp://127.0.0.1:0"]
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("READY "):
            return proc, dict(field.split("=", 1) for field in line[6:].split())
    raise RuntimeError(f"the daemon did not start: {log_path.read_text()[-2000:]}")


def soak(args: argparse.Namespace, tmp: Path) -> dict:
    with EmulatedBenchProcess("six-coil", tmp / "bench.toml") as bench_path:
        rig = load_rig(bench_path)
        rig = rig.model_copy(update={"camera": None, "stream": rig.stream.model_copy(
            update={"rate_hz": 1000.0, "reply_timeout_s": 1.0})})
        rig_path = tmp / "soak.toml"
        rig_path.write_text(dump_rig(rig))
        daemon, endpoints = start_daemon(rig_path, tmp / "runs", tmp / "daemon.log")
        sampler = Sampler(daemon.pid, args.interval)
        unclean: list[dict] = []
        runs = 0
        try:
            with Rig(endpoints["command"], timeout_s=5.0) as client:
                plan_id = client.load(back_and_forth_plan(args.moves))
                sampler.sample(0, force=True)
                deadline = time.monotonic() + 60.0 * args.minutes
                while time.monotonic() < deadline:
                    try:
                        client.execute(plan_id)
                    except CommandRefused as err:  # e.g. a device not yet confirmed safe
                        unclean.append({"run": runs + 1, "refused": f"{err.code}: {err.reason}",
                                        "devices": client.status()["devices"]})
                        time.sleep(0.5)
                        continue
                    while True:
                        status = client.status()
                        if status["run"] is None and status["state"] != "running":
                            break
                        time.sleep(0.05)
                    runs += 1
                    last = status["last_run"] or {}
                    if status["state"] != "idle" or last.get("faults"):
                        unclean.append({"run": runs, "state": status["state"],
                                        "reason": status["reason"], "faults": last.get("faults"),
                                        "run_id": last.get("id"),
                                        "unsafe": [d["name"] for d in status["devices"]
                                                   if d["health"] == "unsafe"]})
                        if status["state"] in ("faulted", "estopped"):
                            client.reset()
                    sampler.sample(runs)
                    print(f"soak: run {runs}, {max(0.0, deadline - time.monotonic()):.0f} s left",
                          file=sys.stderr, flush=True)
                sampler.sample(runs, force=True)
        finally:
            daemon.terminate()
            try:
                daemon.wait(30)
            except subprocess.TimeoutExpired:
                daemon.kill()
                daemon.wait()
            if daemon.stdout is not None:
                daemon.stdout.close()
    samples = sampler.samples
    warmup_s = 60.0 * (args.warmup_minutes if args.warmup_minutes is not None
                       else min(2.0, args.minutes / 5.0))
    return {
        "minutes": args.minutes, "rate_hz": 1000.0, "moves_per_run": args.moves,
        "runs": runs, "runs_not_clean": unclean,
        "warmup_s": round(warmup_s, 1), "interval_s": args.interval,
        "stream_processes_seen": len(sampler.stream_pids),
        "daemon": summarise(samples, warmup_s, "daemon"),
        "stream": summarise(samples, warmup_s, "stream"),
        "goal": "no growth in descriptors or threads, RSS growth under 5 MB per hour",
        "samples": samples,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="how long (default 60)")
    parser.add_argument("--interval", type=float, default=10.0,
                        help="seconds between two samples (default 10)")
    parser.add_argument("--moves", type=int, default=4,
                        help="moves per run, about 0.7 s each (default 4)")
    parser.add_argument("--warmup-minutes", type=float, default=None,
                        help="left out of the slopes (default: the lesser of 2 and a fifth of "
                             "--minutes)")
    args = parser.parse_args()
    if not args.minutes > 0 or not args.interval > 0 or args.moves < 1:
        parser.error("--minutes and --interval must be > 0, --moves >= 1")
    with tempfile.TemporaryDirectory(prefix="rigctl-soak-") as tmp:
        print(json.dumps(soak(args, Path(tmp)), indent=2))


if __name__ == "__main__":
    main()
