"""Field calibration of the six-coil rig (`rigctl calibrate field`): drive current patterns, read a
Hall probe array, fit each coil's gain, centre offset and axis misalignment.

Measure: the supplies are driven through a set of patterns (all off; each coil alone at +I0 and
-I0; a few seeded mixes of every coil), ramped from one to the next within the current and
compliance limits (checked on the whole program before anything is switched on, as the allocator
does), held until the coils settle (5 L/R), and the probe's samples taken after that are averaged.
The fit uses the supplies' *measured* currents, not the setpoints.

Fit, in two linear-then-nonlinear stages (the field is linear in the currents, non-linear in the
geometry):

1. per probe sensor k, B_k = F_k I + b_k over the patterns, by linear least squares: F_k (3 x n)
   is the measured actuation matrix at that sensor, b_k the background (the ambient field plus
   the sensor's zero offset), which is not the coils' and is left out of the calibration;
2. per coil j, the loop model g * loop_field(p; c + d, R(t) a, radius, turns) fitted to the
   column F[:, :, j] at every sensor by `scipy.optimize.least_squares` (6 parameters: gain g,
   centre offset d, two small tilt angles t of the axis a), starting from the rig file's loop.
   One-sigma uncertainties come from the Jacobian at the solution and the residual scatter.

Or an MPEM (`fit_mpem_calibration`; `rigctl calibrate field --model mpem`, the default):
mag_manip's multipole model (`rigctl.physics.fields.fit.fit_mpem`), the format mag_manip and the
Tesla framework read, fitted to the same samples from the drawn loops (`start_from_loops`: one B
source per coil along its axis, orders 1 to the one asked), each source moved back from the coil's
centre by half its radius, away from the workspace (`START_BEHIND_RADII` says why). A quarter of
the probe's sensors (seeded) are held out of that fit, every pattern's reading at them: the fit's
error there, in mT and in % of the mean field magnitude, says how well the model knows the field
between the points it saw, and the drawn loops' error on the same samples is the yardstick. The
file written is that fit (its workspace the whole probe's box), so the error reported is the
written model's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import least_squares

from rigctl.core.errors import ConfigError, DeviceError
from rigctl.physics.field_calibration import FORMAT, CoilFit, FieldCalibration
from rigctl.physics.fields import MPEM, LoopModel, Source
from rigctl.physics.fields.fit import MpemFit, fit_mpem, held_out_error, start_from_loops
from rigctl.physics.magnetics import loop_field

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

log = logging.getLogger(__name__)

PATTERN_FRACTION = 0.5
"""I0 = this x the smallest coil current limit (10 A on the default rig: ~1.5 mT per coil)."""
MIXED_PATTERNS = 6
SAMPLES_PER_PATTERN = 10
SETTLE_TAU = 5.0  # hold this many L/R before the probe's samples count
RAMP_S = 0.1  # each pattern change, ramped linearly
HOLD_TIMEOUT_S = 5.0  # a pattern's samples not all in by then: a fault (the probe is too slow)
HELD_OUT_FRACTION = 0.25
"""Of the probe's sensors, this share (at least one) is kept out of the MPEM fit to judge it."""
START_BEHIND_RADII = 0.5
"""The MPEM fit's start puts each coil's source this many loop radii behind the coil's centre,
along its axis away from the workspace. A multipole about one point reproduces a loop only outside
the sphere about that point through the winding, so about the centre it converges slowly over a
workspace that comes close to the coil (0.25 m from a 0.2 m loop's centre on the default cube),
and from there the fit stops in a local minimum: on the default cube with the emulator's 5 % coil
errors (seed 0, the probe's readings computed, 3 uT noise; order 3) held-out 0.96 % from the
centre, 0.39 % from 0.5, 0.75 or 1 radius back (the same minimum)."""


