"""Two magnetic agents in close proximity (seed 002): the inter-agent force model, the Lie-bracket
controllability check, and the RRT that plans the field angle psi and the pulling force.

Both agents are spheres of diameter D whose moments m follow the applied in-plane field. In the
local frame of the separation vector r (from agent 1 to agent 2, heading phi) a field at local angle
psi = psi_G - phi gives agent 2 the force (eq. 1, alpha = 0)

    f_r = Omega / r^4 (1 - 3 cos^2 psi),   f_phi = Omega / r^4 sin(2 psi),   Omega = 3 mu0 m^2 / (4 pi)

and agent 1 the opposite force. With Stokes drag sigma = 3 pi eta D on each agent the separation
changes at twice the speed one force gives (both agents move). Normalised by the body diameter as
in the paper (r* = r / D, positions in body lengths BL), with K = 2 Omega / (sigma D^5) in 1/s:

    r*' = K (1 - 3 cos^2 psi) / r*^4,   phi' = K sin(2 psi) / r*^5                  (eq. 3, local rows)

so (r*' r*^4 / K, r* phi' r*^4 / K) runs round an ellipse centred on (-1/2, 0) with semi-axes 3/2
and 1 as psi turns (eq. 2 and Fig. 1: the largest transverse force is half the largest radial one).
A weak gradient pulls both agents alike: the centroid moves at f = F / (sigma D) BL/s (eq. 3, first
rows). On the six-coil rig the gradient at the centre has no off-diagonal terms, so a moment along
(cos psi_G, sin psi_G) can be pulled by at most p |cos psi_G| along x and p |sin psi_G| along y
(`rigctl.rigs.six_coil.allocate.max_planar_gradient` gives p): the "singular pulling" constraint of Sec. II-C.

Planner state q = [x_c, y_c, r, phi] (BL, BL, BL, rad); control u = [psi_G, f_x, f_y] held for a
step time dt (psi_G is the global field angle the coils hold; the local psi changes as phi does).
EXTEND (Alg. 3) is a brute force over field angles and step times, integrated together in one
vectorised RK4; for each, the best pull inside the rig's box is found in closed form (the cost
separates into a centroid and a separation part, see `_pair_cost`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.config import settings_of
from rigctl.core.errors import EXIT_NOT_REACHED, EXIT_OK, PlanError
from rigctl.core.jit import njit
from rigctl.plans.schema import rig_running

log = logging.getLogger(__name__)

MU0 = 4e-7 * math.pi
ZERO_RADIAL_ANGLE_RAD = math.acos(1.0 / math.sqrt(3.0))
"""psi at which the radial force vanishes, 54.7356 degrees (cos^2 psi = 1/3)."""
REPLAY_TOLERANCE = 1e-6
"""Agreement (BL, rad) demanded between a plan's expected states and a replay of its segments."""
SUBSTEPS = 12
"""RK4 sub-steps per segment, whatever its length (the planner and every replay use the same)."""
MAX_SEGMENT_S = 0.6
"""Longest segment: keeps a sub-step under 0.05 s, where RK4 is accurate to ~1e-5 BL at r = 1.5."""


# -- physics ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PairPhysics:
    """The two agents and their liquid.

    body_diameter_mm: D; moment_Am2: |m| of each agent; viscosity_Pa_s: eta of the liquid.
    """

    body_diameter_mm: float = 1.0
    moment_Am2: float = 5.6e-7
    viscosity_Pa_s: float = 2.0e-3

    @property
    def diameter_m(self) -> float:
        return self.body_diameter_mm * 1e-3

    @property
    def drag_N_s_per_m(self) -> float:
        """Stokes drag constant sigma = 6 pi eta R of one sphere."""
        return 3.0 * math.pi * self.viscosity_Pa_s * self.diameter_m

    @property
    def force_constant_N_m4(self) -> float:
        """Omega = 3 mu0 m^2 / (4 pi) (eq. 1)."""
        return 3.0 * MU0 * self.moment_Am2**2 / (4.0 * math.pi)

    @property
    def rate_per_s(self) -> float:
        """K = 2 Omega / (sigma D^5): r*' = K (1 - 3 cos^2 psi) / r*^4 in BL/s."""
        return 2.0 * self.force_constant_N_m4 / (self.drag_N_s_per_m * self.diameter_m**5)

    @property
    def pull_bl_s_per_T_m(self) -> float:
        """Centroid speed (BL/s) per T/m of gradient along the moment: m / (sigma D)."""
        return self.moment_Am2 / (self.drag_N_s_per_m * self.diameter_m)


