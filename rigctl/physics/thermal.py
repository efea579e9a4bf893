"""How hot the coils' windings get: one first-order thermal model for the pre-flight, the run and
the emulated coils.

A winding of heat capacity C (J/K) loses heat to the room (ambient T_a) through a thermal
resistance R_th (K/W) and gains the Joule power of its current, with the copper's resistance rising
with its temperature, R(T) = R_0 (1 + alpha (T - T_ref)) (alpha = 0.00393 /K for copper):

    C dT/dt = P(T) - (T - T_a) / R_th.

Driven by a current I (a Kepco BOP in current mode), P = I^2 R(T) is linear in T, so for a current
held over a step dt the solution is exact:

    dT/dt = a - b T,  b = (1/R_th - I^2 R_0 alpha) / C,  a = (I^2 R_0 (1 - alpha T_ref) + T_a/R_th) / C
    T(t + dt) = T(t) e^(-b dt) + a (1 - e^(-b dt)) / b

(b < 0 is thermal runaway: above I^2 = 1/(R_0 alpha R_th) the winding has no steady state, and the
same formula grows exponentially). A stream of piecewise-constant samples is an affine recurrence
T_k+1 = e_k T_k + c_k, evaluated for all samples and coils at once by cumulative products
(`winding_temperatures`). Driven by a voltage V (the coil board's SyRens), P = V^2 / R(T) falls as
the winding warms; a step takes R at its start (`step_voltage`), exact to O(dt / tau). A
`Windings` says which drives it (`volts_per_unit`), so that the live model (`WindingMonitor`)
takes a run's channels as they come: supply currents, or the board's drive.

Units: A, V, ohm, s, K, degrees C; arrays are (samples, coils).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

COPPER_ALPHA_PER_K = 0.00393
"""Temperature coefficient of copper's resistance at 20 C."""

_CHUNK = 512  # samples per cumulative product
_MIN_DECAY = 1e-12  # a step longer than 27.6 time constants: at equilibrium to 1e-12 of the rise


@dataclass(frozen=True)
class Windings:
    """The thermal data of n windings, each attribute (n,): R_th (K/W), C_th (J/K), the room
    (C), the resistance `resistance_ohm` at `reference_C`, alpha (1/K), and the warning and
    maximum winding temperatures (C). `volts_per_unit`: None for windings driven by a current
    (their channels are in A), else the volts one channel unit puts across a winding (the coil
    board: its SyRens' supply over full drive)."""

    names: tuple[str, ...]
    r_th: np.ndarray
    c_th: np.ndarray
    ambient_C: np.ndarray
    resistance_ohm: np.ndarray
    reference_C: np.ndarray
    alpha: np.ndarray
    warning_C: np.ndarray
    limit_C: np.ndarray
    volts_per_unit: float | None = None

    @classmethod
    def of(cls, names: Sequence[str], resistances_ohm: Sequence[float], thermals: Sequence, *,
           volts_per_unit: float | None = None) -> Windings:
        """From rig-file data: one resistance and one `rigctl.core.config.CoilThermal` per winding."""
        def col(key: str) -> np.ndarray:
            return np.array([getattr(t, key) for t in thermals], dtype=float)

        return cls(tuple(names), col("thermal_resistance_K_per_W"), col("thermal_capacity_J_per_K"),
                   col("ambient_C"), np.asarray(resistances_ohm, dtype=float), col("reference_C"),
                   col("alpha_per_K"), col("warning_C"), col("max_winding_C"), volts_per_unit)

    @classmethod
    def of_coils(cls, coils: Sequence) -> Windings:
        """Air-core coils fed by current supplies (each with `name`, `resistance_ohm`, `thermal`)."""
        return cls.of([c.name for c in coils], [c.resistance_ohm for c in coils],
                      [c.thermal for c in coils])

    @classmethod
    def of_board(cls, board) -> Windings:
        """A board's windings, all alike (`coil_names`, `coil_resistance_ohm`, `coil_thermal`),
        driven in drive units: a drive d puts d x `volts_per_unit` across its coil."""
        n = len(board.coil_names)
        return cls.of(board.coil_names, [board.coil_resistance_ohm] * n, [board.coil_thermal] * n,
                      volts_per_unit=board.volts_per_unit)

    @classmethod
    def of_rig(cls, rig) -> Windings | None:
        """The windings a rig's run watches (a `RigConfig`), as its kind says (`RigKind.windings`):
        None where nothing heats (permanent magnets)."""
        from rigctl.core.registry import rig_kind

        return rig_kind(rig.rig.kind).windings(rig)

    def off_by(self, fraction: ArrayLike, capacity_fraction: ArrayLike | None = None) -> Windings:
        """The same windings with R_th `fraction` and C_th `capacity_fraction` (default: the
        same) larger, each a scalar or one per winding (an emulated winding that differs from
        its data)."""
        capacity = fraction if capacity_fraction is None else capacity_fraction
        return replace(self, r_th=self.r_th * (1 + np.asarray(fraction)),
                       c_th=self.c_th * (1 + np.asarray(capacity)))

    @property
    def time_constant_s(self) -> np.ndarray:
        """R_th C_th (s), at zero current."""
        return self.r_th * self.c_th

    def one(self, j: int = 0) -> OneWinding:
        """Winding `j` as plain floats, for `step_current_one`."""
        return OneWinding(float(self.resistance_ohm[j]), 1.0 / float(self.r_th[j]),
                          float(self.c_th[j]), float(self.alpha[j]), float(self.reference_C[j]),
                          float(self.ambient_C[j]))

    def resistance_at(self, temperature_C: ArrayLike) -> np.ndarray:
        """R(T) (..., n) ohm."""
        return self.resistance_ohm * (1 + self.alpha * (np.asarray(temperature_C) - self.reference_C))


