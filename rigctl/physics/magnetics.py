"""Closed-form magnetic fields of the sources rigctl models: circular current loops and dipoles.

Every function is pure and vectorised: observation points come as an array of shape (..., 3) in
metres and the field goes back with the same shape in tesla. Singular points are masked
explicitly (NaN) instead of producing infinities or warnings, so a caller can test for them.

The loop field is the exact off-axis expression in complete elliptic integrals (Simpson, Lane,
Immer, Youngquist 2001, the reference behind seed 000 Sec. V-c). It is evaluated in the loop's own
cylindrical frame (rho, z) and rotated back. Two regions get their own treatment:

- the axis (rho = 0 and a thin cylinder around it, rho < 1e-5 a): the general radial term
  subtracts two nearly equal numbers there, so the on-axis field and its first-order radial
  term (from div B = 0) are used instead; their error is O((rho/a)^2) < 1e-10 relative.
- the wire itself (distance to the wire < 1e-10 a): the field diverges; NaN is returned.

scipy's `ellipk`/`ellipe` take the parameter m = k^2, not the modulus k. K is evaluated with
`ellipkm1(1 - m)` because near the wire 1 - m is tiny and forming m first would lose it.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import ellipe, ellipkm1

from rigctl.core.errors import ConfigError

logger = logging.getLogger(__name__)

MU0 = 4e-7 * np.pi
"""Vacuum permeability in T m / A (the pre-2019 exact value; the SI 2019 value differs by 1e-10)."""

AXIS_BAND = 1e-5
"""Points closer than AXIS_BAND * radius to the loop axis use the near-axis expansion."""

WIRE_BAND = 1e-10
"""Points closer than WIRE_BAND * radius to the wire get NaN."""


def _unit(vector: ArrayLike, name: str) -> np.ndarray:
    vector = np.asarray(vector, dtype=float)
    if vector.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {vector.shape}")
    norm = np.linalg.norm(vector)
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"{name} must be a finite non-zero vector, got {vector}")
    return vector / norm


def loop_field(
    points_m: ArrayLike,
    centre_m: ArrayLike,
    axis: ArrayLike,
    radius_m: float,
    turns: int,
    current_A: ArrayLike,
) -> np.ndarray:
    """Flux density of a thin circular coil of `turns` turns, treated as one loop carrying
    `turns * current_A`.

    Parameters
    ----------
    points_m : array, shape (..., 3)
        Observation points in metres.
    centre_m : array, shape (3,)
        Centre of the loop in metres.
    axis : array, shape (3,)
        Loop normal (normalised here). Positive current makes the field at the centre point
        along +axis (right-hand rule).
    radius_m : float
        Loop radius in metres, > 0.
    turns : int
        Number of turns, > 0.
    current_A : float or array broadcastable to shape (...)
        Current per turn in amperes.

    Returns
    -------
    np.ndarray, shape (..., 3)
        B in tesla. NaN at points on the wire (closer than 1e-10 * radius to it).
    """
    if not radius_m > 0:
        raise ValueError(f"radius_m must be > 0, got {radius_m}")
    if turns <= 0:
        raise ValueError(f"turns must be > 0, got {turns}")
    points = np.asarray(points_m, dtype=float)
    if points.shape[-1:] != (3,):
        raise ValueError(f"points_m must have shape (..., 3), got {points.shape}")
    normal = _unit(axis, "axis")
    centre = np.asarray(centre_m, dtype=float).reshape(3)
    current = np.broadcast_to(np.asarray(current_A, dtype=float) * turns, points.shape[:-1])

    a = float(radius_m)
    rel = points - centre
    z = rel @ normal
    radial = rel - z[..., None] * normal
    rho = np.linalg.norm(radial, axis=-1)
    r2 = rho**2 + z**2

    alpha2 = a * a + r2 - 2.0 * a * rho  # squared distance to the nearest point of the wire
    beta2 = a * a + r2 + 2.0 * a * rho  # squared distance to the farthest point of the wire
    on_wire = alpha2 <= (WIRE_BAND * a) ** 2
    near_axis = rho < AXIS_BAND * a
    general = ~(on_wire | near_axis)

    b_z = np.zeros_like(rho)
    b_rho = np.zeros_like(rho)

    # Near the axis: exact on-axis field, radial term from div B = 0 (Brho = -rho/2 dBz/dz).
    s2 = a * a + z[near_axis] ** 2
    i_na = current[near_axis]
    b_z[near_axis] = MU0 * i_na * a * a / (2.0 * s2**1.5)
    b_rho[near_axis] = 3.0 * MU0 * i_na * a * a * z[near_axis] * rho[near_axis] / (4.0 * s2**2.5)

    # Elsewhere: the elliptic-integral expressions.
    al2 = alpha2[general]
    be2 = beta2[general]
    be = np.sqrt(be2)
    one_minus_m = al2 / be2
    k_int = ellipkm1(one_minus_m)
    e_int = ellipe(1.0 - one_minus_m)
    c = MU0 * current[general] / np.pi
    r2g = r2[general]
    b_z[general] = c / (2.0 * al2 * be) * ((a * a - r2g) * e_int + al2 * k_int)
    b_rho[general] = (
        c * z[general] / (2.0 * al2 * be * rho[general]) * ((a * a + r2g) * e_int - al2 * k_int)
    )

    b_z[on_wire] = np.nan
    b_rho[on_wire] = np.nan

    # Radial unit vector; on the axis b_rho is zero (or O(rho)) so any finite direction will do.
    with np.errstate(invalid="ignore", divide="ignore"):
        rho_hat = np.where(rho[..., None] > 0, radial / rho[..., None], 0.0)
    return b_z[..., None] * normal + b_rho[..., None] * rho_hat


def dipole_field(points_m: ArrayLike, centre_m: ArrayLike, moment_Am2: ArrayLike) -> np.ndarray:
    """Flux density of a point dipole, B = mu0/(4 pi) (3 (m . r_hat) r_hat - m) / r^3.

    Parameters
    ----------
    points_m : array, shape (..., 3)
        Observation points in metres.
    centre_m : array, shape (3,) or broadcastable to (..., 3)
        Dipole position in metres.
    moment_Am2 : array, shape (3,) or broadcastable to (..., 3)
        Magnetic moment in A m^2.

    Returns
    -------
    np.ndarray, shape (..., 3)
        B in tesla; NaN at the dipole's own position (r = 0).
    """
    points = np.asarray(points_m, dtype=float)
    if points.shape[-1:] != (3,):
        raise ValueError(f"points_m must have shape (..., 3), got {points.shape}")
    rel = points - np.asarray(centre_m, dtype=float)
    moment = np.asarray(moment_Am2, dtype=float)
    r = np.linalg.norm(rel, axis=-1, keepdims=True)
    at_source = r == 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        r_hat = rel / r
        m_dot = np.sum(moment * r_hat, axis=-1, keepdims=True)
        field = MU0 / (4.0 * np.pi) * (3.0 * m_dot * r_hat - moment) / r**3
    return np.where(at_source, np.nan, field)


# ---------------------------------------------------------------- dipole gradients and the 8-vector U
#
# Seed 003 (the dual-EPM rig) describes each external permanent magnet (EPM) as a point dipole and
# works with U = [B; dB], the field and the five independent terms of its gradient at the workspace
# centre. Everything below is in SI: positions in m, moments in A m^2, fields in T, gradients in T/m.

U_COMPONENTS = ("Bx", "By", "Bz", "dBx/dx", "dBx/dy", "dBx/dz", "dBy/dy", "dBy/dz")
"""The eight entries of U (seed 003 eq. 6), in this order: field (T) then gradient terms (T/m)."""

GRADIENT_TERMS = U_COMPONENTS[3:]
"""The five independent gradient terms of seed 003 eq. 5. The other four follow from Maxwell
(gradient symmetric: dBy/dx = dBx/dy, dBz/dx = dBx/dz, dBz/dy = dBy/dz; traceless:
dBz/dz = -dBx/dx - dBy/dy)."""

_TERM_INDEX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2))  # (row i, column j) of G[i, j] = dB_i/dx_j


def _dipole_kernel(rel: np.ndarray, moment: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Field (..., 3) and gradient (..., 3, 3) of dipoles `moment` at offsets `rel` = point - dipole.

    Written component by component, without numpy reductions: a reduction's last bit can depend
    on memory alignment, and the planners built on these kernels must repeat exactly run to run.
    NaN where rel = 0.
    """
    x, y, z = rel[..., 0], rel[..., 1], rel[..., 2]
    mx, my, mz = moment[..., 0], moment[..., 1], moment[..., 2]
    r2 = x * x + y * y + z * z
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_r2 = np.where(r2 > 0, 1.0 / r2, np.nan)
        inv_r = np.sqrt(inv_r2)
        inv_r3 = inv_r * inv_r2
        inv_r5 = inv_r3 * inv_r2
    c = MU0 / (4.0 * np.pi)
    m_dot = mx * x + my * y + mz * z
    rel_c = (x, y, z)
    mom_c = (mx, my, mz)
    field = np.stack([c * (3.0 * m_dot * rel_c[i] * inv_r5 - mom_c[i] * inv_r3) for i in range(3)],
                     axis=-1)
    g = 3.0 * c * inv_r5
    rows = []
    for i in range(3):
        row = []
        for j in range(3):
            value = (rel_c[i] * mom_c[j] + mom_c[i] * rel_c[j]
                     - 5.0 * m_dot * rel_c[i] * rel_c[j] * inv_r2)
            if i == j:
                value = value + m_dot
            row.append(g * value)
        rows.append(np.stack(row, axis=-1))
    return field, np.stack(rows, axis=-2)


