"""The one backdoor command table of every emulated bench, over the real backdoor TCP: the
commands it lists, the errors that name them, fault dispatch to the device links, and `speed`
applied to each bench's physics (simulated time bounded by the real time measured around it)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from rigctl.core.errors import DeviceError
from rigctl.core.transport import open_transport
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.emulators.coilboard.bench import CoilBoardBench
from rigctl.emulators.depm import DepmBench

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

BASE = {"ping", "help", "speed", "fault"}
# bench -> (the commands it adds, its fault devices, one device with a link and its own kinds)
KINDS = {
    "six-coil": ({"place", "truth", "mismatch", "camera", "floor", "coil_errors", "coil_fields",
                  "probe"},
                 ["x+", "x-", "y+", "y-", "z+", "z-", "camera", "probe"], "z-", ["overtemp"]),
    "coil-board": ({"place", "truth", "camera", "floor", "windings"}, ["board", "camera"], "board",
                   ["unplug", "replug", "garbage"]),
    "depm": ({"place", "truth"}, ["left", "right", "hall"], "hall", ["skip"]),
}
LINK_FAULTS = ["drop_link", "stall", "corrupt", "restore"]
DISK = {"boundary": {"disk": [0.0, 0.0, 23.0]}, "obstacles": []}


@pytest.fixture(scope="module", params=list(KINDS))
def bench(request):
    make = {"six-coil": SixCoilBench,
            "coil-board": lambda: CoilBoardBench(syren_startup_s=0.05),
            "depm": DepmBench}[request.param]
    with make() as b:
        b.kind_name = request.param
        yield b


@pytest.fixture
def backdoor(bench):
    with BackdoorClient(bench.rig.emulation.backdoor) as client:
        yield client


def raw(bench, request: dict) -> dict:
    """One request line and its reply, as JSON on the wire."""
    transport = open_transport(bench.rig.emulation.backdoor, timeout_s=5.0)
    try:
        transport.write((json.dumps(request) + "\n").encode())
        return json.loads(transport.read_until(b"\n"))
    finally:
        transport.close()


def test_help_lists_the_table_and_an_unknown_command_names_it(bench):
    added, _, _, _ = KINDS[bench.kind_name]
    commands = raw(bench, {"cmd": "help"})["commands"]
    assert set(commands) == BASE | added and len(commands) == len(BASE | added)
    assert raw(bench, {"cmd": "ping"}) == {"ok": True}
    for request in ({"cmd": "fly"}, {"speed": 2}):
        cmd = request.get("cmd")
        assert raw(bench, request) == {
            "ok": False, "error": f"ValueError: unknown command {cmd!r}; use {', '.join(commands)}"}


def test_faults_reach_the_device_links_and_errors_name_devices_and_kinds(bench, backdoor):
    _, devices, device, own = KINDS[bench.kind_name]
    reply = raw(bench, {"cmd": "fault", "device": "nowhere", "kind": "stall"})
    assert reply == {"ok": False, "error": "ValueError: no device 'nowhere'; the bench has "
                     + ", ".join(devices)}
    reply = raw(bench, {"cmd": "fault", "device": device, "kind": "melt"})
    assert reply == {"ok": False, "error": f"ValueError: unknown {device} fault 'melt'; use "
                     + ", ".join(LINK_FAULTS + own)}
    link = {"z-": lambda: bench.supplies[-1].endpoint, "board": lambda: bench.board.endpoint,
            "hall": lambda: bench.hall.endpoint}[device]()
    assert backdoor.request("fault", device=device, kind="stall") == {
        "ok": True, "device": device, "kind": "stall"}
    assert bench.server.call(lambda: link.faults.stalled) is True
    backdoor.request("fault", device=device, kind="corrupt", n=3)
    assert bench.server.call(lambda: link.faults.corrupt_remaining) == 3
    backdoor.request("fault", device=device, kind="restore")
    assert bench.server.call(lambda: (link.faults.stalled, link.faults.corrupt_remaining)) == (
        False, 0)


def physics_time(bench, backdoor) -> np.ndarray:
    """How far the bench's physics has been stepped, in simulated seconds (a backdoor read steps
    it to now): the supplies (six-coil), the particles' world (coil board), each arm (dEPM)."""
    truth = backdoor.request("truth")
    if isinstance(bench, DepmBench):
        return np.array(bench.server.call(lambda: [arm.model.time_s for arm in bench.arms]))
    return np.array([truth["sim_time_s"]])


def measured(bench, backdoor) -> tuple[float, np.ndarray, float]:
    """(real time before, physics time, real time after)."""
    before = time.monotonic()
    sim = physics_time(bench, backdoor)
    return before, sim, time.monotonic()


@pytest.mark.parametrize("factor", [5.0, 0.5])
def test_speed_sets_how_fast_the_physics_runs(bench, backdoor, factor):
    if isinstance(bench, CoilBoardBench):  # the world's time runs once particles are down
        backdoor.request("place", workspace=DISK, agents=[{"position": [0.0, 0.0], "radius": 0.5}])
    assert backdoor.request("speed", factor=factor) == {"ok": True, "factor": factor}
    try:
        r0, first, r1 = measured(bench, backdoor)
        time.sleep(0.3)
        r2, second, r3 = measured(bench, backdoor)
        # the physics was stepped to the clock somewhere inside each bracket of real time
        elapsed = second - first
        assert np.all(factor * (r2 - r1) - 1e-9 <= elapsed), (elapsed, r2 - r1)
        assert np.all(elapsed <= factor * (r3 - r0) + 1e-9), (elapsed, r3 - r0)
    finally:
        backdoor.request("speed", factor=1.0)


def test_a_speed_that_is_not_positive_is_refused(bench, backdoor):
    if isinstance(bench, CoilBoardBench):  # its physics has a time once particles are down
        backdoor.request("place", workspace=DISK, agents=[{"position": [0.0, 0.0], "radius": 0.5}])
    for factor in (0, -2):
        with pytest.raises(DeviceError, match="speed factor must be positive"):
            backdoor.request("speed", factor=factor)
    assert np.all(np.isfinite(physics_time(bench, backdoor)))


def test_restore_cools_an_overheated_supply_so_the_next_run_can_switch_it_on():
    from rigctl.drivers.kepco_bop import KepcoBop

    with SixCoilBench() as bench, BackdoorClient(bench.rig.emulation.backdoor) as backdoor:
        coil = bench.rig.coils[0]
        bop = KepcoBop(open_transport(coil.url), name=coil.name)
        try:
            backdoor.request("fault", device=coil.name, kind="overtemp")
            with pytest.raises(DeviceError, match="(?i)temperature"):
                bop.output(True)
            backdoor.request("fault", device=coil.name, kind="restore")
            bop.configure()  # the error queue drained: the supply reports nothing pending
            bop.output(True)  # the output turns on again
            bop.output(False)
        finally:
            bop.close()