def _decay_and_gain(current_A: np.ndarray, dt_s: np.ndarray, w: Windings,
                    power_factor: float) -> tuple[np.ndarray, np.ndarray]:
    """(e, c) of the exact step T' = e T + c for currents held over dt; shapes broadcast to (T, n)."""
    p = power_factor * np.square(current_A) * w.resistance_ohm  # I^2 R_0, W
    g = 1.0 / w.r_th
    b = (g - p * w.alpha) / w.c_th
    a = (p * (1 - w.alpha * w.reference_C) + g * w.ambient_C) / w.c_th
    x = b * dt_s
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        phi = np.where(np.abs(x) < 1e-12, dt_s * (1 - 0.5 * x), -np.expm1(-x) / b)
    return 1.0 - b * phi, a * phi


def step_current(temperature_C: ArrayLike, current_A: ArrayLike, dt_s: float, w: Windings,
                 power_factor: float = 1.0) -> np.ndarray:
    """Winding temperatures (n,) C after `dt_s` with `current_A` (n,) held (exact)."""
    e, c = _decay_and_gain(np.asarray(current_A, dtype=float), np.asarray(dt_s, dtype=float), w,
                           power_factor)
    return e * np.asarray(temperature_C, dtype=float) + c


class OneWinding(NamedTuple):
    """One winding's data as plain floats (`Windings.one`)."""

    resistance_ohm: float
    conductance_W_per_K: float  # 1 / R_th
    c_th: float
    alpha: float
    reference_C: float
    ambient_C: float


def step_current_one(temperature_C: float, current_A: float, dt_s: float, w: OneWinding) -> float:
    """`step_current` for one winding in plain floats (an emulated coil steps every millisecond:
    numpy's per-call cost would be most of it)."""
    p = current_A * current_A * w.resistance_ohm
    g, c, alpha = w.conductance_W_per_K, w.c_th, w.alpha
    b = (g - p * alpha) / c
    a = (p * (1 - alpha * w.reference_C) + g * w.ambient_C) / c
    x = b * dt_s
    phi = dt_s * (1 - 0.5 * x) if abs(x) < 1e-12 else -math.expm1(-x) / b
    return temperature_C + (a - b * temperature_C) * phi


def step_voltage(temperature_C: ArrayLike, voltage_V: ArrayLike, dt_s: float, w: Windings) -> np.ndarray:
    """Winding temperatures (n,) C after `dt_s` with `voltage_V` (n,) across each winding, its
    resistance taken at the start of the step."""
    t = np.asarray(temperature_C, dtype=float)
    power = np.square(np.asarray(voltage_V, dtype=float)) / w.resistance_at(t)
    tau = w.time_constant_s
    target = w.ambient_C + power * w.r_th
    return target + (t - target) * np.exp(-dt_s / tau)