def interagent_forces(r: ArrayLike, psi: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Radial and transverse force on agent 2 from agent 1 (eq. 1, alpha = 0) in units of
    Omega / D^4: f_r = (1 - 3 cos^2 psi) / r^4, f_phi = sin(2 psi) / r^4.

    r: separation in body diameters (any shape); psi: local field angle in rad (broadcast).
    Positive f_r pushes the agents apart, positive f_phi turns the pair counter-clockwise.
    """
    r = np.asarray(r, dtype=float)
    psi = np.asarray(psi, dtype=float)
    r4 = r**4
    return (1.0 - 3.0 * np.cos(psi) ** 2) / r4, np.sin(2.0 * psi) / r4


def lie_bracket_matrix(r: float, psi: float) -> np.ndarray:
    """Delta = [g, [f, g], [f, [f, g]]] of eq. 5 (Omega = 1) for S_local, state [r, phi, psi],
    drift f = [(1 - 3 cos^2 psi) / r^4, sin(2 psi) / r^5, 0], control g = [0, 0, 1]."""
    s2, c2, c = math.sin(2 * psi), math.cos(2 * psi), math.cos(psi)
    return np.array([
        [0.0, -3.0 * s2 / r**4, 0.0],
        [0.0, -2.0 * c2 / r**5, -10.0 * (1.0 + c * c) / r**10],
        [1.0, 0.0, 0.0],
    ])


def controllability(r: float, phi: float, psi_deg: float) -> dict:
    """The LARC check of Sec. IV at a formation: rank of eq. 5's matrix (3 = small-time locally
    controllable), and the angle at which the radial force vanishes. `phi` does not enter (the
    drift depends on r and the local psi only) but is part of the formation and is echoed."""
    if not (r > 0 and math.isfinite(r)):
        raise PlanError(f"r must be a positive separation in body diameters, got {r}")
    matrix = lie_bracket_matrix(r, math.radians(psi_deg))
    # columns scale as 1, r^-5 and r^-10: compare directions, not sizes
    columns = matrix / np.linalg.norm(matrix, axis=0)
    singular = np.linalg.svd(columns, compute_uv=False)
    rank = int(np.sum(singular > 1e-9 * singular[0]))
    return {
        "rank": rank,
        "zero_radial_angle_deg": round(math.degrees(ZERO_RADIAL_ANGLE_RAD), 4),
        "r": r, "phi": phi, "psi_deg": psi_deg,
        "stlc": rank == 3,
        "matrix": matrix.tolist(),
    }


# -- states and propagation ----------------------------------------------------------------------

def agent_positions(q: ArrayLike) -> np.ndarray:
    """Agents' centres (..., 2, 2) in BL from states q (..., 4) = [x_c, y_c, r, phi]:
    agent 1 at c - r/2 e(phi), agent 2 at c + r/2 e(phi)."""
    q = np.asarray(q, dtype=float)
    half = 0.5 * q[..., 2:3] * np.stack([np.cos(q[..., 3]), np.sin(q[..., 3])], axis=-1)
    c = q[..., :2]
    return np.stack([c - half, c + half], axis=-2)


def state_from_positions(p: ArrayLike) -> np.ndarray:
    """Inverse of `agent_positions`: (..., 2, 2) -> (..., 4)."""
    p = np.asarray(p, dtype=float)
    c = 0.5 * (p[..., 0, :] + p[..., 1, :])
    d = p[..., 1, :] - p[..., 0, :]
    return np.concatenate([c, np.hypot(d[..., 0], d[..., 1])[..., None],
                           np.arctan2(d[..., 1], d[..., 0])[..., None]], axis=-1)


def propagate_local(r: ArrayLike, phi: ArrayLike, psi_g: ArrayLike, dt: ArrayLike,
                    rate_per_s: float, steps: int, *, trace: bool = False):
    """RK4 of (r, phi) under a held global field angle psi_g for dt (all broadcast together).

    Returns (r, phi) at the end, or with `trace` arrays (steps + 1, ...) of every sub-step."""
    r, phi, psi_g, dt = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (r, phi, psi_g, dt)))
    shape = r.shape
    rs = np.empty((steps + 1, r.size))
    ps = np.empty((steps + 1, r.size))
    _rk4_local(np.ravel(r), np.ravel(phi), np.ravel(psi_g), np.ravel(dt), float(rate_per_s),
               rs, ps)
    if trace:
        return rs.reshape((steps + 1,) + shape), ps.reshape((steps + 1,) + shape)
    return rs[-1].reshape(shape), ps[-1].reshape(shape)


@njit(error_model="numpy")
def _rk4_local(r0, phi0, psi_g, dt, rate, rs, ps):  # pragma: no cover - compiled
    """RK4 of eq. 3's local rows for each candidate i (n,), sub-steps as rows of rs, ps
    (steps + 1, n). 1 - 3 cos^2 psi is written -1/2 - 3/2 cos 2 psi (this loop is the planner's
    cost: compiled, it is ~20x the numpy version)."""
    steps = rs.shape[0] - 1
    for i in range(r0.shape[0]):
        r, p = r0[i], phi0[i]
        h = dt[i] / steps
        two_psi = 2.0 * psi_g[i]
        rs[0, i], ps[0, i] = r, p
        for s in range(steps):
            k1r, k1p = _local_rates(r, p, two_psi, rate)
            k2r, k2p = _local_rates(r + 0.5 * h * k1r, p + 0.5 * h * k1p, two_psi, rate)
            k3r, k3p = _local_rates(r + 0.5 * h * k2r, p + 0.5 * h * k2p, two_psi, rate)
            k4r, k4p = _local_rates(r + h * k3r, p + h * k3p, two_psi, rate)
            r = r + h / 6.0 * (k1r + 2.0 * k2r + 2.0 * k3r + k4r)
            p = p + h / 6.0 * (k1p + 2.0 * k2p + 2.0 * k3p + k4p)
            rs[s + 1, i], ps[s + 1, i] = r, p


@njit(error_model="numpy", inline="always")
def _local_rates(r, phi, two_psi_g, rate):  # pragma: no cover - compiled
    a = two_psi_g - 2.0 * phi
    k = rate / (r * r * r * r)
    return k * (-0.5 - 1.5 * math.cos(a)), k * math.sin(a) / r


def step_state(q: ArrayLike, u: ArrayLike, dt: float, rate_per_s: float,
               *, trace: bool = False) -> np.ndarray:
    """S_global (eq. 3) for one segment: q (4,) + u = (psi_g rad, f_x, f_y BL/s) held dt s -> q (4,)
    (or with `trace` the states (steps + 1, 4) at every sub-step)."""
    q = np.asarray(q, dtype=float)
    psi_g, fx, fy = (float(v) for v in u)
    steps = SUBSTEPS
    rs, ps = propagate_local(q[2], q[3], psi_g, dt, rate_per_s, steps, trace=True)
    t = np.linspace(0.0, dt, steps + 1)
    states = np.stack([q[0] + fx * t, q[1] + fy * t, rs, ps], axis=-1)
    return states if trace else states[-1]


def rollout(start: ArrayLike, controls: ArrayLike, dts: ArrayLike, rate_per_s: float) -> np.ndarray:
    """States (k, 4) after each of k segments (controls (k, 3), dts (k,)) from `start` (4,)."""
    q = np.asarray(start, dtype=float)
    out = []
    for u, dt in zip(np.asarray(controls, dtype=float).reshape(-1, 3), np.asarray(dts, dtype=float)):
        q = step_state(q, u, float(dt), rate_per_s)
        out.append(q)
    return np.array(out).reshape(-1, 4)


def pull_box(psi_g: ArrayLike, max_pull: float) -> tuple[np.ndarray, np.ndarray]:
    """Largest |f_x|, |f_y| (BL/s) the coils can pull with the field at psi_g (rad)."""
    psi_g = np.asarray(psi_g, dtype=float)
    return max_pull * np.abs(np.cos(psi_g)), max_pull * np.abs(np.sin(psi_g))


def wrap_angle(a: ArrayLike) -> np.ndarray:
    return (np.asarray(a, dtype=float) + math.pi) % (2.0 * math.pi) - math.pi


# -- the problem and its validity checks ---------------------------------------------------------

@dataclass
class PairProblem:
    """What the planner and the checks need: geometry (mm), physics, limits (BL, BL/s)."""

    workspace: object  # rigctl.plans.workspace.Workspace
    physics: PairPhysics
    r_min: float
    r_max: float
    max_pull: float
    sample_workspace: object | None = None  # obstacles replaced by their convex hulls

    @property
    def diameter_mm(self) -> float:
        return self.physics.body_diameter_mm

    @property
    def rate(self) -> float:
        return self.physics.rate_per_s

    def agents_free(self, states: ArrayLike, workspace=None) -> np.ndarray:
        """(...,) True where both agents of states (..., 4) fit in the workspace."""
        ws = workspace or self.workspace
        p = agent_positions(states) * self.diameter_mm
        return np.all(ws.clearance(p) >= 0.5 * self.diameter_mm, axis=-1)

    def separation_ok(self, r: ArrayLike) -> np.ndarray:
        r = np.asarray(r)
        return (r > self.r_min) & (r < self.r_max)

    def pull_ok(self, u: ArrayLike, slack: float = 1e-9) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        bx, by = pull_box(u[..., 0], self.max_pull)
        return (np.abs(u[..., 1]) <= bx + slack) & (np.abs(u[..., 2]) <= by + slack)

    def edge_problem(self, q: np.ndarray, u: np.ndarray, dt: float) -> str | None:
        """Why the segment from q under u for dt is not allowed, or None."""
        if not 0 < dt <= MAX_SEGMENT_S + 1e-12:
            return f"dt {dt:g} s is outside (0, {MAX_SEGMENT_S:g}]"
        if not bool(self.pull_ok(u)):
            bx, by = pull_box(u[0], self.max_pull)
            return (f"pull ({u[1]:.3f}, {u[2]:.3f}) BL/s exceeds what the coils make at psi "
                    f"{math.degrees(u[0]):.1f} deg (|f_x| <= {bx:.3f}, |f_y| <= {by:.3f})")
        states = step_state(q, u, dt, self.rate, trace=True)
        bad_r = ~self.separation_ok(states[:, 2])
        if bad_r.any():
            r = states[np.argmax(bad_r), 2]
            return f"separation {r:.3f} BL leaves ({self.r_min:g}, {self.r_max:g})"
        free = self.agents_free(states)
        if not free.all():
            s = states[np.argmin(free)]
            p = agent_positions(s) * self.diameter_mm
            return (f"an agent hits a wall near ({p[0, 0]:.2f}, {p[0, 1]:.2f}) / "
                    f"({p[1, 0]:.2f}, {p[1, 1]:.2f}) mm")
        return None


def hull_workspace(spec) -> object | None:
    """The workspace with every polygon obstacle replaced by its convex hull (rects and disks are
    convex already), for rejecting samples inside obstacles' hulls; None for image workspaces."""
    from scipy.spatial import ConvexHull

    from rigctl.plans.workspace import ShapeWorkspace, _shape_tuple

    if not hasattr(spec, "boundary"):
        return None
    obstacles = []
    for shape in spec.obstacles:
        if getattr(shape, "polygon", None) is not None:
            vertices = np.asarray(shape.polygon, dtype=float)
            hull = vertices[ConvexHull(vertices).vertices]
            obstacles.append(("polygon", hull))
        else:
            obstacles.append(_shape_tuple(shape))
    return ShapeWorkspace(boundary=_shape_tuple(spec.boundary), obstacles=obstacles)


