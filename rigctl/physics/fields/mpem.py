"""The Multipole Electromagnet Model (MPEM; Petruska, Edelmann, Nelson, "Model-Based Calibration
for Magnetic Manipulation", IEEE Trans. Magn. 53(7), 2017).

Each coil's field per ampere is the negative gradient of a sum of axisymmetric scalar potentials,
one per *source* s at position p_s with unit direction z_s. With d = x - p_s, r = |d|,
u = d / r and c = u . z_s (the cosine of the angle to the source's axis), a source of order n is

    Phi = A_n r^n P_n(c)                 (an "A" source: regular everywhere, a field made far
                                          away, e.g. order 1 is a uniform field -A_1 z_s)
    Phi = B_n r^-(n+1) P_n(c)            (a "B" source: singular at p_s; order 1 is a dipole of
                                          moment 4 pi B_1 / mu0 along z_s)

with P_n the Legendre polynomial, and B = -grad Phi: Phi is in T m, so A_n is in T m^(1-n) and
B_n in T m^(n+2), per ampere of the coil's current (no mu0 appears; the Offset's without the
ampere). Both are solid harmonics, so the field is curl- and
divergence-free away from the B sources' positions. This is mag_manip's `ScalorPotential`: a
source's coefficient list [c_1, c_2, ...] holds orders 1, 2, ...; a source has A or B
coefficients, never both.

Field and gradient in closed form. Write a source's potential as f(r) P(c) summed over its
orders. With v = grad c = (z - c u) / r:

    grad Phi = alpha u + beta z,    alpha = f' P - (f / r) c P',   beta = (f / r) P'
    B = -(alpha u + beta z)
    G = dB/dx = -(u (grad alpha)^T + alpha (I - u u^T) / r + z (grad beta)^T)
    grad g(r, c) = g_r u + g_c v     for g = alpha, beta

For A sources f = A r^n (f' = n A r^(n-1), f'' = n (n-1) A r^(n-2), f/r = A r^(n-1)); for B
sources f = B r^-(n+1). At an A source's own position (r = 0) u is undefined and the limits are
used: order 1 gives B = -A z, order 2 gives G = -A (3 z z^T - I), higher orders nothing. At a B
source's own position the field diverges: NaN (mag_manip silently skips the source there).

The kernel (numba, `rigctl.core.jit`) evaluates every source once per point, sums its orders into
alpha, beta and their derivatives (the Legendre values by Bonnet's recurrence), and adds the
source's field and gradient into its coil's column; the `Offset` pseudo-coil is column N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.jit import njit
from rigctl.physics.fields.model import FieldModel

KIND_A, KIND_B = 0, 1


@dataclass(frozen=True)
class Source:
    """One multipole source: position (m), direction (normalised when the model is built),
    kind ("A" or "B") and coefficients of orders 1, 2, ... (T m^(1-n) / A for A, T m^(n+2) / A
    for B; for the Offset the same without the ampere)."""

    position_m: tuple[float, float, float]
    direction: tuple[float, float, float]
    kind: str
    coefficients: tuple[float, ...]


@njit()
def _add_source(px, py, pz, s, positions, directions, kinds, coeff_start, coeffs, scale, out):
    """Add `scale` times source s's field (out[0:3]) and row-major gradient (out[3:12]) at the
    point (px, py, pz) m into `out`."""
    dx = px - positions[s, 0]
    dy = py - positions[s, 1]
    dz = pz - positions[s, 2]
    zx, zy, zz = directions[s, 0], directions[s, 1], directions[s, 2]
    first, last = coeff_start[s], coeff_start[s + 1]
    r = np.sqrt(dx * dx + dy * dy + dz * dz)
    if r == 0.0:
        if kinds[s] == KIND_B:
            for k in range(12):
                out[k] = np.nan
            return
        a1 = coeffs[first] * scale
        out[0] -= a1 * zx
        out[1] -= a1 * zy
        out[2] -= a1 * zz
        if last - first >= 2:
            a2 = coeffs[first + 1] * scale
            z3 = (zx, zy, zz)
            for i in range(3):
                for j in range(3):
                    out[3 + 3 * i + j] -= a2 * (3.0 * z3[i] * z3[j] - (1.0 if i == j else 0.0))
        return
    inv_r = 1.0 / r
    ux, uy, uz = dx * inv_r, dy * inv_r, dz * inv_r
    c = ux * zx + uy * zy + uz * zz
    # Legendre P_n, P_n', P_n'' by Bonnet's recurrence, from order 0 and 1
    p_prev, p_cur = 1.0, c
    d_prev, d_cur = 0.0, 1.0
    s_prev, s_cur = 0.0, 0.0
    alpha = 0.0
    alpha_r = 0.0
    alpha_c = 0.0
    beta = 0.0
    beta_r = 0.0
    beta_c = 0.0
    for k in range(first, last):
        n = k - first + 1
        if n > 1:  # step the recurrence from order n-1 to n
            m = n - 1.0
            p_next = ((2.0 * m + 1.0) * c * p_cur - m * p_prev) / (m + 1.0)
            d_next = d_prev + (2.0 * m + 1.0) * p_cur
            s_next = s_prev + (2.0 * m + 1.0) * d_cur
            p_prev, p_cur = p_cur, p_next
            d_prev, d_cur = d_cur, d_next
            s_prev, s_cur = s_cur, s_next
        a = coeffs[k] * scale
        if kinds[s] == KIND_A:  # f = a r^n
            f_over_r = a * r ** (n - 1)
            f1 = n * f_over_r
            f2 = n * (n - 1.0) * a * r ** (n - 2) if n >= 2 else 0.0
            f_over_r_1 = (n - 1.0) * a * r ** (n - 2) if n >= 2 else 0.0
        else:  # f = a r^-(n+1)
            f_over_r = a * r ** (-n - 2)
            f1 = -(n + 1.0) * f_over_r
            f2 = (n + 1.0) * (n + 2.0) * a * r ** (-n - 3)
            f_over_r_1 = -(n + 2.0) * a * r ** (-n - 3)
        alpha += f1 * p_cur - f_over_r * c * d_cur
        alpha_r += f2 * p_cur - f_over_r_1 * c * d_cur
        alpha_c += f1 * d_cur - f_over_r * (d_cur + c * s_cur)
        beta += f_over_r * d_cur
        beta_r += f_over_r_1 * d_cur
        beta_c += f_over_r * s_cur
    u3 = (ux, uy, uz)
    z3 = (zx, zy, zz)
    v3 = ((zx - c * ux) * inv_r, (zy - c * uy) * inv_r, (zz - c * uz) * inv_r)
    for i in range(3):
        out[i] -= alpha * u3[i] + beta * z3[i]
        for j in range(3):
            g_alpha = alpha_r * u3[j] + alpha_c * v3[j]
            g_beta = beta_r * u3[j] + beta_c * v3[j]
            proj = ((1.0 if i == j else 0.0) - u3[i] * u3[j]) * inv_r
            out[3 + 3 * i + j] -= u3[i] * g_alpha + alpha * proj + z3[i] * g_beta


@njit()
def _mpem_kernel(points, positions, directions, kinds, coil_of, coeff_start, coeffs, n_columns):
    """(P, n_columns, 12): field (3) and row-major gradient (9) per column (coil) per point."""
    out = np.zeros((points.shape[0], n_columns, 12))
    for q in range(points.shape[0]):
        for s in range(positions.shape[0]):
            _add_source(points[q, 0], points[q, 1], points[q, 2], s, positions, directions,
                        kinds, coeff_start, coeffs, 1.0, out[q, coil_of[s]])
    return out


@njit()
def _mpem_total(point, currents, positions, directions, kinds, coil_of, coeff_start, coeffs):
    """(12,): field and row-major gradient at one point for `currents`, offset included (the
    columns past the currents, i.e. the offset's, count once)."""
    out = np.zeros(12)
    n = currents.shape[0]
    for s in range(positions.shape[0]):
        col = coil_of[s]
        _add_source(point[0], point[1], point[2], s, positions, directions, kinds, coeff_start,
                    coeffs, currents[col] if col < n else 1.0, out)
    return out


class MPEM(FieldModel):
    """A multipole electromagnet model: per coil a list of `Source`s, and an optional offset.

    Parameters
    ----------
    coil_names : sequence of str
        The coils in the currents' order (mag_manip's `Coil_List` without the Offset).
    coil_sources : sequence of sequences of Source
        The sources of each coil, same order.
    offset_sources : sequence of Source
        The Offset pseudo-coil's sources (empty: no offset).
    name : str
        The system's name (`System_Name`).
    workspace_m : ((xmin, xmax), (ymin, ymax), (zmin, zmax)) in m
        Where the calibration holds (`Workspace_Dimensions`).
    """

    def __init__(self, coil_names, coil_sources, offset_sources=(), *, name: str = "MPEM",
                 workspace_m=((-0.1, 0.1), (-0.1, 0.1), (-0.1, 0.1))) -> None:
        if len(coil_names) != len(coil_sources):
            raise ValueError(f"{len(coil_names)} coil names for {len(coil_sources)} source lists")
        self.coil_names = tuple(coil_names)
        self.coil_sources = tuple(tuple(s) for s in coil_sources)
        self.offset_sources = tuple(offset_sources)
        self.name = name
        self.workspace_m = tuple(tuple(float(v) for v in pair) for pair in workspace_m)
        self._pack()

    def _pack(self) -> None:
        """Flat arrays for the kernel, sources in file order, coil index per source."""
        every = [(k, s) for k, sources in enumerate(self.coil_sources) for s in sources]
        every += [(self.n_coils, s) for s in self.offset_sources]
        for _, s in every:
            if s.kind not in ("A", "B") or not s.coefficients:
                raise ValueError(f"a source needs kind 'A' or 'B' and coefficients, got {s}")
        self._positions = np.array([s.position_m for _, s in every], dtype=float).reshape(-1, 3)
        directions = np.array([s.direction for _, s in every], dtype=float).reshape(-1, 3)
        norms = np.linalg.norm(directions, axis=1)
        if not np.all(np.isfinite(norms) & (norms > 0)):
            raise ValueError("every source direction must be a finite non-zero vector")
        self._directions = directions / norms[:, None]
        self._kinds = np.array([KIND_A if s.kind == "A" else KIND_B for _, s in every],
                               dtype=np.int64)
        self._coil_of = np.array([k for k, _ in every], dtype=np.int64)
        lengths = [len(s.coefficients) for _, s in every]
        self._coeff_start = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        self._coeffs = np.array([c for _, s in every for c in s.coefficients], dtype=float)

    @property
    def has_offset(self) -> bool:
        return bool(self.offset_sources)

    @property
    def max_order(self) -> int:
        return max(len(s.coefficients) for sources in (*self.coil_sources, self.offset_sources)
                   for s in sources)

    def field_and_gradient_per_ampere(self, points_m: np.ndarray) -> np.ndarray:
        points = np.ascontiguousarray(points_m, dtype=float)
        return _mpem_kernel(points, self._positions, self._directions, self._kinds,
                            self._coil_of, self._coeff_start, self._coeffs, self.n_coils + 1)

    def field_and_gradient(self, points_m: ArrayLike, currents_A: ArrayLike
                           ) -> tuple[np.ndarray, np.ndarray]:
        """As `FieldModel.field_and_gradient`; one point is summed in the kernel (the 1 kHz
        stream's case: no per-coil columns formed)."""
        point = np.asarray(points_m, dtype=float)
        if point.shape != (3,):
            return super().field_and_gradient(points_m, currents_A)
        total = _mpem_total(point, self._currents(currents_A), self._positions,
                            self._directions, self._kinds, self._coil_of, self._coeff_start,
                            self._coeffs)
        return total[0:3], total[3:12].reshape(3, 3)

    def in_workspace(self, points_m: ArrayLike) -> np.ndarray:
        """Whether each point (P, 3) m lies in the calibrated workspace (bool (P,))."""
        points = np.asarray(points_m, dtype=float).reshape(-1, 3)
        lo = np.array([pair[0] for pair in self.workspace_m])
        hi = np.array([pair[1] for pair in self.workspace_m])
        return np.all((points >= lo) & (points <= hi), axis=1)
