"""Identification from tracking: what the camera saw each agent do, turned into that agent's own
response to the shared input, with its uncertainty.

One mechanism for every camera rig: a Gaussian estimate of parameters x that enter the measurement
linearly, y = H x + e (e ~ N(0, sigma^2 I)), updated move by move with the Kalman measurement update
(recursive least squares with a prior). `LinearEstimate` is that update; each rig writes down its H:

- rolling magnets (six-coil, seed 000): a commanded displacement u (mm, 2 pi R per turn) moves a
  free agent by y = g R(theta) u + v dt, so with a = g cos theta, b = g sin theta the parameters
  (a, b, v_x, v_y) are linear: H = [[u_x, -u_y, dt, 0], [u_y, u_x, 0, dt]]. g is the agent's
  rolling gain (slip times its own speed spread), theta its heading bias, v a steady drift
  (`RollingIdentifier`, one estimate per agent);
- the coil board (seed 004): the particles' relative position grows under a translation by the
  field's non-uniformity and by the difference of their own mobilities, linear in (k_along,
  k_across, mobility_diff) after a log-mean linearisation
  (`rigctl.rigs.coil_board.run.RelativeDrift` refits a `LinearEstimate` from every free move).

A move a measurement shows to be off the estimate by more than `gate_sigma` standard deviations
(an agent that met a wall unseen, a mis-tracked frame) is left out rather than allowed to bend the
estimate; the caller decides which moves were free at all. A move along a wall is not linear in
the parameters, but the model's image of it is smooth: `RollingIdentifier.observe_linearised`
takes the model's prediction and its derivatives at the present estimate instead (an extended
Kalman filter step).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

GATE_SIGMA = 5.0  # innovations beyond this many standard deviations are outliers


class LinearEstimate:
    """Gaussian estimate of p parameters: mean (p,), covariance (p, p).

    names: one per parameter (for the record); mean, std: the prior; walk_std: the standard
    deviation per update of a random walk of the parameters (0: they are constants), so that an
    estimate keeps following a rig that changes slowly.
    """

    def __init__(self, names: Sequence[str], mean: ArrayLike, std: ArrayLike,
                 walk_std: ArrayLike = 0.0) -> None:
        self.names = list(names)
        self.prior_mean = np.asarray(mean, dtype=float).reshape(-1).copy()
        std = np.broadcast_to(np.asarray(std, dtype=float), self.prior_mean.shape)
        if np.any(std <= 0):
            raise ValueError(f"prior standard deviations must be > 0, got {std.tolist()}")
        self.prior_cov = np.diag(std ** 2)
        self.walk_cov = np.diag(np.broadcast_to(np.asarray(walk_std, dtype=float),
                                                self.prior_mean.shape) ** 2)
        self.mean = self.prior_mean.copy()
        self.cov = self.prior_cov.copy()
        self.updates = 0
        self.rejected = 0

    @property
    def std(self) -> np.ndarray:
        """(p,) standard deviations of the parameters."""
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    def predict(self, h: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Predicted measurement (m,) and its covariance (m, m) for rows h (m, p)."""
        h = np.atleast_2d(np.asarray(h, dtype=float))
        return h @ self.mean, h @ self.cov @ h.T

    def update(self, h: ArrayLike, y: ArrayLike, noise_std: float | ArrayLike,
               gate_sigma: float | None = GATE_SIGMA) -> bool:
        """Fold in one measurement y (m,) = h (m, p) x + noise; False (and no change) when its
        normalised innovation is beyond `gate_sigma` (None: never refused)."""
        h = np.atleast_2d(np.asarray(h, dtype=float))
        y = np.asarray(y, dtype=float).reshape(-1)
        noise = np.broadcast_to(np.asarray(noise_std, dtype=float), y.shape) ** 2
        cov = self.cov + self.walk_cov
        s = h @ cov @ h.T + np.diag(noise)
        innovation = y - h @ self.mean
        if gate_sigma is not None:
            # a chi-square with m degrees of freedom, judged as m one-dimensional gates
            distance = float(innovation @ np.linalg.solve(s, innovation))
            if distance > gate_sigma ** 2 * len(y):
                self.rejected += 1
                return False
        gain = np.linalg.solve(s, h @ cov).T  # cov h^T s^-1 (s symmetric)
        self.mean = self.mean + gain @ innovation
        # Joseph form: stays symmetric and positive however the rows are scaled
        keep = np.eye(len(self.mean)) - gain @ h
        self.cov = keep @ cov @ keep.T + gain @ np.diag(noise) @ gain.T
        self.updates += 1
        return True

    def refit(self, h: ArrayLike, y: ArrayLike, noise_std: float | ArrayLike) -> None:
        """Replace the estimate by the prior updated with every row at once (for models whose
        rows depend on the estimate itself and are re-linearised: the coil board's)."""
        h = np.atleast_2d(np.asarray(h, dtype=float))
        y = np.asarray(y, dtype=float).reshape(-1)
        noise = np.broadcast_to(np.asarray(noise_std, dtype=float), y.shape) ** 2
        information = np.linalg.inv(self.prior_cov) + h.T @ (h / noise[:, None])
        self.cov = np.linalg.inv(information)
        self.mean = self.cov @ (np.linalg.solve(self.prior_cov, self.prior_mean) +
                                h.T @ (y / noise))
        self.updates = len(y)