def drive_patterns(rig: SixCoilRig, *, seed: int = 0, mixed: int = MIXED_PATTERNS,
                   current_A: float | None = None) -> np.ndarray:
    """The current patterns (P, n) A: zero, each coil alone at +-I0, then `mixed` seeded mixes
    (every coil uniform in +-I0); the zero pattern ends the list too, so the rig ends at rest.
    I0 is `current_A` (a station whose field at the probe would saturate it at the default: its
    cores make far more field per ampere than air loops), else `PATTERN_FRACTION` of the
    smallest coil limit; never more than that limit (ConfigError)."""
    n = len(rig.coils)
    limit = min(c.current_limit_A for c in rig.coils)
    if current_A is not None and not 0 < current_A <= limit:
        raise ConfigError(f"--current must be > 0 and at most the smallest coil limit, "
                          f"{limit:g} A; got {current_A:g}")
    i0 = PATTERN_FRACTION * limit if current_A is None else current_A
    single = np.concatenate([np.eye(n), -np.eye(n)])[np.argsort(np.tile(np.arange(n), 2),
                                                                 kind="stable")] * i0
    mixes = np.random.default_rng(seed).uniform(-i0, i0, size=(mixed, n))
    return np.concatenate([np.zeros((1, n)), single, mixes, np.zeros((1, n))])


