"""`rigctl doctor`'s probe of a six-coil rig's supplies (`RigKind.probes`): a Kepco BOP's `*IDN?`
and its error queue, read only; from `rigctl doctor` (`timed`) also its query round trip against the
rig file's `[preflight] scpi_round_trip_ms`."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from rigctl.core.errors import RigError
from rigctl.rigs.base import Device

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

ROUND_TRIPS = 20  # `MEAS:CURR?` queries timed per supply by `rigctl doctor`


def supply(rig: SixCoilRig, device: Device, timed: bool = False) -> str:
    """One supply's identity and empty error queue; `timed`: its query round trip too."""
    from rigctl.core.transport import open_transport
    from rigctl.drivers.kepco_bop import KepcoBop

    coil = next(c for c in rig.coils if c.name == device.name)
    timeout = rig.stream.reply_timeout_s
    bop = KepcoBop(open_transport(coil.url, timeout_s=timeout), name=coil.name,
                   current_limit_A=coil.current_limit_A, compliance_V=coil.compliance_V,
                   timeout_s=timeout)
    try:
        identity = bop.identify()
        queue = bop.errors()
        trips = []
        for _ in range(ROUND_TRIPS if timed else 0):  # a query: nothing is set
            started = time.perf_counter()
            bop.measure_current()
            trips.append(1e3 * (time.perf_counter() - started))
    finally:
        bop.close()
    if queue:
        raise RigError(f"{identity}; error queue: " + "; ".join(f"{c} {t}" for c, t in queue),
                       device=coil.name)
    return f"{identity}; error queue empty" + (_round_trip(rig, coil.url, trips) if trips else "")


def _round_trip(rig: SixCoilRig, url: str, trips_ms: list[float]) -> str:
    """The measured query round trip against what the pre-flight assumes of a LAN link
    (`[preflight] scpi_round_trip_ms`; a serial link's time comes from its baud rate)."""
    p50, worst = float(np.median(trips_ms)), max(trips_ms)
    text = f"; query round trip p50 {p50:.2f} ms, max {worst:.2f} ms over {len(trips_ms)}"
    if url.startswith("serial"):
        return text
    assumed = rig.preflight.scpi_round_trip_ms
    text += f" (rig file: scpi_round_trip_ms {assumed:g})"
    if p50 > assumed:
        text += (f": SLOWER than the pre-flight assumes; set [preflight] scpi_round_trip_ms to "
                 f"{worst:.2g} or more before streaming at the rate it certified")
    return text


