"""Benchmark of the coil-board host link over a pty, for both emulators; prints ONE JSON object.

Per emulator, each in a process of its own with its SyRen wire on a pty (`python`: the Python
firmware emulator; `simavr`: the real AVR firmware in simavr; the reason instead when the toolchain
is missing):
- round_trip_ms: SET -> ACK through the `CoilBoard` driver (p50, p99, max over `--round-trips`);
- set_rate_hz: SETs acknowledged per second, back to back, for `--seconds`;
- watchdog_ms: time from the last valid frame (the moment its write returned) to the zero packet
  of the last of the four drivers as seen on the SyRen wire (median and max over `--trials`),
  the 250 ms goal of issue 6 (watchdog 200 ms + the tick + four packets at 9600 baud).
Computed, not measured: what a real 115200-baud 8N1 link allows with these frame sizes, and the
SyRen bus's update rate at 9600 baud.

Usage: python bench/coilboard_link.py [--round-trips N] [--seconds S] [--trials T] [--only python|simavr]
Figures taken on a busy machine are noisy; say so when quoting them.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import os
import platform
import statistics
import tempfile
import time

import numpy as np

from rigctl.core.errors import RigError
from rigctl.drivers import coilboard_frame as proto
from rigctl.drivers.coilboard import CoilBoard
from rigctl.emulators.coilboard.firmware import serve_in_child_process
from rigctl.emulators.coilboard.syren import BAUD as SYREN_BAUD
from rigctl.emulators.coilboard.syren import SyrenBus, SyrenWireReader

BAUD = 115200
BITS_PER_BYTE = 10  # 8N1


def link_limits() -> dict:
    """SET and ACK sizes from the protocol, and the rates a real serial link allows with them."""
    set_bytes = proto.MIN_FRAME_BYTES + proto.REQUEST_PAYLOAD_BYTES[proto.SET]
    ack_bytes = proto.MIN_FRAME_BYTES + proto.REPLY_PAYLOAD_BYTES[proto.ACK]
    round_trip_bits = (set_bytes + ack_bytes) * BITS_PER_BYTE
    packet_bits = 4 * BITS_PER_BYTE
    return {
        "baud": BAUD,
        "set_frame_bytes": set_bytes,
        "ack_frame_bytes": ack_bytes,
        "round_trip_wire_ms": round_trip_bits / BAUD * 1000.0,
        "set_round_trips_per_s": BAUD / round_trip_bits,  # one SET in flight at a time
        "set_pipelined_per_s": BAUD / (max(set_bytes, ack_bytes) * BITS_PER_BYTE),  # full duplex
        "syren_baud": SYREN_BAUD,
        "syren_packets_per_s": SYREN_BAUD / packet_bits,
        "syren_full_updates_per_s": SYREN_BAUD / (4 * packet_bits),  # all four drivers
    }


class _Board:
    """One emulator in a process of its own, its SyRen wire read from a pty into a bus, for both
    kinds alike (so neither shares this process's interpreter with the driver)."""

    def __init__(self, kind: str, directory: str) -> None:
        self.kind = kind
        self.bus = SyrenBus()
        if kind == "python":
            context = multiprocessing.get_context("spawn")
            self._connection, child = context.Pipe()
            self._process = context.Process(target=serve_in_child_process,
                                            args=(child, os.path.join(directory, "board")))
            self._process.start()
            if not self._connection.poll(30.0):
                self._process.kill()
                raise RuntimeError("the Python firmware emulator process did not start")
            self.url, syren_path = self._connection.recv()
        else:
            from rigctl.emulators.coilboard.simavr import SimavrBoard

            self._harness = SimavrBoard().start()
            self.url, syren_path = self._harness.uart_path, self._harness.syren_path
        self._reader = SyrenWireReader(syren_path, self.bus)

    def close(self) -> None:
        self._reader.close()
        if self.kind == "python":
            self._connection.send("stop")
            self._process.join(10.0)
        else:
            self._harness.stop()


def _percentiles_ms(samples: list[float]) -> dict:
    values = np.asarray(samples) * 1000.0
    return {"p50": float(np.percentile(values, 50)), "p99": float(np.percentile(values, 99)),
            "max": float(values.max()), "n": int(values.size)}


def measure(kind: str, round_trips: int, seconds: float, trials: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="coilboard-bench-") as directory:
        board = _Board(kind, directory)
        try:
            driver = CoilBoard.open(board.url, heartbeat_s=None, reply_timeout_s=0.5)
            try:
                return _measure(board, driver, round_trips, seconds, trials)
            finally:
                driver.close()
        finally:
            board.close()


def _measure(board: _Board, driver: CoilBoard, round_trips: int, seconds: float, trials: int) -> dict:
    times = []
    for k in range(round_trips):
        value = k % 100
        start = time.perf_counter()
        driver.set((value, -value, 0, 0))
        times.append(time.perf_counter() - start)
    count, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        driver.set((count % 100, 0, 0, 0))
        count += 1
    rate = count / elapsed
    # watchdog: a SET, its values seen on the wire, then silence until every driver hears zero
    if not board.bus.wait_autobaud(timeout_s=10.0):
        raise RuntimeError(f"{board.kind}: the SyRen bus never started")
    delays = []
    for trial in range(trials):
        driver.status()  # nothing pending before the timed silence
        value = 40 + trial
        driver.set((value, value, value, value))
        last_frame = time.monotonic()
        for address in (128, 129, 130, 131):
            seen = board.bus.wait_packet(lambda p, a=address: p.address == a and p.data == value,
                                         since=last_frame - 1.0, timeout_s=3.0)
            if seen is None:
                raise RuntimeError(f"{board.kind}: SET {value} never reached SyRen {address}")
        zeros = [board.bus.wait_packet(lambda p, a=address: p.address == a and p.data == 0,
                                       since=last_frame, timeout_s=3.0) for address in (128, 129, 130, 131)]
        if not all(zeros):
            raise RuntimeError(f"{board.kind}: the watchdog did not zero every driver")
        delays.append(max(p.time for p in zeros) - last_frame)
    return {
        "round_trip_ms": _percentiles_ms(times),
        "set_rate_hz": rate,
        "watchdog_ms": {"median": statistics.median(delays) * 1000.0, "max": max(delays) * 1000.0,
                        "trials": trials, "goal_ms": 250.0},
        "lost_replies": driver.lost_replies,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--round-trips", type=int, default=2000)
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--only", choices=["python", "simavr"])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)  # the watchdog trips are the point here, not news
    result: dict = {"bench": "coilboard_link", "host": platform.node(), "cpus": os.cpu_count(),
                    "link": link_limits()}
    for kind in ("python", "simavr"):
        if args.only and kind != args.only:
            continue
        try:
            result[kind] = measure(kind, args.round_trips, args.seconds, args.trials)
        except RigError as err:  # simavr missing: say why instead of a figure
            result[kind] = {"skipped": str(err)}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
