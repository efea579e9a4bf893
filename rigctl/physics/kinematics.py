"""Kinematics of the KUKA LBR iiwa 14 R820 arms that carry the dual-EPM rig's magnets (seed 003).

Each arm is a 7-joint serial chain in standard Denavit-Hartenberg form,
T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i), mounted at a base pose in the world frame (the world
origin is the workspace centre, z up). The end effector carries one external permanent magnet
(EPM): its centre sits `tool_offset_m` along the flange's z axis and its magnetic moment points
along the flange's x axis, so rotating about the flange axis (joint 7) turns the moment, and the
rotation about the moment axis itself is the freedom inverse kinematics may use.

Sources for the arm data (LBR_IIWA_14_R820):
- link lengths d = (0.360, 0, 0.420, 0, 0.400, 0, 0.126) m, all a = 0: KUKA, "Medien-Flansch fuer
  Produktfamilie LBR iiwa, Montage- und Betriebsanleitung" (as tabulated in the KUKA Sunrise
  Toolbox, `constDhDataOf14R820.m`); twists alternate -90/+90 deg as in the Robotics Toolbox
  model of the iiwa.
- joint ranges +-170, +-120, +-170, +-120, +-170, +-120, +-175 deg and maximum joint speeds
  85, 85, 100, 75, 130, 135, 135 deg/s: KUKA, "LBR iiwa 7 R800, LBR iiwa 14 R820 Specification"
  (Spez LBR iiwa, V7), axis data of the 14 R820.
- link capsule radii are our own bounding estimates of the link housings (not from KUKA).
- joint accelerations: KUKA publishes no limits for the LBR iiwa (the controller shapes its own
  motions); 10 rad/s^2 per joint is our assumption, used by the planner's acceleration cap
  (`SafetyLimits.accel_fraction`) and by the emulated arm, so a plan stays well inside what the
  emulated (and, with that margin, the real) arm follows without lagging.

Everything is in SI (m, rad, rad/s) and vectorised over leading axes of the joint array. Inverse
kinematics, which the dual-EPM planner calls hundreds of times per transition, is one compiled
kernel (`_ik_kernel`, numba): the same Levenberg-Marquardt as written out in `ArmKinematics.solve`,
without numpy's per-call overhead on 4x4 and 7x7 arrays.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import LimitError
from rigctl.core.jit import njit

log = logging.getLogger(__name__)

N_JOINTS = 7


@dataclass(frozen=True)
class ArmModel:
    """A 7-joint arm in standard DH form plus the EPM tool and the links' collision capsules."""

    name: str
    d_m: tuple[float, ...]
    a_m: tuple[float, ...]
    alpha_rad: tuple[float, ...]
    joint_limits_rad: tuple[tuple[float, float], ...]
    max_speed_rad_s: tuple[float, ...]
    max_accel_rad_s2: tuple[float, ...] = (10.0,) * 7
    """Assumed (not published by KUKA): see the module docstring."""
    tool_offset_m: float = 0.085
    """EPM centre along the flange z axis (m): magnet radius 50.8 mm + a 34 mm mount."""
    capsule_links: tuple[tuple[int, int], ...] = ((0, 1), (2, 3), (4, 5), (6, 7), (7, 8))
    """Capsules as pairs of frame indices into `ArmKinematics.frames` (0 base ... 7 flange,
    8 EPM centre): base column, upper arm, forearm, wrist, EPM mount."""
    capsule_radii_m: tuple[float, ...] = (0.08, 0.07, 0.07, 0.06, 0.04)
    capsule_names: tuple[str, ...] = ("base", "upper-arm", "forearm", "wrist", "epm-mount")

    @property
    def lower_rad(self) -> np.ndarray:
        return np.array([lo for lo, _ in self.joint_limits_rad])

    @property
    def upper_rad(self) -> np.ndarray:
        return np.array([hi for _, hi in self.joint_limits_rad])

    @property
    def max_speed(self) -> np.ndarray:
        return np.array(self.max_speed_rad_s)

    @property
    def max_accel(self) -> np.ndarray:
        return np.array(self.max_accel_rad_s2)