def step_voltage_one(temperature_C: float, voltage_V: float, dt_s: float, w: OneWinding) -> float:
    """`step_voltage` for one winding in plain floats (the live model steps every stream cycle)."""
    g = w.conductance_W_per_K
    resistance = w.resistance_ohm * (1 + w.alpha * (temperature_C - w.reference_C))
    target = w.ambient_C + voltage_V * voltage_V / resistance / g
    return target + (temperature_C - target) * math.exp(-dt_s * g / w.c_th)


def winding_temperatures(currents_A: ArrayLike, dt_s: ArrayLike, w: Windings, *,
                         start_C: ArrayLike | None = None, power_factor: float = 1.0) -> np.ndarray:
    """Temperatures (T + 1, n) C at the boundaries of T current samples (T, n), sample k held
    for dt_s (scalar or (T,)) s; row 0 is `start_C` (default: the room). `power_factor` scales
    the Joule power (a margin)."""
    currents = np.asarray(currents_A, dtype=float)
    n_samples, n = currents.shape
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (n_samples,))[:, None]
    e, c = _decay_and_gain(currents, dt, w, power_factor)
    e, c = np.broadcast_to(e, currents.shape), np.broadcast_to(c, currents.shape)
    # the scan runs on the rise above the room, x = T - T_a: x' = e x + (c - (1 - e) T_a), so a
    # decay factor floored at _MIN_DECAY keeps a little more heat, never less
    gain = c - (1.0 - e) * w.ambient_C
    e = np.maximum(e, _MIN_DECAY)
    out = np.empty((n_samples + 1, n))
    out[0] = (w.ambient_C if start_C is None else np.asarray(start_C, dtype=float)) - w.ambient_C
    _scan(e, gain, out, 0, n_samples, _CHUNK)
    return out + w.ambient_C