# -- the planner ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class PairPlannerOptions:
    """goal_bias: chance of a GoalZoom sample; goal_tol: both agents within this of the goal (BL);
    n_psi: field angles tried per EXTEND (plus 4 relative to the pair's heading and `n_random`
    random ones); dts: step times tried (s); max_nodes, time_s: when to stop; r_margin: the tree
    keeps this far (BL) inside (r_min, r_max) (0.25: 1.75-3.25 BL by default), because an
    attracting pair is unstable (a little closer, a lot faster) and a path grazing r_min would
    collapse under the smallest error.

    Beyond Alg. 1-3 (all off here, on in `fast()`; docs/pair.md, measured by bench/pair.py):
    bidirectional: also grow a goal tree back in time, joined by `steer_along` (join_bl: how
    near the trees must come; steer_tol, steer_sep_tol: how near a followed waypoint's centroid
    and separation vector a step must land, steer_window: how far ahead it may land,
    steer_dts: its step times); connect_steps: EXTENDs of one tree straight at the other's new
    node (one tree: of a new best node at the goal); best_of: solve this many times (seed, then
    seeds [seed, k]) inside time_s and keep the path that takes least time."""

    goal_bias: float = 0.3
    goal_tol: float = 0.15
    n_psi: int = 24
    n_random: int = 4
    dts: tuple[float, ...] = (0.1, 0.25, 0.5)
    max_nodes: int = 20000
    time_s: float = 10.0
    max_tries: int = 4
    r_margin: float = 0.25
    connect_steps: int = 0
    best_of: int = 1
    bidirectional: bool = False
    join_bl: float = 0.4
    steer_tol: float = 0.1
    steer_sep_tol: float = 0.5
    steer_window: int = 12
    steer_dts: tuple[float, ...] = (0.1, 0.2, 0.3, 0.45, 0.6)

    @classmethod
    def paper(cls, **changes) -> "PairPlannerOptions":
        """Alg. 1-3 as printed: GoalZoom sampling and brute-force EXTEND, nothing else."""
        return cls(**changes)

    @classmethod
    def fast(cls, **changes) -> "PairPlannerOptions":
        """The paper's RRT plus two additions (see docs/pair.md, both measured by bench/pair.py):
        bidirectional: a second tree grows back in time from the goal (`solve_bidirectional`);
        connect_steps: a tree's new node is pulled at by the other tree (or, with one tree, a
        new best node is pushed straight at the goal) for up to this many EXTENDs while the
        distance still falls."""
        return cls(**{"connect_steps": 40, "bidirectional": True, **changes})


@dataclass
class PairPath:
    """Plan output: start (4,), states (k, 4) after each segment, controls (k, 3), dts (k,)."""

    start: np.ndarray
    states: np.ndarray
    controls: np.ndarray
    dts: np.ndarray
    solved: bool
    goal_distance: float  # BL, larger agent distance from its goal at the path's end
    nodes: int
    seconds: float
    reached_goal: int = 0  # index of the goal reached (re-plans have several)


def _pair_cost(c: np.ndarray, d: np.ndarray, c_s: np.ndarray, d_s: np.ndarray) -> np.ndarray:
    """sum_i |P_i - S_i|^2 for agents P = c -+ d/2, S = c_s -+ d_s/2: = 2|c - c_s|^2 + |d - d_s|^2/2."""
    return 2.0 * np.sum((c - c_s) ** 2, axis=-1) + 0.5 * np.sum((d - d_s) ** 2, axis=-1)


def _sep_vector(q: np.ndarray) -> np.ndarray:
    return q[..., 2:3] * np.stack([np.cos(q[..., 3]), np.sin(q[..., 3])], axis=-1)


def goal_error(q: ArrayLike, goal: ArrayLike) -> np.ndarray:
    """Larger of the two agents' distances (BL) from their goal positions."""
    d = agent_positions(q) - agent_positions(goal)
    return np.max(np.hypot(d[..., 0], d[..., 1]), axis=-1)


