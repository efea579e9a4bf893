"""Rolling cylindrical magnets on the workspace floor (seed 000 Sec. V), moved by the field that the
emulated coils really produce.

Each magnet is a radially magnetised cylinder lying on the floor. Its magnetisation follows the field
direction; since the magnetisation is perpendicular to the cylinder's axis u (horizontal), the field
fixes u up to sign (u is parallel to z x B_horizontal), and the field's angle in the plane
perpendicular to u is the cylinder's roll angle. A roll by d_alpha about +u without slip moves the
centre by R * d_alpha * (u x z). So this model needs nothing from the plan or the realizer: it only
watches the field, which is what makes the end-to-end tests honest. The displacement is shared by
all magnets (a uniform field) and goes through the one global-input model, so contacts with walls
and with each other behave as the planner assumed.

All magnets see the same field here (the field at the workspace centre); a field that varies across
the workspace is a later refinement.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from rigctl.plans.model import GlobalInputModel

log = logging.getLogger(__name__)

_Z = np.array([0.0, 0.0, 1.0])


class RollingMagnetWorld:
    """Ground truth of the emulated six-coil bench.

    positions_mm: (n, 2) initial centres; rolling_radius_mm: the cylinders' radius R;
    min_field_T: below this the magnets do not follow the field (friction); slip: distance rolled per
    turn as a fraction of 2*pi*R (1 = no slip).
    """

    def __init__(
        self,
        model: GlobalInputModel,
        positions_mm: np.ndarray,
        *,
        rolling_radius_mm: float,
        min_field_T: float,
        slip: float = 1.0,
    ) -> None:
        self.model = model
        self._positions_mm = np.array(positions_mm, dtype=float).reshape(-1, 2)
        # Displacement felt but not yet applied: the model composes (a move applied in pieces
        # equals the move applied whole), so rolling along one direction is batched into pieces
        # of up to FLUSH_MM instead of one model call per millisecond.
        self._pending = np.zeros(2)
        self.rolling_radius_mm = float(rolling_radius_mm)
        self.min_field_T = float(min_field_T)
        self.slip = float(slip)
        self.axis_xy: np.ndarray | None = None  # unit vector u, None until a field is felt
        self._roll_angle: float | None = None
        self.rolled_rad = 0.0  # total roll, for diagnostics

    FLUSH_MM = 0.5

    @property
    def positions_mm(self) -> np.ndarray:
        """True centres (n, 2) in mm, with every displacement felt so far applied."""
        self._flush()
        return self._positions_mm

    @positions_mm.setter
    def positions_mm(self, value: np.ndarray) -> None:
        self._pending[:] = 0.0
        self._positions_mm = np.array(value, dtype=float).reshape(-1, 2)

    def _flush(self) -> None:
        if self._pending.any():
            self._positions_mm = self.model.apply(self._positions_mm, self._pending)
            self._pending[:] = 0.0

    def feel(self, field_T: np.ndarray) -> None:
        """Advance the magnets to follow `field_T` (3,), the field at this instant.

        Calls must come often enough that the field turns by less than 180 degrees between two of
        them (the bench calls this every millisecond of simulated time).
        """
        b = np.asarray(field_T, dtype=float)
        magnitude = float(np.linalg.norm(b))
        if magnitude < self.min_field_T:
            return
        b_hat = b / magnitude
        horizontal = b_hat[:2]
        if float(np.hypot(*horizontal)) > 1e-6:
            # u is perpendicular to the magnetisation and horizontal: parallel to z x B_h.
            u = np.array([-horizontal[1], horizontal[0]])
            u /= np.linalg.norm(u)
            if self.axis_xy is not None and float(u @ self.axis_xy) < 0:
                u = -u  # the cylinder is symmetric; keep the sign continuous
            self.axis_xy = u
        elif self.axis_xy is None:
            return  # a vertical first field says nothing about the axis yet
        u = self.axis_xy
        # A steering turn keeps B in the uv plane, so the angle below stays 0 or pi: no rolling.
        v = np.array([-u[1], u[0], 0.0])  # v = z x u, so (u, v, z) is right-handed
        angle = math.atan2(float(b_hat[2]), float(b_hat @ v))
        if self._roll_angle is None:
            self._roll_angle = angle  # the magnets align with the first field without rolling
            return
        d_alpha = (angle - self._roll_angle + math.pi) % (2.0 * math.pi) - math.pi
        self._roll_angle = angle
        if d_alpha == 0.0:
            return
        self.rolled_rad += d_alpha
        # centre velocity of a cylinder rolling about +u: omega * R * (u x z) = R * (u_y, -u_x)
        step = self.slip * self.rolling_radius_mm * d_alpha * np.array([u[1], -u[0]])
        pending_norm = float(np.hypot(*self._pending))
        if pending_norm > 0.0:
            # only a displacement along the same line may be batched with what is pending
            cross = self._pending[0] * step[1] - self._pending[1] * step[0]
            if abs(cross) > 1e-9 * pending_norm * float(np.hypot(*step)) or self._pending @ step < 0:
                self._flush()
        self._pending += step
        if float(np.hypot(*self._pending)) >= self.FLUSH_MM:
            self._flush()