class RollingIdentifier:
    """Each rolling agent's gain g_i, heading bias theta_i and drift v_i (mm/s) from the camera.

    n: agents; prior_gain, gain_std: what is believed before any move (g = 1 in the planner's
    model); heading_std_rad, drift_std_mm_s: the priors of the others; noise_mm: the camera's
    error on one displacement (two positions); noise_per_mm: the error that grows with the distance
    rolled (slip that varies from turn to turn); walk_gain_std: per move, how far g may wander;
    names: what the record's series calls each agent (default its index; the pair's "centroid").
    Lengths are in mm.
    """

    def __init__(self, n: int, *, prior_gain: float = 1.0, gain_std: float = 0.3,
                 heading_std_rad: float = 0.1, drift_std_mm_s: float = 0.02,
                 noise_mm: float = 0.08, noise_per_mm: float = 0.004,
                 walk_gain_std: float = 0.002, names: Sequence[str] | None = None) -> None:
        self.n = int(n)
        self.names = [str(i) for i in range(self.n)] if names is None else [str(v) for v in names]
        if len(self.names) != self.n:
            raise ValueError(f"names: one per agent ({self.n}), got {self.names}")
        self.noise_mm, self.noise_per_mm = float(noise_mm), float(noise_per_mm)
        self.known_gain_std = gain_std / 3.0  # `response`: a gain is known below this spread
        ab_std = prior_gain * heading_std_rad
        self.estimates = [
            LinearEstimate(["a", "b", "vx", "vy"], [prior_gain, 0.0, 0.0, 0.0],
                           [gain_std, ab_std, drift_std_mm_s, drift_std_mm_s],
                           [walk_gain_std, walk_gain_std, 0.0, 0.0])
            for _ in range(self.n)]

    @staticmethod
    def rows(commanded_mm: np.ndarray, dt_s: float) -> np.ndarray:
        """H (2, 4) of one move: commanded (2,) mm over dt_s seconds."""
        ux, uy = float(commanded_mm[0]), float(commanded_mm[1])
        return np.array([[ux, -uy, dt_s, 0.0], [uy, ux, 0.0, dt_s]])

    def observe(self, commanded_mm: ArrayLike, displacement_mm: ArrayLike, free: ArrayLike,
                dt_s: float) -> np.ndarray:
        """One move: commanded (2,) mm, each agent's measured displacement (n, 2) mm, which agents
        moved freely (n,) bool (walls and other agents never touched), dt_s between the two
        frames. Returns (n,) True where the move was used."""
        u = np.asarray(commanded_mm, dtype=float).reshape(2)
        y = np.asarray(displacement_mm, dtype=float).reshape(self.n, 2)
        free = np.asarray(free, dtype=bool).reshape(self.n)
        used = np.zeros(self.n, dtype=bool)
        length = float(np.hypot(*u))
        if length <= 0.0:
            return used
        h = self.rows(u, dt_s)
        noise = math.hypot(self.noise_mm, self.noise_per_mm * length)
        for i in np.flatnonzero(free):
            used[i] = self.estimates[i].update(h, y[i], noise)
        return used

    def observe_linearised(self, i: int, commanded_mm: ArrayLike, predicted_mm: ArrayLike,
                           jacobian: ArrayLike, displacement_mm: ArrayLike, dt_s: float,
                           extra_noise_mm: float = 0.0) -> bool:
        """One move of agent i that met a wall: the model's displacement at the present estimate
        (predicted (2,) mm, drift left out) and its derivatives (jacobian (2, 2)) in (a, b) stand
        for the free move's H (the extended Kalman filter's linearisation). Only the gain is
        learnt from it, the heading kept: the derivatives are taken along (a, b) itself. Along a
        wall the part of the input into the wall is lost, and what is left depends on the heading
        only through that lost part (and, on a real rig, the wall's friction): one move that hit
        the ceiling moved the heading 2.5 degrees on an emulator that has none.
        extra_noise_mm: the jitter of the contact, added to the camera's. True where used."""
        e = self.estimates[i]
        along = e.mean[:2] / max(float(np.hypot(*e.mean[:2])), 1e-9)
        jac = np.asarray(jacobian, dtype=float).reshape(2, 2) @ np.outer(along, along)
        h = np.hstack([jac, dt_s * np.eye(2)])
        y = (np.asarray(displacement_mm, dtype=float).reshape(2)
             - np.asarray(predicted_mm, dtype=float).reshape(2) + jac @ e.mean[:2])
        length = float(np.hypot(*np.asarray(commanded_mm, dtype=float).reshape(2)))
        noise = math.hypot(self.noise_mm, self.noise_per_mm * length, extra_noise_mm)
        return e.update(h, y, noise)

    def response(self) -> tuple[np.ndarray, np.ndarray]:
        """(gains (n,), headings_rad (n,)) to plan with: an agent whose gain is not known yet
        (its spread still above a third of the prior's) takes the mean of those that are (what
        they share, the rig's slip, is most of it). A move counted against an agent may have told
        little about it (one pressed into a corner), so the count of moves is no measure."""
        gains, headings = self.gains, self.headings_rad
        seen = self.gain_std <= self.known_gain_std
        if seen.any() and not seen.all():
            gains[~seen] = gains[seen].mean()
            headings[~seen] = headings[seen].mean()
        return gains, headings

    def predict(self, commanded_mm: ArrayLike, dt_s: float = 0.0) -> np.ndarray:
        """(n, 2) mm each free agent is expected to move for a commanded (2,) mm."""
        h = self.rows(np.asarray(commanded_mm, dtype=float), dt_s)
        return np.array([e.predict(h)[0] for e in self.estimates])

    # -- the parameters ---------------------------------------------------------------------------
    @property
    def gains(self) -> np.ndarray:
        """(n,) distance rolled per distance commanded."""
        return np.array([math.hypot(e.mean[0], e.mean[1]) for e in self.estimates])

    @property
    def headings_rad(self) -> np.ndarray:
        """(n,) angle (rad, counter-clockwise) from the commanded to the rolled direction."""
        return np.array([math.atan2(e.mean[1], e.mean[0]) for e in self.estimates])

    @property
    def drift_mm_s(self) -> np.ndarray:
        """(n, 2) steady drift in mm/s."""
        return np.array([e.mean[2:4] for e in self.estimates])

    def _polar_std(self) -> tuple[np.ndarray, np.ndarray]:
        gain_std, heading_std = [], []
        for e in self.estimates:
            a, b = e.mean[0], e.mean[1]
            g = max(math.hypot(a, b), 1e-9)
            radial = np.array([a, b]) / g  # d g / d(a, b)
            tangent = np.array([-b, a]) / g ** 2  # d theta / d(a, b)
            cov = e.cov[:2, :2]
            gain_std.append(math.sqrt(max(float(radial @ cov @ radial), 0.0)))
            heading_std.append(math.sqrt(max(float(tangent @ cov @ tangent), 0.0)))
        return np.array(gain_std), np.array(heading_std)

    @property
    def gain_std(self) -> np.ndarray:
        return self._polar_std()[0]

    @property
    def heading_std_rad(self) -> np.ndarray:
        return self._polar_std()[1]

    @property
    def updates(self) -> np.ndarray:
        return np.array([e.updates for e in self.estimates])

    SERIES_UNITS: ClassVar[dict[str, str]] = {
        "gain": "1", "gain_std": "1", "heading_deg": "deg", "heading_deg_std": "deg",
        "drift_x_mm_s": "mm/s", "drift_y_mm_s": "mm/s", "moves_used": "count"}

    def series_columns(self) -> list[str]:
        """Columns of the record's `identification` series: `t_s`, then per agent i and
        parameter P the column `P_i`, and `P_i_std` for its standard deviation where known."""
        columns = ["t_s"]
        for i in self.names:
            for name in self.SERIES_UNITS:
                columns.append(f"{name[:-4]}_{i}_std" if name.endswith("_std") else f"{name}_{i}")
        return columns

    def series_units(self) -> dict[str, str]:
        units = dict.fromkeys(self.series_columns(), "")
        units["t_s"] = "s"
        for i in self.names:
            for name, unit in self.SERIES_UNITS.items():
                key = f"{name[:-4]}_{i}_std" if name.endswith("_std") else f"{name}_{i}"
                units[key] = unit
        return units

    def series_row(self, t_s: float) -> list[float]:
        """One row of the series at run time t_s (s)."""
        gain_std, heading_std = self._polar_std()
        row = [t_s]
        for i, g, th, d in zip(range(self.n), self.gains, self.headings_rad, self.drift_mm_s):
            row += [g, gain_std[i], math.degrees(th), math.degrees(heading_std[i]),
                    d[0], d[1], self.estimates[i].updates]
        return row

    def summary(self) -> dict:
        """The estimates for the run summary (rounded)."""
        gain_std, heading_std = self._polar_std()
        return {
            "gain": np.round(self.gains, 4).tolist(),
            "gain_std": np.round(gain_std, 4).tolist(),
            "heading_deg": np.round(np.degrees(self.headings_rad), 3).tolist(),
            "heading_std_deg": np.round(np.degrees(heading_std), 3).tolist(),
            "drift_mm_s": np.round(self.drift_mm_s, 5).tolist(),
            "moves_used": self.updates.tolist(),
        }


