"""Execute a `field-sequence` plan on a dual-EPM rig and measure it the way seed 003 Table 1 does.

`rigctl execute PLAN` calls `execute_cli` for plans of kind `field-sequence` (rig `depm`):

1. with `--agnostic`, the plan's magnetic-agnostic baseline is run instead (`baseline_of`: from
   the same start joints, straight joint-space moves to the plan's own end poses);
2. without `--rig`, the emulated bench is started in its own process (nothing real can move);
3. before anything moves, the plan's trajectories are checked densely against the *rig's* safety
   limits (keep-out sphere, EPM-EPM distance, joint limits, 30 % speed; `rigctl.plans.depm_safety`) and
   against the rig's geometry (bases, EPM moment, tool); a breach refuses the run (exit 2, each
   violation printed with its time and constraint, counted in `"violations"`). The approach from
   where the arms stand to the plan's first pose is checked the same way;
4. the arms go to the first pose (KST point-to-point moves at the rig's speed fraction), then both
   joint trajectories are streamed by direct servo at `servo_rate_hz`, every reply checked, the
   measured joints compared with the commanded ones; the Hall board is read throughout and U is
   estimated from its three sensors (eq. 24, `rigctl.drivers.hall`);
5. the run record (`runs/<time>-<plan>/`: plan, rig, events, `joints.csv`, `field.csv`,
   `summary.json`) is written as the run goes; the summary gives the Table 1 metrics per component
   and the cross-activation matrix of Fig. 6 (definitions in docs/depm.md, "Execution and metrics").

Exit status: 0 every requested component's steady state within 2 % of the request, 1 not, 2 the
plan or rig was refused (nothing moved), 3 a device fault stopped the run.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from rigctl.config import RigConfig, dump_rig
from rigctl.drivers.hall import HallBoard, HallSample, HallStream
from rigctl.drivers.kuka_sunrise import KukaArm
from rigctl.errors import ConfigError, DeviceError, RigError
from rigctl.kinematics import ArmKinematics, base_transform
from rigctl.magnetics import U_COMPONENTS, field_vector_from_sensors
from rigctl.plans.depm import joint_trajectory, plan_violations, rig_from_settings
from rigctl.plans.depm_safety import SafetyLimits, Violation, violations
from rigctl.record import RunRecord

log = logging.getLogger(__name__)

STEADY_STATE_TOLERANCE = 0.02  # of the requested value
FIELD_BAND_mT, GRADIENT_BAND_mT_per_m = 0.5, 5.0  # "close to 0" at the end of a fall (Sec. 4.2)
FALL_DWELL_S = 0.5  # "a constant value close to 0": inside the band for this long
SETTLE_FRACTION = 0.25  # the first quarter of a hold is still settling: not steady state
APPROACH_STEPS = 200
TRACKING_TARGETS = 3  # measured joints are checked against the span of the last 3 targets
STALL_TIME_S = 0.5  # behind by more than the tolerance and not catching up this long: a fault
MAX_REAL_RATE_HZ = 100.0  # stream targets per real second on a faster-than-real bench
REQUEST_ZERO = 1e-9  # |requested| below this (mT, mT/m) is "not requested"
UNITS = ["mT"] * 3 + ["mT/m"] * 5


# -- Table 1 and Fig. 6 ---------------------------------------------------------------------------


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


# -- checks before anything moves -----------------------------------------------------------------


def check_plan_against_rig(plan, rig: RigConfig, arms: list[ArmKinematics]) -> None:
    """ConfigError unless the plan was made for this rig's geometry and magnets."""
    d = rig.depm
    assert d is not None
    if len(plan.arms) != len(arms):
        raise ConfigError(f"the plan has {len(plan.arms)} arms, the rig {len(arms)}")
    for arm_plan, kin in zip(plan.arms, arms):
        base = base_transform(np.asarray(arm_plan.position_mm) * 1e-3, arm_plan.rpy_deg)
        if arm_plan.name != kin.name or not np.allclose(base, kin.base, atol=1e-6):
            raise ConfigError(f"plan arm {arm_plan.name!r} stands at {list(arm_plan.position_mm)} mm "
                              f"{list(arm_plan.rpy_deg)} deg; the rig's arm {kin.name!r} elsewhere: "
                              "re-plan for this rig")
    if not math.isclose(plan.epm_moment_Am2, d.epm_moment_Am2, rel_tol=1e-6) or \
            not math.isclose(plan.tool_offset_mm, d.tool_offset_mm, rel_tol=1e-6):
        raise ConfigError(f"the plan assumes EPM moment {plan.epm_moment_Am2} A m^2 and tool offset "
                          f"{plan.tool_offset_mm} mm; the rig has {d.epm_moment_Am2} and "
                          f"{d.tool_offset_mm}: re-plan for this rig")