def ramp_program(rig: SixCoilRig, patterns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Setpoints (T, n) A at the rig's stream rate through `patterns`, each change ramped over
    RAMP_S and then held while the coils settle (the holds last until the probe's samples are in;
    a hold's voltage is R I whatever its length), and the pattern index (T,) each sample holds (-1
    while ramping): what `measure` checks against every limit before it switches anything on."""
    rate = rig.stream.rate_hz
    tau = max(c.inductance_H / c.resistance_ohm for c in rig.coils)
    hold = max(1, int(np.ceil(SETTLE_TAU * tau * rate)))
    ramp = max(1, int(np.ceil(RAMP_S * rate)))
    rows, index = [], []
    previous = np.zeros(patterns.shape[1])
    for p, pattern in enumerate(patterns):
        for k in range(1, ramp + 1):
            rows.append(previous + (pattern - previous) * k / ramp)
            index.append(-1)
        rows += [pattern] * hold
        index += [p] * hold
        previous = pattern
    return np.array(rows), np.array(index)


@dataclass
class Measurements:
    """What the probe saw: sensor positions (K, 3) m, the supplies' measured currents (P, n) A
    and the mean field (P, K, 3) T for each pattern, samples per pattern, and the time taken."""

    points_m: np.ndarray
    currents_A: np.ndarray
    fields_T: np.ndarray
    samples: np.ndarray
    duration_s: float


def measure(rig: SixCoilRig, patterns: np.ndarray, *,
            progress: Callable[[str], None] = lambda _: None) -> Measurements:
    """Drive `patterns` on the rig's supplies and read its `field_probe` (see the module
    docstring). Checks every limit first (LimitError, nothing energised); the supplies are ramped
    to zero and switched off at the end whatever happens."""
    from rigctl.drivers.hall import HallBoard, HallStream
    from rigctl.rigs.six_coil.allocate import check_current_limits
    from rigctl.rigs.six_coil.supplies import CoilSupplies

    if rig.field_probe is None:
        raise ConfigError("the rig has no [field_probe] table (the Hall probe's url): nothing to "
                          "measure the field with")
    program, _ = ramp_program(rig, patterns)
    check_current_limits(program, rig, rig.stream.rate_hz, lambda k: f"calibration sample {k}",
                         current_advice="lower the calibration current")
    stream = HallStream(HallBoard.open(rig.field_probe.url, name="field probe",
                                       timeout_s=rig.field_probe.timeout_s)).start()
    points = stream.board.info.offsets_m
    sums = np.zeros((len(patterns), len(points), 3))
    counts = np.zeros(len(patterns), dtype=int)
    currents = np.zeros((len(patterns), len(rig.coils)))
    current_counts = np.zeros(len(patterns), dtype=int)
    tau = max(c.inductance_H / c.resistance_ohm for c in rig.coils)
    started = time.monotonic()
    supplies = CoilSupplies.connect(rig)
    period = 1.0 / rig.stream.rate_hz
    ramp = max(1, int(np.ceil(RAMP_S * rig.stream.rate_hz)))
    next_cycle = time.monotonic()

    def cycle(setpoints: np.ndarray) -> tuple[np.ndarray, list]:
        nonlocal next_cycle
        measured = supplies.cycle(setpoints).copy()
        next_cycle += period
        time.sleep(max(0.0, next_cycle - time.monotonic()))
        return measured, stream.drain()

    try:
        supplies.energise()
        previous = np.zeros(len(rig.coils))
        for p, pattern in enumerate(patterns):
            progress(f"pattern {p + 1}/{len(patterns)}: {(np.round(pattern, 2) + 0.0).tolist()} A")
            for k in range(1, ramp + 1):
                cycle(previous + (pattern - previous) * k / ramp)
            previous = pattern
            settled_at = time.monotonic() + SETTLE_TAU * tau
            give_up = settled_at + HOLD_TIMEOUT_S
            while counts[p] < SAMPLES_PER_PATTERN and time.monotonic() < give_up:
                measured, samples = cycle(pattern)
                for sample in samples:
                    if sample.received_s < settled_at:
                        continue
                    if sample.saturated.any():
                        raise DeviceError("a probe sensor saturated: lower the calibration "
                                          "current (rigctl calibrate field --current A)",
                                          device="field probe")
                    sums[p] += sample.field_T
                    counts[p] += 1
                if time.monotonic() >= settled_at:
                    currents[p] += measured
                    current_counts[p] += 1
    finally:
        unconfirmed = supplies.stop(ramp_s=rig.stream.ramp_down_s)
        stream.stop()
        if unconfirmed:
            log.error("calibration: supplies %s did not confirm output off", unconfirmed)
    short = np.flatnonzero(counts < SAMPLES_PER_PATTERN)
    if len(short):
        raise DeviceError(f"{counts[short[0]]} of {SAMPLES_PER_PATTERN} probe samples for pattern "
                          f"{int(short[0]) + 1} in {HOLD_TIMEOUT_S:g} s (the probe streams too "
                          "slowly, or stopped)", device="field probe")
    return Measurements(points_m=np.asarray(points, dtype=float),
                        currents_A=currents / np.maximum(current_counts, 1)[:, None],
                        fields_T=sums / counts[:, None, None], samples=counts,
                        duration_s=time.monotonic() - started)


def measured_maps(m: Measurements) -> tuple[np.ndarray, np.ndarray, float]:
    """Stage 1: per sensor, B = F I + b by linear least squares over the patterns. Returns the
    coils' field per ampere at every sensor F (K, 3, n) T/A, the background b (K, 3) T, and the
    residual RMS (T) of that linear fit (the probe's noise, if the coils are linear)."""
    P, n = m.currents_A.shape
    if P < n + 2:
        raise ConfigError(f"{P} patterns cannot separate {n} coils and a background")
    X = np.concatenate([m.currents_A, np.ones((P, 1))], axis=1)  # (P, n + 1)
    Y = m.fields_T.reshape(P, -1)  # (P, K * 3)
    coef, *_ = np.linalg.lstsq(X, Y, rcond=None)  # (n + 1, K * 3)
    residual = Y - X @ coef
    rms = float(np.sqrt(np.sum(residual**2) / max(1, residual.size - coef.size)))
    K = m.fields_T.shape[1]
    F = coef[:n].reshape(n, K, 3).transpose(1, 2, 0)
    return F, coef[n].reshape(K, 3), rms


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def _tilted(axis: np.ndarray, t: np.ndarray) -> np.ndarray:
    e1, e2 = _perpendicular_basis(axis)
    v = axis + t[0] * e1 + t[1] * e2
    return v / np.linalg.norm(v)


def fit_coil(points_m: np.ndarray, column: np.ndarray, centre_m: np.ndarray, axis: np.ndarray,
             radius_m: float, turns: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Stage 2 for one coil: (gain, dx, dy, dz (m), t1, t2 (rad)) fitted to its measured field per
    ampere `column` (K, 3) T/A at `points_m` (K, 3), with their one-sigma, and the RMS residual
    (T/A). Starts from the drawn loop (gain 1, no offset, no tilt)."""
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    scale = float(np.sqrt(np.mean(column**2)))

    def model(x: np.ndarray) -> np.ndarray:
        return x[0] * loop_field(points_m, centre_m + x[1:4], _tilted(axis, x[4:6]), radius_m,
                                 turns, 1.0)

    def residual(x: np.ndarray) -> np.ndarray:
        return ((model(x) - column) / scale).ravel()

    x0 = np.zeros(6)
    x0[0] = 1.0
    fit = least_squares(residual, x0, x_scale=np.array([0.01, 1e-3, 1e-3, 1e-3, 1e-2, 1e-2]),
                        method="lm")
    dof = max(1, fit.fun.size - fit.x.size)
    s2 = float(fit.fun @ fit.fun) / dof
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * s2
        sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        sigma = np.full(6, np.nan)
    return fit.x, sigma, float(np.sqrt(s2)) * scale


def fit_calibration(rig: SixCoilRig, m: Measurements, *, name: str | None = None) -> FieldCalibration:
    """The calibration of the rig's coils from the probe's measurements (both stages)."""
    F, background, linear_rms = measured_maps(m)
    fits: dict[str, CoilFit] = {}
    residuals = {}
    for j, coil in enumerate(rig.coils):
        centre = np.asarray(coil.centre_mm, dtype=float) * 1e-3
        axis = np.asarray(coil.axis, dtype=float)
        x, sigma, rms = fit_coil(m.points_m, F[:, :, j], centre, axis, coil.loop_radius_mm * 1e-3,
                                 coil.turns)
        fitted_axis = _tilted(axis, x[4:6])
        # populate_by_name: mypy knows only the aliases (Loop_Centre, ...) as arguments
        fits[coil.name] = CoilFit(  # type: ignore[call-arg]
            centre_m=tuple(float(v) for v in centre + x[1:4]),
            axis=tuple(float(v) for v in fitted_axis), radius_m=coil.loop_radius_mm * 1e-3,
            turns=coil.turns, gain=float(x[0]), offset_m=tuple(float(v) for v in x[1:4]),
            tilt_rad=float(np.arccos(np.clip(fitted_axis @ axis, -1.0, 1.0))),
            sigma={"gain": float(sigma[0]), "offset_m": float(np.linalg.norm(sigma[1:4])),
                   "tilt_rad": float(np.linalg.norm(sigma[4:6]))})
        residuals[coil.name] = rms
    matrix = np.stack([fits[c.name].gain * loop_field(
        np.zeros(3), fits[c.name].centre_m, fits[c.name].axis, fits[c.name].radius_m,
        fits[c.name].turns, 1.0) for c in rig.coils], axis=1)
    lo, hi = m.points_m.min(axis=0), m.points_m.max(axis=0)
    return FieldCalibration(  # type: ignore[call-arg]  # by name, as CoilFit above
        name=name or f"{rig.rig.name} field calibration",
        model=FORMAT,
        workspace_m=(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), float(lo[2]),
                     float(hi[2])),
        coil_list=[c.name for c in rig.coils], coils=fits, actuation_matrix=matrix.tolist(),
        fit={"date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
             "patterns": len(m.currents_A), "probe_points_m": m.points_m.tolist(),
             "samples_per_pattern_min": int(m.samples.min()),
             "linear_residual_rms_T": linear_rms,
             "loop_residual_rms_T_per_A": residuals,
             "background_T": background.mean(axis=0).tolist(),
             "duration_s": round(m.duration_s, 3)})


def model_field(rig: SixCoilRig, points_m: np.ndarray, currents_A: np.ndarray) -> np.ndarray:
    """The field (P, K, 3) T the rig's model (its calibration if it names one, else the drawn
    coils) predicts at points (K, 3) m for currents (P, n) A."""
    from rigctl.physics.coils import coil_loops

    maps = np.stack([gain * loop_field(points_m, c, a, r, t, 1.0)
                     for c, a, r, t, gain in coil_loops(rig)], axis=-1)  # (K, 3, n)
    return np.einsum("kin,pn->pki", maps, currents_A)


def prediction_error(rig: SixCoilRig, m: Measurements) -> float:
    """RMS |B_model - B_measured| (T) over every pattern and sensor, the background taken out
    (it is not the coils'): how well `rig`'s model explains the probe."""
    _, background, _ = measured_maps(m)
    predicted = model_field(rig, m.points_m, m.currents_A)
    return float(np.sqrt(np.mean(np.sum((predicted - (m.fields_T - background)) ** 2, axis=-1))))


def held_out_split(n_points: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(indices fitted, indices held out) of `n_points` probe sensors: HELD_OUT_FRACTION of them,
    at least one, chosen by `seed`, at least one left to fit; both sorted."""
    if n_points < 2:
        raise ConfigError(f"{n_points} probe sensor cannot be split into fitted and held-out "
                          "points")
    held = min(n_points - 1, max(1, round(HELD_OUT_FRACTION * n_points)))
    order = np.random.default_rng(seed).permutation(n_points)
    return np.sort(order[held:]), np.sort(order[:held])


@dataclass(frozen=True)
class MpemCalibration:
    """An MPEM fitted to the probe (`fit`: the model, its time), and on the held-out sensors'
    samples the RMS error (mT) and that as % of the mean field magnitude there, of the fitted
    model (`held_out_mT`, `held_out_pct`) and of the drawn loops (`drawn_mT`, `drawn_pct`)."""

    fit: MpemFit
    fitted_points: np.ndarray
    held_points: np.ndarray
    held_out_mT: float
    held_out_pct: float
    drawn_mT: float
    drawn_pct: float

    @property
    def model(self) -> MPEM:
        return self.fit.model


def mpem_start(loops: LoopModel, workspace_centre_m: np.ndarray) -> MPEM:
    """The MPEM fit's starting geometry: `start_from_loops` (a B source at each drawn coil's
    centre along its axis), each source moved START_BEHIND_RADII loop radii along its axis, away
    from `workspace_centre_m` (3,) m."""
    start = start_from_loops(loops)

    def moved(s: Source, shift_m: np.ndarray) -> Source:
        x, y, z = (float(v) for v in np.asarray(s.position_m) + shift_m)
        return Source((x, y, z), s.direction, s.kind, s.coefficients)

    sources = []
    for (centre, axis, radius, _, _), coil in zip(loops.loops, start.coil_sources):
        away = 1.0 if axis @ (centre - workspace_centre_m) >= 0 else -1.0
        sources.append([moved(s, away * START_BEHIND_RADII * radius * axis) for s in coil])
    return MPEM(start.coil_names, sources, name=start.name)


def fit_mpem_calibration(rig: SixCoilRig, m: Measurements, *, order: int = 3, seed: int = 0,
                         name: str | None = None) -> MpemCalibration:
    """An MPEM of `order` for the rig's coils (its coil order) fitted to the probe's samples at
    the sensors `held_out_split` keeps, from the drawn loops (see the module docstring), and its
    error and the drawing's on the sensors held out. `rig` is the drawing (its own field
    calibration, if any, is not the start)."""
    drawn = rig.model_copy(update={"field_calibration": None})
    loops = LoopModel.from_rig(drawn)
    fitted, held = held_out_split(len(m.points_m), seed=seed)
    result = fit_mpem(m.points_m[fitted], m.currents_A, m.fields_T[:, fitted],
                      mpem_start(loops, m.points_m.mean(axis=0)), order=order,
                      name=name or f"{rig.rig.name} field calibration")
    lo, hi = m.points_m.min(axis=0), m.points_m.max(axis=0)
    model = result.model
    model = MPEM(model.coil_names, model.coil_sources, model.offset_sources, name=model.name,
                 workspace_m=[(float(a), float(b)) for a, b in zip(lo, hi)])
    result = MpemFit(model=model, rms_T=result.rms_T, duration_s=result.duration_s,
                     cpu_s=result.cpu_s, evaluations=result.evaluations)
    samples = (m.points_m[held], m.currents_A, m.fields_T[:, held])
    held_mT, held_pct = held_out_error(model, *samples)
    drawn_mT, drawn_pct = held_out_error(loops, *samples)
    return MpemCalibration(fit=result, fitted_points=m.points_m[fitted],
                           held_points=m.points_m[held], held_out_mT=held_mT,
                           held_out_pct=held_pct, drawn_mT=drawn_mT, drawn_pct=drawn_pct)
