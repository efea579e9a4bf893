"""Seed 003's measures of a field sequence: Table 1 per component and the Fig. 6 cross-activation.

Both take the measured U (T, 8) (mT, mT/m) at times on the plan's clock and the plan's windows (one
per requested component: when its transition starts, when the arms reach its pose, when its hold
ends). Definitions in docs/depm.md ("Execution and metrics"); pure functions, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rigctl.physics.magnetics import U_COMPONENTS

STEADY_STATE_TOLERANCE = 0.02  # of the requested value
FIELD_BAND_mT, GRADIENT_BAND_mT_per_m = 0.5, 5.0  # "close to 0" at the end of a fall (Sec. 4.2)
FALL_DWELL_S = 0.5  # "a constant value close to 0": inside the band for this long
SETTLE_FRACTION = 0.25  # the first quarter of a hold is still settling: not steady state
REQUEST_ZERO = 1e-9  # |requested| below this (mT, mT/m) is "not requested"
UNITS = ["mT"] * 3 + ["mT/m"] * 5


@dataclass
class Window:
    start_s: float
    reached_s: float
    end_s: float
    U: np.ndarray  # requested (8,), mT and mT/m
    name: str


def _signed_peak(values: np.ndarray) -> float | None:
    if values.size == 0:
        return None
    return float(values[np.argmax(np.abs(values))])


def _overshoot_pct(values: np.ndarray, requested: float) -> float | None:
    """Seed 003 Sec. 4.2: by how much the value passed the request (+ %, overshoot) or went to the
    opposite sign (- %, undershoot), as a percentage of the request; the larger of the two."""
    if values.size == 0 or requested == 0:
        return None
    v = values * math.copysign(1.0, requested) / abs(requested)
    over = max(float(v.max()) - 1.0, 0.0)
    under = min(float(v.min()), 0.0)
    return 100.0 * (under if -under > over else over)


def _fall_end(t: np.ndarray, u: np.ndarray, start_s: float, limit_s: float, band: float) -> float:
    """The end of a fall: the first time after `start_s` from which |u| stays within `band` for
    FALL_DWELL_S (or up to `limit_s`); `limit_s` if it never does."""
    inside = (t >= start_s) & (t <= limit_s)
    times, values = t[inside], u[inside]
    out = np.flatnonzero(np.abs(values) > band)
    for i in range(len(times)):
        if abs(values[i]) > band:
            continue
        k = np.searchsorted(out, i)
        next_out_s = times[out[k]] if k < len(out) else limit_s + FALL_DWELL_S
        if next_out_s - times[i] >= min(FALL_DWELL_S, limit_s - times[i]):
            return float(times[i])
    return limit_s


def table1(t: np.ndarray, U: np.ndarray, windows: list[Window]) -> dict:
    """Seed 003 Table 1 from measured U (T, 8) at times t (T,) on the plan's clock.

    Per component: steady-state value, its error (% of the request), peak off-activation (signed),
    overshoot during rise and fall (%), sigma while off (RMS about zero); and averages of the
    absolute values over fields and over gradients. Definitions: docs/depm.md.
    """
    t, U = np.asarray(t, float), np.asarray(U, float)
    out: dict = {}
    run_end = float(t[-1]) if len(t) else 0.0
    for c, label in enumerate(U_COMPONENTS):
        band = FIELD_BAND_mT if c < 3 else GRADIENT_BAND_mT_per_m
        u = U[:, c]
        active = [i for i, w in enumerate(windows) if abs(w.U[c]) > REQUEST_ZERO]
        on = np.zeros(len(t), dtype=bool)
        entry: dict = {"unit": UNITS[c], "requested": None, "steady_state": None,
                       "steady_state_error_pct": None, "overshoot_rise_pct": None,
                       "overshoot_fall_pct": None}
        for i in active:
            w = windows[i]
            hold = w.end_s - w.reached_s
            steady = (t >= w.reached_s + SETTLE_FRACTION * hold) & (t <= w.end_s)
            rise = (t >= w.start_s) & (t < w.reached_s + SETTLE_FRACTION * hold)
            next_end = windows[i + 1].end_s if i + 1 < len(windows) else run_end
            fall_end = _fall_end(t, u, w.end_s, next_end, band) if i + 1 < len(windows) else w.end_s
            fall = (t >= w.end_s) & (t <= fall_end)
            on |= (t >= w.start_s) & (t < fall_end if i + 1 < len(windows) else t <= run_end)
            if entry["requested"] is None:  # the first time the component is asked for
                requested = float(w.U[c])
                value = float(np.mean(u[steady])) if steady.any() else None
                sem = float(np.std(u[steady]) / np.sqrt(steady.sum())) if steady.sum() > 1 else 0.0
                # the pass mark: 2 % of the largest request of this kind (field / gradient) in the
                # segment, or 3 standard errors of the mean if the sensors' noise is larger than
                # that, so a small component is not judged on the noise alone
                kind = slice(0, 3) if c < 3 else slice(3, 8)
                margin = max(STEADY_STATE_TOLERANCE * float(np.max(np.abs(w.U[kind]))), 3.0 * sem)
                entry.update(
                    requested=requested, steady_state=value,
                    steady_state_error_pct=None if value is None
                    else 100.0 * abs(value - requested) / abs(requested),
                    steady_state_sem=sem,
                    steady_state_ok=value is not None and abs(value - requested) <= margin,
                    overshoot_rise_pct=_overshoot_pct(u[rise], requested),
                    overshoot_fall_pct=_overshoot_pct(u[fall], requested) if fall.any() and
                    i + 1 < len(windows) else None,
                    fall_time_s=fall_end - w.end_s if i + 1 < len(windows) else None)
        off = ~on
        entry["peak_off_activation"] = _signed_peak(u[off])
        entry["sigma_off"] = float(np.sqrt(np.mean(u[off] ** 2))) if off.any() else None
        out[label] = entry
    out["average"] = _averages(out)
    return out


def _mean_abs(entries: list[dict], key: str) -> float | None:
    values = [abs(e[key]) for e in entries if e.get(key) is not None]
    return float(np.mean(values)) if values else None


def _averages(per_component: dict) -> dict:
    fields = [per_component[label] for label in U_COMPONENTS[:3]]
    gradients = [per_component[label] for label in U_COMPONENTS[3:]]
    every = fields + gradients
    errors = [e["steady_state_error_pct"] for e in every if e["steady_state_error_pct"] is not None]
    return {
        "steady_state_field_mT": _mean_abs(fields, "steady_state"),
        "steady_state_gradient_mT_per_m": _mean_abs(gradients, "steady_state"),
        "steady_state_error_pct": float(np.mean(errors)) if errors else None,
        "steady_state_error_max_pct": float(np.max(errors)) if errors else None,
        "peak_off_activation_field_mT": _mean_abs(fields, "peak_off_activation"),
        "peak_off_activation_gradient_mT_per_m": _mean_abs(gradients, "peak_off_activation"),
        "overshoot_rise_pct": _mean_abs(every, "overshoot_rise_pct"),
        "overshoot_fall_pct": _mean_abs(every, "overshoot_fall_pct"),
        "sigma_off_field_mT": _mean_abs(fields, "sigma_off"),
        "sigma_off_gradient_mT_per_m": _mean_abs(gradients, "sigma_off"),
    }


def cross_activation(t: np.ndarray, U: np.ndarray, windows: list[Window]) -> dict:
    """Seed 003 Fig. 6: for each requested component (row, in sequence order), the signed peak of
    every component (column) during that component's rise, as % of the requested magnitude of
    that column's kind (mean |request| of the fields, or of the gradients, in the sequence)."""
    t, U = np.asarray(t, float), np.asarray(U, float)
    requested = np.array([w.U for w in windows]) if windows else np.zeros((0, 8))
    scale = np.ones(8)
    for part in (slice(0, 3), slice(3, 8)):
        nonzero = np.abs(requested[:, part])[np.abs(requested[:, part]) > REQUEST_ZERO]
        scale[part] = float(np.mean(nonzero)) if nonzero.size else 1.0
    rows, names = [], []
    for w in windows:
        hold = w.end_s - w.reached_s
        rise = (t >= w.start_s) & (t < w.reached_s + SETTLE_FRACTION * hold)
        row = [None if not rise.any() else 100.0 * _signed_peak(U[rise, j]) / scale[j]
               for j in range(8)]
        rows.append(row)
        names.append(w.name)
    return {"rows": names, "columns": list(U_COMPONENTS), "percent": rows}


def windows_of(plan) -> list[Window]:
    return [Window(s.start_s, s.reached_s, s.end_s, np.asarray(s.U, float), s.name)
            for s in plan.segments]


def steady_state_reached(table: dict | None) -> bool:
    """The run's goal (Table 1): every requested component's steady state within its margin
    (`steady_state_ok`: 2 % of the largest request of its kind, or 3 standard errors)."""
    if table is None:
        return False
    checked = [e["steady_state_ok"] for label, e in table.items()
               if label != "average" and e["requested"] is not None]
    return bool(checked) and all(checked)
