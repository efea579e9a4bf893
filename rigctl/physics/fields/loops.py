"""Today's coil model behind the `FieldModel` interface: each coil a thin circular loop
(`rigctl.physics.magnetics.loop_field`, exact in elliptic integrals) times a fitted gain.

It is the model of the six-coil rig file (`coil_loops`: the rig's loops, or the loops a
"rigctl-loop-v1" field calibration fitted) and of those calibration files on their own. The
gradient is the central difference of the exact field with the step `GRADIENT_STEP_MM`,
as the six-coil allocator computes it (truncation about 3e-8 relative at the cube's distances).
A loop model has no current-independent offset.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rigctl.core.config import CoilRig
from rigctl.physics.field_calibration import FieldCalibration, fitted_loops
from rigctl.physics.fields.model import FieldModel
from rigctl.physics.magnetics import loop_field

Loop = tuple[np.ndarray, np.ndarray, float, int, float]
"""(centre m, unit axis, radius m, turns, gain) of one coil."""

GRADIENT_STEP_MM = 0.05
"""Central-difference step: truncation ~ (step / distance to the winding)^2 / 6, about 3e-8
relative for the cube's coils; round-off ~1e-10 relative."""


def coil_loops(rig: CoilRig) -> list[Loop]:
    """(centre m, unit axis, radius m, turns, gain) of each coil, in `rig.coils` order: the fitted
    loops of the rig's `field_calibration` if it is a "rigctl-loop-v1" file, else the rig file's
    (gain 1; also for a rig whose calibration is an MPEM: these are the coils as drawn)."""
    calibration = getattr(rig, "field_calibration", None)
    if isinstance(calibration, FieldCalibration):
        return fitted_loops(calibration, [c.name for c in rig.coils])
    return [(np.asarray(c.centre_mm, dtype=float) * 1e-3, np.asarray(c.axis, dtype=float),
             c.loop_radius_mm * 1e-3, c.turns, 1.0) for c in rig.coils]


class LoopModel(FieldModel):
    """N coils, each a circular loop of `turns` turns scaled by `gain`."""

    def __init__(self, coil_names: Sequence[str], loops: Sequence[Loop]) -> None:
        if len(coil_names) != len(loops):
            raise ValueError(f"{len(coil_names)} coil names for {len(loops)} loops")
        self.coil_names = tuple(coil_names)
        self.loops = tuple((np.asarray(c, dtype=float).reshape(3), np.asarray(a, dtype=float)
                            / np.linalg.norm(a), float(r), int(t), float(g))
                           for c, a, r, t, g in loops)

    @classmethod
    def from_rig(cls, rig: CoilRig) -> LoopModel:
        """The rig file's coils, or the loops of the field calibration it names."""
        return cls([c.name for c in rig.coils], coil_loops(rig))

    @classmethod
    def from_calibration(cls, calibration: FieldCalibration) -> LoopModel:
        """A "rigctl-loop-v1" calibration file's fitted loops, in its Coil_List order."""
        names = list(calibration.coil_list)
        return cls(names, fitted_loops(calibration, names))

    def field_and_gradient_per_ampere(self, points_m: np.ndarray) -> np.ndarray:
        points = np.asarray(points_m, dtype=float).reshape(-1, 3)
        h = GRADIENT_STEP_MM * 1e-3
        steps = np.concatenate([np.zeros((1, 3)), h * np.eye(3), -h * np.eye(3)])  # (7, 3)
        probes = points[:, None, :] + steps  # (P, 7, 3)
        out = np.zeros((points.shape[0], self.n_coils + 1, 12))
        for k, (centre, axis, radius, turns, gain) in enumerate(self.loops):
            b = gain * loop_field(probes, centre, axis, radius, turns, 1.0)  # (P, 7, 3)
            out[:, k, 0:3] = b[:, 0]
            grad = (b[:, 1:4] - b[:, 4:7]) / (2.0 * h)  # (P, j, i) = dB_i/dx_j
            out[:, k, 3:] = grad.transpose(0, 2, 1).reshape(-1, 9)
        return out
