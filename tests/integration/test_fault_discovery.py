"""The fault campaign asks each emulated bench which faults it has (`rigctl.apps.faults.bench_faults`)
over the bench's real backdoor; the answer must be what each bench module's docstring documents
(the lists below are copied from those docstrings, not from the code that serves them)."""

from __future__ import annotations

import pytest

from rigctl.apps.faults import bench_faults
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.emulators.coilboard.bench import CoilBoardBench
from rigctl.emulators.depm import DepmBench

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

LINK = {"drop_link", "stall", "corrupt"}  # emulators/base.py: a device with a link
CAMERA = {"drop_frames", "freeze", "black_out", "occlude", "drop_link"}

BENCHES = {
    # emulators/bench.py: devices "x+" ... "z-" (each supply: its link's faults and `overtemp`)
    # "camera", and "probe" (its link's faults and `skip`)
    "six-coil": (SixCoilBench, {**{n: LINK | {"overtemp"} for n in
                                   ("x+", "x-", "y+", "y-", "z+", "z-")}, "camera": CAMERA,
                                "probe": LINK | {"skip"}}),
    # emulators/coilboard/bench.py: "board" (its link's faults and `unplug`, `replug`, `garbage`)
    # and "camera"; replug ends an unplug, it is no fault of its own
    "coil-board": (lambda: CoilBoardBench(syren_startup_s=0.0),
                   {"board": LINK | {"unplug", "garbage"}, "camera": CAMERA}),
    # emulators/depm.py: "left", "right" (their link's faults, `stall_joint`, `unstall`) and
    # "hall" (its link's faults, `skip`); unstall ends a stall
    "depm": (DepmBench, {"left": LINK | {"stall_joint"}, "right": LINK | {"stall_joint"},
                         "hall": LINK | {"skip"}}),
}


@pytest.mark.parametrize("kind", sorted(BENCHES))
def test_the_campaign_finds_every_documented_fault_of_the_bench(kind):
    make, documented = BENCHES[kind]
    with make() as bench, BackdoorClient(bench.backdoor.url) as backdoor:
        found = bench_faults(backdoor)
    assert {device: set(kinds) for device, kinds in found.items()} == documented
