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
from rigctl.physics.fields.model import FieldModel
from rigctl.physics.magnetics import GRADIENT_TERMS, wrench_map

FIELD_FLOOR_T = 1e-3
"""The field scale of a request for zero field (1 mT: the size of fields these rigs make)."""

GRADIENT_FLOOR_T_PER_M = 1e-2
"""The gradient scale of a request for zero gradient (10 mT/m)."""

FORCE_FLOOR_N = 1e-6
"""The force scale of a request for zero force (1 uN)."""

RESIDUAL_RTOL = 1e-6
"""Largest weighted residual accepted (the weights make each block of order one)."""

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


def _block_scale(value: np.ndarray, floor: float) -> float:
    return max(float(np.linalg.norm(value)), floor)


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
    field = np.asarray(field_T, dtype=float).reshape(3)
    n = model.n_coils
    per_A = model.field_and_gradient_per_ampere(point[None, :])[0]  # (N + 1, 12)
    a8 = np.empty((8, n + 1))
    a8[0:3] = per_A[:, 0:3].T
    a8[3:6] = per_A[:, 3:6].T  # G00, G01, G02
    a8[6:8] = per_A[:, 7:9].T  # G11, G12
    A, off = a8[:, :n], a8[:, n]
    if gradient_T_per_m is not None:
        if n < 8:
            raise LimitError(f"{n} coils cannot set field and gradient (8 independent terms) "
                             "at a point: 8 coils at least")
        grad = np.asarray(gradient_T_per_m, dtype=float).reshape(5)
        M, asked, off_rows = A, np.concatenate([field, grad]), off
        kinds = ["field", "gradient"]
        scale = np.repeat([_block_scale(field, FIELD_FLOOR_T),
                           _block_scale(grad, GRADIENT_FLOOR_T_PER_M)], [3, 5])
    elif force_N is not None:
        force = np.asarray(force_N, dtype=float).reshape(3)
        S = wrench_map(np.asarray(moment_Am2, dtype=float).reshape(3))[0:3]  # (3, 8)
        M = np.concatenate([A[0:3], S @ A])
        asked, off_rows = np.concatenate([field, force]), np.concatenate([off[0:3], S @ off])
        kinds = ["field", "force"]
        scale = np.repeat([_block_scale(field, FIELD_FLOOR_T),
                           _block_scale(force, FORCE_FLOOR_N)], [3, 3])
    else:
        M, asked, off_rows = A[0:3], field, off[0:3]
        kinds = ["field"]
        scale = np.full(3, _block_scale(field, FIELD_FLOOR_T))
    b = asked - off_rows
    w = 1.0 / scale if weights is None else np.asarray(weights, dtype=float).reshape(len(b))
    Mw, bw = M * w[:, None], b * w
    u, s, vt = np.linalg.svd(Mw, full_matrices=False)
    keep = s > RANK_RCOND * s[0]
    currents = vt[keep].T @ ((u.T @ bw)[keep] / s[keep])
    residual = Mw @ currents - bw
    if np.max(np.abs(residual)) > RESIDUAL_RTOL * max(1.0, float(np.max(np.abs(bw)))):
        raise LimitError(f"this rig cannot make {_describe(asked, kinds)} at {_mm(point)}; the "
                         f"nearest it makes is {_describe(M @ currents + off_rows, kinds)}")
    if current_limits_A is not None:
        limits = np.broadcast_to(np.asarray(current_limits_A, dtype=float), (n,))
        ratio = np.abs(currents) / limits
        worst = int(np.argmax(ratio))
        if ratio[worst] > 1.0:
            # currents are linear in the request above the offset: 1/ratio of it fits
            raise LimitError(
                f"{_describe(asked, kinds)} at {_mm(point)} needs {currents[worst]:.4g} A in coil "
                f"{model.coil_names[worst]} (limit {limits[worst]:.4g} A); within the limits "
                f"this rig makes {1.0 / ratio[worst]:.1%} of it above the offset: "
                f"{_describe(off_rows + b / ratio[worst], kinds)}")
    return Allocation(currents_A=currents, made=A @ currents + off)


def _mm(point_m: np.ndarray) -> str:
    return "(" + ", ".join(f"{v * 1e3:.4g}" for v in point_m) + ") mm"