def approach_violations(q_now: np.ndarray, q_start: np.ndarray, arms: list[ArmKinematics],
                        limits: SafetyLimits) -> list[Violation]:
    """Constraints broken by moving the arms one after the other, straight in joint space, from
    `q_now` (A, 7) to `q_start` (A, 7) (positions only: the robot times its own PTP moves)."""
    s = np.linspace(0.0, 1.0, APPROACH_STEPS)
    phases = []
    q = q_now.copy()
    for a in range(len(arms)):
        path = np.repeat(q[:, None, :], APPROACH_STEPS, axis=1)
        path[a] = q[a] + (q_start[a] - q[a]) * s[:, None]
        phases.append(path)
        q = path[:, -1]
    path = np.concatenate(phases, axis=1)
    return violations(np.arange(path.shape[1]) * 1.0, path, None, arms, limits)


# -- the run --------------------------------------------------------------------------------------


@dataclass
class RunResult:
    plan_name: str
    planner: str
    violations: list[Violation] = field(default_factory=list)
    refused: str | None = None
    faults: list[str] = field(default_factory=list)
    table1: dict | None = None
    cross_activation: dict | None = None
    duration_s: float = 0.0
    samples: int = 0
    samples_lost: int = 0
    saturated_samples: int = 0
    skipped_cycles: int = 0
    max_cycle_gap_s: float = 0.0  # longest real time between two stream cycles
    time_scale: float = 1.0
    run_dir: str | None = None

    @property
    def reached(self) -> bool:
        if self.refused or self.faults or self.table1 is None:
            return False
        checked = [e["steady_state_ok"] for label, e in self.table1.items()
                   if label != "average" and e["requested"] is not None]
        return bool(checked) and all(checked)

    def json(self) -> dict:
        return {"plan": self.plan_name, "planner": self.planner, "reached": self.reached,
                "violations": len(self.violations),
                "violation_list": [str(v) for v in self.violations], "refused": self.refused,
                "faults": self.faults, "table1": self.table1,
                "cross_activation": self.cross_activation, "duration_s": self.duration_s,
                "samples": self.samples, "samples_lost": self.samples_lost,
                "saturated_samples": self.saturated_samples,
                "skipped_cycles": self.skipped_cycles,
                "max_cycle_gap_s": round(self.max_cycle_gap_s, 4), "time_scale": self.time_scale,
                "run": self.run_dir}


class _Csv:
    """An append-only, line-buffered CSV in the run record (readable after a crash)."""

    def __init__(self, path: Path, header: list[str]) -> None:
        self._file: TextIO = open(path, "a", buffering=1)
        self._file.write(",".join(header) + "\n")

    def row(self, values) -> None:
        self._file.write(",".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in values)
                         + "\n")

    def close(self) -> None:
        self._file.close()


def progress_line(out: TextIO | None, text: str) -> None:
    if out is not None:
        print(text, file=out, flush=True)


