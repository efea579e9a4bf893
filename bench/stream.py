"""Benchmark: stream six coil currents to the emulated supplies at 100, 500 and 1000 Hz.

The bench runs in its own process (as `rigctl emulate six-coil`), the stream loop here, each over
real TCP sockets on loopback, one SCPI exchange per supply per cycle. The program is a 3 mT field
rolling at one turn per second, allocated to the six coils. Prints one JSON object:
per rate, the period error p50/p99/max (microseconds), late cycles and their share, overruns.

    python bench/stream.py                 # 20 s per rate, as the issue asks
    python bench/stream.py --seconds 3     # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np

from rigctl.core.config import load_rig
from rigctl.core.stream import StreamLoop
from rigctl.core.transport import open_transport
from rigctl.drivers.kepco_bop import KepcoBop
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.physics.coils import actuation_matrix
from rigctl.rigs.six_coil.allocate import currents_for_field


def rolling_currents(rig, rate_hz: float, seconds: float) -> np.ndarray:
    t = np.arange(int(rate_hz * seconds)) / rate_hz
    angle = 2 * np.pi * 1.0 * t
    b = 3e-3 * np.stack([np.zeros_like(t), np.cos(angle), np.sin(angle)], axis=1)
    return currents_for_field(actuation_matrix(rig), b)


def run_rate(rig, rate_hz: float, seconds: float) -> dict:
    supplies = []
    for coil in rig.coils:
        supply = KepcoBop(open_transport(coil.url, timeout_s=0.5), name=coil.name, timeout_s=0.5)
        supply.configure()
        supply.output(True)
        supplies.append(supply)
    program = rolling_currents(rig, rate_hz, seconds)
    measured = np.zeros(len(supplies))

    def cycle(k: int) -> None:
        for supply, amps in zip(supplies, program[k]):
            supply.send_setpoint(float(amps))
        for j, supply in enumerate(supplies):
            measured[j] = supply.read_measured()

    try:
        stats = StreamLoop(rate_hz).run(cycle, max_cycles=len(program))
    finally:
        for supply in supplies:
            supply.safe_stop(ramp_s=0.05)
            supply.close()
    return stats.as_dict()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="duration per rate")
    parser.add_argument("--rates", default="100,500,1000", help="comma-separated rates in Hz")
    args = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        with EmulatedBenchProcess("six-coil", Path(tmp) / "bench.toml") as rig_path:
            rig = load_rig(rig_path)
            for rate in (float(r) for r in args.rates.split(",")):
                results[f"{rate:g}"] = run_rate(rig, rate, args.seconds)
    print(json.dumps({
        "benchmark": "stream",
        "supplies": 6,
        "transport": "tcp loopback, bench in its own process",
        "seconds_per_rate": args.seconds,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "rates": results,
    }, indent=2))


if __name__ == "__main__":
    main()
