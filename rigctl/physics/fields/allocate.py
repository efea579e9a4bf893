"""Currents for a wanted field (and gradient, or force on a dipole) at a point, for any N coils.

At a point the rig's field and gradient are affine in the currents (`rigctl.physics.fields.model`):
U = A I + U_off, U the 8-vector (Bx, By, Bz, dBx/dx, dBx/dy, dBx/dz, dBy/dy, dBy/dz). A request
picks rows of it:

- field only            M = A[0:3]                 b = B - B_off            (N >= 3)
- field and gradient    M = A                      b = U - U_off            (N >= 8)
- field and force       M = [A[0:3]; S A]          b = [B; F] - [B_off; S U_off]   (N >= 6)

with S the 3 x 8 force rows of the wrench map of the dipole's moment m (F = G m,
`rigctl.physics.magnetics.wrench_map`). Unlike mag_manip's backward model (plain pseudo-inverse of
the actuation matrix) this

- subtracts the Offset field, which a calibrated iron-core rig has and mag_manip ignores;
- weights the rows by what is asked: each block (field T, gradient T/m, force N) divided by the
  size of its request (or a floor when zero is asked), so that T and T/m rows, whose numbers
  differ a hundredfold, count alike when the rig cannot meet them all and in the rank decision;
- takes the minimum-norm currents (least Joule heat for equal resistances) among those that meet
  the weighted request, I = pinv(W M) W b, by SVD;
- refuses, with LimitError, a request the rig cannot make: one outside the range of M (naming
  what the rig makes instead, the least-squares nearest), or one whose currents exceed a coil's
  limit (naming the largest fraction of the request, about the offset, that fits). Nothing is
  clipped; a caller gets currents that make what was asked, or an error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import LimitError
from rigctl.core.jit import njit
from rigctl.physics.fields.model import FieldModel
from rigctl.physics.magnetics import GRADIENT_TERMS

FIELD_FLOOR_T = 1e-3
"""The field scale of a request for zero field (1 mT: the size of fields these rigs make)."""

GRADIENT_FLOOR_T_PER_M = 1e-2
"""The gradient scale of a request for zero gradient (10 mT/m)."""

FORCE_FLOOR_N = 1e-6
"""The force scale of a request for zero force (1 uN)."""

RESIDUAL_RTOL = 1e-6
"""Largest weighted residual accepted (the weights make each block of order one)."""

LIMIT_RTOL = 1e-9
"""A current this much (relative) above its limit is taken as at it: round-off of a request made
at the limit on purpose."""

RANK_RCOND = 1e-9
"""Singular values of W M below this times the largest are taken as zero: directions the rig
cannot make."""


@dataclass(frozen=True)
class Allocation:
    """Currents (A, model coil order) for a request and what they make.

    `made` is the full 8-vector U (T, T/m) the currents make at the point, offset included.
    """

    currents_A: np.ndarray
    made: np.ndarray


def _describe(rows: np.ndarray, kinds: list[str]) -> str:
    parts, start = [], 0
    for kind in kinds:
        if kind == "field":
            parts.append("B = [" + ", ".join(f"{v * 1e3:.4g}" for v in rows[start:start + 3])
                         + "] mT")
            start += 3
        elif kind == "gradient":
            parts.append("gradient (" + ", ".join(GRADIENT_TERMS) + ") = ["
                         + ", ".join(f"{v * 1e3:.4g}" for v in rows[start:start + 5]) + "] mT/m")
            start += 5
        else:
            parts.append("F = [" + ", ".join(f"{v * 1e6:.4g}" for v in rows[start:start + 3])
                         + "] uN")
            start += 3
    return ", ".join(parts)


def allocate(model: FieldModel, point_m: ArrayLike, field_T: ArrayLike, *,
             gradient_T_per_m: ArrayLike | None = None, force_N: ArrayLike | None = None,
             moment_Am2: ArrayLike | None = None, current_limits_A: ArrayLike | None = None,
             weights: ArrayLike | None = None) -> Allocation:
    """Minimum-norm currents making `field_T` (3,) and optionally the five gradient terms
    `gradient_T_per_m` (5,) (order `GRADIENT_TERMS`) or the force `force_N` (3,) on a dipole of
    `moment_Am2` (3,) at `point_m` (3,) m.

    `current_limits_A`: one limit per coil (or one for all), |I_k| <= limit_k; None: no limit.
    `weights`: per-row weights (3, 8 or 6 entries, in the rows' order) replacing the default
    1 / (size of each block's request).

    Raises LimitError when the rig cannot make the request (the message says what it can make)
    or when a current limit would be exceeded; ValueError on inconsistent arguments.
    """
    if gradient_T_per_m is not None and force_N is not None:
        raise ValueError("ask for a gradient or for a force, not both")
    if (force_N is None) != (moment_Am2 is None):
        raise ValueError("a force request needs the dipole's moment_Am2, and only it")
    point = np.asarray(point_m, dtype=float).reshape(3)
    n = model.n_coils
    moment = np.zeros(3)
    if gradient_T_per_m is not None:
        if n < 8:
            raise LimitError(f"{n} coils cannot set field and gradient (8 independent terms) "
                             "at a point: 8 coils at least")
        mode, kinds = MODE_GRADIENT, ["field", "gradient"]
        asked = np.concatenate([np.asarray(field_T, dtype=float).reshape(3),
                                np.asarray(gradient_T_per_m, dtype=float).reshape(5)])
    elif force_N is not None:
        mode, kinds = MODE_FORCE, ["field", "force"]
        asked = np.concatenate([np.asarray(field_T, dtype=float).reshape(3),
                                np.asarray(force_N, dtype=float).reshape(3)])
        moment = np.asarray(moment_Am2, dtype=float).reshape(3)
    else:
        mode, kinds = MODE_FIELD, ["field"]
        asked = np.asarray(field_T, dtype=float).reshape(3)
    w = np.empty(0) if weights is None else np.asarray(weights, dtype=float).reshape(len(asked))
    per_A = model.field_and_gradient_per_ampere(point[None, :])[0]
    currents, made, M, off_rows, bad = _solve(per_A, mode, asked, moment, w)
    if bad:
        raise LimitError(f"this rig cannot make {_describe(asked, kinds)} at {_mm(point)}; the "
                         f"nearest it makes is {_describe(M @ currents + off_rows, kinds)}")
    if current_limits_A is not None:
        limits = np.broadcast_to(np.asarray(current_limits_A, dtype=float), (n,))
        ratio = np.abs(currents) / limits
        worst = int(np.argmax(ratio))
        if ratio[worst] > 1.0 + LIMIT_RTOL:
            # currents are linear in the request above the offset: 1/ratio of it fits
            raise LimitError(
                f"{_describe(asked, kinds)} at {_mm(point)} needs {currents[worst]:.4g} A in coil "
                f"{model.coil_names[worst]} (limit {limits[worst]:.4g} A); within the limits "
                f"this rig makes {1.0 / ratio[worst]:.1%} of it above the offset: "
                f"{_describe(off_rows + (asked - off_rows) / ratio[worst], kinds)}")
    return Allocation(currents_A=currents, made=made)


MODE_FIELD, MODE_GRADIENT, MODE_FORCE = 0, 1, 2


@njit()
def _solve(per_A, mode, asked, moment, weights):
    """The numbers of `allocate` in one compiled call: (currents (N,), made U (8,), the rows M
    (k, N), the offset's rows (k,), whether the request is out of reach)."""
    n = per_A.shape[0] - 1
    a8 = np.empty((8, n + 1))
    for c in range(n + 1):
        for i in range(3):
            a8[i, c] = per_A[c, i]
        a8[3, c] = per_A[c, 3]  # G00
        a8[4, c] = per_A[c, 4]  # G01
        a8[5, c] = per_A[c, 5]  # G02
        a8[6, c] = per_A[c, 7]  # G11
        a8[7, c] = per_A[c, 8]  # G12
    k = asked.shape[0]
    rows = np.empty((k, n + 1))  # the asked rows, offset in the last column
    rows[0:3] = a8[0:3]
    scale = np.empty(k)
    field_size = max(np.sqrt(asked[0] ** 2 + asked[1] ** 2 + asked[2] ** 2), FIELD_FLOOR_T)
    scale[0:3] = field_size
    if mode == MODE_GRADIENT:
        rows[3:8] = a8[3:8]
        scale[3:8] = max(np.sqrt(np.sum(asked[3:8] ** 2)), GRADIENT_FLOOR_T_PER_M)
    elif mode == MODE_FORCE:
        # F = G m with G symmetric: rows of the five terms (seed 003 wrench map, force part)
        mx, my, mz = moment[0], moment[1], moment[2]
        rows[3] = mx * a8[3] + my * a8[4] + mz * a8[5]
        rows[4] = mx * a8[4] + my * a8[6] + mz * a8[7]
        rows[5] = mx * a8[5] + my * a8[7] - mz * (a8[3] + a8[6])
        scale[3:6] = max(np.sqrt(np.sum(asked[3:6] ** 2)), FORCE_FLOOR_N)
    w = 1.0 / scale if weights.shape[0] == 0 else weights
    M = np.ascontiguousarray(rows[:, 0:n])
    off_rows = rows[:, n].copy()
    Mw = M * w.reshape(-1, 1)
    bw = (asked - off_rows) * w
    u, s, vt = np.linalg.svd(Mw, full_matrices=False)
    ub = u.T @ bw
    currents = np.zeros(n)
    for i in range(s.shape[0]):
        if s[i] > RANK_RCOND * s[0]:
            currents += vt[i] * (ub[i] / s[i])
    residual = np.max(np.abs(Mw @ currents - bw))
    bad = residual > RESIDUAL_RTOL * max(1.0, np.max(np.abs(bw)))
    made = a8[:, n].copy()
    for c in range(n):
        made += a8[:, c] * currents[c]
    return currents, made, M, off_rows, bad


def _mm(point_m: np.ndarray) -> str:
    return "(" + ", ".join(f"{v * 1e3:.4g}" for v in point_m) + ") mm"
