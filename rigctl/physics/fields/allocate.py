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
def _dot(a, i, j, n):
    total = 0.0
    for c in range(n):
        total += a[i, c] * a[j, c]
    return total


@njit()
def _min_norm_solution(M, b):
    """pinv(M) b for M (k, N), k <= N small, by one-sided Jacobi (Hestenes) SVD.

    Rotating pairs of M's rows until they are orthogonal gives X = V^T M with V (k, k)
    orthogonal, so M = V X: the singular values are X's row norms, the left singular vectors
    V's columns, the right ones X's normalised rows, and pinv(M) b =
    sum_i X_i (V_i . b) / |X_i|^2 over the singular values above RANK_RCOND times the largest.
    Written in scalar loops: numba's np.linalg.svd (LAPACK) takes tens of seconds to compile.
    """
    k, n = M.shape
    X = M.copy()
    V = np.eye(k)
    for _sweep in range(60):
        rotated = False
        for i in range(k - 1):
            for j in range(i + 1, k):
                alpha = _dot(X, i, i, n)
                beta = _dot(X, j, j, n)
                gamma = _dot(X, i, j, n)
                if gamma == 0.0 or abs(gamma) <= 1e-15 * np.sqrt(alpha * beta):
                    continue
                rotated = True
                zeta = (beta - alpha) / (2.0 * gamma)
                t = (1.0 if zeta >= 0 else -1.0) / (abs(zeta) + np.sqrt(1.0 + zeta * zeta))
                c = 1.0 / np.sqrt(1.0 + t * t)
                s = c * t
                for q in range(n):
                    xi, xj = X[i, q], X[j, q]
                    X[i, q], X[j, q] = c * xi - s * xj, s * xi + c * xj
                for q in range(k):
                    vi, vj = V[q, i], V[q, j]
                    V[q, i], V[q, j] = c * vi - s * vj, s * vi + c * vj
        if not rotated:
            break
    largest = 0.0
    for i in range(k):
        largest = max(largest, _dot(X, i, i, n))
    out = np.zeros(n)
    for i in range(k):
        sq = _dot(X, i, i, n)
        if sq > 0.0 and sq > (RANK_RCOND * RANK_RCOND) * largest:
            vb = 0.0
            for q in range(k):
                vb += V[q, i] * b[q]
            for q in range(n):
                out[q] += X[i, q] * (vb / sq)
    return out


@njit()
def _norm(values, first, last):
    total = 0.0
    for i in range(first, last):
        total += values[i] * values[i]
    return np.sqrt(total)


@njit()
def _eight_rows(per_A):
    """U's eight rows per coil (and the offset's, last column) from the field and the full
    gradient per ampere: Bx, By, Bz, then the five gradient terms G00 G01 G02 G11 G12."""
    n = per_A.shape[0] - 1
    a8 = np.empty((8, n + 1))
    for c in range(n + 1):
        for i in range(6):  # Bx, By, Bz, G00, G01, G02
            a8[i, c] = per_A[c, i]
        a8[6, c] = per_A[c, 7]  # G11
        a8[7, c] = per_A[c, 8]  # G12
    return a8


@njit()
def _asked_rows(a8, mode, moment, k):
    """The rows of what is asked (field; field and gradient; field and force on `moment`)."""
    rows = np.empty((k, a8.shape[1]))  # the asked rows, the offset in the last column
    for c in range(a8.shape[1]):
        for i in range(3):
            rows[i, c] = a8[i, c]
        if mode == MODE_GRADIENT:
            for i in range(3, 8):
                rows[i, c] = a8[i, c]
        elif mode == MODE_FORCE:
            # F = G m, G symmetric and traceless in its five terms (the wrench map's force rows)
            mx, my, mz = moment[0], moment[1], moment[2]
            rows[3, c] = mx * a8[3, c] + my * a8[4, c] + mz * a8[5, c]
            rows[4, c] = mx * a8[4, c] + my * a8[6, c] + mz * a8[7, c]
            rows[5, c] = mx * a8[5, c] + my * a8[7, c] - mz * (a8[3, c] + a8[6, c])
    return rows


@njit()
def _row_scales(asked, mode, k):
    """Each row's size: a block's rows are weighted by 1 / (the size of that block's request)."""
    scale = np.empty(k)
    field_size = max(_norm(asked, 0, 3), FIELD_FLOOR_T)
    for i in range(3):
        scale[i] = field_size
    if mode == MODE_GRADIENT:
        size = max(_norm(asked, 3, 8), GRADIENT_FLOOR_T_PER_M)
        for i in range(3, 8):
            scale[i] = size
    elif mode == MODE_FORCE:
        size = max(_norm(asked, 3, 6), FORCE_FLOOR_N)
        for i in range(3, 6):
            scale[i] = size
    return scale


@njit()
def _solve(per_A, mode, asked, moment, weights):
    """The numbers of `allocate` in one compiled call: (currents (N,), made U (8,), the rows M
    (k, N), the offset's rows (k,), whether the request is out of reach). Scalar loops only:
    numba compiles array expressions slowly (seconds of CPU each)."""
    n = per_A.shape[0] - 1
    a8 = _eight_rows(per_A)
    k = asked.shape[0]
    rows = _asked_rows(a8, mode, moment, k)
    scale = _row_scales(asked, mode, k)
    M = np.empty((k, n))
    Mw = np.empty((k, n))
    off_rows = np.empty(k)
    bw = np.empty(k)
    for i in range(k):
        w = 1.0 / scale[i] if weights.shape[0] == 0 else weights[i]
        off_rows[i] = rows[i, n]
        bw[i] = (asked[i] - off_rows[i]) * w
        for c in range(n):
            M[i, c] = rows[i, c]
            Mw[i, c] = rows[i, c] * w
    currents = _min_norm_solution(Mw, bw)
    residual, size = 0.0, 1.0
    for i in range(k):
        made_i = 0.0
        for c in range(n):
            made_i += Mw[i, c] * currents[c]
        residual = max(residual, abs(made_i - bw[i]))
        size = max(size, abs(bw[i]))
    made = np.empty(8)
    for i in range(8):
        made[i] = a8[i, n]
        for c in range(n):
            made[i] += a8[i, c] * currents[c]
    return currents, made, M, off_rows, residual > RESIDUAL_RTOL * size


def _mm(point_m: np.ndarray) -> str:
    return "(" + ", ".join(f"{v * 1e3:.4g}" for v in point_m) + ") mm"
