"""Fit an MPEM (`rigctl.physics.fields.mpem`) to Hall-probe samples.

Data: the probe's points (K, 3) m, the coil currents of each drive pattern (P, N) A (the supplies'
measured currents), and the fields read (P, K, 3) T. The model is B = sum_j I_j B_j(x) + B_off(x),
linear in every source's coefficients, non-linear in the sources' positions and directions.

Starting values: the caller's start model gives each coil's sources' kinds, positions and
directions (`start_from_loops`: one B source, a dipole, at each drawn coil's centre along its
axis); its coefficients are not used. The offset is a uniform field (three A sources of order 1
along x, y, z at the probe's centre, geometry fixed): the ambient field and the cores'
remanence as far as they are uniform.

Optimiser: `scipy.optimize.least_squares` (trust-region reflective, 2-point finite-difference
Jacobian, x_scale 1 mm and 0.01 rad) over the geometry only, every coil source's position (3)
and direction (2 tilt angles about its starting direction, as `rigctl.rigs.six_coil.field_fit`
tilts a loop's axis), by variable projection: for each geometry the coefficients of every order
up to the one asked (1 to 3) and the offset are the linear least-squares solution (`_Problem`),
and the residual, scaled by the RMS field, is what remains. Solving the linear part exactly
turned a 454 s joint fit of an order-3 octopole into a few seconds.

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
from rigctl.physics.fields.model import FieldModel
from rigctl.physics.fields.mpem import KIND_A, KIND_B, MPEM, Source, _mpem_kernel
from rigctl.physics.magnetics import MU0

ORDERS = (1, 2, 3)


@dataclass(frozen=True)
class MpemFit:
    """The fitted model, its RMS residual on the fitted samples (T), the wall and CPU time of
    the fit (s) and the number of residual evaluations the optimiser made (its finite-difference
    Jacobians not counted)."""

    model: MPEM
    rms_T: float
    duration_s: float
    cpu_s: float
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
    """Variable projection: the residual of a geometry with its best coefficients.

    Every (source, order) pair is a *term* with its own coefficient. For a geometry the kernel
    gives each term's field per unit coefficient U[k, t] (3,) at the probe points; a sample is
    B[p, k] = sum_t D[p, coil(t)] c_t U[k, t] with D the drive (currents, and 1 for the offset).
    Because every pattern is read at the same points, the normal equations factor:
    (D^T D)[coil(t), coil(u)] * (sum_k U[k, t] . U[k, u]) c = sum_k U[k, t] . (D^T B)[coil(t), k],
    so the coefficients of a geometry cost a T x T solve, not a fit over every sample.
    """

    def __init__(self, start: MPEM, order: int, points: np.ndarray, currents: np.ndarray,
                 fields: np.ndarray, centre: np.ndarray) -> None:
        self.names = start.coil_names
        n = len(self.names)
        self.coil_sources = [(k, s) for k, sources in enumerate(start.coil_sources)
                             for s in sources]
        S = len(self.coil_sources)
        self.order, self.n_sources = order, S
        self.points, self.fields = points, fields
        drive = np.concatenate([currents, np.ones((currents.shape[0], 1))], axis=1)  # (P, n+1)
        self.drive = drive
        self.gram_drive = drive.T @ drive  # (n+1, n+1)
        self.drive_fields = np.einsum("pc,pkj->ckj", drive, fields)  # (n+1, K, 3)
        # terms: every source at every order 1..order, then the offset's uniform x, y, z
        self.term_source = np.concatenate([np.repeat(np.arange(S), order), [S, S + 1, S + 2]])
        self.term_order = np.concatenate([np.tile(np.arange(1, order + 1), S), [1, 1, 1]])
        self.term_coil = np.array([self.coil_sources[s][0] if s < S else n
                                   for s in self.term_source], dtype=np.int64)
        T = len(self.term_source)
        self.kinds = np.array([KIND_A if s >= S or self.coil_sources[s][1].kind == "A" else KIND_B
                               for s in self.term_source], dtype=np.int64)
        self.coeff_start = np.concatenate([[0], np.cumsum(self.term_order)]).astype(np.int64)
        unit = np.zeros(int(self.coeff_start[-1]))
        unit[self.coeff_start[1:] - 1] = 1.0  # each term: zeros below its order, 1 at it
        self.unit = unit
        self.columns = np.arange(T, dtype=np.int64)
        self.pos0 = np.array([s.position_m for _, s in self.coil_sources], dtype=float)
        dirs = np.array([s.direction for _, s in self.coil_sources], dtype=float)
        self.dir0 = dirs / np.linalg.norm(dirs, axis=1)[:, None]
        self.basis = [_perpendicular_basis(d) for d in self.dir0]
        self.centre = centre
        self.scale = float(np.sqrt(np.mean(fields**2)))

    def geometry(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions and unit directions of the sources (and the offset's), x = per source
        (dx, dy, dz in m, two tilts in rad)."""
        g = x.reshape(self.n_sources, 5)
        positions = np.concatenate([self.pos0 + g[:, 0:3], np.tile(self.centre, (3, 1))])
        dirs = (self.dir0 + g[:, 3:4] * np.array([e1 for e1, _ in self.basis])
                + g[:, 4:5] * np.array([e2 for _, e2 in self.basis]))
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        return positions, np.concatenate([dirs, np.eye(3)])

    def solve(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(coefficients (T,), predicted fields (P, K, 3)) for geometry x."""
        positions, dirs = self.geometry(x)
        term_pos, term_dir = positions[self.term_source], dirs[self.term_source]
        U = _mpem_kernel(self.points, term_pos, term_dir, self.kinds, self.columns,
                         self.coeff_start, self.unit, len(self.columns))[:, :, 0:3]  # (K, T, 3)
        Uf = U.transpose(1, 0, 2).reshape(len(self.columns), -1)  # (T, K*3)
        normal = self.gram_drive[np.ix_(self.term_coil, self.term_coil)] * (Uf @ Uf.T)
        rhs = np.einsum("tq,tq->t", Uf, self.drive_fields.reshape(self.drive.shape[1], -1)[
            self.term_coil])
        size = np.sqrt(np.diag(normal))
        size[size == 0] = 1.0
        coeffs = np.linalg.lstsq(normal / np.outer(size, size), rhs / size, rcond=1e-12)[0] / size
        per_coil = np.zeros((self.drive.shape[1], Uf.shape[1]))
        np.add.at(per_coil, self.term_coil, coeffs[:, None] * Uf)
        predicted = (self.drive @ per_coil).reshape(self.fields.shape)
        return coeffs, predicted

    def residual(self, x: np.ndarray) -> np.ndarray:
        return ((self.solve(x)[1] - self.fields) / self.scale).ravel()

    def to_model(self, x: np.ndarray, name: str, workspace: np.ndarray) -> MPEM:
        coeffs, _ = self.solve(x)
        positions, dirs = self.geometry(x)
        per_source = coeffs[:self.n_sources * self.order].reshape(self.n_sources, self.order)
        coil_sources: list[list[Source]] = [[] for _ in self.names]
        for s, (k, src) in enumerate(self.coil_sources):
            coil_sources[k].append(Source(tuple(positions[s]), tuple(dirs[s]), src.kind,
                                          tuple(float(c) for c in per_source[s])))
        centre = (float(self.centre[0]), float(self.centre[1]), float(self.centre[2]))
        offset = [Source(centre, tuple(np.eye(3)[i]), "A",
                         (float(coeffs[self.n_sources * self.order + i]),)) for i in range(3)]
        return MPEM(self.names, coil_sources, offset, name=name,
                    workspace_m=[(float(lo), float(hi)) for lo, hi in workspace])


def fit_mpem(points_m: np.ndarray, currents_A: np.ndarray, fields_T: np.ndarray, start: MPEM,
             *, order: int = 3, name: str = "rigctl MPEM calibration",
             max_evaluations: int = 200) -> MpemFit:
    """Fit an MPEM of `order` (1-3) to probe samples, starting from `start`'s geometry (its
    coefficients are not used).

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
    if currents.shape[0] < start.n_coils + 1:
        raise ConfigError(f"{currents.shape[0]} patterns cannot separate {start.n_coils} coils "
                          "and the offset")
    started, started_cpu = time.perf_counter(), time.process_time()
    lo, hi = points.min(axis=0), points.max(axis=0)
    problem = _Problem(start, order, points, currents, fields, 0.5 * (lo + hi))
    n_params = len(problem.columns) + 5 * problem.n_sources
    if fields.size < 2 * n_params:
        raise ConfigError(f"{fields.size} field components cannot fit {n_params} parameters of an "
                          f"order-{order} MPEM: measure more points or patterns")
    # geometry steps: positions in m (1 mm typical), tilts in rad (0.01 typical)
    x_scale = np.tile([1e-3, 1e-3, 1e-3, 1e-2, 1e-2], problem.n_sources)
    fit = least_squares(problem.residual, np.zeros(5 * problem.n_sources), x_scale=x_scale,
                        method="trf", max_nfev=max_evaluations)
    rms = float(np.sqrt(np.mean(np.sum((fit.fun.reshape(fields.shape) * problem.scale) ** 2,
                                       axis=-1))))
    model = problem.to_model(fit.x, name, np.stack([lo, hi], axis=1))
    return MpemFit(model=model, rms_T=rms, duration_s=time.perf_counter() - started,
                   cpu_s=time.process_time() - started_cpu, evaluations=int(fit.nfev))


def held_out_error(model: FieldModel, points_m: np.ndarray, currents_A: np.ndarray,
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