class CommandedVelocity:
    """A commanded velocity (2,) that holds from each time it was sent until the next, for
    integrating over the interval between two camera frames: how far an agent was told to go
    while the camera watched (a rig that commands velocities, not moves: the pair's pull).

    keep_s: how much history is kept (older entries are dropped once a newer one covers them).
    """

    def __init__(self, keep_s: float = 10.0) -> None:
        self.keep_s = float(keep_s)
        self._t: list[float] = []
        self._v: list[np.ndarray] = []

    def send(self, t: float, velocity: ArrayLike) -> None:
        """From time t (s, the caller's clock) on, `velocity` (2,) is commanded."""
        self._t.append(float(t))
        self._v.append(np.asarray(velocity, dtype=float).reshape(2).copy())
        while len(self._t) > 1 and self._t[1] < t - self.keep_s:
            del self._t[0], self._v[0]

    def integral(self, t0: float, t1: float) -> np.ndarray:
        """(2,) the commanded velocity integrated over [t0, t1] (nothing before the first send)."""
        total = np.zeros(2)
        for i, start in enumerate(self._t):
            end = self._t[i + 1] if i + 1 < len(self._t) else math.inf
            lo, hi = max(start, t0), min(end, t1)
            if hi > lo:
                total += self._v[i] * (hi - lo)
        return total
