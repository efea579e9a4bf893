"""The six-coil rig's pre-flight checks of a current program (`rigctl.run.certificate`): every coil's
current, its supply's voltage R(T) I + L dI/dt with the resistance at the winding's hottest, the
winding's temperature, the field and gradient at the workspace centre, each supply link's time per
stream cycle, and the program's size and duration."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from rigctl.core.transport import parse_url
from rigctl.physics.coils import actuation_matrix, field_offset, u_actuation_matrix
from rigctl.physics.magnetics import U_COMPONENTS
from rigctl.physics.thermal import Windings
from rigctl.plans.schema import MAX_DURATION_S, MAX_PROGRAM_SAMPLES
from rigctl.run.certificate import (
    Check,
    ceiling,
    heating_checks,
    link_checks,
    serial_seconds,
    size_checks,
)

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

# one stream cycle on a supply's link: the setpoint and the query in one line, and its answer
# (drivers/kepco_bop.py `send_setpoint`, the BOP's scientific-notation reply)
CYCLE_REQUEST = "CURR -20.0000;:MEAS:CURR?\n"
CYCLE_REPLY = "-2.000000E+01\n"


def supply_link_seconds(rig: SixCoilRig) -> dict[str, float]:
    """Each supply link's time per stream cycle, s: the bytes at its baud rate on a serial link
    (both directions share the time: the reply follows the request), the rig file's measured
    round trip on a LAN link."""
    out = {}
    for coil in rig.coils:
        scheme, _, baud = parse_url(coil.url)
        if scheme == "serial":
            seconds = serial_seconds(len(CYCLE_REQUEST) + len(CYCLE_REPLY), baud)
            out[f"supply {coil.name} ({baud} baud)"] = seconds
        else:
            out[f"supply {coil.name} (LAN)"] = rig.preflight.scpi_round_trip_ms * 1e-3
    return out


def current_program_checks(rig: SixCoilRig, currents_A: np.ndarray, rate_hz: float, *,
                           move_ends: Sequence[int], describe: Callable[[int], str] | None = None,
                           rest_key: str = "field.rest_s") -> list[Check]:
    """Every check of a current program (T, n) A streamed at `rate_hz` from 0 A (a re-plan: the
    whole stream, the samples already sent first, `rigctl.rigs.six_coil.supervisor.
    certified_replan`); `move_ends`: the samples before which `rest_key` would insert its rest."""
    windings = Windings.of_coils(rig.coils)
    checks, peaks = heating_checks(currents_A, rate_hz, windings, move_ends=move_ends,
                                   margin=rig.preflight.heating_margin, describe=describe,
                                   rest_key=rest_key)
    slope = np.diff(currents_A, axis=0, prepend=np.zeros((1, currents_A.shape[1]))) * rate_hz
    hot = windings.resistance_at(np.maximum(peaks, windings.ambient_C))
    volts = np.abs(hot * currents_A + np.array([c.inductance_H for c in rig.coils]) * slope)
    for j, coil in enumerate(rig.coils):
        k = int(np.argmax(np.abs(currents_A[:, j]))) if len(currents_A) else 0
        where = f" ({describe(k)})" if describe and len(currents_A) else ""
        checks.append(ceiling("current", f"coil {coil.name}", np.abs(currents_A[:, j]).max(
            initial=0.0), coil.current_limit_A, "A", f"peak{where}"))
        kv = int(np.argmax(volts[:, j])) if len(volts) else 0
        checks.append(ceiling("voltage R(T) I + L dI/dt", f"supply {coil.name}",
                              volts[:, j].max(initial=0.0), coil.compliance_V, "V",
                              f"R at the winding's hottest, {hot[j]:.3g} ohm"
                              + (f" ({describe(kv)})" if describe and len(volts) else "")))
    offset = field_offset(rig)  # an MPEM rig's Offset field (T, T/m); 0 for loops
    field = currents_A @ actuation_matrix(rig).T + offset[0:3]
    checks.append(ceiling("field |B| at the centre", "workspace", 1e3 * np.linalg.norm(
        field, axis=1).max(initial=0.0), rig.preflight.max_field_mT, "mT"))
    if rig.actuation_matrix_T_per_A is None:  # a measured matrix has no gradients
        terms = np.abs(currents_A @ u_actuation_matrix(rig)[3:].T + offset[3:]) * 1e3
        t = int(np.argmax(terms.max(axis=0, initial=0.0))) if len(terms) else 0
        checks.append(ceiling("gradient at the centre", f"workspace ({U_COMPONENTS[3 + t]})",
                              terms.max(initial=0.0), rig.preflight.max_gradient_mT_per_m, "mT/m"))
    checks += link_checks(supply_link_seconds(rig), rate_hz)
    checks += size_checks(len(currents_A), MAX_PROGRAM_SAMPLES, len(currents_A) / rate_hz,
                          MAX_DURATION_S)
    return checks