def run_field_sequence(plan, rig: RigConfig, *, runs_dir: str | Path = "runs",
                       progress_out: TextIO | None = None, time_scale: float = 1.0) -> RunResult:
    """Check, then run `plan` on `rig`; never raises for device faults (they go in `faults`)."""
    if rig.rig.kind != "depm" or rig.depm is None:
        raise ConfigError(f"a field-sequence plan runs on a depm rig with a [depm] table; this rig "
                          f"is {rig.rig.kind!r}")
    if time_scale != 1.0 and not rig.emulated:
        raise ConfigError("--time-scale is for emulated benches only; a real rig runs at 1")
    d = rig.depm
    depm_rig = rig_from_settings(d)
    arms, limits = depm_rig.arms, depm_rig.limits
    result = RunResult(plan_name=plan.name or "field-sequence", planner=plan.planner,
                       time_scale=time_scale)
    check_plan_against_rig(plan, rig, arms)
    result.violations = plan_violations(plan, arms, limits)
    if result.violations:
        result.refused = f"the trajectories break {len(result.violations)} safety constraint(s)"
        return result
    joint_limits = np.stack([arms[0].model.lower_rad, arms[0].model.upper_rad], axis=1)
    record = RunRecord(runs_dir, result.plan_name)
    result.run_dir = str(record.path)
    record.write_file("plan.json", plan.model_dump_json(indent=1))
    record.write_file("rig.toml", dump_rig(rig))
    if rig.emulated and rig.emulation is not None:
        from rigctl.emulators.backdoor import BackdoorClient

        with BackdoorClient(rig.emulation.backdoor) as backdoor:
            backdoor.request("speed", factor=time_scale)
    kuka: list[KukaArm] = []
    stream: HallStream | None = None
    times: list[float] = []
    estimates: list[np.ndarray] = []
    try:
        for name, url in zip(d.arm_names, d.arm_urls):
            kuka.append(KukaArm.open(url, name=name, timeout_s=d.reply_timeout_s,
                                     joint_limits_rad=joint_limits))
        board = HallBoard.open(d.hall_url, timeout_s=d.reply_timeout_s + 1.0 / 10)
        stream = HallStream(board).start()
        estimator = sensor_estimator(board.info.offsets_m)  # once: the offsets are fixed
        record.event("connected", arms=d.arm_urls, hall=d.hall_url)
        q_now = np.array([arm.joint_positions() for arm in kuka])
        q_start = np.array([a.joints_rad[0] for a in plan.arms], dtype=float)
        approach = approach_violations(q_now, q_start, arms, limits)
        if approach:
            result.violations = approach
            result.refused = "the approach to the plan's first pose breaks a safety constraint"
            record.event("refused", reason=result.refused, violations=[str(v) for v in approach])
        else:
            progress_line(progress_out, f"approach: moving the arms to the plan's first pose at "
                                    f"{d.speed_fraction:.0%} speed")
            for arm, q in zip(kuka, q_start):
                distance = float(np.max(np.abs(q - arm.joint_positions())))
                timeout = 30.0 + 4.0 * distance / (d.speed_fraction * 0.5) / time_scale
                arm.move_to(q, relative_velocity=d.speed_fraction, timeout_s=timeout)
            record.event("at_start")
            _stream_plan(plan, kuka, stream, d, record, time_scale, progress_out, times, estimates,
                         estimator, result)
            record.event("done")
    except RigError as err:
        result.faults.append(str(err))
        record.event("fault", reason=str(err), device=err.device)
        progress_line(progress_out, f"fault: {err}")
    finally:
        for arm in kuka:
            arm.close()
        if stream is not None:
            stream.stop()
            result.samples_lost = stream.board.missed
    if times:
        t, U = np.array(times), np.array(estimates)
        windows = windows_of(plan)
        result.table1 = table1(t, U, windows)
        result.cross_activation = cross_activation(t, U, windows)
    record.finish(result.json())
    return result


