"""Fit an MPEM (`rigctl.physics.fields.mpem`) to Hall-probe samples.

Data: the probe's points (K, 3) m, the coil currents of each drive pattern (P, N) A (the supplies'
measured currents), and the fields read (P, K, 3) T. The model is B = sum_j I_j B_j(x) + B_off(x),
linear in every source's coefficients, non-linear in the sources' positions and directions. So:

1. Starting values: the caller's start model gives each coil's sources' kinds, positions and
   directions (`start_from_loops`: one B source, a dipole, at each drawn coil's centre along its
   axis); the coefficients are not taken from it but solved for by linear least squares with the
   geometry fixed, up to the order asked (1 to 3). The offset is a uniform field (three A sources
   of order 1 along x, y, z at the workspace centre, geometry fixed): the ambient field and the
   cores' remanence as far as they are uniform.
2. Everything at once, by `scipy.optimize.least_squares` (trust-region reflective, 2-point
   finite-difference Jacobian, residuals scaled by the RMS field so that the tolerances are
   relative): every coefficient, every coil source's position (3) and direction (2 tilt angles
   about the starting direction, as `rigctl.rigs.six_coil.field_fit` tilts a loop's axis).

`held_out_error` reports the fit's error on samples it did not see, in mT and in % of the mean
field magnitude there.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from rigctl.core.errors import ConfigError
from rigctl.physics.fields.loops import LoopModel
from rigctl.physics.fields.mpem import KIND_A, KIND_B, MPEM, Source, _mpem_kernel
from rigctl.physics.magnetics import MU0

ORDERS = (1, 2, 3)


@dataclass(frozen=True)
class MpemFit:
    """The fitted model, its RMS residual on the fitted samples (T), the wall time of the fit
    (s) and the number of model evaluations the optimiser made."""

    model: MPEM
    rms_T: float
    duration_s: float
    evaluations: int


def start_from_loops(loops: LoopModel) -> MPEM:
    """Starting geometry from drawn coils: one B source per coil at the loop's centre along its
    axis, with the loop's dipole coefficient mu0 N pi a^2 / (4 pi) per ampere (the fit solves
    the coefficients again)."""
    sources = [[Source(tuple(c), tuple(a), "B", (MU0 * t * np.pi * r * r / (4.0 * np.pi),))]
               for c, a, r, t, _ in loops.loops]
    return MPEM(loops.coil_names, sources, name="start")


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


class _Problem:
    """The packed parameters and the residual of one fit."""

    def __init__(self, start: MPEM, order: int, points: np.ndarray, currents: np.ndarray,
                 fields: np.ndarray, centre: np.ndarray) -> None:
        self.names = start.coil_names
        self.coil_sources = [(k, s) for k, sources in enumerate(start.coil_sources)
                             for s in sources]
        S = len(self.coil_sources)
        self.order = order
        self.points, self.fields = points, fields
        # currents with a column of ones for the offset pseudo-coil
        self.drive = np.concatenate([currents, np.ones((currents.shape[0], 1))], axis=1)
        n = len(self.names)
        self.kinds = np.array([KIND_A if s.kind == "A" else KIND_B for _, s in self.coil_sources]
                              + [KIND_A] * 3, dtype=np.int64)
        self.coil_of = np.array([k for k, _ in self.coil_sources] + [n] * 3, dtype=np.int64)
        self.coeff_start = np.arange(S + 4, dtype=np.int64) * order
        self.pos0 = np.array([s.position_m for _, s in self.coil_sources], dtype=float)
        dirs = np.array([s.direction for _, s in self.coil_sources], dtype=float)
        self.dir0 = dirs / np.linalg.norm(dirs, axis=1)[:, None]
        self.basis = [_perpendicular_basis(d) for d in self.dir0]
        self.offset_pos = np.tile(centre, (3, 1))
        self.n_coeffs = (S + 3) * order
        self.n_sources = S

    def geometry(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        S = self.n_sources
        g = x[self.n_coeffs:].reshape(S, 5)
        positions = self.pos0 + g[:, 0:3]
        dirs = np.array([d + t[0] * e1 + t[1] * e2
                         for d, t, (e1, e2) in zip(self.dir0, g[:, 3:5], self.basis)])
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        return np.concatenate([positions, self.offset_pos]), np.concatenate([dirs, np.eye(3)])

    def coefficients(self, x: np.ndarray) -> np.ndarray:
        """Coefficients, offset's A sources' zeroed above order 1 (a uniform offset)."""
        coeffs = x[:self.n_coeffs].copy()
        off = coeffs[self.n_sources * self.order:].reshape(3, self.order)
        off[:, 1:] = 0.0
        return coeffs

    def predict(self, x: np.ndarray) -> np.ndarray:
        positions, dirs = self.geometry(x)
        per_col = _mpem_kernel(self.points, positions, dirs, self.kinds, self.coil_of,
                               self.coeff_start, self.coefficients(x), len(self.names) + 1)
        return np.einsum("kcj,pc->pkj", per_col[:, :, 0:3], self.drive)

    def linear_coefficients(self) -> np.ndarray:
        """Stage 1: coefficients by linear least squares, geometry at the start."""
        total = self.n_coeffs
        columns = np.empty((self.fields.size, total))
        x = np.zeros(total + 5 * self.n_sources)
        for t in range(total):
            x[:total] = 0.0
            x[t] = 1.0
            columns[:, t] = self.predict(x).ravel()
        offset_higher = [(self.n_sources + k) * self.order + o
                         for k in range(3) for o in range(1, self.order)]
        keep = np.setdiff1d(np.arange(total), offset_higher)
        solution = np.zeros(total)
        solution[keep] = np.linalg.lstsq(columns[:, keep], self.fields.ravel(), rcond=None)[0]
        return solution

    def to_model(self, x: np.ndarray, name: str, workspace: np.ndarray) -> MPEM:
        positions, dirs = self.geometry(x)
        coeffs = self.coefficients(x).reshape(-1, self.order)
        coil_sources: list[list[Source]] = [[] for _ in self.names]
        for s, (k, src) in enumerate(self.coil_sources):
            coil_sources[k].append(Source(tuple(positions[s]), tuple(dirs[s]), src.kind,
                                          tuple(coeffs[s])))
        offset = [Source(tuple(self.offset_pos[i]), tuple(np.eye(3)[i]), "A",
                         (float(coeffs[self.n_sources + i, 0]),)) for i in range(3)]
        return MPEM(self.names, coil_sources, offset, name=name,
                    workspace_m=[(float(lo), float(hi)) for lo, hi in workspace])


def fit_mpem(points_m: np.ndarray, currents_A: np.ndarray, fields_T: np.ndarray, start: MPEM,
             *, order: int = 3, name: str = "rigctl MPEM calibration",
             max_evaluations: int = 4000) -> MpemFit:
    """Fit an MPEM of `order` (1-3) to probe samples, starting from `start`'s geometry.

    points_m (K, 3) m, currents_A (P, N) A, fields_T (P, K, 3) T; the fitted model's workspace is
    the probe points' bounding box. ConfigError if the data cannot determine the model.
    """
    if order not in ORDERS:
        raise ConfigError(f"MPEM order {order}: choose 1, 2 or 3")
    points = np.ascontiguousarray(points_m, dtype=float).reshape(-1, 3)
    currents = np.asarray(currents_A, dtype=float)
    fields = np.asarray(fields_T, dtype=float)
    if currents.ndim != 2 or currents.shape[1] != start.n_coils:
        raise ConfigError(f"currents must be (patterns, {start.n_coils}), got {currents.shape}")
    if fields.shape != (currents.shape[0], points.shape[0], 3):
        raise ConfigError(f"fields must be (patterns, points, 3) = ({currents.shape[0]}, "
                          f"{points.shape[0]}, 3), got {fields.shape}")
    started = time.perf_counter()
    lo, hi = points.min(axis=0), points.max(axis=0)
    problem = _Problem(start, order, points, currents, fields, 0.5 * (lo + hi))
    n_params = problem.n_coeffs + 5 * problem.n_sources
    if fields.size < 2 * n_params:
        raise ConfigError(f"{fields.size} field components cannot fit {n_params} parameters of an "
                          f"order-{order} MPEM: measure more points or patterns")
    scale = float(np.sqrt(np.mean(fields**2)))
    x0 = np.zeros(n_params)
    x0[:problem.n_coeffs] = problem.linear_coefficients()

    def residual(x: np.ndarray) -> np.ndarray:
        return ((problem.predict(x) - fields) / scale).ravel()

    # parameters scaled by the Jacobian's columns: coefficients (1e-7 T m^2/A) and positions
    # (1e-3 m) differ by orders of magnitude
    fit = least_squares(residual, x0, x_scale="jac", method="trf", max_nfev=max_evaluations)
    rms = float(np.sqrt(np.mean(np.sum((fit.fun.reshape(fields.shape) * scale) ** 2, axis=-1))))
    model = problem.to_model(fit.x, name, np.stack([lo, hi], axis=1))
    return MpemFit(model=model, rms_T=rms, duration_s=time.perf_counter() - started,
                   evaluations=int(fit.nfev))


def held_out_error(model: MPEM, points_m: np.ndarray, currents_A: np.ndarray,
                   fields_T: np.ndarray) -> tuple[float, float]:
    """(RMS |B_model - B_measured| in mT, that as % of the mean |B_measured|) over samples
    points (K, 3), currents (P, N), fields (P, K, 3)."""
    per_A = model.field_and_gradient_per_ampere(np.asarray(points_m, dtype=float).reshape(-1, 3))
    currents = np.asarray(currents_A, dtype=float)
    drive = np.concatenate([currents, np.ones((currents.shape[0], 1))], axis=1)
    predicted = np.einsum("kcj,pc->pkj", per_A[:, :, 0:3], drive)
    error = np.sqrt(np.mean(np.sum((predicted - fields_T) ** 2, axis=-1)))
    mean_field = np.mean(np.linalg.norm(fields_T, axis=-1))
    return float(error * 1e3), float(100.0 * error / mean_field)