class PairRRT:
    """Unidirectional RRT with GoalZoom sampling and brute-force EXTEND (Alg. 1-3)."""

    def __init__(self, problem: PairProblem, options: PairPlannerOptions,
                 rng: np.random.Generator) -> None:
        self.problem = problem
        self.options = options
        self.rng = rng
        xmin, ymin, xmax, ymax = problem.workspace.bounds
        self.lo = np.array([xmin, ymin]) / problem.diameter_mm
        self.hi = np.array([xmax, ymax]) / problem.diameter_mm
        self._psi_grid = np.linspace(-math.pi, math.pi, options.n_psi, endpoint=False)
        self._dts = np.asarray(options.dts, dtype=float)
        if self._dts.max() > MAX_SEGMENT_S or self._dts.min() <= 0:
            raise PlanError(f"step times must lie in (0, {MAX_SEGMENT_S:g}] s, got {options.dts}")

    def solve(self, start: ArrayLike, goals: ArrayLike) -> PairPath:
        """Grow from `start` (4,) until any of `goals` (g, 4) is reached within goal_tol."""
        t0 = time.perf_counter()
        opt = self.options
        start = np.asarray(start, dtype=float)
        goals = np.asarray(goals, dtype=float).reshape(-1, 4)
        tree = _Tree(start, opt.max_nodes)
        errors = goal_error(start[None], goals)
        best, best_err, best_goal = 0, float(errors.min()), int(errors.argmin())
        while best_err > opt.goal_tol and tree.n < tree.cap and time.perf_counter() - t0 < opt.time_s:
            sample = self._sample(goals[best_goal], best_err)
            new = None if sample is None else self._grow(tree, sample, backward=False)
            # a new best node is pushed straight at its goal while that still helps
            for _ in range(1 + opt.connect_steps):
                if new is None:
                    break
                err = goal_error(tree.nodes[new][None], goals)
                if err.min() >= best_err:
                    break
                best, best_err, best_goal = new, float(err.min()), int(err.argmin())
                if best_err <= opt.goal_tol or tree.n >= tree.cap or not opt.connect_steps:
                    break
                new = self._grow(tree, goals[best_goal], backward=False, near=best)
        path = self._path(start, tree, best, best_err, best_err <= opt.goal_tol, t0)
        path.reached_goal = best_goal
        return path

    def solve_bidirectional(self, start: ArrayLike, goal: ArrayLike) -> PairPath:
        """A second tree grows back in time from the goal (EXTEND with negative step times), so
        the way into a narrow goal (the micro-factory's chambers) is found from the inside out.
        Each tree's new node pulls the other tree towards it (up to `connect_steps` EXTENDs
        while the distance falls); when a forward node comes within `join_bl` of a goal-tree
        node, the goal tree's branch from there is followed forward by `steer_along` (the goal
        tree's controls cannot simply be replayed: the open-loop chain is chaotic)."""
        t0 = time.perf_counter()
        opt = self.options
        start = np.asarray(start, dtype=float)
        goal = np.asarray(goal, dtype=float)
        trees = [_Tree(start, opt.max_nodes), _Tree(goal, opt.max_nodes)]
        tried: set[tuple[int, int]] = set()
        best_err = float(goal_error(start[None], goal[None])[0])
        if best_err <= opt.goal_tol:
            return self._path(start, trees[0], 0, best_err, True, t0)
        tail = None
        while time.perf_counter() - t0 < opt.time_s and all(t.n < t.cap for t in trees):
            for side in (0, 1):
                grow, other = trees[side], trees[1 - side]
                sample = self._sample(goal if side == 0 else start, best_err if side == 0 else
                                      float(goal_error(start[None], goal[None])[0]))
                if sample is None:
                    continue
                new = self._grow(grow, sample, backward=side == 1)
                if new is None:
                    continue
                # the other tree connects towards the new node
                near = other.nearest_agents(grow.nodes[new])
                for _ in range(opt.connect_steps):
                    err = float(goal_error(other.nodes[near][None], grow.nodes[new][None])[0])
                    added = self._grow(other, grow.nodes[new], backward=side == 0, near=near)
                    if added is None or float(goal_error(other.nodes[added][None],
                                                         grow.nodes[new][None])[0]) >= err:
                        break
                    near = added
                pair = (new, near) if side == 0 else (near, new)
                err = float(goal_error(trees[0].nodes[pair[0]][None],
                                       trees[1].nodes[pair[1]][None])[0])
                best_err = min(best_err, float(goal_error(trees[0].nodes[pair[0]][None], goal[None])[0]))
                if err <= opt.join_bl and pair not in tried:
                    tried.add(pair)
                    waypoints = trees[1].nodes[trees[1].branch(pair[1])]  # goal-tree node .. goal
                    tail = steer_along(self.problem, trees[0].nodes[pair[0]], waypoints, opt,
                                       final=goal)
                    if tail is not None:
                        break
            if tail is not None:
                break
        if tail is None:
            k = int(np.argmin(goal_error(trees[0].nodes[:trees[0].n], goal[None])))
            err = float(goal_error(trees[0].nodes[k][None], goal[None])[0])
            return self._path(start, trees[0], k, err, False, t0)
        head = self._path(start, trees[0], pair[0], 0.0, True, t0)
        states, controls, dts = tail
        err = float(goal_error(states[-1][None], goal[None])[0])
        return PairPath(start=start, states=np.vstack([head.states, states]),
                        controls=np.vstack([head.controls, controls]),
                        dts=np.concatenate([head.dts, dts]), solved=True, goal_distance=err,
                        nodes=trees[0].n + trees[1].n, seconds=time.perf_counter() - t0)

    def _grow(self, tree: "_Tree", sample: np.ndarray, backward: bool, near: int | None = None):
        if near is None:
            near = tree.nearest(sample)
        new = self._extend(tree.nodes[near], sample, backward=backward)
        if new is None:
            return None
        return tree.add(new[0], near, new[1], abs(new[2]))

    @staticmethod
    def _path(start, tree: "_Tree", k: int, err: float, solved: bool, t0: float) -> PairPath:
        chain = tree.branch(k)[::-1][1:]  # root excluded
        return PairPath(start=start, states=tree.nodes[chain].copy(),
                        controls=tree.controls[chain].copy(), dts=tree.dts[chain].copy(),
                        solved=solved, goal_distance=err, nodes=tree.n,
                        seconds=time.perf_counter() - t0)

    def _sample(self, goal: np.ndarray, best_err: float) -> np.ndarray | None:
        """GoalZoom: near the goal (spread shrinking with the best distance so far) or uniform."""
        prob, rng = self.problem, self.rng
        for _ in range(20):
            if rng.random() < self.options.goal_bias:
                spread = max(self.options.goal_tol, 0.5 * best_err)
                pos = agent_positions(goal) + rng.normal(0.0, spread, (2, 2))
                q = state_from_positions(pos)
            else:
                q = np.array([*rng.uniform(self.lo, self.hi), rng.uniform(prob.r_min, prob.r_max),
                              rng.uniform(-math.pi, math.pi)])
            if not prob.separation_ok(q[2]):
                continue
            if bool(prob.agents_free(q[None], prob.sample_workspace)[0]):
                return q
        return None

    def _extend(self, q: np.ndarray, sample: np.ndarray, backward: bool = False):
        """Alg. 3: every (psi_g, dt) integrated at once; the pull for each in closed form.
        `backward`: integrate back in time (the goal tree): the returned dt is negative, and
        the control held for -dt from the returned state leads to q."""
        psi = np.concatenate([
            self._psi_grid, heading_angles(q[3]),
            self.rng.uniform(-math.pi, math.pi, self.options.n_random),
        ])
        psi_g, dt = (a.ravel() for a in np.meshgrid(psi, -self._dts if backward else self._dts,
                                                    indexing="ij"))
        margin = self.options.r_margin
        ranked = rank_controls(q, sample, psi_g, dt, self.problem, SUBSTEPS,
                               (self.problem.r_min + margin, self.problem.r_max - margin))
        if ranked is None:
            return None
        order, u, rs, ps = ranked
        t = np.linspace(0.0, 1.0, SUBSTEPS + 1)[:, None]
        for k in order[: self.options.max_tries]:
            centre = q[:2] + u[k, 1:] * dt[k] * t
            states = np.column_stack([centre, rs[:, k], ps[:, k]])
            if self.problem.agents_free(states).all():
                return states[-1], u[k], float(dt[k])
        return None


