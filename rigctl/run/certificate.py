"""The pre-flight certificate: every limit of the rig checked on the whole plan before anything is
energised, each check with its value, its limit and its margin, and the hash of the rig file the
plan was checked against. A run starts only with a certificate that passed; the run record keeps
it (`certificate.json`) and `rigctl report` shows it.

What a rig checks is its own (`rigctl.rigs.<kind>.certify`, called by each program's `checks()`);
this module holds what they share: the check and certificate shapes, the coil-heating check with
the rest between moves that would make a refused plan pass (`rigctl.physics.thermal`), the stream rate a
link can carry, and the static-field exposure at named points (ICNIRP 2009).

A margin is in the check's unit, positive when the check passes: limit - value for a ceiling,
value - limit for a floor. Units are in each check's `unit`.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.config import ExposurePoint, RigConfig, dump_rig
from rigctl.core.errors import LimitError
from rigctl.physics.thermal import Windings, first_crossing, rest_to_pass, winding_temperatures

ICNIRP_2009_MT = 400.0
"""ICNIRP, "Guidelines on limits of exposure to static magnetic fields", Health Physics 96(4)
504-514 (2009): 400 mT for the general public, any part of the body (occupational: 2 T head and
trunk, 8 T limbs)."""

BITS_PER_BYTE = 10  # 8N1: a start bit, eight data bits, a stop bit
LINK_SHARE = 0.8
"""A link may take this share of a stream period: the rest is the host's own work and jitter."""


@dataclass(frozen=True)
class Check:
    """One limit checked on the whole plan."""

    check: str  # what: "current", "voltage", "winding temperature", ...
    subject: str  # of what: "coil x+", "arm left joint A3", "operator"
    value: float
    limit: float
    unit: str
    margin: float
    passed: bool
    detail: str = ""  # where or when; on a refusal, what would make it pass

    def __str__(self) -> str:
        verdict = "ok" if self.passed else "REFUSED"
        detail = f"; {self.detail}" if self.detail else ""
        return (f"{verdict}: {self.check} of {self.subject}: {self.value:.4g} {self.unit} "
                f"(limit {self.limit:.4g}, margin {self.margin:+.4g}){detail}")


def ceiling(check: str, subject: str, value: float, limit: float, unit: str, detail: str = "",
            tolerance: float = 1e-9) -> Check:
    """A check that `value` <= `limit` (within a relative `tolerance`)."""
    value, limit = float(value), float(limit)
    return Check(check, subject, value, limit, unit, limit - value,
                 value <= limit * (1 + tolerance) + 1e-12, detail)


def floor(check: str, subject: str, value: float, limit: float, unit: str,
          detail: str = "") -> Check:
    """A check that `value` >= `limit`."""
    value, limit = float(value), float(limit)
    return Check(check, subject, value, limit, unit, value - limit, value >= limit - 1e-12, detail)


def rig_hash(rig: RigConfig) -> str:
    """sha256 of the rig file as rigctl reads it (`dump_rig`: every key, defaults included)."""
    return hashlib.sha256(dump_rig(rig).encode()).hexdigest()


class CertificateRefused(LimitError):
    """A plan's pre-flight found a limit it would break: nothing was energised (exit 2)."""

    def __init__(self, certificate: Certificate,
                 refused: str = "pre-flight: refused, nothing energised") -> None:
        self.certificate = certificate
        failed = certificate.failed
        more = f" (and {len(failed) - 1} more)" if len(failed) > 1 else ""
        super().__init__(f"{refused}: {failed[0]}{more}")
        self.violations = failed


@dataclass
class Certificate:
    """Every check of one plan on one rig."""

    rig_kind: str
    rig_name: str
    rig_hash: str
    plan_kind: str
    plan_name: str
    checks: list[Check] = field(default_factory=list)
    issued: str = field(default_factory=lambda: datetime.now(UTC).isoformat(
        timespec="seconds"))
    elapsed_s: float = 0.0

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks)

    @property
    def failed(self) -> list[Check]:
        return [c for c in self.checks if not c.passed]

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["passed"] = self.passed
        return out

    def to_json(self) -> str:
        return json.dumps(self.as_dict(), indent=1) + "\n"

    def lines(self) -> list[str]:
        """For a terminal: the verdict, then one line per check, refused ones first."""
        verdict = "passed" if self.passed else f"REFUSED ({len(self.failed)} of {len(self.checks)})"
        head = (f"pre-flight certificate: {verdict}: {len(self.checks)} checks of a "
                f"{self.plan_kind} plan on {self.rig_name} ({self.rig_kind}), rig file sha256 "
                f"{self.rig_hash[:12]}")
        ordered = sorted(self.checks, key=lambda c: c.passed)
        return [head] + [f"  {c}" for c in ordered]

    def require(self, refused: str = "pre-flight: refused, nothing energised") -> Certificate:
        """Itself if it passed; else CertificateRefused naming the first failed check after
        `refused` (what was refused: a plan before anything was energised, a re-plan mid-run)."""
        if not self.passed:
            raise CertificateRefused(self, refused)
        return self


def certify(rig: RigConfig, plan_kind: str, plan_name: str, checks: Sequence[Check]) -> Certificate:
    return Certificate(rig.rig.kind, rig.rig.name, rig_hash(rig), plan_kind, plan_name,
                       list(checks))