def _stream_plan(plan, kuka: list[KukaArm], stream: HallStream, d, record: RunRecord,
                 time_scale: float, progress_out, times: list, estimates: list,
                 estimator: np.ndarray, result: RunResult) -> None:
    curves = joint_trajectory(plan)
    end_s = float(plan.t_s[-1])
    # a faster-than-real emulated bench gets the same number of targets per real second, at most
    # MAX_REAL_RATE_HZ: the robot interpolates between them as it does at the nominal rate
    rate = min(d.servo_rate_hz, MAX_REAL_RATE_HZ / time_scale) if time_scale > 1 else d.servo_rate_hz
    tolerance = math.radians(d.tracking_tolerance_deg)
    names = [a.name for a in kuka]
    joints_csv = _Csv(record.path / "joints.csv", ["t_s"] + [
        f"{kind}_{n}_q{j + 1}" for n in names for kind in ("cmd", "meas") for j in range(7)])
    field_csv = _Csv(record.path / "field.csv", ["t_s", "seq"] + [
        f"B{i + 1}{axis}_mT" for i in range(estimator.shape[1] // 3) for axis in "xyz"] + [
        f"U_{c}" for c in U_COMPONENTS])
    segment_starts = [(s.start_s, s.name) for s in plan.segments]
    announced = 0
    try:
        for arm in kuka:
            arm.start_servo()
        stream.drain()  # samples from before the run are not part of it
        record.event("servo_started", rate_hz=rate, time_scale=time_scale)
        recent = [deque([curve(0.0)], maxlen=TRACKING_TARGETS) for curve in curves]
        trackers = [_Tracking(tolerance) for _ in curves]
        clock: tuple[list[float], list[float]] = ([], [])  # (monotonic s, plan s) of each cycle
        t0 = time.monotonic()
        n = 0
        while True:
            t_plan = n / rate
            if t_plan > end_s:
                break
            delay = t0 + t_plan / time_scale - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif -delay > 1.0 / (rate * time_scale):
                # late by more than a period (a loaded computer): skip the missed ticks rather
                # than send them in a burst the arms could not follow
                skipped = int(-delay * rate * time_scale)
                n += skipped
                result.skipped_cycles += skipped
                t_plan = min(n / rate, end_s)
            while announced < len(segment_starts) and segment_starts[announced][0] <= t_plan:
                progress_line(progress_out, f"t = {t_plan:6.2f} s: toward {segment_starts[announced][1]}")
                record.event("segment", name=segment_starts[announced][1], t_plan_s=t_plan)
                announced += 1
            now = time.monotonic()
            if clock[0]:
                result.max_cycle_gap_s = max(result.max_cycle_gap_s, now - clock[0][-1])
            clock[0].append(now)
            clock[1].append(t_plan)
            row: list = [t_plan]
            for a, (arm, curve) in enumerate(zip(kuka, curves)):
                q_cmd = curve(t_plan)
                q_meas = arm.servo(q_cmd)
                lag = _distance_to_span(q_meas, recent[a])
                recent[a].append(q_cmd)
                stuck = trackers[a].update(t_plan, lag)
                if stuck is not None:
                    j, behind, since = stuck
                    raise DeviceError(
                        f"joint A{j + 1} is {math.degrees(behind):.1f} deg behind its targets and "
                        f"not catching up since t = {since:.2f} s (tolerance "
                        f"{d.tracking_tolerance_deg:g} deg): a stalled or blocked joint; run stopped",
                        device=arm.name)
                row += [*q_cmd, *q_meas]
            joints_csv.row(row)
            if n % 5 == 0:
                _take_samples(stream, clock, estimator, times, estimates, field_csv, result)
            n += 1
        _take_samples(stream, clock, estimator, times, estimates, field_csv, result)
        for arm in kuka:
            arm.stop_servo()
        result.duration_s = end_s
    finally:
        joints_csv.close()
        field_csv.close()


class _Tracking:
    """Notices a joint that is behind its targets by more than the tolerance and does not catch up
    for STALL_TIME_S (plan seconds). A joint that lags but gains ground (after a late stream cycle
    it races after a target that jumped) is fine; a stalled one loses ground or holds."""

    def __init__(self, tolerance_rad: float) -> None:
        self.tolerance = tolerance_rad
        self.since: np.ndarray = np.full(7, np.nan)  # plan time the joint fell behind
        self.lag_then = np.zeros(7)

    def update(self, t_plan: float, lag: np.ndarray) -> tuple[int, float, float] | None:
        behind = lag > self.tolerance
        gained = behind & (lag < self.lag_then - self.tolerance / 2)
        start = behind & (np.isnan(self.since) | gained)
        self.since[start] = t_plan
        self.lag_then[start] = lag[start]
        self.since[~behind] = np.nan
        stuck = np.flatnonzero(behind & (t_plan - self.since > STALL_TIME_S))
        if len(stuck):
            j = int(stuck[np.argmax(lag[stuck])])
            return j, float(lag[j]), float(self.since[j])
        return None


def _distance_to_span(q: np.ndarray, targets) -> np.ndarray:
    """Per joint, how far `q` is outside the range the previous targets span: the robot is
    somewhere on its way between them (it interpolates from one to the next over a stream period,
    and a period can be longer or shorter than the last one), so only beyond them is it behind."""
    span = np.array(targets)
    below = span.min(axis=0) - q
    above = q - span.max(axis=0)
    return np.maximum(np.maximum(below, above), 0.0)


def sensor_estimator(offsets_m: np.ndarray) -> np.ndarray:
    """E (8, 3 n) with U = E @ fields.ravel() (T, T/m at the reference sensor) for the n sensors'
    fields (n, 3) T at `offsets_m` (n, 3) m: `field_vector_from_sensors` (eq. 24) is linear in the
    fields, so its matrix is its value on the unit fields. It depends only on the board's fixed
    sensor offsets: built once per run instead of a least-squares fit per batch of samples.
    ConfigError if the offsets cannot give all five gradient terms."""
    n_values = 3 * len(offsets_m)
    unit_fields = np.eye(n_values).reshape(n_values, len(offsets_m), 3)
    return field_vector_from_sensors(unit_fields, offsets_m).T


def _take_samples(stream: HallStream, clock: tuple[list[float], list[float]], estimator: np.ndarray,
                  times: list, estimates: list, field_csv: _Csv, result: RunResult) -> None:
    """Samples read so far, on the plan's clock: a sample's arrival is placed between the stream
    cycles around it, so a stream that runs late (a loaded computer) stays aligned with the plan."""
    samples: list[HallSample] = stream.drain()
    if not samples:
        return
    fields = np.array([s.field_T for s in samples])
    U = fields.reshape(len(fields), -1) @ estimator.T * 1e3  # mT and mT/m
    t_plans = np.interp([s.received_s for s in samples], clock[0], clock[1])
    for sample, u, f, t_plan in zip(samples, U, fields, t_plans):
        t_plan = float(t_plan)
        times.append(t_plan)
        estimates.append(u)
        result.samples += 1
        result.saturated_samples += int(sample.saturated.any())
        field_csv.row([t_plan, sample.seq, *(f.ravel() * 1e3), *u])


# -- the command line -----------------------------------------------------------------------------


def _fmt(value, digits=2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def format_summary(result: RunResult) -> str:
    lines = [f"depm run: {result.plan_name} ({result.planner} planner), "
             f"violations: {len(result.violations)}"]
    for v in result.violations[:10]:
        lines.append(f"  refused: {v}")
    if result.refused:
        lines.append(f"refused: {result.refused}; nothing moved")
        return "\n".join(lines)
    for fault in result.faults:
        lines.append(f"fault: {fault}")
    if result.table1 is not None:
        lines.append(f"{'':8}{'request':>9}{'steady':>9}{'err %':>7}{'peak off':>10}{'rise %':>8}"
                     f"{'fall %':>8}{'sigma off':>10}  unit")
        for label in U_COMPONENTS:
            e = result.table1[label]
            lines.append(f"{label:8}{_fmt(e['requested']):>9}{_fmt(e['steady_state']):>9}"
                         f"{_fmt(e['steady_state_error_pct'], 1):>7}"
                         f"{_fmt(e['peak_off_activation']):>10}{_fmt(e['overshoot_rise_pct'], 1):>8}"
                         f"{_fmt(e['overshoot_fall_pct'], 1):>8}{_fmt(e['sigma_off']):>10}  {e['unit']}")
        a = result.table1["average"]
        lines.append(f"average  fields: peak off {_fmt(a['peak_off_activation_field_mT'])} mT, sigma "
                     f"{_fmt(a['sigma_off_field_mT'])} mT; gradients: peak off "
                     f"{_fmt(a['peak_off_activation_gradient_mT_per_m'])} mT/m, sigma "
                     f"{_fmt(a['sigma_off_gradient_mT_per_m'])} mT/m; overshoot rise "
                     f"{_fmt(a['overshoot_rise_pct'], 1)} %, fall {_fmt(a['overshoot_fall_pct'], 1)} %")
        lines.append(f"steady-state error: mean {_fmt(a['steady_state_error_pct'])} %, max "
                     f"{_fmt(a['steady_state_error_max_pct'])} % (goal < {100 * STEADY_STATE_TOLERANCE:g} %)")
    if result.cross_activation is not None:
        ca = result.cross_activation
        lines.append("cross-activation during each rise (% of the requested field / gradient):")
        lines.append(f"{'':8}" + "".join(f"{c:>8}" for c in ca["columns"]))
        for name, row in zip(ca["rows"], ca["percent"]):
            lines.append(f"{name:8}" + "".join(f"{_fmt(v, 0):>8}" for v in row))
    lines.append(f"samples: {result.samples} ({result.samples_lost} lost, {result.saturated_samples} "
                 f"saturated); plan duration {result.duration_s:.1f} s; time scale {result.time_scale:g}; "
                 f"{result.skipped_cycles} stream cycles skipped (late, longest gap "
                 f"{result.max_cycle_gap_s * 1e3:.0f} ms)")
    if result.run_dir:
        lines.append(f"run record: {result.run_dir}")
    return "\n".join(lines)