def _scan(e: np.ndarray, gain: np.ndarray, out: np.ndarray, start: int, stop: int, chunk: int) -> None:
    """out[k + 1] = e[k] out[k] + gain[k] for k in [start, stop), by cumulative products of at
    most `chunk` samples (smaller where the products would underflow)."""
    for s in range(start, stop, chunk):
        ee, gg = e[s:min(s + chunk, stop)], gain[s:min(s + chunk, stop)]
        # x_k+1 = P_k (x_s + sum_{j<=k} g_j / P_j), P_k = e_s ... e_k
        products = np.cumprod(ee, axis=0)
        if chunk > 8 and products[-1].min() < 1e-200:
            _scan(e, gain, out, s, s + len(ee), chunk // 8)
            continue
        out[s + 1:s + 1 + len(ee)] = products * (out[s] + np.cumsum(gg / products, axis=0))


@dataclass(frozen=True)
class Crossing:
    """The first time a winding reaches a temperature: coil index, boundary index, time (s)."""

    coil: int
    index: int
    time_s: float


def first_crossing(temperatures_C: np.ndarray, threshold_C: np.ndarray,
                   times_s: np.ndarray) -> Crossing | None:
    """The earliest boundary (any coil) at or above its threshold, or None."""
    over = temperatures_C >= threshold_C
    if not over.any():
        return None
    rows = np.where(over.any(axis=0), over.argmax(axis=0), len(over))
    j = int(np.argmin(rows))
    return Crossing(j, int(rows[j]), float(times_s[rows[j]]))


def with_rests(currents_A: np.ndarray, dt_s: float, move_ends: Sequence[int],
               rest_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Currents (T + m, n) and durations (T + m,) with a zero-current rest of `rest_s` before
    each sample index in `move_ends` (where a move, its hold included, is over)."""
    ends = np.asarray(move_ends, dtype=int)
    currents = np.insert(currents_A, ends, 0.0, axis=0)
    dt = np.insert(np.full(len(currents_A), float(dt_s)), ends, float(rest_s))
    return currents, dt


def rest_to_pass(currents_A: np.ndarray, dt_s: float, move_ends: Sequence[int], w: Windings, *,
                 power_factor: float = 1.0, tolerance_s: float = 0.5) -> float | None:
    """The shortest zero-current rest after every move that keeps every winding below its warning
    level (so that the run goes through without a pause; 0.0 when none is needed, within
    `tolerance_s`), or None when no rest would do (one move alone heats a winding that far).
    Bisection on the rest, each try one pass of the model."""
    def peak_margin(rest: float) -> float:
        currents, dt = with_rests(currents_A, dt_s, move_ends, rest)
        temps = winding_temperatures(currents, dt, w, power_factor=power_factor)
        return float(np.min(w.warning_C - temps.max(axis=0)))

    if peak_margin(0.0) > 0:
        return 0.0
    longest = float(20 * w.time_constant_s.max())  # the windings are back at the room by then
    if len(move_ends) == 0 or peak_margin(longest) <= 0:
        return None
    low, high = 0.0, longest
    while high - low > tolerance_s:
        mid = 0.5 * (low + high)
        low, high = (low, mid) if peak_margin(mid) > 0 else (mid, high)
    return high


def voltage_steady_C(voltage_V: ArrayLike, w: Windings) -> np.ndarray:
    """The steady winding temperature (n,) C under a constant voltage: T = T_a + R_th V^2/R(T),
    the positive root of R_0 alpha x^2 + R_0 (1 + alpha (T_a - T_ref)) x - R_th V^2 = 0 with
    x = T - T_a."""
    v2 = np.square(np.asarray(voltage_V, dtype=float))
    qa = w.resistance_ohm * w.alpha
    qb = w.resistance_ohm * (1 + w.alpha * (w.ambient_C - w.reference_C))
    qc = -w.r_th * v2
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.where(qa > 0, (-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa), -qc / qb)
    return w.ambient_C + x


def voltage_crossing_s(voltage_V: ArrayLike, w: Windings, threshold_C: np.ndarray,
                       horizon_s: float, step_s: float | None = None) -> np.ndarray:
    """When each winding (n,) under a constant voltage from the room first reaches its
    threshold, s; inf if not within `horizon_s`."""
    step = step_s or float(w.time_constant_s.min()) / 200
    t = np.array(w.ambient_C, dtype=float)
    when = np.full(len(t), math.inf)
    elapsed = 0.0
    while elapsed < horizon_s and np.isinf(when).any():
        t = step_voltage(t, voltage_V, step, w)
        elapsed += step
        when[np.isinf(when) & (t >= threshold_C)] = elapsed
    return when


class WindingMonitor:
    """The model run live on what drives the windings, a value per winding: measured currents
    (A), or a drive of `Windings.volts_per_unit` volts per unit. `update` advances it by one
    stream cycle and says whether a winding is at its warning or its limit ("ok", "warning",
    "limit")."""

    def __init__(self, w: Windings, start_C: ArrayLike | None = None) -> None:
        self.windings = w
        self.temperature_C = np.array(w.ambient_C if start_C is None else start_C, dtype=float)
        self.peak_C = self.temperature_C.copy()
        # the stream thread's per-cycle work in plain floats (numpy's per-call cost is 20x)
        self._one = [w.one(j) for j in range(len(w.names))]
        self._limits = [float(v) for v in w.limit_C]
        self._warnings = [float(v) for v in w.warning_C]
        self._step = step_current_one if w.volts_per_unit is None else step_voltage_one
        self._scale = 1.0 if w.volts_per_unit is None else float(w.volts_per_unit)

    def update(self, drive: ArrayLike, dt_s: float) -> str:
        state = "ok"
        temperatures, step, scale = self.temperature_C, self._step, self._scale
        drive = np.asarray(drive, dtype=float)
        for j, one in enumerate(self._one):
            t = step(float(temperatures[j]), float(drive[j]) * scale, dt_s, one)
            temperatures[j] = t
            self.peak_C[j] = max(self.peak_C[j], t)
            if t >= self._limits[j]:
                state = "limit"
            elif t >= self._warnings[j] and state == "ok":
                state = "warning"
        return state

    def hottest(self) -> tuple[str, float]:
        j = int(np.argmax(self.temperature_C - self.windings.limit_C))
        return self.windings.names[j], float(self.temperature_C[j])
