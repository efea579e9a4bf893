"""The real driver over TCP against the emulated BOP on the shared emulator server.

Every wait is on readiness (the server returns once it listens; fault switches return once in
force); the step-response test reads time from the same monotonic clock the emulator uses.
"""

from __future__ import annotations

import math
import statistics
import threading
import time

import pytest

from rigctl.core.errors import DeviceError, DeviceTimeout, Disconnected, ProtocolError
from rigctl.core.transport import open_transport
from rigctl.drivers.kepco_bop import GARBLED_STREAK, KepcoBop
from rigctl.emulators.kepco_bop import serve_bop
from rigctl.emulators.server import EmulatorServer

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

R, L = 1.5, 0.075  # tau = L/R = 50 ms
TAU = L / R


@pytest.fixture
def server():
    with EmulatorServer() as running:
        yield running


@pytest.fixture
def bench(server):
    emulated = serve_bop(server, name="x+", resistance_ohm=R, inductance_H=L)
    driver = KepcoBop(open_transport(emulated.endpoint.url), name="x+", timeout_s=0.1)
    yield emulated, driver
    driver.close()


def test_endpoint_url_carries_the_bound_port(bench) -> None:
    emulated, _ = bench
    url = emulated.endpoint.url
    assert url.startswith("tcp://127.0.0.1:")
    assert int(url.rsplit(":", 1)[1]) > 0


def test_identify_and_configure(bench, server) -> None:
    emulated, driver = bench
    assert driver.identify().startswith("KEPCO,BOP 50-20GL")
    server.call(emulated.model.set_mode, "VOLT")
    driver.configure()
    status = server.call(emulated.model.status)
    assert status.mode == "CURR"
    assert status.voltage_setpoint_V == 100.0
    assert status.current_setpoint_A == 0.0


def test_current_step_reaches_63_percent_after_l_over_r(bench) -> None:
    _, driver = bench
    driver.configure()
    driver.output(True)
    setpoint = 10.0
    t0 = time.monotonic()
    driver.send_setpoint(setpoint)
    samples = [(time.monotonic() - t0, driver.read_measured())]
    while samples[-1][0] < 3 * TAU:
        before = time.monotonic()
        current = driver.measure_current()
        samples.append(((before + time.monotonic()) / 2 - t0, current))
    threshold = setpoint * (1 - math.exp(-1))
    k = next(k for k, (_, amps) in enumerate(samples) if amps >= threshold)
    # the crossing lies between the last sample below and the first at or above 63 %
    assert samples[k - 1][0] <= 1.1 * TAU
    assert samples[k][0] >= 0.9 * TAU
    assert samples[-1][1] == pytest.approx(setpoint * (1 - math.exp(-samples[-1][0] / TAU)), rel=0.05)


def test_out_of_range_sent_raw_is_refused_with_222(bench, server) -> None:
    emulated, driver = bench
    driver.configure()
    driver.set_current(2.0)
    driver._transport.write(b"CURR 25\n")  # bypass the driver's own limit check
    assert driver.errors() == [(-222, "Data out of range")]
    assert server.call(lambda: emulated.model.current_setpoint_A) == 2.0


def test_drop_link_is_disconnected_naming_the_device(bench) -> None:
    emulated, driver = bench
    driver.configure()
    emulated.endpoint.drop_link()
    with pytest.raises(Disconnected) as info:
        driver.measure_current()
    assert str(info.value).startswith("x+: link lost (")
    assert emulated.endpoint.url in str(info.value)
    with pytest.raises(Disconnected, match="refused"):
        open_transport(emulated.endpoint.url)
    emulated.endpoint.restore()
    again = KepcoBop(open_transport(emulated.endpoint.url), name="x+")
    assert again.identify().startswith("KEPCO")
    again.close()


def test_stall_times_out_within_the_watchdog(bench) -> None:
    emulated, driver = bench
    driver.configure()
    emulated.endpoint.stall()
    start = time.monotonic()
    with pytest.raises(DeviceTimeout, match="x\\+: no reply within 0.1 s"):
        driver.measure_current()
    elapsed = time.monotonic() - start
    assert 0.1 <= elapsed < 0.1 + 0.15
    emulated.endpoint.restore()
    assert driver.measure_current() == pytest.approx(0.0)  # resynchronised, no stale reply


