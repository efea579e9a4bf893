"""The direct make-safe of the six supplies (`zero_supplies_directly`: the e-stop with no run, the
daemon's re-zero of a supply a run could not confirm, the unit's stop-post) must not call a hung
supply safe. Found by the fault campaign (`rigctl faults`, x+:stall while ramping down): a stalled
link takes the bytes and never answers, the e-stop's write succeeded, and the daemon marked the
supply "made safe once its link answered again" while it held 2.9 A. The currents here are read
from the emulator's truth."""

from __future__ import annotations

import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.transport import open_transport
from rigctl.drivers.kepco_bop import KepcoBop
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.rigs.six_coil.supplies import zero_supplies_directly

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick


def test_a_stalled_supply_is_reported_not_confirmed_and_zeroed_once_it_answers():
    with SixCoilBench() as bench, BackdoorClient(bench.backdoor.url) as backdoor:
        rig = bench.rig.model_copy(update={"stream": bench.rig.stream.model_copy(
            update={"reply_timeout_s": 0.2})})
        coil = rig.coils[0]
        supply = KepcoBop(open_transport(coil.url, timeout_s=1.0), name=coil.name,
                          current_limit_A=coil.current_limit_A, compliance_V=coil.compliance_V)
        supply.configure()
        supply.set_current(2.0)
        supply.output(True)
        supply.close()

        def current() -> float:
            return abs(backdoor.request("truth")["currents_A"][coil.name])

        wait_for(lambda: current() > 1.9, 10, f"{coil.name} at 2 A")
        backdoor.request("fault", device=coil.name, kind="stall")
        result = zero_supplies_directly(rig)
        assert result[coil.name] is not None and "not confirmed" in result[coil.name], result
        assert all(result[c.name] is None for c in rig.coils[1:]), result
        assert current() > 1.9  # the hung supply still holds its current: nobody may say safe

        backdoor.request("fault", device=coil.name, kind="restore")
        result = zero_supplies_directly(rig)
        assert result[coil.name] is None, result
        wait_for(lambda: current() < 0.05, 10, f"{coil.name} under 50 mA")