def summary_line(certificate: dict[str, Any] | None) -> str:
    """One line for a report: the verdict, how many checks, the tightest one (smallest margin
    relative to its limit), the rig file's hash; for a record without one, that it has none."""
    if certificate is None:
        return "no pre-flight certificate in this record"
    checks = certificate.get("checks") or []
    verdict = "passed" if certificate.get("passed") else "REFUSED"
    line = f"pre-flight certificate {verdict}: {len(checks)} checks"
    if checks:
        tight = min(checks, key=lambda c: c["margin"] / max(abs(c["limit"]), 1e-12))
        line += (f", tightest: {tight['check']} of {tight['subject']} {tight['value']:.4g} "
                 f"{tight['unit']} (limit {tight['limit']:.4g})")
    return line + f"; rig file sha256 {str(certificate.get('rig_hash'))[:12]}"


def read_certificate(run_dir: str | Path) -> dict[str, Any] | None:
    """A run record's certificate as written, or None (a record from before certificates)."""
    path = Path(run_dir) / "certificate.json"
    return json.loads(path.read_text()) if path.is_file() else None


# -- shared checks --------------------------------------------------------------------------------


def heating_checks(currents_A: np.ndarray, rate_hz: float, windings: Windings, *,
                   move_ends: Sequence[int], margin: float,
                   describe: Callable[[int], str] | None = None,
                   rest_key: str = "field.rest_s") -> tuple[list[Check], np.ndarray]:
    """One winding-temperature check per coil for a current program (T, n) A at `rate_hz`, its
    Joule power raised by `margin` (the closed loop's corrections); returns the checks and the
    peak temperatures (n,) C. A refused coil's detail names the time it would cross its limit,
    the sample's part of the plan (`describe(k)`), and the rest after every move (`rest_key`)
    that would keep every coil below its limit, or that no rest would."""
    dt = 1.0 / rate_hz
    temps = winding_temperatures(currents_A, dt, windings, power_factor=1 + margin)
    peaks = temps.max(axis=0)
    times = np.arange(len(temps)) * dt
    advice = ""
    if (peaks >= windings.limit_C).any():
        rest = rest_to_pass(currents_A, dt, move_ends, windings, power_factor=1 + margin)
        if not len(move_ends):
            advice = "the plan has no pauses between moves: shorten it or lower its field"
        elif rest is None:
            advice = ("no rest between moves would do: one move alone heats it to its warning "
                      "level; lower the field, shorten the moves, or cool the coils")
        else:
            advice = (f"a rest of {np.ceil(rest + 1):.0f} s between moves ({rest_key}) would keep "
                      f"every coil below its warning level")
    checks = []
    for j, name in enumerate(windings.names):
        detail = f"with {margin:.0%} more Joule power for the closed loop; starts at " \
                 f"{windings.ambient_C[j]:.0f} C"
        if peaks[j] >= windings.limit_C[j]:
            crossing = first_crossing(temps[:, j:j + 1], windings.limit_C[j:j + 1], times)
            assert crossing is not None
            where = f" ({describe(max(crossing.index - 1, 0))})" if describe else ""
            detail = f"it would reach {windings.limit_C[j]:.0f} C at t = {crossing.time_s:.1f} s" \
                     f"{where}; {advice}"
        checks.append(ceiling("winding temperature", f"coil {name}", peaks[j],
                              windings.limit_C[j], "C", detail))
    return checks, peaks


def link_checks(per_cycle_s: dict[str, float], rate_hz: float,
                share: float = LINK_SHARE) -> list[Check]:
    """Each link's time per stream cycle against `share` of the period, in ms."""
    period_ms = 1e3 / rate_hz
    return [ceiling("link time per cycle", link, 1e3 * seconds, share * period_ms, "ms",
                    f"{rate_hz:g} Hz stream; the link may take {share:.0%} of each period")
            for link, seconds in per_cycle_s.items()]


def serial_seconds(n_bytes: int, baud: int) -> float:
    """Time on the wire of `n_bytes` at `baud`, 8N1."""
    return n_bytes * BITS_PER_BYTE / baud


def size_checks(samples: int, max_samples: int, duration_s: float | None,
                max_duration_s: float, unit: str = "samples") -> list[Check]:
    checks = [ceiling("program size", "plan", samples, max_samples, unit)]
    if duration_s is not None:
        checks.append(ceiling("duration", "plan", duration_s, max_duration_s, "s"))
    return checks


def exposure_checks(points: Sequence[ExposurePoint], times_s: np.ndarray, centres_m: np.ndarray,
                    moments_Am2: np.ndarray, limit_mT: float) -> list[Check]:
    """The static field of dipoles at each named point (`ExposurePoint`: name, position_mm)
    along a trajectory: centres (T, A, 3) m, moments (T, A, 3) A m^2; the peak |B| against
    `limit_mT` (the rig file's, ICNIRP 2009's 400 mT by default)."""
    from rigctl.physics.magnetics import dipole_field

    checks = []
    for point in points:
        at = np.asarray(point.position_mm, dtype=float) * 1e-3
        field = np.zeros((len(times_s), 3))
        for a in range(centres_m.shape[1]):
            field += dipole_field(np.broadcast_to(at, (len(times_s), 3)), centres_m[:, a],
                                  moments_Am2[:, a])
        magnitude = np.linalg.norm(field, axis=1) * 1e3
        k = int(np.argmax(magnitude))
        checks.append(ceiling("static field exposure", point.name, magnitude[k], limit_mT, "mT",
                              f"at {list(point.position_mm)} mm, peak at t = {times_s[k]:.2f} s; "
                              "limit: ICNIRP 2009 general public unless the rig file sets one"))
    return checks
