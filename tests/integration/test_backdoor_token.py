"""An emulated bench serving beyond loopback takes backdoor requests only with its token (issue
38): `rigctl emulate --host` (its own process, as a user starts it) writes the token into the rig
file, readable by its owner only; a request without it, or with another, is refused in one line
and not run, and the bench goes on serving; `BackdoorClient.of(rig.emulation)`, as every rigctl
client opens it, is served. On loopback nothing changes: no token, every request served."""

from __future__ import annotations

import json
import socket
import stat
from pathlib import Path

import pytest

from rigctl.core.config import load_rig
from rigctl.core.errors import DeviceError
from rigctl.core.transport import open_transport
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.emulators.depm import DepmBench
from rigctl.emulators.process import EmulatedBenchProcess


def beyond_loopback() -> str:
    """This machine's own non-loopback address (the one a route to a TEST-NET address leaves
    from; a UDP connect sends nothing), else every interface."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.123", 9))
            address = probe.getsockname()[0]
        except OSError:
            return "0.0.0.0"
    return address if not address.startswith("127.") else "0.0.0.0"


def raw(url: str, request: dict) -> dict:
    """One request line and its reply, as JSON on the wire, on a connection of its own."""
    transport = open_transport(url, timeout_s=5.0)
    try:
        transport.write((json.dumps(request) + "\n").encode())
        return json.loads(transport.read_until(b"\n"))
    finally:
        transport.close()


def test_rigctl_emulate_beyond_loopback_serves_its_backdoor_only_with_the_token(tmp_path):
    with EmulatedBenchProcess("depm", tmp_path / "bench.toml",
                              extra_args=["--host", beyond_loopback()]) as rig_path:
        assert stat.S_IMODE(rig_path.stat().st_mode) == 0o600
        emulation = load_rig(rig_path).emulation
        assert emulation is not None and emulation.backdoor_token
        url, token = emulation.backdoor, emulation.backdoor_token
        for request in ({"cmd": "ping"}, {"cmd": "ping", "token": token[:-1]},
                        {"cmd": "ping", "token": ""}, {"cmd": "ping", "token": 7},
                        {"cmd": "help", "token": token.upper() if token != token.upper()
                         else token.lower()}):
            reply = raw(url, request)
            assert reply["ok"] is False and reply["error"].startswith("refused: "), request
            assert "\n" not in reply["error"]
        with BackdoorClient(url) as tokenless:  # rigctl's client without the token: refused too
            with pytest.raises(DeviceError, match="refused"):
                tokenless.request("ping")
            assert raw(url, {"cmd": "ping", "token": token}) == {"ok": True}  # still serving
        with BackdoorClient.of(emulation) as backdoor:
            assert "truth" in backdoor.request("help")["commands"]


def test_a_refused_request_is_not_run():
    with DepmBench(host=beyond_loopback()) as bench:
        assert bench.rig.emulation.backdoor_token == bench.token
        reply = raw(bench.backdoor.url, {"cmd": "speed", "factor": 4.0})
        assert reply["ok"] is False and bench.clock.speed == 1.0
        with BackdoorClient.of(bench.rig.emulation) as backdoor:
            assert backdoor.request("speed", factor=4.0) == {"ok": True, "factor": 4.0}
        assert bench.clock.speed == 4.0


def test_on_loopback_the_backdoor_needs_no_token():
    with DepmBench() as bench:
        assert bench.token is None and bench.rig.emulation.backdoor_token is None
        assert raw(bench.backdoor.url, {"cmd": "ping"}) == {"ok": True}


def test_a_run_on_a_bench_beyond_loopback_uses_the_token_and_records_none(tmp_path):
    """The engine's own backdoor client (placing the robots, reading ground truth) is served on a
    tokened bench; the run record's copy of the rig file leaves the token out."""
    from rigctl.plans.schema import parse_plan
    from rigctl.rigs.six_coil.global_moves import execute_plan

    # fig4-quick's first move cut to 10 mm: a second of rolling
    document = json.loads((Path(__file__).resolve().parents[2] / "plans" / "examples"
                           / "fig4-quick.json").read_text())
    document.update(moves=[[0.0, -10.0]], expected=[[[220.0, 230.0], [100.0, 230.0]]])
    for agent, goal in zip(document["agents"], document["expected"][0]):
        agent["goal"] = goal
    plan = parse_plan(document, "fig4-quick, one short move")
    with SixCoilBench(host=beyond_loopback()) as bench:
        summary = execute_plan(plan, bench.rig, runs_dir=tmp_path, progress_out=None,
                               closed_loop=False)
        token = bench.token
    assert summary.positions_from != "unknown" and not summary.faults
    (recorded,) = tmp_path.glob("*/rig.toml")
    emulation = load_rig(recorded).emulation
    assert emulation is not None and emulation.backdoor_token is None
    assert token not in recorded.read_text()
