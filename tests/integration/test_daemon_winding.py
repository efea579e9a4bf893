"""The daemon's `winding` topic, read through a ZeroMQ SUB socket of our own, against the daemon on
emulated benches in this process (the devices on real ptys and TCP sockets, the run in the
daemon's stream process): ten times a second the live winding model's estimate, a run's own while
it streams, the last one cooling between runs (nothing once back at the room), and the next run
starting from it. The coil board's
windings here have no temperature coefficient (alpha = 0), so that a held drive heats them along
the first-order closed form T(t) = T_inf + (T(t0) - T_inf) exp(-(t - t0) / tau), computed here from
the rig file's data."""

from __future__ import annotations

import itertools
import json
import math
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import zmq

from rigctl.apps.testing import daemon_on, wait_for
from rigctl.core.config import CoilThermal
from rigctl.core.record import read_series
from rigctl.emulators.bench import SixCoilBench
from rigctl.emulators.coilboard.bench import CoilBoardBench
from rigctl.emulators.depm import DepmBench

# 6 ohm on 12 V: full drive is 24 W, T_inf = 25 + 2.5 x 24 = 85 C, tau = 2.5 x 4 = 10 s
THERMAL = CoilThermal(thermal_resistance_K_per_W=2.5, thermal_capacity_J_per_K=4.0, ambient_C=25.0,
                      warning_C=90.0, max_winding_C=100.0, alpha_per_K=0.0)
TAU_S, HOT_C, ROOM_C = 10.0, 85.0, 25.0
NAMES = ["+x", "-x", "+y", "-y"]


@contextmanager
def winding_feed(bench, runs: Path):
    """(client, SUB socket on `winding`, backdoor) of a daemon on `bench`, started here."""
    with daemon_on(bench, runs) as (rig, backdoor, _), zmq.Context() as context:
        sub = context.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"winding")
        sub.connect(rig.ping()["telemetry"]["data"])
        try:
            yield rig, sub, backdoor
        finally:
            sub.close()


def receive(sub, seconds: float) -> list[dict]:
    """Every `winding` message for `seconds`."""
    messages, deadline = [], time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        if sub.poll(int(left * 1000) + 1):
            topic, payload = sub.recv_multipart()
            assert topic == b"winding"
            messages.append(json.loads(payload))
    return messages


def until(sub, what, timeout_s: float) -> list[dict]:
    """Messages until one satisfies `what` (that one included)."""
    messages, deadline = [], time.monotonic() + timeout_s
    while not messages or not what(messages[-1]):
        assert time.monotonic() < deadline, "no such winding message"
        messages += receive(sub, 0.05)
    return messages


def test_a_board_hold_heats_the_published_estimate_along_the_closed_form_and_it_cools_after(
        tmp_path):
    bench = CoilBoardBench(syren_startup_s=0.05, coil_thermal=THERMAL)
    with winding_feed(bench, tmp_path / "runs") as (rig, sub, backdoor):
        assert receive(sub, 1.0) == []  # at rest at the room: nothing to tell

        rig.hold({"drive": [127, 0, 0, 0]}, ramp_s=0.05)
        rates = until(sub, lambda m: m["temperature_C"][0] > 50.0, 30.0)
        assert len(rates) > 20 and {m["source"] for m in rates} == {"run"}
        first = rates[0]
        assert first["names"] == NAMES and first["warning_C"] == [90.0] * 4
        assert first["limit_C"] == [100.0] * 4 and first["state"] == "ok"
        truth = backdoor.request("truth")["winding_C"]
        for a, b in itertools.pairwise(rates[2:]):  # past the 50 ms ramp: the drive held at full
            expected = HOT_C + (a["temperature_C"][0] - HOT_C) * math.exp(-(b["t"] - a["t"]) / TAU_S)
            assert b["temperature_C"][0] == pytest.approx(expected, abs=0.02)
            assert b["temperature_C"][1:] == [ROOM_C] * 3
        span = rates[-1]["t"] - rates[0]["t"]
        assert len(rates) - 1 == pytest.approx(10 * span, abs=3)  # ten a second
        # the model (the rig file's windings) against the emulator's (5 % off, its own clock)
        assert truth["+x"] == pytest.approx(rates[-1]["temperature_C"][0], abs=2.0)

        rig.release(ramp_s=0.05)
        wait_for(lambda: rig.status()["run"] is None, 30.0, "the hold released")
        cooling = until(sub, lambda m: m["source"] == "cooling", 5.0)
        last_run = [m for m in cooling if m["source"] == "run"][-1]
        later = cooling[-1:] + receive(sub, 1.5)
        assert len(later) > 10 and {m["source"] for m in later} == {"cooling"}
        for m in later:  # T = Ta + (T_r - Ta) exp(-(t - t_r) / tau) from the run's last estimate
            expected = ROOM_C + (last_run["temperature_C"][0] - ROOM_C) * math.exp(
                -(m["t"] - last_run["t"]) / TAU_S)
            assert m["temperature_C"][0] == pytest.approx(expected, abs=0.3)

        # the next run starts as warm as the estimate, not at the room
        before = receive(sub, 0.3)[-1]["temperature_C"][0]
        rig.hold({"drive": [0, 0, 0, 30]}, ramp_s=0.05)
        wait_for(lambda: rig.status()["run"] is not None, 10.0, "the second hold")
        receive(sub, 0.5)
        rig.release(ramp_s=0.05)
        wait_for(lambda: rig.status()["run"] is None, 30.0, "the second hold released")
        series = read_series(rig.status()["last_run"]["run"], "winding")
        assert series["+x"][0] == pytest.approx(before, abs=0.3) and series["+x"][0] > 40.0


def test_the_six_coil_daemon_publishes_its_six_windings_and_the_arms_none(tmp_path):
    with winding_feed(SixCoilBench(), tmp_path / "six") as (rig, sub, _):
        rig.set_field([2.0, 0.0, 0.0], ramp_s=0.05)
        messages = until(sub, lambda m: True, 10.0) + receive(sub, 1.0)
        rig.set_field([0.0, 0.0, 0.0], ramp_s=0.05)
    assert len(messages) > 5 and {m["source"] for m in messages} == {"run"}
    assert messages[-1]["names"] == ["x+", "x-", "y+", "y-", "z+", "z-"]
    # the defaults' 10 kJ/K windings: a few amperes for a second warm them by millikelvin
    assert np.allclose(messages[-1]["temperature_C"], 25.0, atol=0.05)
    assert messages[-1]["limit_C"] == [100.0] * 6 and messages[-1]["warning_C"] == [90.0] * 6
    with winding_feed(DepmBench(), tmp_path / "depm") as (rig, sub, _):
        rig.hold({"joints_rad": [[0.0] * 7] * 2}, ramp_s=0.1)  # the arms held where they stand
        assert receive(sub, 1.0) == []  # permanent magnets: nothing heats
        rig.release()