def dipole_gradient(
    points_m: ArrayLike, centre_m: ArrayLike, moment_Am2: ArrayLike
) -> np.ndarray:
    """Spatial gradient of a point dipole's field (seed 003 eq. 3).

    G[..., i, j] = dB_i / dx_j = 3 mu0 / (4 pi r^4) ((I - 5 r_hat r_hat^T)(r_hat . m)
    + m r_hat^T + r_hat m^T)_ij, symmetric and traceless away from the dipole.

    Parameters
    ----------
    points_m : array, shape (..., 3)
        Observation points in metres.
    centre_m, moment_Am2 : arrays broadcastable to (..., 3)
        Dipole position (m) and moment (A m^2).

    Returns
    -------
    np.ndarray, shape (..., 3, 3)
        The gradient in T/m; NaN at the dipole's own position.
    """
    points = np.asarray(points_m, dtype=float)
    if points.shape[-1:] != (3,):
        raise ValueError(f"points_m must have shape (..., 3), got {points.shape}")
    rel = points - np.asarray(centre_m, dtype=float)
    moment = np.broadcast_to(np.asarray(moment_Am2, dtype=float), rel.shape)
    return _dipole_kernel(rel, moment)[1]


def gradient_terms(gradient: ArrayLike) -> np.ndarray:
    """The five independent terms (dBx/dx, dBx/dy, dBx/dz, dBy/dy, dBy/dz) of gradients (..., 3, 3)
    -> (..., 5), same unit as the input."""
    gradient = np.asarray(gradient, dtype=float)
    if gradient.shape[-2:] != (3, 3):
        raise ValueError(f"gradient must have shape (..., 3, 3), got {gradient.shape}")
    return np.stack([gradient[..., i, j] for i, j in _TERM_INDEX], axis=-1)