class _Tree:
    """Nodes (cap, 4), parent, the control and step time of the edge into each node."""

    def __init__(self, root: np.ndarray, max_nodes: int) -> None:
        self.cap = max_nodes + 1
        self.nodes = np.zeros((self.cap, 4))
        self.nodes[0] = root
        self.parent = np.full(self.cap, -1)
        self.controls = np.zeros((self.cap, 3))
        self.dts = np.zeros(self.cap)
        self.n = 1

    def add(self, q: np.ndarray, parent: int, u: np.ndarray, dt: float) -> int:
        k = self.n
        self.nodes[k], self.parent[k], self.controls[k], self.dts[k] = q, parent, u, dt
        self.n += 1
        return k

    def nearest(self, sample: np.ndarray) -> int:
        """Nearest node by the planner's metric (sum of the agents' squared distances)."""
        nodes = self.nodes[:self.n]
        return int(np.argmin(_pair_cost(nodes[:, :2], _sep_vector(nodes), sample[:2],
                                        _sep_vector(sample))))

    def nearest_agents(self, q: np.ndarray) -> int:
        """Node whose farther agent is nearest (the goal test's metric)."""
        return int(np.argmin(goal_error(self.nodes[:self.n], q[None])))

    def branch(self, k: int) -> list[int]:
        """Node indices from k up to the root."""
        out = [k]
        while self.parent[out[-1]] >= 0:
            out.append(int(self.parent[out[-1]]))
        return out


def steer_along(problem: PairProblem, q0: ArrayLike, waypoints: ArrayLike,
                options: PairPlannerOptions, *, final: ArrayLike | None = None):
    """Follow waypoints (m, 4) forward from the state q0 (4,) with new segments, each simulated
    from where the last one really ended (so nothing of the waypoints' own controls is
    replayed): every step tries all field angles (grid + zero-radial) and step times at once and
    takes the segment that lands within `steer_tol` of the farthest waypoint (up to
    `steer_window` ahead); failing that, the one that comes nearest the next waypoint, if it
    comes nearer. Done within goal_tol of `final` (default the last waypoint).

    Joins the goal tree to the start tree (`PairRRT.solve_bidirectional`). Returns (states
    (k, 4), controls (k, 3), dts (k,)) or None if it got stuck."""
    opt = options
    waypoints = np.asarray(waypoints, dtype=float).reshape(-1, 4)
    final = waypoints[-1] if final is None else np.asarray(final, dtype=float)
    waypoints = np.vstack([waypoints, final[None]])
    last = len(waypoints) - 1
    grid = np.linspace(-math.pi, math.pi, opt.n_psi, endpoint=False)
    step_times = np.asarray(opt.steer_dts, dtype=float)
    r_range = (problem.r_min + opt.r_margin, problem.r_max - opt.r_margin)
    q = np.asarray(q0, dtype=float)
    i = 0
    states, controls, dts = [], [], []
    for _ in range(4 * len(waypoints) + 40):
        if float(goal_error(q[None], final[None])[0]) <= opt.goal_tol:
            return np.array(states).reshape(-1, 4), np.array(controls).reshape(-1, 3), np.array(dts)
        psi = np.concatenate([grid, heading_angles(q[3])])
        psi_g, dt = (a.ravel() for a in np.meshgrid(psi, step_times, indexing="ij"))
        rs, ps = propagate_local(q[2], q[3], psi_g, dt, problem.rate, SUBSTEPS, trace=True)
        ok = np.all((rs > r_range[0]) & (rs < r_range[1]), axis=0)
        if not ok.any():
            return None
        end_rp = np.stack([rs[-1], ps[-1]], axis=-1)
        chosen = None
        for j in range(min(i + opt.steer_window, last), i - 1, -1):
            u, ends = _land(q, waypoints[j], psi_g, dt, end_rp, problem.max_pull)
            err = goal_error(ends, waypoints[j][None])
            if j == last:
                landed = err <= opt.goal_tol
            else:  # on the way only the centroid must land; the formation may differ a little
                landed = ((np.hypot(*(ends[:, :2] - waypoints[j, :2]).T) <= opt.steer_tol)
                          & (np.hypot(*(_sep_vector(ends) - _sep_vector(waypoints[j])).T)
                             <= opt.steer_sep_tol))
            reach = np.flatnonzero(ok & landed)
            if len(reach):  # the longest step that lands (then the nearest)
                reach = reach[np.lexsort((err[reach], -dt[reach]))]
            chosen = _first_clear(problem, q, u, dt, rs, ps, reach, j)
            if chosen is not None:
                break
        # no landing: the best step towards the farthest waypoint in sight, else the next ones
        aims = [i + _in_sight(problem, q, waypoints[i:min(i + opt.steer_window, last) + 1])]
        aims += [a for a in range(i, min(i + 3, last + 1)) if a != aims[0]]
        for a in aims if chosen is None else ():
            u, ends = _land(q, waypoints[a], psi_g, dt, end_rp, problem.max_pull)
            cost = _pair_cost(ends[:, :2], _sep_vector(ends), waypoints[a, :2],
                              _sep_vector(waypoints[a]))
            now = float(_pair_cost(q[:2], _sep_vector(q), waypoints[a, :2],
                                   _sep_vector(waypoints[a])))
            reach = np.flatnonzero(ok & (cost < now - 1e-4))
            chosen = _first_clear(problem, q, u, dt, rs, ps, reach[np.argsort(cost[reach])], a)
            if chosen is not None:
                break
        if chosen is None:
            log.debug("steer_along: stuck before waypoint %d of %d, %.3f BL from it", i, last,
                      float(goal_error(q[None], waypoints[i][None])[0]))
            return None
        q, u_k, dt_k, j = chosen
        states.append(q)
        controls.append(u_k)
        dts.append(dt_k)
        if np.hypot(*(q[:2] - waypoints[j, :2])) <= opt.steer_tol and np.hypot(
                *(_sep_vector(q) - _sep_vector(waypoints[j]))) <= opt.steer_sep_tol:
            i = min(j + 1, last)
    return None