_DEG = np.pi / 180.0

LBR_IIWA_14_R820 = ArmModel(
    name="KUKA LBR iiwa 14 R820",
    d_m=(0.360, 0.0, 0.420, 0.0, 0.400, 0.0, 0.126),
    a_m=(0.0,) * 7,
    alpha_rad=(-np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, 0.0),
    joint_limits_rad=tuple(
        (-lim * _DEG, lim * _DEG) for lim in (170.0, 120.0, 170.0, 120.0, 170.0, 120.0, 175.0)
    ),
    max_speed_rad_s=tuple(v * _DEG for v in (85.0, 85.0, 100.0, 75.0, 130.0, 135.0, 135.0)),
)


def base_transform(position_m: ArrayLike, rpy_deg: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 pose of an arm's base in the world frame: translation (m) and fixed-axis roll, pitch,
    yaw (deg), R = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll, pitch, yaw = np.asarray(rpy_deg, dtype=float) * _DEG
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1.0]])
    ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    rx = np.array([[1.0, 0, 0], [0, cr, -sr], [0, sr, cr]])
    pose = np.eye(4)
    pose[:3, :3] = rz @ ry @ rx
    pose[:3, 3] = np.asarray(position_m, dtype=float)
    return pose


DEFAULT_BASES = (
    ("left", (-0.80, 0.0, -0.50), (0.0, 0.0, 0.0)),
    ("right", (0.80, 0.0, -0.50), (0.0, 0.0, 180.0)),
)
"""The rig's default arm bases (name, position m, rpy deg): facing each other across the
workspace centre along x, shoulders (joint 2) level with the centre."""


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (np.cross is slow for the small arrays of the IK loop)."""
    return np.stack([
        a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
        a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
        a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
    ], axis=-1)


@dataclass(frozen=True)
class IKResult:
    """An inverse-kinematics answer: joints (rad), EPM position error (m), moment direction error
    (rad), and whether both are within the requested tolerances."""

    q: np.ndarray
    position_error_m: float
    direction_error_rad: float
    ok: bool


@dataclass
class ArmKinematics:
    """One arm at its base pose: forward kinematics of every frame, the EPM pose, the collision
    capsules, and inverse kinematics for an EPM position + moment direction."""

    base: np.ndarray = field(default_factory=lambda: np.eye(4))
    model: ArmModel = LBR_IIWA_14_R820
    name: str = "arm"

    def __post_init__(self) -> None:
        self.base = np.asarray(self.base, dtype=float)
        if self.base.shape != (4, 4):
            raise ValueError(f"base must be a 4x4 pose, got shape {self.base.shape}")
        m = self.model
        self._dh = [(float(np.cos(m.alpha_rad[i])), float(np.sin(m.alpha_rad[i])), float(m.a_m[i]),
                     float(m.d_m[i])) for i in range(N_JOINTS)]
        self._dh_table = np.array(self._dh)  # (7, 4): cos alpha, sin alpha, a, d (the IK kernel's)
        self._capsule_links = np.array(m.capsule_links, dtype=np.int64)
        self._capsule_radii = np.array(m.capsule_radii_m, dtype=float)

    # ------------------------------------------------------------ forward kinematics

    def frames(self, q: ArrayLike) -> np.ndarray:
        """World poses of the base (0), the seven DH frames (1-7, 7 = flange) and the EPM (8).

        q : (..., 7) joint angles in rad -> (..., 9, 4, 4) homogeneous transforms."""
        q = np.asarray(q, dtype=float)
        if q.shape[-1:] != (N_JOINTS,):
            raise ValueError(f"q must have shape (..., 7), got {q.shape}")
        if q.ndim == 1:
            return self._frames_one(q)
        m = self.model
        batch = q.shape[:-1]
        out = np.empty(batch + (9, 4, 4))
        current = np.broadcast_to(self.base, batch + (4, 4)).copy()
        out[..., 0, :, :] = current
        ca, sa = np.cos(m.alpha_rad), np.sin(m.alpha_rad)
        for i in range(N_JOINTS):
            ct, st = np.cos(q[..., i]), np.sin(q[..., i])
            link = np.zeros(batch + (4, 4))
            link[..., 0, 0], link[..., 0, 1], link[..., 0, 2] = ct, -st * ca[i], st * sa[i]
            link[..., 1, 0], link[..., 1, 1], link[..., 1, 2] = st, ct * ca[i], -ct * sa[i]
            link[..., 2, 1], link[..., 2, 2] = sa[i], ca[i]
            link[..., 0, 3] = m.a_m[i] * ct
            link[..., 1, 3] = m.a_m[i] * st
            link[..., 2, 3] = m.d_m[i]
            link[..., 3, 3] = 1.0
            current = current @ link
            out[..., i + 1, :, :] = current
        tool = np.eye(4)
        tool[2, 3] = m.tool_offset_m
        out[..., 8, :, :] = current @ tool
        return out

    def _frames_one(self, q: np.ndarray) -> np.ndarray:
        """`frames` of one joint vector (7,): the same products, in plain floats (inverse
        kinematics calls this thousands of times per plan; numpy's per-call overhead dominates)."""
        m = self.model
        out = np.empty((9, 4, 4))
        current = self.base
        out[0] = current
        for i, (ct, st) in enumerate(zip(np.cos(q).tolist(), np.sin(q).tolist())):
            ca, sa, a, d = self._dh[i]
            link = np.array([[ct, -st * ca, st * sa, a * ct],
                             [st, ct * ca, -ct * sa, a * st],
                             [0.0, sa, ca, d],
                             [0.0, 0.0, 0.0, 1.0]])
            current = current @ link
            out[i + 1] = current
        out[8] = current
        out[8, :3, 3] = current[:3, 3] + m.tool_offset_m * current[:3, 2]
        return out

    def flange(self, q: ArrayLike) -> np.ndarray:
        """World pose (..., 4, 4) of the flange (frame 7)."""
        return self.frames(q)[..., 7, :, :]

    def epm_pose(self, q: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """EPM centre (..., 3) in m and unit moment direction (..., 3) (the flange x axis)."""
        epm = self.frames(q)[..., 8, :, :]
        return epm[..., :3, 3], epm[..., :3, 0]

    def capsules(self, q: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Link capsules: segment end points (..., L, 2, 3) in m and radii (L,) in m, in the order
        of `model.capsule_names`."""
        origins = self.frames(q)[..., :3, 3]  # (..., 9, 3)
        index = np.array(self.model.capsule_links)
        return origins[..., index, :], np.array(self.model.capsule_radii_m)

    def within_limits(self, q: ArrayLike) -> np.ndarray:
        """True where every joint lies inside its range (..., 7) -> (...)."""
        q = np.asarray(q, dtype=float)
        return np.all((q >= self.model.lower_rad) & (q <= self.model.upper_rad), axis=-1)

    # ------------------------------------------------------------ inverse kinematics

    def _origin_jacobians(self, frames: np.ndarray) -> np.ndarray:
        """Positional Jacobians (9, 3, 7) of the origins of all frames (base ... flange, EPM)."""
        origins = frames[:, :3, 3]
        axes = frames[:N_JOINTS, :3, 2]  # joint i+1 turns about z of frame i
        jac = _cross(axes[:, None, :], origins[None, :, :] - origins[:N_JOINTS, None, :])
        moves = np.arange(N_JOINTS)[:, None] < np.arange(9)[None, :]  # joint i+1 moves frame f > i
        return (jac * moves[..., None]).transpose(1, 2, 0)

    def solve(
        self,
        position_m: ArrayLike,
        moment_direction: ArrayLike,
        q_seed: ArrayLike,
        *,
        keep_out: tuple[ArrayLike, float] | None = None,
        stay_weight: float = 0.02,
        position_tol_m: float = 1e-4,
        direction_tol_rad: float = 1e-3,
        max_iterations: int = 100,
    ) -> IKResult:
        """Joints that put the EPM centre at `position_m` with its moment along
        `moment_direction`, as close as possible to `q_seed` (rad).

        The task has 5 constraints (3 position, 2 direction) for 7 joints; the two spare degrees
        of freedom (the rotation about the moment axis and the elbow's self-motion) are spent on
        staying near `q_seed` (a residual `stay_weight * (q - q_seed)`) and, when `keep_out`
        = (centre_m, radius_m) is given, on keeping five points along every link capsule at
        least radius_m + the capsule's radius from centre_m (a one-sided penalty; the exact
        capsule test is `rigctl.plans.depm_safety`'s). Joint ranges are hard bounds (projection).
        Solved by Levenberg-Marquardt on the analytic geometric Jacobian, in two passes: the
        first trades a little task error for closeness to the seed, the second pulls 1000 times
        more weakly toward that answer so the task is met exactly from near it.
        """
        target = np.asarray(position_m, dtype=float)
        direction = np.asarray(moment_direction, dtype=float)
        direction = direction / np.linalg.norm(direction)
        lower, upper = self.model.lower_rad, self.model.upper_rad
        seed = np.clip(np.asarray(q_seed, dtype=float), lower, upper)
        if keep_out is None:
            ko_centre, ko_radius = np.zeros(3), -1.0  # a negative radius: no keep-out residuals
        else:
            ko_centre, ko_radius = np.asarray(keep_out[0], dtype=float), float(keep_out[1])
        q = _ik_kernel(self.base, self._dh_table, self.model.tool_offset_m, lower, upper, target,
                       direction, seed, ko_centre, ko_radius, self._capsule_links,
                       self._capsule_radii, stay_weight, position_tol_m, direction_tol_rad,
                       max_iterations)
        # numpy's vectorised sums can differ in the last bit with memory alignment; rounding far
        # below any physical scale keeps plans identical from run to run.
        q = np.round(q, 12)
        pos_err, dir_err = _ik_errors(self.base, self._dh_table, self.model.tool_offset_m, q,
                                      target, direction)
        ok = pos_err <= position_tol_m and dir_err <= direction_tol_rad
        return IKResult(q=q, position_error_m=pos_err, direction_error_rad=dir_err, ok=ok)

    def solve_or_raise(self, position_m, moment_direction, q_seed, **kwargs) -> np.ndarray:
        """`solve`, raising LimitError (naming this arm and the target) when it does not reach."""
        result = self.solve(position_m, moment_direction, q_seed, **kwargs)
        if not result.ok:
            p = np.asarray(position_m, dtype=float)
            raise LimitError(
                f"no joint solution puts the EPM at ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m with the "
                f"requested moment direction (left {result.position_error_m * 1e3:.1f} mm, "
                f"{np.degrees(result.direction_error_rad):.1f} deg off): outside the arm's reach or "
                "joint ranges; move the target or the arm's base",
                device=self.name,
            )
        return result.q


# ---------------------------------------------------------------- the inverse-kinematics kernel
# `ArmKinematics.solve` in compiled form. Residuals, in this order: EPM position error (3, m), the
# scaled moment direction error (3), the pull toward the anchor (7) and the keep-out penalty of
# every link point inside its reach; the normal equations J^T J and J^T r are summed row by row
# instead of stacking J.

_IK_DIRECTION_SCALE = 0.3  # m: a 1 rad direction error weighs like a 0.3 m position error
_IK_PENALTY_SCALE = 3.0  # penetrating the keep-out sphere costs 3x a position error
_IK_FRACTIONS = (0.0, 0.25, 0.5, 0.75, 1.0)  # five points along every link capsule
_IK_SYMMETRY_BREAK = (1.0, 0.0, -1.0, 0.0, 1.0, 0.0, -1.0)


@njit(error_model="numpy")
def frames_kernel(base, dh, tool_offset, q, frames):  # pragma: no cover - compiled
    """`ArmKinematics._frames_one` into `frames` (9, 4, 4)."""
    frames[0] = base
    for i in range(N_JOINTS):
        ct, st = np.cos(q[i]), np.sin(q[i])
        ca, sa, a, d = dh[i, 0], dh[i, 1], dh[i, 2], dh[i, 3]
        for r in range(4):  # row r of frames[i] @ the DH link transform
            x, y, z, w = frames[i, r, 0], frames[i, r, 1], frames[i, r, 2], frames[i, r, 3]
            frames[i + 1, r, 0] = x * ct + y * st
            frames[i + 1, r, 1] = x * (-st * ca) + y * (ct * ca) + z * sa
            frames[i + 1, r, 2] = x * (st * sa) + y * (-ct * sa) + z * ca
            frames[i + 1, r, 3] = x * (a * ct) + y * (a * st) + z * d + w
    frames[8] = frames[7]
    for k in range(3):
        frames[8, k, 3] = frames[7, k, 3] + tool_offset * frames[7, k, 2]


@njit(error_model="numpy")
def _ik_evaluate(q, weight, anchor, base, dh, tool_offset, target, direction, ko_centre,
                 ko_radius, links, radii, frames, jo, jtj, jtr):  # pragma: no cover - compiled
    """Normal equations of the IK residuals at q into jtj (7, 7) and jtr (7,); returns the cost
    |r|^2 and the norms of the position and (scaled) direction residuals."""
    frames_kernel(base, dh, tool_offset, q, frames)
    _ik_origin_jacobians(frames, jo)
    jtj[:, :] = 0.0
    jtr[:] = 0.0
    row = np.empty(N_JOINTS)
    position_sq = 0.0
    for k in range(3):  # the EPM position
        r = frames[8, k, 3] - target[k]
        for i in range(N_JOINTS):
            row[i] = jo[8, k, i]
        _ik_accumulate(row, r, jtj, jtr)
        position_sq += r * r
    direction_sq = 0.0
    epm_d = frames[8, :3, 0]
    for k in range(3):  # the moment direction: d(epm_d)/dq_i = z_i x epm_d
        r = _IK_DIRECTION_SCALE * (epm_d[k] - direction[k])
        for i in range(N_JOINTS):
            z = frames[i, :3, 2]
            if k == 0:
                row[i] = _IK_DIRECTION_SCALE * (z[1] * epm_d[2] - z[2] * epm_d[1])
            elif k == 1:
                row[i] = _IK_DIRECTION_SCALE * (z[2] * epm_d[0] - z[0] * epm_d[2])
            else:
                row[i] = _IK_DIRECTION_SCALE * (z[0] * epm_d[1] - z[1] * epm_d[0])
        _ik_accumulate(row, r, jtj, jtr)
        direction_sq += r * r
    cost = position_sq + direction_sq
    for i in range(N_JOINTS):  # the pull toward the anchor
        r = weight * (q[i] - anchor[i])
        jtj[i, i] += weight * weight
        jtr[i] += weight * r
        cost += r * r
    if ko_radius >= 0.0:
        cost += _ik_keep_out(frames, jo, ko_centre, ko_radius, links, radii, row, jtj, jtr)
    return cost, np.sqrt(position_sq), np.sqrt(direction_sq)


@njit(error_model="numpy")
def _ik_origin_jacobians(frames, jo):  # pragma: no cover - compiled
    """Positional Jacobians (9, 3, 7) of every frame origin into jo (`_origin_jacobians`): joint
    i turns about z of frame i and moves every frame after it."""
    for f in range(9):
        for i in range(N_JOINTS):
            if i < f:
                z = frames[i, :3, 2]
                dx = frames[f, 0, 3] - frames[i, 0, 3]
                dy = frames[f, 1, 3] - frames[i, 1, 3]
                dz = frames[f, 2, 3] - frames[i, 2, 3]
                jo[f, 0, i] = z[1] * dz - z[2] * dy
                jo[f, 1, i] = z[2] * dx - z[0] * dz
                jo[f, 2, i] = z[0] * dy - z[1] * dx
            else:
                jo[f, 0, i] = jo[f, 1, i] = jo[f, 2, i] = 0.0


@njit(error_model="numpy")
def _ik_keep_out(frames, jo, ko_centre, ko_radius, links, radii, row, jtj,
                 jtr):  # pragma: no cover - compiled
    """The keep-out penalties of the link points into the normal equations (only penetrating
    points have a residual); returns their part of the cost."""
    cost = 0.0
    for link in range(links.shape[0]):
        first, second = links[link, 0], links[link, 1]
        reach = ko_radius + radii[link]
        for f in _IK_FRACTIONS:
            rel = np.empty(3)
            for k in range(3):
                rel[k] = (1.0 - f) * frames[first, k, 3] + f * frames[second, k, 3] - ko_centre[k]
            dist = np.sqrt(rel[0] * rel[0] + rel[1] * rel[1] + rel[2] * rel[2])
            depth = reach - dist
            if depth <= 0.0:
                continue
            scale = -_IK_PENALTY_SCALE / max(dist, 1e-9)
            for i in range(N_JOINTS):
                total = 0.0
                for k in range(3):
                    total += rel[k] * ((1.0 - f) * jo[first, k, i] + f * jo[second, k, i])
                row[i] = scale * total
            r = _IK_PENALTY_SCALE * depth
            _ik_accumulate(row, r, jtj, jtr)
            cost += r * r
    return cost


@njit(error_model="numpy")
def _ik_accumulate(row, r, jtj, jtr):  # pragma: no cover - compiled
    """Add one residual r with Jacobian row (7,) to the normal equations."""
    for i in range(N_JOINTS):
        jtr[i] += row[i] * r
        for j in range(N_JOINTS):
            jtj[i, j] += row[i] * row[j]


@njit(error_model="numpy")
def cholesky_solve(matrix, rhs):  # pragma: no cover - compiled
    """x with matrix @ x = rhs for a symmetric positive definite matrix (n, n) (its lower
    triangle is read), by Cholesky: for the small normal equations of Levenberg-Marquardt, where
    numba's LAPACK binding would cost more to compile than the solve."""
    n = rhs.shape[0]
    low = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            total = matrix[i, j]
            for k in range(j):
                total -= low[i, k] * low[j, k]
            low[i, j] = np.sqrt(total) if i == j else total / low[j, j]
    x = np.empty(n)
    for i in range(n):
        total = rhs[i]
        for k in range(i):
            total -= low[i, k] * x[k]
        x[i] = total / low[i, i]
    for i in range(n - 1, -1, -1):
        total = x[i]
        for k in range(i + 1, n):
            total -= low[k, i] * x[k]
        x[i] = total / low[i, i]
    return x


@njit(error_model="numpy")
def _ik_errors(base, dh, tool_offset, q, target, direction):  # pragma: no cover - compiled
    """The EPM's position error (m) and moment direction error (rad) at joints q (7,)."""
    frames = np.empty((9, 4, 4))
    frames_kernel(base, dh, tool_offset, q, frames)
    position_sq, cosine = 0.0, 0.0
    for k in range(3):
        position_sq += (frames[8, k, 3] - target[k]) ** 2
        cosine += frames[8, k, 0] * direction[k]
    return np.sqrt(position_sq), np.arccos(min(max(cosine, -1.0), 1.0))


@njit(error_model="numpy")
def _ik_kernel(base, dh, tool_offset, lower, upper, target, direction, seed, ko_centre, ko_radius,
               links, radii, stay_weight, position_tol, direction_tol,
               max_iterations):  # pragma: no cover - compiled
    """The two Levenberg-Marquardt passes of `ArmKinematics.solve` from `seed` (7,): joints (7,)."""
    n = N_JOINTS
    frames = np.empty((9, 4, 4))
    jo = np.empty((9, 3, n))
    jtj, jtr = np.empty((n, n)), np.empty(n)
    jtj_trial, jtr_trial = np.empty((n, n)), np.empty(n)
    system, rhs = np.empty((n, n)), np.empty(n)
    # A seed on a symmetric configuration (q1 = q3 = q5 = 0) can sit on a saddle of the task:
    # a tiny fixed offset breaks the symmetry without moving the answer noticeably.
    q = np.empty(n)
    for i in range(n):
        q[i] = min(max(seed[i] + 1e-4 * _IK_SYMMETRY_BREAK[i], lower[i]), upper[i])
    for stage in range(2):
        weight = stay_weight if stage == 0 else stay_weight * 1e-3
        rel_tol = 1e-3 if stage == 0 else 1e-12
        anchor = seed.copy() if weight == stay_weight else q.copy()
        cost, _, _ = _ik_evaluate(q, weight, anchor, base, dh, tool_offset, target, direction,
                                  ko_centre, ko_radius, links, radii, frames, jo, jtj, jtr)
        damping = 1e-4
        for _ in range(max_iterations):
            # Joints resting on a bound and pushed outward are held (active set).
            free = np.ones(n, dtype=np.bool_)
            step = np.zeros(n)
            for _pass in range(2):
                for i in range(n):
                    rhs[i] = -jtr[i] if free[i] else 0.0
                    for j in range(n):
                        system[i, j] = jtj[i, j] if free[i] and free[j] else 0.0
                    system[i, i] += damping * system[i, i] + (1e-9 + damping * 1e-6)
                step = cholesky_solve(system, rhs)
                newly_blocked = False
                for i in range(n):
                    blocked = ((q[i] <= lower[i] + 1e-12 and step[i] < 0.0)
                               or (q[i] >= upper[i] - 1e-12 and step[i] > 0.0))
                    if blocked and free[i]:
                        free[i] = False
                        newly_blocked = True
                if not newly_blocked:
                    break
            trial = np.empty(n)
            moved = 0.0
            for i in range(n):
                trial[i] = min(max(q[i] + (step[i] if free[i] else 0.0), lower[i]), upper[i])
                moved = max(moved, abs(trial[i] - q[i]))
            cost_trial, position_norm, direction_norm = _ik_evaluate(
                trial, weight, anchor, base, dh, tool_offset, target, direction, ko_centre,
                ko_radius, links, radii, frames, jo, jtj_trial, jtr_trial)
            if cost_trial < cost:
                converged = (cost - cost_trial <= rel_tol * cost) or moved < 1e-10
                q, cost = trial, cost_trial
                jtj, jtj_trial = jtj_trial, jtj
                jtr, jtr_trial = jtr_trial, jtr
                damping = max(damping / 3.0, 1e-9)
                task_met = (position_norm < 1e-3 * position_tol
                            and direction_norm < 1e-3 * direction_tol * _IK_DIRECTION_SCALE)
                if converged or cost < 1e-24 or (rel_tol < 1e-6 and task_met):
                    break
            else:
                damping *= 4.0
                if damping > 1e8:
                    break
    return q


def default_arms(model: ArmModel = LBR_IIWA_14_R820) -> list[ArmKinematics]:
    """The two arms of the default rig (`DEFAULT_BASES`)."""
    return [
        ArmKinematics(base=base_transform(pos, rpy), model=model, name=name)
        for name, pos, rpy in DEFAULT_BASES
    ]
