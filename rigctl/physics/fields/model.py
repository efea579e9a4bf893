"""One interface for the field an electromagnet rig makes: `FieldModel`.

Air-core and unsaturated iron-core electromagnets add linearly, so at a point p the flux density
and its spatial gradient are affine in the coil currents I (N of them, in the file's or rig's
coil order):

    B(p) = A_B(p) I + B_off(p)          (3,)   T
    G(p) = A_G(p) I + G_off(p)          (3, 3) T/m,  G[i, j] = dB_i / dx_j

with B_off, G_off the current-independent part (mag_manip's `Offset` pseudo-coil: remanence of
the cores, the earth's field). Outside the windings and cores B is curl- and divergence-free, so
G is symmetric and traceless and five terms carry it all. They are, in this order, the five of
`rigctl.physics.magnetics.GRADIENT_TERMS` and of mag_manip's `Gradient5Vec`
(`remapSecondDerivativeMat`):

    dBx/dx, dBx/dy, dBx/dz, dBy/dy, dBy/dz

and the 8 x N actuation matrix stacks the field rows (Bx, By, Bz) on those five, as
`rigctl.physics.magnetics.U_COMPONENTS` and mag_manip's `getActuationMatrix` do.

A model implements one method, `field_and_gradient_per_ampere(points_m)`, which gives every
coil's field and gradient per ampere and the offset's at once; everything else is derived here,
batched over points (shape (P, 3), or (3,) for one point, which drops the point axis).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
from numpy.typing import ArrayLike

from rigctl.physics.magnetics import GRADIENT_TERMS, U_COMPONENTS, gradient_terms

__all__ = ["FieldModel", "GRADIENT_TERMS", "U_COMPONENTS", "points_array"]


def points_array(points_m: ArrayLike) -> tuple[np.ndarray, bool]:
    """(P, 3) float array of the points and whether a single (3,) point was given."""
    points = np.asarray(points_m, dtype=float)
    if points.shape == (3,):
        return points[None, :], True
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points_m must have shape (3,) or (P, 3), got {points.shape}")
    return points, False


class FieldModel(ABC):
    """The field of N coils and a current-independent offset, per ampere, at any points.

    Attributes
    ----------
    coil_names : tuple[str, ...]
        The coils in the currents' order.
    """

    coil_names: tuple[str, ...]

    @property
    def n_coils(self) -> int:
        return len(self.coil_names)

    @abstractmethod
    def field_and_gradient_per_ampere(self, points_m: np.ndarray) -> np.ndarray:
        """Every coil's field and gradient per ampere, and the offset's, at `points_m` (P, 3) m.

        Returns
        -------
        np.ndarray, shape (P, N + 1, 12)
            [..., k, 0:3] the field (T/A) of coil k, [..., k, 3:12] its gradient G (T/m/A,
            row-major, G[i, j] = dB_i/dx_j); k = N is the offset (T and T/m, no ampere).
        """

    # ------------------------------------------------------------------ derived, batched
    def _evaluate(self, points_m: ArrayLike) -> tuple[np.ndarray, bool]:
        points, single = points_array(points_m)
        return self.field_and_gradient_per_ampere(points), single

    def _currents(self, currents_A: ArrayLike) -> np.ndarray:
        currents = np.asarray(currents_A, dtype=float)
        if currents.shape != (self.n_coils,):
            raise ValueError(f"{self.n_coils} currents needed (one per coil, in the order "
                             f"{', '.join(self.coil_names)}), got shape {currents.shape}")
        return currents

    def field(self, points_m: ArrayLike, currents_A: ArrayLike) -> np.ndarray:
        """B (T), shape (P, 3) (or (3,) for one point), for coil currents (N,) in A, offset
        included."""
        per_A, single = self._evaluate(points_m)
        out = per_A[:, :-1, 0:3].transpose(0, 2, 1) @ self._currents(currents_A) + per_A[:, -1, 0:3]
        return out[0] if single else out

    def gradient(self, points_m: ArrayLike, currents_A: ArrayLike) -> np.ndarray:
        """G (T/m), shape (P, 3, 3) (or (3, 3)), G[i, j] = dB_i/dx_j, offset included."""
        per_A, single = self._evaluate(points_m)
        flat = per_A[:, :-1, 3:].transpose(0, 2, 1) @ self._currents(currents_A) + per_A[:, -1, 3:]
        out = flat.reshape(-1, 3, 3)
        return out[0] if single else out

    def field_and_gradient(self, points_m: ArrayLike, currents_A: ArrayLike
                           ) -> tuple[np.ndarray, np.ndarray]:
        """(B (P, 3) T, G (P, 3, 3) T/m) in one evaluation; (3,) and (3, 3) for one point."""
        per_A, single = self._evaluate(points_m)
        both = per_A[:, :-1, :].transpose(0, 2, 1) @ self._currents(currents_A) + per_A[:, -1, :]
        field, grad = both[:, 0:3], both[:, 3:].reshape(-1, 3, 3)
        return (field[0], grad[0]) if single else (field, grad)

    def actuation(self, points_m: ArrayLike) -> np.ndarray:
        """The 8 x N actuation matrix (rows `U_COMPONENTS`: T/A then T/m/A) at each point,
        shape (P, 8, N) (or (8, N)); its first three rows are the 3 x N field actuation matrix."""
        per_A, single = self._evaluate(points_m)
        coils = per_A[:, :-1, :]
        out = np.concatenate([coils[:, :, 0:3], gradient_terms(
            coils[:, :, 3:].reshape(coils.shape[0], coils.shape[1], 3, 3))], axis=-1)
        out = out.transpose(0, 2, 1)
        return out[0] if single else out

    def field_actuation(self, points_m: ArrayLike) -> np.ndarray:
        """The 3 x N field actuation matrix (T/A), shape (P, 3, N) (or (3, N))."""
        return self.actuation(points_m)[..., 0:3, :]

    def offset(self, points_m: ArrayLike) -> np.ndarray:
        """The current-independent part as an 8-vector (T, T/m; `U_COMPONENTS`), shape (P, 8)
        (or (8,)); zero for a model without one."""
        per_A, single = self._evaluate(points_m)
        off = per_A[:, -1, :]
        out = np.concatenate([off[:, 0:3], gradient_terms(off[:, 3:].reshape(-1, 3, 3))], axis=-1)
        return out[0] if single else out
