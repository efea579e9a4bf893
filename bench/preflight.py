"""Benchmark: how fast rigctl refuses what must not start, and how long `rigctl doctor` takes, on
every emulated bench. Prints one JSON object.

For each rig kind (`--rig`, default all three) its emulated bench runs in a process of its own;
then, each as a `rigctl` process timed from spawn to exit (the least of `--repeat` tries), next
to `rigctl --version` (the interpreter and the imports, nothing else: the floor on this machine
now), and each refusal's own work timed in this process:
- a second owner: `rigctl execute` while this process holds the rig's lock -> exit 2, the
  holder named (in process: `RigLock.acquire`);
- a wrong port: the rig file with one device's TCP port closed, or its serial port absent ->
  exit 2, the device named, no run record (in process: `preflight`);
- a bad URL: that device's URL `htp:/typo` -> exit 2, the field named (in process: `load_rig`);
- `rigctl doctor --rig` on the healthy bench -> exit 0 (in process: `probe_rig`).
The issue's goal: each refusal under 1 s, the doctor under 3 s.

    python bench/preflight.py                  # every rig, about 20 s each
    python bench/preflight.py --rig depm --repeat 1
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rigctl.core.config import RigConfig, load_rig
from rigctl.core.errors import ConfigError
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.rigs.doctor import DeviceUnreachable, preflight, probe_rig
from rigctl.rigs.owner import RigInUse, RigLock

EXAMPLES = Path(__file__).resolve().parents[1] / "plans" / "examples"
PLANS = {"six-coil": "fig4-quick.json", "coil-board": "coilboard-disk.json",
         "depm": "depm-plan.json"}


def a_device_url(rig: RigConfig) -> str:
    """The URL of the rig's first actuator (a supply, the board, an arm)."""
    from rigctl.core.registry import rig_kind

    return rig_kind(rig.rig.kind).devices(rig)[0].url


def timed(cmd: list[str], repeat: int) -> tuple[float, subprocess.CompletedProcess]:
    best, done = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        best = min(best, time.perf_counter() - t0)
    return best, done


def in_process(check, expected: type[Exception], repeat: int) -> float | None:
    """The least time `check()` takes to raise `expected` (None if it did not raise it)."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        try:
            check()
        except expected:
            best = min(best, time.perf_counter() - t0)
        else:
            return None
    return round(best * 1e3, 1)


def figure(wall_s: float, floor_s: float, done: subprocess.CompletedProcess, names: str,
           own_ms: float | None) -> dict:
    last = (done.stderr.strip().splitlines() or [""])[-1]
    return {"exit_code": done.returncode, "named": names in last, "message": last[:200],
            "process_ms": round(wall_s * 1e3, 1),
            "process_over_floor": round(wall_s / floor_s, 2), "check_in_process_ms": own_ms}


def bench_rig(kind: str, repeat: int, tmp: Path) -> dict:
    rigctl = [sys.executable, "-m", "rigctl"]
    floor_s, _ = timed([*rigctl, "--version"], repeat)
    with EmulatedBenchProcess(kind, tmp / f"{kind}.toml") as rig_path:
        rig = load_rig(rig_path)
        url = a_device_url(rig)
        plan = str(EXAMPLES / PLANS[kind])
        runs = str(tmp / "runs")
        out: dict = {"floor_rigctl_version_ms": round(floor_s * 1e3, 1)}

        with RigLock(rig, "bench/preflight.py"):
            wall, done = timed([*rigctl, "execute", plan, "--rig", str(rig_path), "--runs", runs],
                               repeat)
            own = in_process(lambda: RigLock(rig, "second").acquire(), RigInUse, repeat)
        out["second_owner"] = figure(wall, floor_s, done, "bench/preflight.py", own)

        closed = tmp / f"{kind}-closed-port.toml"  # a TCP port nobody serves, a serial port absent
        wrong = (f"{url.rsplit(':', 1)[0]}:1" if url.startswith("tcp://")
                 else "serial:///dev/ttyNOSUCHPORT?baud=115200")
        closed.write_text(rig_path.read_text().replace(url, wrong))
        wall, done = timed([*rigctl, "execute", plan, "--rig", str(closed), "--runs", runs], repeat)
        own = in_process(lambda: preflight(load_rig(closed)), DeviceUnreachable, repeat)
        out["wrong_port"] = figure(wall, floor_s, done, wrong.split("?")[0], own)
        out["wrong_port"]["run_record_written"] = Path(runs).exists()

        typo = tmp / f"{kind}-bad-url.toml"
        typo.write_text(rig_path.read_text().replace(url, "htp:/typo"))
        wall, done = timed([*rigctl, "execute", plan, "--rig", str(typo), "--runs", runs], repeat)
        own = in_process(lambda: load_rig(typo), ConfigError, repeat)
        out["bad_url"] = figure(wall, floor_s, done, "htp:/typo", own)

        wall, done = timed([*rigctl, "doctor", "--rig", str(rig_path)], repeat)
        t0 = time.perf_counter()
        healthy = all(p.ok for p in probe_rig(rig))
        out["doctor"] = {"exit_code": done.returncode, "process_ms": round(wall * 1e3, 1),
                         "process_over_floor": round(wall / floor_s, 2),
                         "probes_in_process_ms": round((time.perf_counter() - t0) * 1e3, 1),
                         "every_device_answered": healthy}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", choices=[*PLANS, "all"], default="all")
    parser.add_argument("--repeat", type=int, default=3, help="tries per figure (the least counts)")
    args = parser.parse_args()
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    load_before = round(os.getloadavg()[0], 2)
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-preflight-") as tmp:
        rigs = {kind: bench_rig(kind, args.repeat, Path(tmp))
                for kind in (PLANS if args.rig == "all" else [args.rig])}
    print(json.dumps({"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                  "load_average_1min_before": load_before},
                      "repeat": args.repeat, "rigs": rigs}, indent=2))


if __name__ == "__main__":
    main()
