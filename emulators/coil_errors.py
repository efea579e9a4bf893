"""The emulated six-coil bench's coils as built, not as drawn: each one's true gain, centre and axis
differ from the rig file's by a seeded random error, so allocation from the rig file is wrong by
what a real rig's winding and mounting tolerances make it, and `rigctl calibrate field` has
something to find.

`CoilErrors(size, seed)`: each coil's field per ampere is (1 + e_g) times its drawn loop's, with
e_g uniform in +-size; its loop centre moves by up to size x its loop radius (uniform in a ball);
its axis tilts by up to size rad (uniform angle, random direction about the drawn axis). The
default, size 0.05, is the issue's "several percent": gains +-5 %, centres up to 10 mm off for the
200 mm loops of the default cube, axes up to 2.9 deg off. size 0 is the ideal bench (the rig file
is the truth), for the open-loop tests that need one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigctl.core.config import Coil
from rigctl.physics.field_calibration import CoilFit, FieldCalibration
from rigctl.physics.magnetics import loop_field

DEFAULT_SIZE = 0.05


@dataclass(frozen=True)
class CoilErrors:
    """How far the bench's coils are from the rig file's (see the module docstring)."""

    size: float = DEFAULT_SIZE
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.size < 0.5:
            raise ValueError(f"coil error size must be in [0, 0.5), got {self.size}")


@dataclass(frozen=True)
class TrueCoil:
    """One coil as the bench builds it: a loop (centre m, unit axis, radius m, turns) x gain."""

    name: str
    centre_m: np.ndarray
    axis: np.ndarray
    radius_m: float
    turns: int
    gain: float

    def field_per_amp(self, points_m: np.ndarray) -> np.ndarray:
        """Field (..., 3) T per ampere at points (..., 3) m."""
        return self.gain * loop_field(points_m, self.centre_m, self.axis, self.radius_m,
                                      self.turns, 1.0)

    def truth(self) -> dict:
        return {"name": self.name, "centre_mm": (self.centre_m * 1e3).tolist(),
                "axis": self.axis.tolist(), "gain": self.gain}


def true_coils(coils: list[Coil], errors: CoilErrors) -> list[TrueCoil]:
    """The bench's coils for the rig file's `coils` (same order) under `errors`."""
    rng = np.random.default_rng(errors.seed)
    out = []
    for coil in coils:
        axis = np.asarray(coil.axis, dtype=float)
        centre = np.asarray(coil.centre_mm, dtype=float) * 1e-3
        radius = coil.loop_radius_mm * 1e-3
        gain_error, shift, tilt, turn = rng.uniform(-1, 1), rng.normal(size=3), rng.uniform(), \
            rng.uniform(0, 2 * np.pi)
        shift *= errors.size * radius * rng.uniform() ** (1 / 3) / np.linalg.norm(shift)
        # a perpendicular basis about the drawn axis; tilt by size x U(0, 1) rad towards `turn`
        helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        angle = errors.size * tilt
        tilted = np.cos(angle) * axis + np.sin(angle) * (np.cos(turn) * e1 + np.sin(turn) * e2)
        out.append(TrueCoil(coil.name, centre + shift, tilted / np.linalg.norm(tilted), radius,
                            coil.turns, 1.0 + errors.size * gain_error))
    return out


def as_calibration(coils: list[TrueCoil], drawn: list[Coil]) -> FieldCalibration:
    """The true coils as a (perfect) field calibration of the drawn ones: the pair world takes its
    coils' fields and gradients through `rigctl.physics.coils` with it, as an allocator would."""
    fits = {}
    for true, coil in zip(coils, drawn):
        drawn_axis = np.asarray(coil.axis, dtype=float)
        # populate_by_name: mypy knows only the aliases (Loop_Centre, ...) as arguments
        fits[true.name] = CoilFit(  # type: ignore[call-arg]
            centre_m=tuple(true.centre_m), axis=tuple(true.axis), radius_m=true.radius_m,
            turns=true.turns, gain=true.gain,
            offset_m=tuple(true.centre_m - np.asarray(coil.centre_mm) * 1e-3),
            tilt_rad=float(np.arccos(np.clip(true.axis @ drawn_axis, -1.0, 1.0))))
    matrix = np.stack([c.field_per_amp(np.zeros(3)) for c in coils], axis=1)
    return FieldCalibration(  # type: ignore[call-arg]  # by name, as CoilFit above
        name="emulated bench: true coils", workspace_m=(0.0,) * 6,
        coil_list=[c.name for c in coils], coils=fits, actuation_matrix=matrix.tolist())
