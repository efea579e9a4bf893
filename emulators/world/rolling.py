"""Rolling cylindrical magnets on the workspace floor (seed 000 Sec. V), moved by the field that the
emulated coils really produce, with the ways a real rig departs from the planner's model.

Each magnet is a radially magnetised cylinder lying on the floor. Its magnetisation follows the field
direction; since the magnetisation is perpendicular to the cylinder's axis u (horizontal), the field
fixes u up to sign (u is parallel to z x B_horizontal), and the field's angle in the plane
perpendicular to u is the cylinder's roll angle. A roll by d_alpha about +u without slip moves the
centre by R * d_alpha * (u x z). So this model needs nothing from the plan or the realizer: it only
watches the field, which is what makes the end-to-end tests honest.

Every magnet has its own axis and roll angle, so each may feel its own field (the coils' field at
its own position: a field that is not uniform across the workspace). The model mismatch a real rig
shows (`Mismatch`) is applied here: rolling slip (distance per turn times `slip`), a per-robot
spread of that distance (times 1 + s_i, s_i ~ N(0, speed_spread) drawn once), a slow steady drift,
and position jitter while a robot touches a wall or another robot. Displacements still go through
the one global-input model: a shared one in a single call; different ones per robot by moving each
robot with its own displacement against the others' old positions (pieces of at most `FLUSH_MM`, so
the others barely moved), a robot that would then overlap another staying where it was.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rigctl.plans.model import GlobalInputModel

log = logging.getLogger(__name__)

_CONTACT_MARGIN_MM = 0.05  # closer than this to a wall or another robot counts as contact
_DRIFT_FLUSH_MM = 0.05
_BATCH_ANGLE_RAD = 1e-3


@dataclass(frozen=True)
class Mismatch:
    """How the emulated rig departs from the planner's model (all neutral by default).

    slip: distance per turn as a fraction of 2 pi R (the pair world: speed under a force as a
    fraction of the plan's Stokes drag, `rigctl.emulators.world.pair`); speed_spread: standard
    deviation of the per-robot factor s_i (distance per turn x (1 + s_i)); drift_mm_per_s: speed
    of a steady drift in a direction drawn from the seed; noise_mm: standard deviation of the jitter per turn rolled
    while in contact; seed: draws s_i, the drift direction and the jitter; field_at_robots: each
    robot feels the field at its own position instead of the workspace centre's.
    """

    slip: float = 1.0
    speed_spread: float = 0.0
    drift_mm_per_s: float = 0.0
    noise_mm: float = 0.0
    seed: int = 0
    field_at_robots: bool = False


class RollingMagnetWorld:
    """Ground truth of the emulated six-coil bench.

    positions_mm: (n, 2) initial centres; rolling_radius_mm: the cylinders' radius R;
    min_field_T: below this the magnets do not follow the field (friction); slip: distance rolled per
    turn as a fraction of 2*pi*R (1 = no slip), kept for callers that set no `mismatch`.
    """

    FLUSH_MM = 0.5

    def __init__(
        self,
        model: GlobalInputModel,
        positions_mm: ArrayLike,
        *,
        rolling_radius_mm: float,
        min_field_T: float,
        slip: float = 1.0,
        mismatch: Mismatch | None = None,
    ) -> None:
        self.model = model
        self._positions_mm = np.array(positions_mm, dtype=float).reshape(-1, 2)
        n = len(self._positions_mm)
        self.mismatch = mismatch if mismatch is not None else Mismatch(slip=slip)
        rng = np.random.default_rng(self.mismatch.seed)
        spread = rng.normal(0.0, self.mismatch.speed_spread, n) if self.mismatch.speed_spread else \
            np.zeros(n)
        self.speed_factors = 1.0 + spread  # (n,) 1 + s_i
        self.distance_scale = self.mismatch.slip * self.speed_factors  # (n,) of 2 pi R per turn
        heading = rng.uniform(0.0, 2.0 * math.pi)
        self.drift_velocity_mm_s = self.mismatch.drift_mm_per_s * np.array(
            [math.cos(heading), math.sin(heading)])
        self._rng = rng
        # Displacement felt but not yet applied: the model composes (a move applied in pieces
        # equals the move applied whole), so rolling along one line is batched into pieces of up
        # to FLUSH_MM instead of one model call per millisecond.
        self._pending = np.zeros((n, 2))
        self._drift_pending = np.zeros(2)
        self.rolling_radius_mm = float(rolling_radius_mm)
        self.min_field_T = float(min_field_T)
        self._axes = np.zeros((n, 2))  # unit vectors u; rows of zeros until a field is felt
        self._has_axis = np.zeros(n, dtype=bool)
        self._roll_angle = np.full(n, np.nan)
        self.rolled_rad = np.zeros(n)  # total roll per robot, for diagnostics
        self._radii = np.asarray(model.radii, dtype=float)
        first, second = np.triu_indices(n, 1)
        self._pairs = (first, second)
        self._reach = self._radii[first] + self._radii[second] + model.min_separation_mm

    @property
    def slip(self) -> float:
        return self.mismatch.slip

    @slip.setter
    def slip(self, value: float) -> None:
        self._flush()
        self.mismatch = Mismatch(**{**self.mismatch.__dict__, "slip": float(value)})
        self.distance_scale = self.mismatch.slip * self.speed_factors

    @property
    def axis_xy(self) -> np.ndarray | None:
        """Robot 0's axis u (2,), None until a field is felt (all robots share it in a uniform field)."""
        return self._axes[0].copy() if self._has_axis[0] else None

    @property
    def positions_mm(self) -> np.ndarray:
        """True centres (n, 2) in mm, with every displacement felt so far applied."""
        self._flush()
        return self._positions_mm

    @positions_mm.setter
    def positions_mm(self, value: ArrayLike) -> None:
        self._pending[:] = 0.0
        self._positions_mm = np.array(value, dtype=float).reshape(-1, 2)

    @property
    def settled_positions_mm(self) -> np.ndarray:
        """Centres (n, 2) mm as of the last applied piece (up to FLUSH_MM behind), without applying
        what is pending: cheap enough to call every simulation step."""
        return self._positions_mm

    # -- moving ---------------------------------------------------------------------------------
    def _move(self, displacements: np.ndarray) -> None:
        """Apply per-robot displacements (n, 2) mm through the global-input model."""
        p = self._positions_mm
        if np.all(np.abs(displacements - displacements[0]) <= 1e-12):
            self._positions_mm = self.model.apply(p, displacements[0])
            return
        n = len(p)
        each = self.model.apply(np.broadcast_to(p, (n, n, 2)), displacements)
        moved = each[np.arange(n), np.arange(n)].copy()
        first, second = self._pairs
        for _ in range(n):
            gap = moved[second] - moved[first]
            overlap = np.hypot(gap[:, 0], gap[:, 1]) < self._reach - 1e-7
            if not overlap.any():
                break
            for i, j in zip(first[overlap], second[overlap]):
                # the one that moved towards the other gives way and keeps its old place
                towards_i = float(displacements[i] @ (p[j] - p[i]))
                towards_j = float(displacements[j] @ (p[i] - p[j]))
                moved[i if towards_i >= towards_j else j] = p[i if towards_i >= towards_j else j]
        self._positions_mm = moved

    def _flush(self) -> None:
        if not self._pending.any():
            return
        pieces = self._pending.copy()
        self._pending[:] = 0.0
        self._move(pieces)
        if self.mismatch.noise_mm > 0.0:
            self._jitter(np.hypot(pieces[:, 0], pieces[:, 1]))

    def _in_contact(self) -> np.ndarray:
        """(n,) True where a robot touches a wall or another robot."""
        p = self._positions_mm
        touching = self.model.workspace.clearance(p) <= self._radii + _CONTACT_MARGIN_MM
        first, second = self._pairs
        if len(first):
            gap = p[second] - p[first]
            close = np.hypot(gap[:, 0], gap[:, 1]) <= self._reach + _CONTACT_MARGIN_MM
            touching[first[close]] = True
            touching[second[close]] = True
        return touching

    def _jitter(self, rolled_mm: np.ndarray) -> None:
        """Jitter the robots in contact: variance noise_mm^2 per turn rolled (a random walk)."""
        contact = self._in_contact() & (rolled_mm > 0)
        if not contact.any():
            return
        turn_mm = 2.0 * math.pi * self.rolling_radius_mm
        sigma = self.mismatch.noise_mm * np.sqrt(rolled_mm / turn_mm)
        jitter = self._rng.normal(0.0, 1.0, (len(sigma), 2)) * sigma[:, None]
        jitter[~contact] = 0.0
        self._move(jitter)

    def drift(self, dt_s: float) -> None:
        """Let the steady drift act for `dt_s` seconds."""
        if not self.mismatch.drift_mm_per_s:
            return
        self._drift_pending += self.drift_velocity_mm_s * dt_s
        if float(np.hypot(*self._drift_pending)) >= _DRIFT_FLUSH_MM:
            self._flush()
            self._positions_mm = self.model.apply(self._positions_mm, self._drift_pending)
            self._drift_pending[:] = 0.0

    def feel(self, field_T: ArrayLike) -> None:
        """Advance the magnets to follow the field at this instant: (3,) felt by all, or (n, 3) one
        per robot, in tesla.

        Calls must come often enough that the field turns by less than 180 degrees between two of
        them (the bench calls this every millisecond of simulated time).
        """
        b = np.asarray(field_T, dtype=float)
        n = len(self._positions_mm)
        if b.ndim == 1:
            self._feel_uniform(b)
            return
        magnitude = np.linalg.norm(b, axis=1)
        follows = magnitude >= self.min_field_T
        if not follows.any():
            return
        b_hat = b / np.maximum(magnitude, 1e-300)[:, None]
        horizontal = b_hat[:, :2]
        h_norm = np.hypot(horizontal[:, 0], horizontal[:, 1])
        turn = follows & (h_norm > 1e-6)
        if turn.any():
            # u is perpendicular to the magnetisation and horizontal: parallel to z x B_h.
            u = np.stack([-horizontal[:, 1], horizontal[:, 0]], axis=1) / np.maximum(h_norm, 1e-300)[:, None]
            flip = self._has_axis & (np.sum(u * self._axes, axis=1) < 0)
            u[flip] = -u[flip]  # the cylinder is symmetric; keep the sign continuous
            self._axes[turn] = u[turn]
            self._has_axis |= turn
        live = follows & self._has_axis  # a vertical first field says nothing about the axis yet
        if not live.any():
            return
        u = self._axes
        v = np.stack([-u[:, 1], u[:, 0], np.zeros(n)], axis=1)  # v = z x u: (u, v, z) right-handed
        # A steering turn keeps B in the vz plane's own angle: no rolling.
        angle = np.arctan2(b_hat[:, 2], np.sum(b_hat * v, axis=1))
        first = live & np.isnan(self._roll_angle)
        self._roll_angle[first] = angle[first]  # they align with the first field without rolling
        rolling = live & ~first
        d_alpha = np.zeros(n)
        d_alpha[rolling] = (angle[rolling] - self._roll_angle[rolling] + math.pi) % (2 * math.pi) - math.pi
        self._roll_angle[live] = angle[live]
        self._roll(d_alpha)

    def _feel_uniform(self, b: np.ndarray) -> None:
        """`feel` for one field felt by every robot: the same steps as the general case, robot by
        robot in scalars (the bench calls this every simulated millisecond; with a few robots,
        numpy's per-call cost was most of the bench's CPU)."""
        bx, by, bz = b.tolist()
        magnitude = math.sqrt(bx * bx + by * by + bz * bz)
        if magnitude < self.min_field_T:
            return
        bx, by, bz = bx / magnitude, by / magnitude, bz / magnitude
        h_norm = math.hypot(bx, by)
        axes, has_axis, roll_angle = self._axes, self._has_axis, self._roll_angle
        n = len(axes)
        if h_norm > 1e-6:
            ux, uy = -by / h_norm, bx / h_norm  # perpendicular to B, horizontal: along z x B_h
            for i in range(n):
                sign = -1.0 if has_axis[i] and ux * axes[i, 0] + uy * axes[i, 1] < 0 else 1.0
                axes[i, 0], axes[i, 1] = sign * ux, sign * uy  # symmetric: keep the sign
                has_axis[i] = True
        d_alpha = np.zeros(n)
        for i in range(n):
            if not has_axis[i]:
                continue  # a vertical first field says nothing about the axis yet
            ux, uy = axes[i, 0], axes[i, 1]
            angle = math.atan2(bz, bx * -uy + by * ux)  # B's angle in the (v, z) plane, v = z x u
            if not math.isnan(roll_angle[i]):
                d_alpha[i] = (angle - roll_angle[i] + math.pi) % (2 * math.pi) - math.pi
            roll_angle[i] = angle  # the first field aligns them without rolling
        self._roll(d_alpha)

    def _roll(self, d_alpha: np.ndarray) -> None:
        """Roll each robot by d_alpha (n,) rad about its axis."""
        if not d_alpha.any():
            return
        u = self._axes
        self.rolled_rad += d_alpha
        # centre velocity of a cylinder rolling about +u: omega * R * (u x z) = R * (u_y, -u_x)
        step = (self.distance_scale * self.rolling_radius_mm * d_alpha)[:, None] * np.stack(
            [u[:, 1], -u[:, 0]], axis=1)
        pending_norm = np.hypot(self._pending[:, 0], self._pending[:, 1])
        if pending_norm.any():
            # only a displacement along the same line may be batched with what is pending (within
            # _BATCH_ANGLE_RAD: a field that varies across the floor turns the axis slowly, and a
            # chord of such a curve is off by far less than a micrometre over FLUSH_MM)
            cross = self._pending[:, 0] * step[:, 1] - self._pending[:, 1] * step[:, 0]
            step_norm = np.hypot(step[:, 0], step[:, 1])
            turned = (np.abs(cross) > _BATCH_ANGLE_RAD * pending_norm * step_norm) | (
                np.sum(self._pending * step, axis=1) < 0)
            if turned.any():
                self._flush()
        self._pending += step
        if float(np.max(np.hypot(self._pending[:, 0], self._pending[:, 1]))) >= self.FLUSH_MM:
            self._flush()
