"""`rigctl doctor --rig`: every device of each emulated bench reached with nothing energised, and
a device broken through the bench's backdoor named."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from rigctl.core.config import load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess

# rig kind -> (a backdoor fault that breaks one device's link, that device)
BROKEN = {"six-coil": ({"cmd": "fault", "device": "y-", "kind": "drop_link"}, "y-"),
          "coil-board": ({"cmd": "fault", "device": "board", "kind": "unplug"}, "coil board"),
          "depm": ({"cmd": "fault", "device": "right", "kind": "drop_link"}, "right")}


def doctor(rig_path) -> tuple[int, dict]:
    done = subprocess.run([sys.executable, "-m", "rigctl", "doctor", "--rig", str(rig_path),
                           "--json"], capture_output=True, text=True, timeout=60)
    return done.returncode, json.loads(done.stdout)


@pytest.mark.parametrize("kind", list(BROKEN))
def test_doctor_reaches_every_device_and_names_a_broken_one(kind, tmp_path):
    with EmulatedBenchProcess(kind, tmp_path / "bench.toml") as rig_path:
        rig = load_rig(rig_path)
        code, report = doctor(rig_path)
        assert code == 0 and report["ok"], report
        from rigctl.rigs import rig_kind

        assert {d["device"] for d in report["devices"]} == \
            {d.name for d in rig_kind(kind).devices(rig)}
        with BackdoorClient(rig.emulation.backdoor) as backdoor:
            truth = backdoor.request("truth")
            fault, broken = BROKEN[kind]
            request = dict(fault)
            backdoor.request(request.pop("cmd"), **request)
            code, report = doctor(rig_path)
            assert backdoor.request("truth").keys() == truth.keys()  # the bench still serves
        assert code == 3
        failed = [d["device"] for d in report["devices"] if not d["ok"]]
        assert failed == [broken], report


# a device stopped (reads, never answers), unplugged (link gone) or answering garbage
LINK_FAULTS = ({"kind": "stall"}, {"kind": "drop_link"}, {"kind": "corrupt", "n": 50})
# the device of each bench whose link faults are tried, as the backdoor and the rig name it
LINKED = {"six-coil": ("y-", "y-"), "coil-board": ("board", "coil board"),
          "depm": ("right", "right")}


@pytest.mark.parametrize("kind", list(LINKED))
def test_doctor_names_a_device_stopped_unplugged_or_answering_garbage(kind, tmp_path):
    """The doctor's probes in this process (the command around them is the test above)."""
    from rigctl.rigs.doctor import probe_rig

    target, shown = LINKED[kind]
    with EmulatedBenchProcess(kind, tmp_path / "bench.toml") as rig_path:
        rig = load_rig(rig_path)
        with BackdoorClient(rig.emulation.backdoor) as backdoor:
            for fault in LINK_FAULTS:
                backdoor.request("fault", device=target, **fault)
                try:
                    probes = probe_rig(rig)
                finally:
                    backdoor.request("fault", device=target, kind="restore")
                failed = {p.device: p.detail for p in probes if not p.ok}
                assert list(failed) == [shown], (fault, probes)
                assert failed[shown], "the failure says what went wrong"
            assert all(p.ok for p in probe_rig(rig))  # restored: every device answers again


def test_doctor_times_each_supplys_round_trip_against_the_rig_files(tmp_path):
    from rigctl.core.config import dump_rig

    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml") as rig_path:
        code, report = doctor(rig_path)
        supplies = [d for d in report["devices"] if d["kind"] == "supply"]
        assert code == 0 and len(supplies) == 6
        for d in supplies:
            assert "query round trip p50" in d["detail"] and "over 20" in d["detail"], d
            assert "(rig file: scpi_round_trip_ms 0.3)" in d["detail"], d
        # a rig file claiming a link faster than any TCP round trip (1 us): said, not refused
        rig = load_rig(rig_path)
        fast = tmp_path / "fast.toml"
        fast.write_text(dump_rig(rig.model_copy(update={"preflight": rig.preflight.model_copy(
            update={"scpi_round_trip_ms": 0.001})})))
        code, report = doctor(fast)
        assert code == 0
        for d in (d for d in report["devices"] if d["kind"] == "supply"):
            assert "SLOWER than the pre-flight assumes" in d["detail"], d