def _first_clear(problem: PairProblem, q, u, dt, rs, ps, candidates, j):
    """The first of `candidates` (indices, best first) whose whole segment keeps both agents
    clear of the walls, as (end state, control, dt, j); every trace checked at once."""
    if not len(candidates):
        return None
    t = np.linspace(0.0, 1.0, rs.shape[0])[:, None, None]
    centre = q[:2] + u[candidates, 1:] * (dt[candidates, None] * t)
    trace = np.concatenate([centre, rs[:, candidates, None], ps[:, candidates, None]], axis=-1)
    clear = np.flatnonzero(problem.agents_free(trace).all(axis=0))
    if not len(clear):
        return None
    k = candidates[clear[0]]
    return trace[-1, clear[0]], u[k], float(dt[k]), j


def _in_sight(problem: PairProblem, q: np.ndarray, ahead: np.ndarray, margin_bl: float = 0.15) -> int:
    """Index of the farthest of the states `ahead` (m, 4) that each agent can reach from q in a
    straight line keeping `margin_bl` more than its radius from every wall (0 if none)."""
    s = np.linspace(0.0, 1.0, 24)[None, :, None, None]
    p0, p1 = agent_positions(q)[None, None], agent_positions(ahead)[:, None]
    lines = (p0 + s * (p1 - p0)) * problem.diameter_mm  # (m, 24, 2, 2) mm
    clear = problem.workspace.clearance(lines) >= (0.5 + margin_bl) * problem.diameter_mm
    seen = np.flatnonzero(clear.reshape(len(ahead), -1).all(axis=1))
    return int(seen.max()) if len(seen) else 0


def _land(q, target, psi_g, dt, end_rp, max_pull):
    """Controls (m, 3) and end states (m, 4) of candidates psi_g, dt whose (r, phi) end at
    end_rp (m, 2), with the pull inside the coils' box that brings the centroid nearest the
    target's."""
    bx, by = pull_box(psi_g, max_pull)
    want = (target[:2] - q[:2])[None, :] / dt[:, None]  # the pull that would land on the target
    f = np.stack([np.clip(want[:, 0], -bx, bx), np.clip(want[:, 1], -by, by)], axis=-1)
    ends = np.column_stack([q[:2] + f * dt[:, None], end_rp])
    return np.column_stack([psi_g, f]), ends


def heading_angles(phi: float) -> np.ndarray:
    """Global field angles at +-54.74 deg and +-125.26 deg from the pair's heading: zero radial
    force, transverse force either way (the angles that hold a formation)."""
    z = ZERO_RADIAL_ANGLE_RAD
    return phi + np.array([z, -z, math.pi - z, z - math.pi])


def rank_controls(q: np.ndarray, target: np.ndarray, psi_g: np.ndarray, dt: np.ndarray,
                  problem: PairProblem, steps: int, r_range: tuple[float, float],
                  max_pull: float | None = None):
    """Brute force over candidate field angles psi_g (m,) held for dt (m,) from q (4,) towards
    `target` (4,): the pull of each is the one inside the coils' box that brings the centroid
    nearest to the target's (the cost separates, see `_pair_cost`), so only (r, phi) need
    integrating. Candidates whose separation leaves `r_range` on the way are dropped (from a
    state outside it: those that go further out than it).

    Returns (order of valid candidates, best first; controls (m, 3); r and phi traces
    (steps + 1, m)), or None if no candidate is valid."""
    rs, ps = propagate_local(q[2], q[3], psi_g, dt, problem.rate, steps, trace=True)
    # a measured state may start inside the margin (a re-plan): then no worse than it started
    low, high = min(r_range[0], q[2]), max(r_range[1], q[2])
    ok = np.all((rs >= low) & (rs <= high), axis=0)
    if not ok.any():
        return None
    u, ends = _land(q, target, psi_g, dt, np.stack([rs[-1], ps[-1]], axis=-1),
                    problem.max_pull if max_pull is None else max_pull)
    cost = _pair_cost(ends[:, :2], _sep_vector(ends), target[:2], _sep_vector(target))
    order = np.flatnonzero(ok)[np.argsort(cost[ok])]
    return order, u, rs, ps


def plan_pair(problem: PairProblem, start: ArrayLike, goal: ArrayLike,
              options: PairPlannerOptions = PairPlannerOptions(), seed: int = 0) -> PairPath:
    """Plan from `start` to `goal` (states (4,), BL and rad). Raises PlanError for a start or goal
    that is not valid (agents in walls, separation out of range)."""
    for name, q in (("start", start), ("goal", goal)):
        q = np.asarray(q, dtype=float)
        if not bool(problem.separation_ok(q[2])):
            raise PlanError(f"{name}: separation {q[2]:g} BL is outside ({problem.r_min:g}, "
                            f"{problem.r_max:g}); change --r-min/--r-max or the {name}")
        if not bool(problem.agents_free(q[None])[0]):
            p = agent_positions(q) * problem.diameter_mm
            raise PlanError(f"{name}: an agent at ({p[0, 0]:.2f}, {p[0, 1]:.2f}) or "
                            f"({p[1, 0]:.2f}, {p[1, 1]:.2f}) mm is inside a wall or too close to one")
    t0 = time.perf_counter()
    best = None
    for attempt in range(max(1, options.best_of)):
        left = options.time_s - (time.perf_counter() - t0)
        if attempt and left <= 0:
            break
        rng = np.random.default_rng(seed if attempt == 0 else [seed, attempt])
        rrt = PairRRT(problem, replace(options, time_s=left), rng)
        path = rrt.solve_bidirectional(start, goal) if options.bidirectional else rrt.solve(start, goal)
        if best is None or _shorter(path, best):
            best = path
        best.nodes = max(best.nodes, path.nodes)
    best.seconds = time.perf_counter() - t0
    return best


def _shorter(a: PairPath, b: PairPath) -> bool:
    """Solved beats unsolved; then the shorter in time; unsolved, the nearer the goal."""
    if a.solved != b.solved:
        return a.solved
    return float(a.dts.sum()) < float(b.dts.sum()) if a.solved else a.goal_distance < b.goal_distance


def replan_pair(problem: PairProblem, measured: ArrayLike, path_states: ArrayLike,
                from_index: int, options: PairPlannerOptions = PairPlannerOptions(),
                seed: int = 0) -> tuple[PairPath, int]:
    """Re-plan from a measured state back onto a path: grow until any node of `path_states` at or
    after `from_index` is reached. Returns the connecting path and the index of the node reached
    (continue with the original segments after it)."""
    targets = np.asarray(path_states, dtype=float)[from_index:]
    if len(targets) == 0:
        raise PlanError("nothing left of the path to re-plan onto")
    path = PairRRT(problem, options, np.random.default_rng(seed)).solve(measured, targets)
    return path, from_index + path.reached_goal