def gradient_from_terms(terms: ArrayLike) -> np.ndarray:
    """The full symmetric, traceless gradient (..., 3, 3) from its five terms (..., 5) (eq. 4)."""
    t = np.asarray(terms, dtype=float)
    if t.shape[-1:] != (5,):
        raise ValueError(f"terms must have shape (..., 5), got {t.shape}")
    xx, xy, xz, yy, yz = (t[..., k] for k in range(5))
    rows = [
        np.stack([xx, xy, xz], axis=-1),
        np.stack([xy, yy, yz], axis=-1),
        np.stack([xz, yz, -xx - yy], axis=-1),
    ]
    return np.stack(rows, axis=-2)


def _magnets(centres_m: ArrayLike, moments_Am2: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    centres = np.asarray(centres_m, dtype=float)
    moments = np.asarray(moments_Am2, dtype=float)
    if centres.ndim == 1:
        centres = centres[None, :]
    if moments.ndim == 1:
        moments = moments[None, :]
    if centres.shape[-1:] != (3,) or moments.shape[-1:] != (3,):
        raise ValueError(
            f"centres_m and moments_Am2 must have shape (K, 3), got {centres.shape} and "
            f"{moments.shape}"
        )
    if centres.shape[-2] != moments.shape[-2]:
        raise ValueError(
            f"one moment per magnet: {centres.shape[-2]} centres, {moments.shape[-2]} moments"
        )
    return centres, moments


def field_and_gradient(
    points_m: ArrayLike, centres_m: ArrayLike, moments_Am2: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """Field and gradient of any number of dipoles by superposition (seed 003 eq. 8).

    Parameters
    ----------
    points_m : array, shape (..., 3)
        Observation points (m).
    centres_m, moments_Am2 : arrays, shape (K, 3)
        The magnets' positions (m) and moments (A m^2); a single (3,) vector means one magnet.
        Leading batch axes are allowed as (..., K, 3) when they match the points' batch axes.

    Returns
    -------
    B : (..., 3) in T, G : (..., 3, 3) in T/m (G[..., i, j] = dB_i/dx_j).
    """
    centres, moments = _magnets(centres_m, moments_Am2)
    points = np.asarray(points_m, dtype=float)
    if points.shape[-1:] != (3,):
        raise ValueError(f"points_m must have shape (..., 3), got {points.shape}")
    rel = points[..., None, :] - centres  # (..., K, 3)
    fields, gradients = _dipole_kernel(rel, np.broadcast_to(moments, rel.shape))
    field, gradient = fields[..., 0, :], gradients[..., 0, :, :]
    for k in range(1, rel.shape[-2]):  # superposition, added in a fixed order
        field = field + fields[..., k, :]
        gradient = gradient + gradients[..., k, :, :]
    return field, gradient


def field_vector(points_m: ArrayLike, centres_m: ArrayLike, moments_Am2: ArrayLike) -> np.ndarray:
    """U = [Bx, By, Bz, dBx/dx, dBx/dy, dBx/dz, dBy/dy, dBy/dz] of K dipoles at the points
    (seed 003 eq. 6 and 8): points (..., 3) in m, magnets (K, 3) in m and A m^2 -> (..., 8) in
    T and T/m."""
    field, gradient = field_and_gradient(points_m, centres_m, moments_Am2)
    return np.concatenate([field, gradient_terms(gradient)], axis=-1)


def field_matrix(point_m: ArrayLike, centres_m: ArrayLike) -> np.ndarray:
    """L of seed 003 eq. 17: B at `point_m` (3,) = L @ [m_1; ...; m_K] for magnets at
    `centres_m` (K, 3). Shape (3, 3K), in T per A m^2. Batch: point (..., 3), centres (..., K, 3)
    -> (..., 3, 3K)."""
    return actuation_matrix(point_m, centres_m)[..., :3, :]


def gradient_matrix(point_m: ArrayLike, centres_m: ArrayLike) -> np.ndarray:
    """M of seed 003 eq. 18-19: the five gradient terms at `point_m` = M @ [m_1; ...; m_K].
    Shape (5, 3K), in T/m per A m^2 (batch as in `field_matrix`)."""
    return actuation_matrix(point_m, centres_m)[..., 3:, :]


def actuation_matrix(point_m: ArrayLike, centres_m: ArrayLike) -> np.ndarray:
    """[L; M] of seed 003 eq. 20: U at `point_m` = A @ [m_1; ...; m_K] for fixed magnet positions.

    Built in closed form per column (the unit moments e_j of eq. 19): column 3k + j holds U of
    magnet k with moment e_j. Shapes: point (..., 3), centres (..., K, 3) -> (..., 8, 3K); rows in
    the order of `U_COMPONENTS`, units T (rows 0-2) and T/m (rows 3-7) per A m^2.
    """
    point = np.asarray(point_m, dtype=float)
    centres = np.asarray(centres_m, dtype=float)
    if centres.ndim == 1:
        centres = centres[None, :]
    rel = point[..., None, :] - centres  # (..., K, 3) from each magnet to the point
    r = np.sqrt(rel[..., 0] ** 2 + rel[..., 1] ** 2 + rel[..., 2] ** 2)  # (..., K), no reduction
    with np.errstate(invalid="ignore", divide="ignore"):
        r_hat = rel / r[..., None]
        # Field per unit moment: B = mu0/(4 pi r^3) (3 r r^T - I) m   -> (..., K, 3, 3)
        eye = np.eye(3)
        outer_rr = r_hat[..., :, None] * r_hat[..., None, :]
        field_block = MU0 / (4.0 * np.pi) * (3.0 * outer_rr - eye) / (r**3)[..., None, None]
        # Gradient term (i, j) per unit moment along e_l:
        # 3 mu0/(4 pi r^4) ((delta_ij - 5 ri rj) r_l + delta_il r_j + r_i delta_jl)
        c = 3.0 * MU0 / (4.0 * np.pi) / r**4  # (..., K)
        rows = []
        for i, j in _TERM_INDEX:
            term = (float(i == j) - 5.0 * r_hat[..., i] * r_hat[..., j])[..., None] * r_hat
            term = term + eye[i] * r_hat[..., j, None] + r_hat[..., i, None] * eye[j]
            rows.append(c[..., None] * term)  # (..., K, 3)
        grad_block = np.stack(rows, axis=-2)  # (..., K, 5, 3)
    blocks = np.concatenate([field_block, grad_block], axis=-2)  # (..., K, 8, 3)
    # (..., K, 8, 3) -> (..., 8, K, 3) -> (..., 8, 3K): magnet-major columns as in eq. 17
    blocks = np.moveaxis(blocks, -3, -2)
    return blocks.reshape(blocks.shape[:-2] + (3 * centres.shape[-2],))


def wrench_map(moment_Am2: ArrayLike) -> np.ndarray:
    """S of seed 003 eq. 7: the wrench [f; tau] (N, N m) on a dipole of moment `moment_Am2`
    (..., 3) in A m^2 is S @ U with U in T and T/m. Shape (..., 6, 8).

    f = (m . grad) B = G m (G symmetric), tau = m x B, written in the five independent terms."""
    m = np.asarray(moment_Am2, dtype=float)
    if m.shape[-1:] != (3,):
        raise ValueError(f"moment_Am2 must have shape (..., 3), got {m.shape}")
    mx, my, mz = m[..., 0], m[..., 1], m[..., 2]
    zero = np.zeros_like(mx)
    rows = [
        [zero, zero, zero, mx, my, mz, zero, zero],
        [zero, zero, zero, zero, mx, zero, my, mz],
        [zero, zero, zero, -mz, zero, mx, -mz, my],
        [zero, -mz, my, zero, zero, zero, zero, zero],
        [mz, zero, -mx, zero, zero, zero, zero, zero],
        [-my, mx, zero, zero, zero, zero, zero, zero],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def cylinder_moment(diameter_m: float, length_m: float, remanence_T: float) -> float:
    """|m| (A m^2) of a uniformly, axially magnetised cylinder: Br V / mu0."""
    if not (diameter_m > 0 and length_m > 0 and remanence_T > 0):
        raise ValueError("diameter_m, length_m and remanence_T must be > 0")
    volume = np.pi * (0.5 * diameter_m) ** 2 * length_m
    return float(remanence_T * volume / MU0)


def gradient_design(offsets_m: np.ndarray, reference: int = 0) -> np.ndarray:
    """The least-squares map from sensor field differences to the five gradient terms.

    With G symmetric and traceless (Maxwell, eq. 4) parameterised by its five terms t (eq. 5),
    each other sensor i gives B_i - B_ref = G (p_i - p_ref) to first order: three equations per
    sensor. Returns P (5, 3 (n - 1)) with t = P @ [B_i - B_ref for i != ref].ravel().
    ConfigError if the offsets do not determine all five terms (fewer than two independent
    directions).
    """
    offsets = np.asarray(offsets_m, dtype=float)
    deltas = np.delete(offsets - offsets[reference], reference, axis=0)  # (n-1, 3)
    basis = gradient_from_terms(np.eye(5))  # (5, 3, 3): G for each unit term
    design = np.einsum("kij,nj->nik", basis, deltas).reshape(-1, 5)  # rows: sensor, component
    if np.linalg.matrix_rank(design, tol=1e-9) < 5:
        raise ConfigError(f"sensor offsets {offsets.tolist()} m do not determine all five gradient "
                          "terms: place two sensors along two different directions from the first")
    return np.linalg.pinv(design)


def field_vector_from_sensors(fields_T: np.ndarray, offsets_m: np.ndarray,
                              reference: int = 0) -> np.ndarray:
    """U (..., 8) in T and T/m at the reference sensor from fields (..., n, 3) T at `offsets_m`.

    Seed 003 eq. 24 takes dB_m/dn = (B_m,i - B_m,1) / delta_1i for sensors displaced along the
    axes. This is the same finite difference written as a least-squares fit of a symmetric,
    traceless gradient, so it works for any offsets; with sensor 2 at +delta x and sensor 3 at
    +delta y (the paper's board) it reduces exactly to eq. 24, with dBx/dy (measured twice, as
    dBx/dy from sensor 3 and dBy/dx from sensor 2) averaged. The estimate is first-order accurate:
    its error is about (delta / 2) times the field's second derivative.
    """
    fields = np.asarray(fields_T, dtype=float)
    projector = gradient_design(offsets_m, reference)
    diffs = np.delete(fields - fields[..., reference:reference + 1, :], reference, axis=-2)
    terms = np.einsum("kn,...n->...k", projector, diffs.reshape(*diffs.shape[:-2], -1))
    return np.concatenate([fields[..., reference, :], terms], axis=-1)


def _cel(kc: np.ndarray, p: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Bulirsch's generalised complete elliptic integral
    cel(kc, p, c, s) = int_0^(pi/2) (c cos^2 t + s sin^2 t) / ((cos^2 t + p sin^2 t)
    sqrt(cos^2 t + kc^2 sin^2 t)) dt, by his iteration (Bulirsch 1969; as in Numerical Recipes),
    vectorised and run until every element has converged to double precision (it converges
    quadratically: 4-6 rounds). p <= 0 is first carried to a positive parameter."""
    kc, p, c, s = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (kc, p, c, s)))
    qc = np.abs(kc)
    e, em = qc.copy(), np.ones_like(qc)
    positive = p > 0
    g0 = np.where(positive, 1.0, 1.0 - p)
    turned = np.sqrt(np.where(positive, 1.0, (qc * qc - p) / g0))
    a_turned = (c - s) / g0
    a = np.where(positive, c, a_turned)
    pp = np.where(positive, np.sqrt(np.where(positive, p, 1.0)), turned)
    b = np.where(positive, s / pp, -(1.0 - qc * qc) * (s - c * p) / (g0 * g0 * turned) + a_turned * turned)
    for _ in range(40):
        f = a
        a = a + b / pp
        g = e / pp
        b = 2.0 * (b + f * g)
        pp = g + pp
        g = em
        em = em + qc
        if np.all(np.abs(g - qc) <= g * 1e-13):
            break
        qc = 2.0 * np.sqrt(e)
        e = qc * em
    return 0.5 * np.pi * (b + a * em) / (em * (em + pp))


def cylinder_axial_field(half_length: ArrayLike, rho: ArrayLike, z: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(B_rho, B_z) of a uniformly, axially magnetised cylinder of unit polarisation (J = mu0 M =
    1 T), centred at the origin with its axis along z; every length in units of the radius. The
    cylinder's field is that of an ideal solenoid with surface current M (Derby and Olbert, Am. J.
    Phys. 78, 229 (2010), eq. 8-9, in Bulirsch's cel): with z_+- = z +- half_length,
    alpha_+- = 1 / sqrt(z_+-^2 + (1 + rho)^2), k_+- = sqrt((z_+-^2 + (1 - rho)^2) alpha_+-^2) and
    gamma = (1 - rho) / (1 + rho),
        B_rho = [alpha_+ cel(k_+, 1, 1, -1) - alpha_- cel(k_-, 1, 1, -1)] / pi,
        B_z = [z_+ alpha_+ cel(k_+, gamma^2, 1, gamma) - z_- alpha_- cel(k_-, gamma^2, 1, gamma)]
              / (pi (1 + rho)).
    On the axis it is the solenoid's (z_+ / sqrt(z_+^2 + 1) - z_- / sqrt(z_-^2 + 1)) / 2; far away
    a dipole of moment J V / mu0. On the rim (rho = 1, z = +-half_length) it diverges."""
    half, rho, z = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (half_length, rho, z)))
    one = np.ones_like(rho)
    gamma = (1.0 - rho) / (1.0 + rho)
    b_rho = np.zeros_like(rho)
    b_z = np.zeros_like(rho)
    for sign in (1.0, -1.0):
        zs = z + sign * half
        alpha = 1.0 / np.sqrt(zs * zs + (1.0 + rho) ** 2)
        k = np.sqrt((zs * zs + (1.0 - rho) ** 2)) * alpha
        b_rho += sign * alpha * _cel(k, one, one, -one)
        b_z += sign * zs * alpha * _cel(k, gamma * gamma, one, gamma)
    return b_rho / np.pi, b_z / (np.pi * (1.0 + rho))
