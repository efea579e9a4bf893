"""Tracking a pair-formation path from camera measurements (seed 002 Sec. III-B, V-C).

Two modes, switched on the distance from the measured formation to the path, as in the paper:

- *proximity*: the agents are farther than `tolerance_bl` from every path node ahead: steer them
  back to the nearest node (brute force over the controls, as the paper's proximity controller);
- *pursuit*: on the path, each agent i heads for a look-ahead point in the direction of eq. 6,
  d_l = L d_1 + (1 - L) d_2, with d_1 the unit normal back to its current path segment and d_2 the
  unit direction to the segment's end P_k; the segment index advances when both agents reach (or
  pass) their P_k;
- at the last node the controller *holds* the goal formation (the targets are the goal positions;
  the brute force then dithers the field about +-54.74 deg, where the radial force vanishes, and
  the transverse force flips sign).

Every decision is a brute force over field angles (a grid plus the four zero-radial angles of the
measured heading) held for `horizon_s`, predicted with the planner's model (`rank_controls`); the
pull of each is the best one inside the coils' box. The measurement is first carried forward from
the frame's capture time to now with the last control, so camera latency does not show as lag.
With an identified pull response (`set_pull_response`: the centroid moves gain R(heading) f for a
pull f, `rigctl.rigs.six_coil.pair.PullIdentification`) the brute force predicts with what the
agents will do and the pull sent is its inverse image (`commanded`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from rigctl.plans.pair import (
    PairProblem,
    agent_positions,
    heading_angles,
    propagate_local,
    rank_controls,
    state_from_positions,
    step_state,
)

log = logging.getLogger(__name__)

PREDICTION_STEPS = 4  # RK4 sub-steps of a decision's prediction (30 ms each at the default horizon)
MAX_CARRY_S = 0.1  # a measurement older than this is carried forward no further


@dataclass(frozen=True)
class PursuitSettings:
    """gain_L: eq. 6's L; lookahead_bl: distance to the look-ahead point; tolerance_bl: the
    proximity controller's epsilon; reach_bl: a node counts as reached this close; horizon_s: how
    far ahead each decision predicts; safety_s: how long the chosen field may be held without the
    separation leaving (r_min + safety_margin_bl, r_max) (the margin: an attracting pair closes
    ever faster, and a stalled cycle on a busy machine holds a field longer); n_psi: field
    angles of the brute force; max_pull: BL/s the controller may pull (None: the problem's)."""

    gain_L: float = 0.5
    lookahead_bl: float = 0.4
    tolerance_bl: float = 0.4
    reach_bl: float = 0.12
    horizon_s: float = 0.12
    safety_s: float = 0.5
    safety_margin_bl: float = 0.1
    n_psi: int = 72
    max_pull: float | None = None


def closest_on_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points (..., 2) on segments a-b to points p, and the segment parameter t in [0, 1]."""
    ab = b - a
    length2 = np.sum(ab * ab, axis=-1)
    t = np.where(length2 > 0, np.sum((p - a) * ab, axis=-1) / np.maximum(length2, 1e-300), 1.0)
    t = np.clip(t, 0.0, 1.0)
    return a + t[..., None] * ab, t


def distance_to_path(p: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance (2,) of each agent p (2, 2) to its own polyline path (k, 2, 2)."""
    if len(path) == 1:
        return np.hypot(*(p - path[0]).T)
    c, _ = closest_on_segments(p[None], path[:-1], path[1:])  # (k - 1, 2, 2)
    d = np.hypot(c[..., 0] - p[None, :, 0], c[..., 1] - p[None, :, 1])
    return d.min(axis=0)


class PairPursuit:
    """The tracking controller. `nodes` (k + 1, 4): the plan's start and expected states (BL, rad)."""

    def __init__(self, problem: PairProblem, nodes: np.ndarray,
                 settings: PursuitSettings = PursuitSettings()) -> None:
        self.problem = problem
        self.settings = settings
        self.nodes = np.asarray(nodes, dtype=float)
        self.paths = agent_positions(self.nodes)  # (k + 1, 2, 2) BL
        self.k = 1 if len(self.nodes) > 1 else 0  # the node being headed for
        self.mode = "pursuit"
        grid = np.linspace(-math.pi, math.pi, settings.n_psi, endpoint=False)
        self._grid = grid
        self.last_u = np.zeros(3)  # the control as the agents feel it (the model's)
        self._max_pull = settings.max_pull if settings.max_pull is not None else problem.max_pull
        self.pull_gain, self.pull_heading_rad = 1.0, 0.0

    def set_pull_response(self, gain: float, heading_rad: float) -> None:
        """How the agents answer a commanded pull f (identified from tracking): their centroid
        moves by gain R(heading) f. The controller then predicts with what they will do and
        commands what makes them do it (`commanded`)."""
        self.pull_gain, self.pull_heading_rad = float(gain), float(heading_rad)

    def commanded(self, u: np.ndarray) -> np.ndarray:
        """The control to send for u = (psi_g, f_x, f_y) as the agents should feel it: the pull
        through the inverse of the identified response, kept inside the coils' box at psi_g."""
        c, s = math.cos(self.pull_heading_rad), math.sin(self.pull_heading_rad)
        f = np.array([c * u[1] + s * u[2], -s * u[1] + c * u[2]]) / self.pull_gain
        box = self._max_pull * np.abs(np.array([math.cos(u[0]), math.sin(u[0])]))
        return np.array([u[0], *np.clip(f, -box, box)])

    def splice(self, new_nodes: np.ndarray, joined: int) -> None:
        """Re-planned: go through `new_nodes` (m, 4) and continue with the old nodes after `joined`."""
        self.nodes = np.vstack([new_nodes, self.nodes[joined + 1:]])
        self.paths = agent_positions(self.nodes)
        self.k = 1 if len(self.nodes) > 1 else 0

    def carry_forward(self, q: np.ndarray, seconds: float) -> np.ndarray:
        """The measured state q moved on by `seconds` under the last control (latency)."""
        if seconds <= 0:
            return q
        return step_state(q, self.last_u, min(seconds, MAX_CARRY_S), self.problem.rate)

    def decide(self, q: np.ndarray) -> np.ndarray:
        """The control u = (psi_g rad, f_x, f_y BL/s) to send now for measured state q (4,)
        (`last_u` keeps it as the agents feel it)."""
        s = self.settings
        p = agent_positions(q)
        last = len(self.nodes) - 1
        # where are we: the nearest node at or after the previous one
        ahead = self.paths[max(self.k - 1, 0):]
        gap = np.max(np.hypot(*(ahead - p[None]).transpose(2, 0, 1)), axis=1)  # (m,)
        on_path = distance_to_path(p, self.paths[max(self.k - 1, 0):]).max() <= s.tolerance_bl
        if not on_path and gap.min() > s.tolerance_bl:
            self.mode = "proximity"
            nearest = max(self.k - 1, 0) + int(np.argmin(gap))
            self.k = max(nearest, 1) if last > 0 else 0
            target = self.nodes[nearest]
        else:
            # advance past every node both agents have reached or passed
            while self.k < last:
                a, b = self.paths[self.k - 1], self.paths[self.k]
                _, t = closest_on_segments(p, a, b)
                near = np.max(np.hypot(*(b - p).T)) <= s.reach_bl
                if near or np.all(t >= 1.0):
                    self.k += 1
                else:
                    break
            end = self.paths[self.k]
            if self.k == last and np.max(np.hypot(*(end - p).T)) <= s.tolerance_bl:
                self.mode = "hold"
                target = self.nodes[last]
            else:
                self.mode = "pursuit"
                a = self.paths[max(self.k - 1, 0)]
                c, _ = closest_on_segments(p, a, end)
                d1 = _unit(c - p)
                d2 = _unit(end - p)
                heading = _unit(s.gain_L * d1 + (1.0 - s.gain_L) * d2)  # eq. 6
                remaining = np.hypot(*(end - p).T)
                step = np.minimum(s.lookahead_bl, remaining)[:, None]
                target = state_from_positions(p + step * heading)
        psi = np.concatenate([self._grid, heading_angles(q[3])])
        # a field held longer than planned (a late frame, a stalled cycle) must not bring the
        # agents together: keep only angles whose separation stays in range for safety_s
        rs, _ = propagate_local(q[2], q[3], psi, s.safety_s, self.problem.rate, PREDICTION_STEPS + 2,
                                trace=True)
        low = self.problem.r_min + s.safety_margin_bl
        safe = np.all((rs > low) & (rs < self.problem.r_max), axis=0)
        if safe.any():
            psi = psi[safe]
        dt = np.full(len(psi), s.horizon_s)
        margin = 0.05
        reach = self._max_pull * self.pull_gain  # what the agents can be made to do
        ranked = rank_controls(q, target, psi, dt, self.problem, PREDICTION_STEPS,
                               (self.problem.r_min + margin, self.problem.r_max - margin),
                               max_pull=reach)
        if ranked is None:  # every angle leaves the separation range: the least bad one
            ranked = rank_controls(q, target, psi, dt, self.problem, PREDICTION_STEPS,
                                   (0.5, math.inf), max_pull=reach)
        if ranked is None:  # too close for any prediction: push apart (side by side repel)
            self.last_u = np.array([q[3] + math.pi / 2, 0.0, 0.0])
        else:
            order, u, _, _ = ranked
            self.last_u = u[order[0]].copy()
        return self.commanded(self.last_u)


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.hypot(v[..., 0], v[..., 1])[..., None]
    return np.where(n > 1e-9, v / np.maximum(n, 1e-300), 0.0)