# -- plan documents (kind pair-formation) ---------------------------------------------------------

def state_to_doc(q: ArrayLike, diameter_mm: float) -> dict:
    q = np.asarray(q, dtype=float)
    return {"x_mm": round(float(q[0] * diameter_mm), 9), "y_mm": round(float(q[1] * diameter_mm), 9),
            "r_bl": round(float(q[2]), 9), "phi_deg": round(math.degrees(float(q[3])), 9)}


def state_of(doc, diameter_mm: float) -> np.ndarray:
    """A plan's PairState as q (4,) in BL and rad."""
    return np.array([doc.x_mm / diameter_mm, doc.y_mm / diameter_mm, doc.r_bl,
                     math.radians(doc.phi_deg)])


def physics_of(plan) -> PairPhysics:
    a = plan.agents
    return PairPhysics(a.body_diameter_mm, a.moment_Am2, a.viscosity_Pa_s)


def problem_of(plan, workspace=None) -> PairProblem:
    from rigctl.plans.checks import plan_workspace

    ws = workspace if workspace is not None else plan_workspace(plan)
    return PairProblem(ws, physics_of(plan), plan.r_min_bl, plan.r_max_bl, plan.max_pull_bl_s,
                       sample_workspace=hull_workspace(plan.workspace) or ws)