def test_over_temperature_is_a_device_error_naming_it(bench, server) -> None:
    emulated, driver = bench
    driver.configure()
    driver.output(True)
    server.call(emulated.model.inject_overtemperature)
    with pytest.raises(DeviceError, match='x\\+: device error 20101 "OVER TEMPERATURE"'):
        driver.check_errors()
    with pytest.raises(DeviceError, match="output did not turn on.*OVER TEMPERATURE"):
        driver.output(True)


def test_a_corrupt_reply_is_skipped_a_streak_is_a_protocol_error_then_the_link_recovers(
        bench) -> None:
    emulated, driver = bench
    driver.configure()
    driver.send_setpoint(0.0)
    good = driver.read_measured()
    emulated.endpoint.corrupt(1)
    driver.send_setpoint(1.0)
    assert driver.read_measured() == good and driver.garbled == 1  # the last good one again
    driver.send_setpoint(1.0)
    driver.read_measured()
    emulated.endpoint.corrupt(GARBLED_STREAK)
    for _ in range(GARBLED_STREAK - 1):
        driver.send_setpoint(1.0)
        driver.read_measured()
    driver.send_setpoint(1.0)
    with pytest.raises(ProtocolError, match="x\\+: unreadable reply b'\\\\xfe.*3 unreadable"):
        driver.read_measured()
    assert driver.garbled == 1 + GARBLED_STREAK
    assert driver.measure_voltage() == pytest.approx(0.0)  # output is off


def test_safe_stop_leaves_the_supply_at_zero_and_off(bench, server) -> None:
    emulated, driver = bench
    driver.configure()
    driver.output(True)
    driver.set_current(6.0)
    driver.safe_stop(ramp_s=0.02, steps=4)
    driver.measure_current()  # one more command: the emulator has processed everything before
    status = server.call(emulated.model.status)
    assert (status.output_on, status.current_setpoint_A) == (False, 0.0)


def test_one_server_serves_several_devices_and_periodic_tasks(server) -> None:
    a = serve_bop(server, name="x+")
    b = serve_bop(server, name="x-")
    assert a.endpoint.url != b.endpoint.url
    ticks = threading.Event()
    count = [0]

    def tick() -> None:
        count[0] += 1
        if count[0] == 3:
            ticks.set()

    server.every(0.005, tick)
    assert ticks.wait(2.0)
    for emulated, name in ((a, "x+"), (b, "x-")):
        driver = KepcoBop(open_transport(emulated.endpoint.url), name=name)
        driver.set_current(1.0)
        driver.measure_current()
        assert server.call(lambda e=emulated: e.model.current_setpoint_A) == 1.0
        driver.close()


def test_round_trip_time_on_loopback(bench) -> None:
    """send_setpoint + read_measured to one emulated supply, 2000 cycles (a 1 kHz budget check)."""
    _, driver = bench
    driver.configure()
    driver.output(True)
    times = []
    for k in range(2000):
        start = time.perf_counter()
        driver.send_setpoint(1.0 if k % 2 else -1.0)
        driver.read_measured()
        times.append(time.perf_counter() - start)
    times.sort()
    p50, p99 = statistics.median(times), times[int(0.99 * len(times))]
    print(f"BOP round trip over loopback: p50 {p50 * 1e6:.0f} us, p99 {p99 * 1e6:.0f} us")
    assert p50 < 2e-3  # generous: a 1 kHz loop over six supplies needs far less
    assert p99 < 20e-3


def test_server_stop_is_idempotent_and_ends_service() -> None:
    server = EmulatorServer()
    server.start()
    emulated = serve_bop(server, name="z+")
    client = open_transport(emulated.endpoint.url, timeout_s=0.5)
    client.write(b"*OPC?\n")
    assert client.read_until(b"\n") == b"1\n"  # served: the connection is registered
    assert emulated.endpoint.connection_count == 1
    server.stop()
    server.stop()
    with pytest.raises(RuntimeError):
        server.call(len, [])
    with pytest.raises(Disconnected):
        client.write(b"*IDN?\n")
        client.read_until(b"\n")
    client.close()