def plan_arrays(plan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(start (4,), controls (k, 3) with psi in rad, dts (k,)) of a pair-formation plan."""
    d = plan.agents.body_diameter_mm
    start = state_of(plan.start, d)
    controls = np.array([[math.radians(s.psi_deg), s.f_x, s.f_y] for s in plan.segments]).reshape(-1, 3)
    dts = np.array([s.dt_s for s in plan.segments], dtype=float)
    return start, controls, dts


def simulate(plan):
    """A copy of the plan with `expected` filled in by the model."""
    start, controls, dts = plan_arrays(plan)
    states = rollout(start, controls, dts, physics_of(plan).rate_per_s)
    d = plan.agents.body_diameter_mm
    copy = plan.model_copy(update={"expected": [
        type(plan.start).model_validate(state_to_doc(q, d)) for q in states]})
    copy._source, copy._base_dir = plan._source, plan._base_dir
    return copy


def check(plan) -> None:
    """Semantic checks of a pair-formation plan; PlanError naming the field.

    Start and goal valid (agents in free space, separation in range); every segment's pull within
    the plan's max_pull_bl_s box at its field angle, its separation in range and its agents clear
    of walls along the way; `expected` (if given) reproduced by the model within 1e-6.
    """
    source = plan.source
    prob = problem_of(plan)
    d = plan.agents.body_diameter_mm
    if plan.r_min_bl >= plan.r_max_bl:
        raise PlanError(f"{source}: r_min_bl: {plan.r_min_bl:g} is not below r_max_bl {plan.r_max_bl:g}")
    for name in ("start", "goal"):
        q = state_of(getattr(plan, name), d)
        if not bool(prob.separation_ok(q[2])):
            raise PlanError(f"{source}: {name}.r_bl: {q[2]:g} is outside (r_min_bl, r_max_bl) = "
                            f"({plan.r_min_bl:g}, {plan.r_max_bl:g})")
        if not bool(prob.agents_free(q[None])[0]):
            raise PlanError(f"{source}: {name}: an agent is inside a wall or closer to one than its "
                            f"radius ({0.5 * d:g} mm)")
    start, controls, dts = plan_arrays(plan)
    if plan.expected is not None and len(plan.expected) != len(plan.segments):
        raise PlanError(f"{source}: expected: has {len(plan.expected)} entries for "
                        f"{len(plan.segments)} segments (one per segment)")
    # segment by segment, each from the expected state before it (without `expected`, from the
    # replay): the open-loop chain is chaotic, so a whole-chain replay would amplify rounding
    # differences past any tolerance
    q = start
    for k, (u, dt) in enumerate(zip(controls, dts)):
        problem = prob.edge_problem(q, u, float(dt))
        if problem is not None:
            raise PlanError(f"{source}: segments.{k}: {problem}")
        q = step_state(q, u, float(dt), prob.rate) if plan.expected is None else \
            state_of(plan.expected[k], d)
    if plan.expected is None:
        return
    before = [start] + [state_of(doc, d) for doc in plan.expected[:-1]]
    for k, (q0, u, dt, doc) in enumerate(zip(before, controls, dts, plan.expected)):
        got = step_state(q0, u, float(dt), prob.rate)
        want = state_of(doc, d)
        diff = np.abs(got - want)
        diff[3] = abs(float(wrap_angle(got[3] - want[3])))
        if diff.max() > REPLAY_TOLERANCE * max(1.0, float(np.abs(want[:3]).max())):
            raise PlanError(f"{source}: expected.{k}: the model gives {state_to_doc(got, d)} after "
                            f"segment {k}, not {doc.model_dump()}")


# -- command line: `rigctl plan pair` --------------------------------------------------------------

PULL_MARGIN = 0.8
"""Share of the rig's largest pull the planner uses: the rest is for the tracking controller."""


def add_cli(planners) -> None:
    """Add `pair` to the `rigctl plan` subparsers."""
    p = planners.add_parser(
        "pair", help="two interacting agents (seed 002): rank check or RRT over field angle + pull",
        description="--check CONFIG: the Lie-bracket rank of eq. 5 at a formation "
        '(CONFIG = {"r": BL, "phi": rad, "psi_deg": deg}, JSON text or a file). Otherwise plan '
        "from --start to --goal (X_MM,Y_MM,R_BL,PHI_DEG: centroid, separation in body diameters, "
        "heading of agent 1 -> 2) and write a pair-formation plan. Exit 0 solved (or rank 3), "
        "1 not solved (plan still written) or rank < 3, 2 bad input.",
    )
    p.add_argument("--check", metavar="CONFIG", help="controllability check only")
    p.add_argument("--workspace", metavar="WS.json", help="workspace document (or a plan's)")
    p.add_argument("--start", metavar="X,Y,R,PHI", help="start formation")
    p.add_argument("--goal", metavar="X,Y,R,PHI", help="goal formation")
    p.add_argument("--r-min", type=float, default=1.5, help="smallest separation, BL (default 1.5)")
    p.add_argument("--r-max", type=float, default=3.5, help="largest separation, BL (default 3.5)")
    p.add_argument("--goal-bias", type=float, default=PairPlannerOptions.goal_bias,
                   help="GoalZoom: chance of sampling near the goal (default 0.3)")
    p.add_argument("--paper", action="store_true",
                   help="Alg. 1-3 as printed (one tree, GoalZoom, brute-force EXTEND); default: "
                   "also a goal tree grown back in time and connect steps (see docs/pair.md)")
    p.add_argument("--best-of", type=int, default=1, metavar="N",
                   help="solve N times (within --time) and keep the quickest path (default 1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--time", type=float, default=20.0, metavar="T", help="time limit, s (default 20)")
    p.add_argument("--tolerance", type=float, default=0.2, metavar="BL",
                   help="goal tolerance written into the plan (execution), BL (default 0.2)")
    p.add_argument("--hold", type=float, default=3.0, metavar="S", help="hold the goal S s (default 3)")
    p.add_argument("--field-mT", type=float, default=2.0, help="field magnitude (default 2 mT)")
    p.add_argument("--diameter", type=float, default=PairPhysics.body_diameter_mm,
                   help="body diameter, mm")
    p.add_argument("--moment", type=float, default=PairPhysics.moment_Am2, help="moment, A m^2")
    p.add_argument("--viscosity", type=float, default=PairPhysics.viscosity_Pa_s, help="Pa s")
    p.add_argument("--rig", metavar="RIG.toml", help="coils whose pull bounds the plan (default: "
                   "the emulated six-coil bench's)")
    p.add_argument("--name", help="plan name")
    p.add_argument("-o", "--output", metavar="PLAN.json", help="plan file to write")
    p.add_argument("--json", action="store_true", help="end the output with one JSON line")
    p.set_defaults(func=run_cli)


def _config_arg(text: str) -> dict:
    import json
    from pathlib import Path

    try:
        data = json.loads(Path(text).read_text() if not text.lstrip().startswith("{") else text)
    except (OSError, ValueError) as err:
        raise PlanError(f"--check: {text!r} is neither a JSON object nor a readable JSON file: "
                        f"{err}") from None
    missing = [k for k in ("r", "phi", "psi_deg") if k not in data]
    if not isinstance(data, dict) or missing:
        raise PlanError(f'--check: expected {{"r": BL, "phi": rad, "psi_deg": deg}}, missing {missing}')
    return data


def _formation_arg(text: str | None, flag: str) -> list[float]:
    try:
        values = [float(v) for v in (text or "").split(",")]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise PlanError(f"{flag}: expected X_MM,Y_MM,R_BL,PHI_DEG, got {text!r}")
    return values


def rig_max_pull(rig, physics: PairPhysics, field_mT: float) -> float:
    """The largest pull (BL/s) the rig's coils give these agents with this field, at any angle."""
    from rigctl.physics.coils import max_planar_gradient

    return max_planar_gradient(rig, field_mT * 1e-3) * physics.pull_bl_s_per_T_m


def default_rig():
    """The emulated bench's rig of the kind that runs pair plans: the cube of coils."""
    from rigctl.core.config import RigInfo, default_six_coil_coils

    kind = rig_running("pair-formation")
    return settings_of(kind)(rig=RigInfo(kind=kind, name=f"emulated {kind} bench"),
                             coils=default_six_coil_coils())


def run_cli(args) -> int:
    import json
    from pathlib import Path

    if args.check is not None:
        config = _config_arg(args.check)
        result = controllability(float(config["r"]), float(config["phi"]), float(config["psi_deg"]))
        verdict = "small-time locally controllable" if result["stlc"] else "NOT controllable here"
        print(f"rank {result['rank']} at r = {result['r']:g} BL, psi = {result['psi_deg']:g} deg: "
              f"{verdict}; zero radial force at psi = +-{result['zero_radial_angle_deg']:.2f} deg")
        if args.json:
            print(json.dumps({"rank": result["rank"],
                              "zero_radial_angle_deg": result["zero_radial_angle_deg"]}))
        return EXIT_OK if result["stlc"] else EXIT_NOT_REACHED
    if not args.workspace or not args.output:
        raise PlanError("plan pair: give --workspace, --start, --goal and -o (or --check CONFIG)")
    from rigctl.core.config import load_rig
    from rigctl.plans.checks import WorkspaceSource
    from rigctl.plans.schema import dump_plan, parse_plan

    start_doc = _formation_arg(args.start, "--start")
    goal_doc = _formation_arg(args.goal, "--goal")
    physics = PairPhysics(args.diameter, args.moment, args.viscosity)
    rig = load_rig(args.rig) if args.rig else default_rig()
    max_pull = PULL_MARGIN * rig_max_pull(rig, physics, args.field_mT)
    source = WorkspaceSource(args.workspace)
    output = Path(args.output)
    d = physics.body_diameter_mm
    base = {
        "schema": "rigctl.plan/1", "kind": "pair-formation", "rig": rig_running("pair-formation"),
        "workspace": source.document_for(output),
        "agents": {"body_diameter_mm": d, "moment_Am2": args.moment, "viscosity_Pa_s": args.viscosity},
        "field_mT": args.field_mT, "max_pull_bl_s": round(max_pull, 6),
        "r_min_bl": args.r_min, "r_max_bl": args.r_max,
        "start": dict(zip(("x_mm", "y_mm", "r_bl", "phi_deg"), start_doc)),
        "goal": dict(zip(("x_mm", "y_mm", "r_bl", "phi_deg"), goal_doc)),
        "segments": [], "tolerance_bl": args.tolerance, "hold_s": args.hold,
    }
    skeleton = parse_plan(base, str(output), base_dir=output.parent)
    problem = problem_of(skeleton)
    start = state_of(skeleton.start, d)
    goal = state_of(skeleton.goal, d)
    variant = PairPlannerOptions.paper if args.paper else PairPlannerOptions.fast
    options = variant(goal_bias=args.goal_bias, time_s=args.time, best_of=args.best_of,
                      goal_tol=min(PairPlannerOptions.goal_tol, args.tolerance))
    path = plan_pair(problem, start, goal, options, seed=args.seed)
    name = args.name or output.stem
    base["name"] = name if path.solved else f"{name} (NOT SOLVED: best path ends " \
        f"{path.goal_distance:.2f} BL from the goal)"
    base["segments"] = [
        {"psi_deg": float(math.degrees(wrap_angle(u[0]))), "f_x": float(u[1]), "f_y": float(u[2]),
         "dt_s": float(dt)} for u, dt in zip(path.controls, path.dts)]
    plan = simulate(parse_plan(base, str(output), base_dir=output.parent))
    check(plan)
    output.write_text(dump_plan(plan))
    summary = {"solved": path.solved, "segments": len(path.dts),
               "duration_s": round(float(path.dts.sum()), 3),
               "goal_distance_bl": round(path.goal_distance, 4), "nodes": path.nodes,
               "seconds": round(path.seconds, 4), "max_pull_bl_s": round(max_pull, 4),
               "plan": str(output)}
    print(f"{'solved' if path.solved else 'NOT solved'}: {summary['segments']} segments, "
          f"{summary['duration_s']:g} s, ends {path.goal_distance:.3f} BL from the goal; "
          f"{path.nodes} nodes in {path.seconds:.2f} s; written to {output}")
    if args.json:
        print(json.dumps(summary))
    return EXIT_OK if path.solved else EXIT_NOT_REACHED
