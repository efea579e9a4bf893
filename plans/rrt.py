"""The global-input RRT of seed 000 (Alg. 1 GENERATERRT, Alg. 2 LOCALPLANNER), batched for speed.

Every robot receives the same move; only contacts with obstacles (and with each other) change the
robots' relative positions. The tree lives in the 2n-dimensional configuration space (n robots, mm).
Each node is reached from its parent by one move of length `robostep` in one of `k` evenly spaced
directions, chosen as the candidate that ends closest to a uniformly drawn free configuration
(LOCALPLANNER); the successor of a configuration under a move comes from the one global-input model
(`GlobalInputModel.apply`), which also decides every collision.

Speed comes from batching: a batch of samples is drawn at once, their nearest tree nodes are found
together in a k-d forest (`NearestNodeIndex`), and the whole batch x k candidate moves is expanded
in ONE call to the model. Within a batch the samples see the tree as it was when the batch started;
the batch is at most an eighth of the tree, so this changes which node a few samples extend and not
the distribution the tree grows with (docs/rrt.md discusses it).

Departures from the paper are options, all off by default (`RrtOptions`): goal bias, greedy descent
toward the goal from each new best node, and a final approach with shorter moves and the common
translation that best fits the remaining error. Randomness comes only from the
`numpy.random.Generator` passed in: the same seed and the same options give the same tree, unless a
time budget stops it.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from rigctl.core.errors import PlanError

log = logging.getLogger(__name__)

TREE_FORMAT = "rigctl.rrt-tree/1"

# A move shorter than this (mm, every robot) leaves the configuration where it was: no new node.
_STUCK_MM = 1e-9
# The final approach checks at most this many fitted translations per batch (the best offsets).
_TRANSLATIONS_PER_BATCH = 16
# Relative positions must improve by this much (mm) to be refined or translated again: free moves
# keep them up to rounding, and the same formation elsewhere is not worth another try.
_OFFSET_GAIN_MM = 1e-3
# Descents add nodes, which are considered in turn; this bounds the nesting.
_MAX_APPROACH_DEPTH = 32
# The longest move an offset descent tries (mm): enough to reach a wall across a room.
_OFFSET_REACH_MM = 80.0
# Near the end, probe the relative positions where a new node is at most once per this many nodes.
_PROBE_EVERY = 256


class FreeSpaceSampler(Protocol):
    """The workspace as the planner sees it: draws robot centres in free space."""

    def sample_free(self, rng: np.random.Generator, n: int, radius: float) -> np.ndarray:
        """n centres (n, 2) mm where a disc of `radius` mm lies in free space."""


class GlobalInputPropagator(Protocol):
    """What the planner needs from the global-input model (plans/model.py provides it)."""

    workspace: FreeSpaceSampler
    radii: np.ndarray

    def apply(self, positions: np.ndarray, moves: np.ndarray) -> np.ndarray:
        """positions (..., n, 2) mm and moves (..., 2) mm, broadcast -> positions (..., n, 2)."""

    def free_displacement(self, moves: np.ndarray) -> np.ndarray:
        """Each robot's displacement (..., n, 2) under moves (..., 2) with nothing in the way
        (the move itself unless the robots have their own identified responses)."""

    def fit_translation(self, residual: np.ndarray) -> np.ndarray:
        """The move (..., 2) whose free displacements best fit residual (..., n, 2)."""


@dataclass(frozen=True)
class RrtOptions:
    """How the tree grows. Defaults follow seed 000 (k = 16, no goal bias, no shortcuts).

    robostep_mm: length of every tree move (Alg. 2's Robostep).
    k: number of evenly spaced candidate directions (ignored with axis_only, which uses 4).
    axis_only: only +x, +y, -x, -y (seed 000 Sec. V-e: the hardware run).
    turn_mm: when set, every move is a whole number of these (one magnet turn on the six-coil rig);
        robostep_mm must then be a whole multiple of it.
    max_nodes: stop when the tree holds this many nodes.
    tolerance_mm: solved when the Euclidean distance in R^2n to the goal is at most this.
    stop_when_solved: stop growing as soon as a node is within tolerance.
    goal_bias: probability that a sample is the goal itself.
    greedy: after each new best node, descend toward the goal with tree moves while that helps.
    final_approach: in that descent also try moves of 1/2 .. 1/64 robostep and the common
        translation that best fits the remaining error (multiples of turn_mm when set); and from
        each node that sets the robots' relative positions better than any before (`offset_error`)
        descend first on that error, then on the distance.
    batch_size: largest number of samples expanded per model call; None: 4,096 for the plain
        algorithm (larger batches cost less per node), 512 with `greedy` or `final_approach`,
        whose descents react to new nodes between batches (with 4,096 they react too late:
        18 / 20 instead of 20 / 20 seeds solved on environment 1).
    formation_bias: probability that a sample is the goal formation translated to a random place
        where every robot fits (the goal's relative positions anywhere: from there one
        translation reaches the goal).
    nn_eps: accept a node up to (1 + nn_eps) times farther than the nearest one (0: exact, as in
        the paper; a k-d search for a sample far from the tree is much cheaper when approximate).
    """

    robostep_mm: float = 5.0
    k: int = 16
    axis_only: bool = False
    turn_mm: float | None = None
    max_nodes: int = 40_000
    tolerance_mm: float = 1.0
    stop_when_solved: bool = True
    goal_bias: float = 0.0
    greedy: bool = False
    final_approach: bool = False
    batch_size: int | None = None
    nn_eps: float = 0.0
    formation_bias: float = 0.0

    def __post_init__(self) -> None:
        if not self.robostep_mm > 0:
            raise PlanError(f"robostep must be > 0 mm, got {self.robostep_mm}")
        if self.k < 1:
            raise PlanError(f"k must be >= 1, got {self.k}")
        if self.max_nodes < 1:
            raise PlanError(f"max_nodes must be >= 1, got {self.max_nodes}")
        if not self.tolerance_mm >= 0:
            raise PlanError(f"tolerance must be >= 0 mm, got {self.tolerance_mm}")
        if not 0.0 <= self.goal_bias <= 1.0:
            raise PlanError(f"goal bias must lie in [0, 1], got {self.goal_bias}")
        if not 0.0 <= self.formation_bias <= 1.0 - self.goal_bias:
            raise PlanError(
                f"formation bias must lie in [0, 1 - goal bias], got {self.formation_bias}"
            )
        if not self.nn_eps >= 0.0:
            raise PlanError(f"nn_eps must be >= 0, got {self.nn_eps}")
        if self.batch_size is not None and self.batch_size < 1:
            raise PlanError(f"batch size must be >= 1, got {self.batch_size}")
        if self.turn_mm is not None:
            if not self.turn_mm > 0:
                raise PlanError(f"turn length must be > 0 mm, got {self.turn_mm}")
            turns = self.robostep_mm / self.turn_mm
            if abs(turns - round(turns)) > 1e-9 or round(turns) < 1:
                raise PlanError(
                    f"robostep {self.robostep_mm:g} mm is not a whole number of magnet turns "
                    f"({self.turn_mm:g} mm each)"
                )

    def tree_moves(self) -> np.ndarray:
        """The candidate moves of Alg. 2, (k, 2) mm: robostep along phi = 2 pi a / k.

        Directions along the axes are exact (cos(pi/2) is set to 0, not 6e-17), so axis moves
        slide exactly along axis-aligned walls.
        """
        return self.robostep_mm * _unit_directions(4 if self.axis_only else self.k)

    def approach_moves(self, objective: str = "distance") -> np.ndarray:
        """Moves tried by a descent toward the goal, (m, 2) mm (without fitted translations).

        Greedy only: the tree moves. Final approach, objective "distance": also 1/2 .. 1/64 of
        robostep; objective "offset" (setting relative positions with contacts): also 2, 4, ...
        robostep up to 80 mm, so that a robot can first reach the wall it must be held by. With
        a turn length, lengths are whole turns instead (1, 2, 4, ... turns).
        """
        directions = _unit_directions(4 if self.axis_only else self.k)
        reach = max(self.robostep_mm, _OFFSET_REACH_MM)
        if not self.final_approach:
            lengths = [self.robostep_mm]
        elif self.turn_mm is not None:
            most = int(round(self.robostep_mm / self.turn_mm))
            if objective == "offset":
                most = max(most, int(reach // self.turn_mm))
            lengths = [self.turn_mm * t for t in sorted({1, most} | {2**j for j in range(9)})
                       if t <= most]
        elif objective == "offset":
            lengths = [self.robostep_mm * 2.0**j for j in range(-6, 5)
                       if self.robostep_mm * 2.0**j <= reach]
        else:
            lengths = [self.robostep_mm / 2.0**j for j in range(7)]
        return np.concatenate([length * directions for length in lengths])

    def legal_moves(self, moves: np.ndarray) -> np.ndarray:
        """Fitted translations (m, 2) mm made legal for these options, row by row.

        Axis-only keeps each row's larger component; a turn length rounds each length to whole
        turns (a row shorter than half a turn becomes (0, 0), which moves nothing).
        """
        moves = np.array(moves, dtype=float).reshape(-1, 2)
        if self.axis_only:
            drop = np.where(np.abs(moves[:, 0]) >= np.abs(moves[:, 1]), 1, 0)
            moves[np.arange(len(moves)), drop] = 0.0
        if self.turn_mm is not None:
            length = np.hypot(moves[:, 0], moves[:, 1])
            turns = np.round(length / self.turn_mm)
            scale = np.where(length > 0, turns * self.turn_mm / np.maximum(length, 1e-300), 0.0)
            moves *= scale[:, None]
        return moves

    def turn_legs(self, moves: np.ndarray) -> np.ndarray:
        """Translations moves (m, 2) mm as three whole-turn moves each, (m, 3, 2) mm, that add up
        to them exactly (with a turn length and any direction; unused legs are (0, 0)).

        A length L that is a whole number of turns t is one move. Otherwise the first leg is
        j = max(0, ceil(L / t) - 2) turns along the translation, which leaves r = L - j t in
        (0, 2t]; two one-turn moves at +-acos(r / 2t) from the translation's direction add up
        to r along it. Rounding each length to whole turns instead misses by up to t / 2.
        """
        moves = np.asarray(moves, dtype=float).reshape(-1, 2)
        legs = np.zeros((len(moves), 3, 2))
        if self.turn_mm is None:
            legs[:, 0] = moves
            return legs
        turn = self.turn_mm
        length = np.hypot(moves[:, 0], moves[:, 1])
        moving = length > _STUCK_MM
        unit = moves / np.where(moving, length, 1.0)[:, None]
        whole = np.abs(length / turn - np.round(length / turn)) <= 1e-9
        first = np.where(whole, np.round(length / turn), np.maximum(np.ceil(length / turn) - 2, 0))
        rest = np.where(whole, 0.0, length - first * turn)  # in (0, 2t] where not whole
        half_angle = np.arccos(np.clip(rest / (2.0 * turn), -1.0, 1.0))
        c, s = np.cos(half_angle), np.sin(half_angle)
        pair = ~whole & moving
        legs[moving, 0] = (first * turn)[moving, None] * unit[moving]
        for leg, sign in ((1, 1.0), (2, -1.0)):
            turned = np.stack([c * unit[:, 0] - sign * s * unit[:, 1],
                               sign * s * unit[:, 0] + c * unit[:, 1]], axis=1)
            legs[pair, leg] = turn * turned[pair]
        return legs

    def legal_move(self, move: np.ndarray) -> np.ndarray | None:
        """The fitted translation `move` (2,) mm made legal for these options, or None.

        Axis-only keeps its larger component; a turn length rounds the length to whole turns.
        """
        move = np.array(move, dtype=float)
        if self.axis_only:
            keep = int(np.argmax(np.abs(move)))
            move[1 - keep] = 0.0
        length = float(np.hypot(move[0], move[1]))
        if self.turn_mm is not None:
            turns = round(length / self.turn_mm)
            if turns < 1:
                return None
            move *= turns * self.turn_mm / length
        if length <= _STUCK_MM:
            return None
        return move


def _unit_directions(k: int) -> np.ndarray:
    """k unit vectors (k, 2) at angles 2 pi a / k, exact along the axes."""
    angles = 2.0 * np.pi * np.arange(k) / k
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    quarter = (4 * np.arange(k)) % k == 0
    directions[quarter] = np.round(directions[quarter])
    return directions


class RrtTree:
    """The tree: configurations (N, n, 2) mm, each node's parent index and the move that reached it.

    The root (index 0) has parent -1 and move (0, 0). Storage grows by doubling. `meta` says what
    the tree was built for (workspace hash, radii, robostep, ...), so a saved tree is only reused
    with the workspace and robots it belongs to.
    """

    def __init__(self, root: ArrayLike, meta: dict | None = None, capacity: int = 1024) -> None:
        root = np.asarray(root, dtype=float)
        if root.ndim != 2 or root.shape[1] != 2:
            raise PlanError(f"tree root must be (n, 2) robot positions, got shape {root.shape}")
        self.n_agents = root.shape[0]
        capacity = max(int(capacity), 1)
        self._nodes = np.empty((capacity, self.n_agents, 2))
        self._parents = np.empty(capacity, dtype=np.int64)
        self._moves = np.empty((capacity, 2))
        self._nodes[0] = root
        self._parents[0] = -1
        self._moves[0] = 0.0
        self._size = 1
        self.meta: dict = dict(meta or {})

    def __len__(self) -> int:
        return self._size

    @property
    def nodes(self) -> np.ndarray:
        """(N, n, 2) mm, a view."""
        return self._nodes[: self._size]

    @property
    def parents(self) -> np.ndarray:
        """(N,) parent index of each node, -1 at the root; a view."""
        return self._parents[: self._size]

    @property
    def moves(self) -> np.ndarray:
        """(N, 2) mm move from the parent to each node; a view."""
        return self._moves[: self._size]

    @property
    def root(self) -> np.ndarray:
        return self._nodes[0]

    def add(self, states: np.ndarray, parents: np.ndarray, moves: np.ndarray) -> np.ndarray:
        """Append nodes: states (b, n, 2) mm, parents (b,), moves (b, 2) mm; returns indices."""
        count = len(parents)
        needed = self._size + count
        if needed > len(self._parents):
            capacity = max(needed, 2 * len(self._parents))
            self._nodes = _grown(self._nodes, capacity, self._size)
            self._parents = _grown(self._parents, capacity, self._size)
            self._moves = _grown(self._moves, capacity, self._size)
        self._nodes[self._size : needed] = states
        self._parents[self._size : needed] = parents
        self._moves[self._size : needed] = moves
        indices = np.arange(self._size, needed)
        self._size = needed
        return indices

    def path_to(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """The way from the root to node `index`: moves (m, 2) mm and node indices (m + 1,)."""
        chain = [int(index)]
        parents = self._parents
        while parents[chain[-1]] >= 0:
            chain.append(int(parents[chain[-1]]))
        chain.reverse()
        nodes = np.asarray(chain, dtype=np.int64)
        return self._moves[nodes[1:]].copy(), nodes

    def save(self, path: str | Path) -> None:
        """Write the tree as .npz: nodes (N, n, 2), parents (N,), moves (N, 2), meta (JSON text)."""
        meta = dict(self.meta, format=TREE_FORMAT)
        with open(path, "wb") as stream:
            np.savez(
                stream,
                nodes=self.nodes,
                parents=self.parents,
                moves=self.moves,
                meta=np.array(json.dumps(meta, sort_keys=True)),
            )

    @classmethod
    def load(cls, path: str | Path) -> "RrtTree":
        """Read a tree written by `save`; PlanError when the file is not one."""
        try:
            with np.load(path, allow_pickle=False) as data:
                nodes = data["nodes"]
                parents = data["parents"]
                moves = data["moves"]
                meta = json.loads(str(data["meta"]))
        except FileNotFoundError:
            raise PlanError(f"tree file {path} does not exist") from None
        except (OSError, KeyError, ValueError) as err:
            raise PlanError(f"{path}: not an RRT tree file ({err})") from None
        if meta.get("format") != TREE_FORMAT:
            raise PlanError(f"{path}: not an RRT tree file (format {meta.get('format')!r})")
        if nodes.ndim != 3 or nodes.shape[2] != 2 or len(parents) != len(nodes) != len(moves):
            raise PlanError(f"{path}: inconsistent tree arrays")
        if len(nodes) == 0 or parents[0] != -1 or np.any(parents[1:] >= np.arange(1, len(nodes))):
            raise PlanError(f"{path}: parents must precede their children")
        meta.pop("format")
        tree = cls(nodes[0], meta=meta, capacity=len(nodes))
        tree.add(nodes[1:], parents[1:], moves[1:])
        return tree


def _grown(array: np.ndarray, capacity: int, used: int) -> np.ndarray:
    grown = np.empty((capacity,) + array.shape[1:], dtype=array.dtype)
    grown[:used] = array[:used]
    return grown


class NearestNodeIndex:
    """Exact Euclidean nearest neighbour over a growing point set, as a forest of k-d trees.

    Points are appended in blocks; each block becomes a small `cKDTree`, and two neighbouring
    trees are rebuilt as one whenever the older is not at least twice the newer (a binary
    counter, Bentley-Saxe). So each point is rebuilt O(log N) times, a query visits O(log N)
    trees, and no rebuild ever copies the whole set twice in a row. A query visits the largest
    tree first and bounds the search in the others by the worst distance found so far.
    """

    def __init__(self, dimension: int) -> None:
        self.dimension = dimension
        self._points = np.empty((1024, dimension))
        self._size = 0
        self._forest: list[tuple[int, int, cKDTree]] = []

    def __len__(self) -> int:
        return self._size

    def extend(self, points: np.ndarray) -> None:
        """Append points (b, dimension); their indices continue from len(self)."""
        points = np.asarray(points, dtype=float).reshape(-1, self.dimension)
        if len(points) == 0:
            return
        needed = self._size + len(points)
        if needed > len(self._points):
            self._points = _grown(self._points, max(needed, 2 * len(self._points)), self._size)
        self._points[self._size : needed] = points
        self._forest.append((self._size, needed, _kd_tree(self._points[self._size : needed])))
        self._size = needed
        forest = self._forest
        while len(forest) >= 2:
            (start, middle, _), (_, stop, _) = forest[-2], forest[-1]
            if middle - start >= 2 * (stop - middle):
                break
            forest[-2:] = [(start, stop, _kd_tree(self._points[start:stop]))]

    def query(self, samples: np.ndarray, eps: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Nearest point to each sample (B, dimension): distances (B,) and indices (B,).

        With eps > 0 the point found is at most (1 + eps) times farther than the nearest.
        """
        samples = np.asarray(samples, dtype=float).reshape(-1, self.dimension)
        # Samples near each other visit the same tree nodes: asking in the order of a coarse
        # grid (8 cells a side over the batch) keeps those in cache (about 1.2x faster); the
        # answers do not depend on the order.
        low, high = samples.min(axis=0, initial=np.inf), samples.max(axis=0, initial=-np.inf)
        cell = max(float((high - low).max()) / 8.0, 1e-300) if len(samples) else 1.0
        order = np.lexsort(np.floor((samples - low) / cell).T[::-1])
        ordered = samples[order]
        best = np.full(len(samples), np.inf)
        index = np.zeros(len(samples), dtype=np.int64)
        for start, _, kd in self._forest:
            worst = best.max(initial=-np.inf)
            bound = np.inf if not np.isfinite(worst) else worst * (1.0 + 1e-12) + 1e-12
            distance, found = kd.query(ordered, k=1, eps=eps, distance_upper_bound=bound)
            closer = distance < best
            best[closer] = distance[closer]
            index[closer] = found[closer] + start
        best[order], index[order] = best.copy(), index.copy()
        return best, index


def _kd_tree(points: np.ndarray) -> cKDTree:
    # sliding-midpoint splits build about twice as fast as balanced ones and query as fast here;
    # leaves of 64: queries from samples far from the tree (most of them, in 4-D) visit many
    # leaves, and fewer, fuller ones cost less (about 1.4x faster than 16 at 40,000 nodes)
    return cKDTree(points, leafsize=64, balanced_tree=False, compact_nodes=False)


@dataclass
class RrtResult:
    """What a planning call found.

    moves (m, 2) mm from the start to the best node; states (m, n, 2) mm the configuration after
    each move; solved: distance <= tolerance; distance: Euclidean distance in R^2n (mm) between
    the final configuration (the start when m = 0) and the goal; nodes: tree size at the end;
    seconds: wall time spent; best_node: index of the final node in `tree`.
    """

    moves: np.ndarray
    states: np.ndarray
    solved: bool
    distance: float
    nodes: int
    seconds: float
    tree: RrtTree
    best_node: int
    history: list[tuple[int, float]] = field(default_factory=list)

ProgressCallback = Callable[[int, float, float], None]


def plan_rrt(
    model: GlobalInputPropagator,
    start: ArrayLike,
    goal: ArrayLike,
    *,
    options: RrtOptions = RrtOptions(),
    rng: np.random.Generator,
    time_budget_s: float | None = None,
    tree: RrtTree | None = None,
    progress: ProgressCallback | None = None,
    progress_every_s: float = 1.0,
) -> RrtResult:
    """Grow an RRT from `start` (n, 2) mm toward `goal` (n, 2) mm; return the best path found.

    With `tree`, the tree (rooted at `start`) is reused: the goal is first answered from its
    nodes, and the tree keeps growing (in place) only if that is not yet within tolerance.
    `time_budget_s` bounds the wall time (the camera loop re-plans mid-run with it); `max_nodes`
    in `options` bounds the tree. `progress(nodes, best_distance_mm, seconds)` is called about
    every `progress_every_s` seconds.
    """
    started = time.perf_counter()
    start = np.asarray(start, dtype=float)
    goal = np.asarray(goal, dtype=float)
    radii = np.asarray(model.radii, dtype=float).reshape(-1)
    n = len(radii)
    if start.shape != (n, 2) or goal.shape != (n, 2):
        raise PlanError(
            f"start and goal must be ({n}, 2) positions for {n} robots, "
            f"got {start.shape} and {goal.shape}"
        )
    if tree is None:
        tree = RrtTree(start, capacity=min(options.max_nodes, 1 << 16))
    elif tree.n_agents != n or not np.allclose(tree.root, start, atol=1e-9, rtol=0):
        raise PlanError("the tree was grown from another start configuration or robot count")

    deadline = None if time_budget_s is None else started + time_budget_s
    search = _GoalSearch(model, tree, goal, options, deadline)
    tree_moves = options.tree_moves()
    batch_cap = options.batch_size
    if batch_cap is None:
        batch_cap = 512 if options.greedy or options.final_approach else 4096
    next_report = started + progress_every_s
    search.consider(np.arange(len(tree)))

    while len(tree) < options.max_nodes and not search.done():
        now = time.perf_counter()
        if deadline is not None and now >= deadline:
            break
        if progress is not None and now >= next_report:
            progress(len(tree), search.best_distance, now - started)
            next_report = now + progress_every_s
        # Samples in a batch see the tree as it was when the batch began; the batch is at most
        # an eighth of the tree so that departs little from one-sample-at-a-time Alg. 1.
        batch = min(batch_cap, max(1, len(tree) // 8), options.max_nodes - len(tree))
        samples = _sample_configurations(model, radii, rng, batch)
        if options.goal_bias > 0.0 or options.formation_bias > 0.0:
            draw = rng.random(batch)
            samples[draw < options.goal_bias] = goal
            formation = np.flatnonzero(
                (draw >= options.goal_bias) & (draw < options.goal_bias + options.formation_bias)
            )
            if len(formation):
                samples[formation] = _goal_formations(model, radii, goal, rng, len(formation))
        _, near = search.index.query(samples.reshape(batch, -1), eps=options.nn_eps)
        parents_at = tree.nodes[near]
        candidates = model.apply(parents_at[:, None], tree_moves[None, :])  # (b, k, n, 2)
        gap = candidates.reshape(batch, len(tree_moves), -1) - samples.reshape(batch, 1, -1)
        gap = np.einsum("bkd,bkd->bk", gap, gap)
        choice = np.argmin(gap, axis=1)  # LOCALPLANNER: the candidate closest to the sample
        new_states = candidates[np.arange(batch), choice]
        moved = np.abs(new_states - parents_at).max(axis=(1, 2)) > _STUCK_MM
        # two samples that pick the same node and the same move would add the same node twice
        _, first = np.unique(near * len(tree_moves) + choice, return_index=True)
        keep = np.zeros(batch, dtype=bool)
        keep[first] = True
        keep &= moved
        if keep.any():
            added = tree.add(new_states[keep], near[keep], tree_moves[choice[keep]])
            search.consider(added)

    seconds = time.perf_counter() - started
    moves, path = tree.path_to(search.best)
    if progress is not None:
        progress(len(tree), search.best_distance, seconds)
    log.info(
        "rrt: %d nodes, best distance %.3f mm after %d moves, %.2f s",
        len(tree), search.best_distance, len(moves), seconds,
    )
    return RrtResult(
        moves=moves,
        states=tree.nodes[path[1:]].copy(),
        solved=search.best_distance <= options.tolerance_mm,
        distance=search.best_distance,
        nodes=len(tree),
        seconds=seconds,
        tree=tree,
        best_node=search.best,
        history=search.history,
    )


class _GoalSearch:
    """Everything plan_rrt keeps about the goal: the nearest-node index over the tree, the node
    closest to the goal, and (with the options that go beyond the paper) the descents toward it.

    `consider(indices)` is called with every batch of nodes added to the tree. It indexes them,
    updates the best node, and then, with `greedy`, descends from a new best node; with
    `final_approach`: a node whose relative robot positions (offset error) beat all seen starts
    a descent on that error (and near the end, now and then, the batch's best node does: a
    probe); a node whose offset error beats every node translated before is translated toward
    the goal when the way is clear, and a descent on the offset error then on the distance
    starts from where that ends. Nodes the descents add are considered in turn.
    """

    def __init__(self, model: GlobalInputPropagator, tree: RrtTree, goal: np.ndarray,
                 options: RrtOptions, deadline: float | None = None) -> None:
        self.model = model
        self.deadline = deadline
        self.tree = tree
        self.goal = goal
        self.goal_flat = goal.reshape(-1)
        self.options = options
        self.index = NearestNodeIndex(goal.size)
        self.best = 0
        self.best_distance = math.inf
        self.history: list[tuple[int, float]] = []
        self.translated_offset = math.inf  # offset error of the last node translated
        self.best_offset = math.inf  # best offset error seen
        # near the end, now and then refine relative positions where a new node is (a probe):
        # the formation at the goal may need a wall elsewhere to fix its last millimetres
        self.next_probe = 0
        self.depth = 0  # nesting of consider() through descents

    def done(self) -> bool:
        return self.options.stop_when_solved and self.best_distance <= self.options.tolerance_mm

    def consider(self, indices: np.ndarray) -> None:
        if len(indices) == 0:
            return
        states = self.tree.nodes[indices]
        self.index.extend(states.reshape(len(indices), -1))
        improved = self._update_best(indices, states)
        if self.done() or (self.deadline is not None and time.perf_counter() >= self.deadline):
            return
        if self.depth >= _MAX_APPROACH_DEPTH:  # descents that keep improving: let the tree grow
            return
        self.depth += 1
        try:
            self._approach(indices, states, improved)
        finally:
            self.depth -= 1

    def _approach(self, indices: np.ndarray, states: np.ndarray, improved: bool) -> None:
        """The work beyond Alg. 1 for a batch of new nodes (see the class docstring)."""
        if self.options.final_approach:
            offsets = offset_error(states, self.goal, self.model)
            closest = int(np.argmin(offsets))
            probe = (
                self.best_distance < 3.0 * self.options.robostep_mm
                and offsets[closest] < self.best_distance + self.options.robostep_mm
                and len(self.tree) >= self.next_probe
            )
            if probe:
                self.next_probe = len(self.tree) + max(_PROBE_EVERY, len(self.tree) // 16)
            if offsets[closest] < self.best_offset - _OFFSET_GAIN_MM or probe:
                # relative positions better than ever, or (probe) close to what would beat the
                # best: try to refine them with contacts where this node is
                self.best_offset = min(self.best_offset, float(offsets[closest]))
                self.consider(self._descend(int(indices[closest]), "offset"))
                if self.done():
                    return
            translated = self._translate(indices, states)
            if len(translated) and not self.done():
                end = int(translated[-1])
                found = self._descend(end, "offset")
                self.consider(found)
                if not self.done():
                    self.consider(self._descend(int(found[-1]) if len(found) else end, "distance"))
                return
        if improved and self.options.greedy:
            self.consider(self._descend(self.best, "distance"))

    def _update_best(self, indices: np.ndarray, states: np.ndarray) -> bool:
        distances = np.linalg.norm(states.reshape(len(indices), -1) - self.goal_flat, axis=1)
        closest = int(np.argmin(distances))
        if distances[closest] < self.best_distance:
            self.best, self.best_distance = int(indices[closest]), float(distances[closest])
            self.history.append((len(self.tree), self.best_distance))
            return True
        return False

    def _descend(self, node: int, objective: str) -> np.ndarray:
        return _descend(self.model, self.tree, node, self.goal, self.options, objective,
                        self.deadline)

    def _translate(self, indices: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Translate the robots of the most promising new node toward the goal, if the way is clear.

        Promising: relative positions (offset error) better than both the best distance so far
        and the last node translated. For the best few, the translation that best fits the
        remaining error is checked straight and as two axis legs (x then y, y then x) against
        the workspace's clearance along every robot's segment; the first clear one is applied
        with the model and added to the tree. Returns the indices of the nodes added.
        """
        offsets = offset_error(states, self.goal, self.model)
        promising = np.flatnonzero(
            offsets < min(self.best_distance, self.translated_offset - _OFFSET_GAIN_MM)
        )
        if len(promising) == 0:
            return np.zeros(0, dtype=np.int64)
        order = np.argsort(offsets[promising], kind="stable")
        promising = promising[order[:_TRANSLATIONS_PER_BATCH]]
        states, indices = states[promising], indices[promising]
        m = len(states)
        fitted = self.model.fit_translation(self.goal - states)  # (m, 2)
        legs_x = self.options.legal_moves(fitted * [1.0, 0.0])
        legs_y = self.options.legal_moves(fitted * [0.0, 1.0])
        straight = self.options.legal_moves(fitted)
        none = np.zeros_like(straight)
        # candidate paths per node, three legs each: [straight], [x leg, y leg], [y leg, x leg],
        # and with whole turns in any direction the exact sum of whole turns (`turn_legs`)
        paths = [np.stack(legs, axis=1) for legs in
                 ((straight, none, none), (legs_x, legs_y, none), (legs_y, legs_x, none))]
        if self.options.turn_mm is not None and not self.options.axis_only:
            paths.append(self.options.turn_legs(fitted))
        legs = np.concatenate(paths)  # (variants * m, 3, 2)
        variants_count = len(paths)
        starts = np.concatenate([states] * variants_count)
        clear = np.ones(len(legs), dtype=bool)
        for leg in range(3):
            clear &= _path_clear(self.model, starts, legs[:, leg])
            starts = starts + legs[:, leg, None, :]
        if not clear.any():
            return np.zeros(0, dtype=np.int64)
        # the node with the best offset whose way is clear; its clear variants through the model
        row = int(np.flatnonzero(clear.reshape(variants_count, m).any(axis=0))[0])
        self.translated_offset = float(offsets[promising[row]])
        variants = [v for v in range(variants_count) if clear[v * m + row]]
        chosen = legs[[v * m + row for v in variants]]  # (V, 3, 2)
        ways = [states[row][None].repeat(len(variants), axis=0)]
        for leg in range(3):
            ways.append(self.model.apply(ways[-1], chosen[:, leg]))
        ends = ways[-1]
        best = int(np.argmin(((ends - self.goal) ** 2).sum(axis=(1, 2))))
        parent = int(indices[row])
        added = []
        for move, state in zip(chosen[best], (way[best] for way in ways[1:])):
            if not np.any(move):
                continue
            parent = int(self.tree.add(state[None], np.array([parent]), move[None])[0])
            added.append(parent)
        added = np.asarray(added, dtype=np.int64)
        if len(added):
            self.index.extend(self.tree.nodes[added].reshape(len(added), -1))
            self._update_best(added, self.tree.nodes[added])
        return added


def _path_clear(model: GlobalInputPropagator, starts: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """True where every robot of starts (m, n, 2) can move by moves (m, 2) touching nothing.

    Checks the clearance at points spaced delta = radius / 2 along each robot's segment: since the
    clearance changes by at most the distance moved, clearance >= r + delta / 2 at every point
    keeps the whole segment clear. Robots that all move freely keep their relative positions,
    so they cannot meet either. A robot sliding along a wall it touches (clearance == r all the
    way, e.g. under the L's bar) also passes: the model slides it parallel to the wall, which
    is a free move; only the model's answer is ever added to the tree, so a miss costs one call.
    """
    radii = np.asarray(model.radii, dtype=float)
    each = model.free_displacement(moves)  # (m, n, 2): robots with their own response differ
    length = np.hypot(each[..., 0], each[..., 1]).max(axis=1, initial=0.0)
    delta = 0.5 * float(radii.min())
    samples = int(np.ceil(length.max() / delta)) + 1 if len(moves) else 1
    fractions = np.linspace(0.0, 1.0, samples)
    points = starts[:, None] + fractions[None, :, None, None] * each[:, None, :, :]
    room = model.workspace.clearance(points) - radii  # (m, samples, n)
    needed = 0.5 * length / max(samples - 1, 1) + 1e-6
    clear = room >= needed[:, None, None]
    grazing = np.abs(room) <= 1e-6
    return np.all(clear | grazing, axis=(1, 2))


def _sample_configurations(
    model: GlobalInputPropagator, radii: np.ndarray, rng: np.random.Generator, count: int
) -> np.ndarray:
    """SAMPLERANDOMFREECONFIG for `count` samples: (count, n, 2) mm, each robot in free space."""
    return np.stack(
        [model.workspace.sample_free(rng, count, float(radius)) for radius in radii], axis=1
    )


def offset_error(states: np.ndarray, goal: np.ndarray,
                 model: GlobalInputPropagator | None = None) -> np.ndarray:
    """Distance (mm) to the goal left after the best common translation, for states (..., n, 2).

    All robots move alike in free space, so a configuration whose robots sit at the goal's
    relative offsets is one unobstructed translation away from the goal; this is what remains
    when that translation is done: sqrt(sum_i |(g_i - x_i) - mean_j (g_j - x_j)|^2). With the
    `model`'s own per-robot responses the translation is the one that fits them best.
    """
    residual = goal - states
    if model is None:
        residual = residual - residual.mean(axis=-2, keepdims=True)
    else:
        residual = residual - model.free_displacement(model.fit_translation(residual))
    return np.sqrt((residual**2).sum(axis=(-1, -2)))


def _goal_formations(
    model: GlobalInputPropagator, radii: np.ndarray, goal: np.ndarray, rng: np.random.Generator,
    count: int,
) -> np.ndarray:
    """`count` copies (count, n, 2) of the goal translated uniformly to where every robot fits.

    Translations are drawn over the workspace bounds shifted by the goal's centre and kept when
    every robot fits; a workspace where the formation fits nowhere else gives the goal itself.
    """
    xmin, ymin, xmax, ymax = model.workspace.bounds
    centre = goal.mean(axis=0)
    found = []
    total = 0
    for _ in range(50):
        shifts = rng.uniform((xmin, ymin), (xmax, ymax), size=(4 * count, 2)) - centre
        placed = goal[None] + shifts[:, None, :]
        fits = np.all(model.workspace.clearance(placed) >= radii, axis=1)
        found.append(placed[fits])
        total += int(fits.sum())
        if total >= count:
            break
    placed = np.concatenate(found)[:count]
    if len(placed) < count:
        placed = np.concatenate([placed, np.repeat(goal[None], count - len(placed), axis=0)])
    return placed


def _descend(
    model: GlobalInputPropagator,
    tree: RrtTree,
    node: int,
    goal: np.ndarray,
    options: RrtOptions,
    objective: str = "distance",
    deadline: float | None = None,
) -> np.ndarray:
    """Greedy descent from tree node `node`; adds the nodes it visits to `tree`.

    Each step applies every approach move to the current configuration in one model call and
    keeps the one that lowers the objective most, while that helps: "distance" is the Euclidean
    distance to `goal` (with the final approach the candidates also include the translation that
    best fits the remaining error, whole and as its x and y legs, and with whole turns the legs
    that add up to it exactly, `RrtOptions.turn_legs`); "offset" is `offset_error`,
    i.e. it uses contacts to set the robots' relative positions for a final translation.
    Returns the indices of the nodes added, in order; stops at `deadline` (perf_counter s).
    """
    moves = options.approach_moves(objective)
    # with whole turns in any direction, a step may also be the fitted translation made of them
    turn_legs = (options.final_approach and objective == "distance"
                 and options.turn_mm is not None and not options.axis_only)
    state = tree.nodes[node].copy()
    score = _score(state[None], goal, objective, model)[0]
    added: list[int] = []
    parent = node
    for _ in range(1000):
        if objective == "distance" and score <= options.tolerance_mm and options.stop_when_solved:
            break
        if deadline is not None and time.perf_counter() >= deadline:
            break
        step_moves = moves
        if options.final_approach and objective == "distance":
            fitted = model.fit_translation(goal - state)
            legs = [options.legal_move(m) for m in (fitted, fitted * [1, 0], fitted * [0, 1])]
            legs = [m for m in legs if m is not None]
            if legs:
                step_moves = np.concatenate([moves, np.array(legs)])
        candidates = model.apply(state[None], step_moves)  # (m, n, 2)
        scores = _score(candidates, goal, objective, model)
        choice = int(np.argmin(scores))
        turns = [leg for leg in options.turn_legs(fitted)[0] if np.any(leg)] if turn_legs else []
        if len(turns) > 1:  # the fitted translation as whole turns that add up to it, leg by leg
            ways = [state]
            for leg in turns:
                ways.append(model.apply(ways[-1], leg))
            combined = _score(ways[-1][None], goal, objective, model)[0]
            if combined < min(scores[choice], score - 1e-9):
                for leg, way in zip(turns, ways[1:]):
                    parent = int(tree.add(way[None], np.array([parent]), leg[None])[0])
                    added.append(parent)
                state, score = ways[-1], float(combined)
                continue
        if not scores[choice] < score - 1e-9:
            break
        state = candidates[choice]
        score = float(scores[choice])
        parent = int(tree.add(state[None], np.array([parent]), step_moves[choice][None])[0])
        added.append(parent)
    return np.asarray(added, dtype=np.int64)


def _score(states: np.ndarray, goal: np.ndarray, objective: str,
           model: GlobalInputPropagator) -> np.ndarray:
    if objective == "offset":
        return offset_error(states, goal, model)
    return np.sqrt(((states - goal) ** 2).sum(axis=(-1, -2)))


def replay(model: GlobalInputPropagator, start: ArrayLike, moves: ArrayLike) -> np.ndarray:
    """Positions after each move (m, n, 2) mm, by applying the moves one by one with `model`."""
    state = np.asarray(start, dtype=float)
    moves = np.asarray(moves, dtype=float).reshape(-1, 2)
    states = np.empty((len(moves),) + state.shape)
    for i, move in enumerate(moves):
        state = model.apply(state, move)
        states[i] = state
    return states


def polish(
    model: GlobalInputPropagator,
    start: ArrayLike,
    goal: ArrayLike,
    moves: ArrayLike,
    options: RrtOptions,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Replay `moves` with `model` (e.g. the exact workspace after planning on a raster) and, if
    the end is outside tolerance, descend toward the goal with the final-approach moves.

    Returns moves (m', 2) mm, states (m', n, 2) mm and the final distance to the goal in mm.
    """
    start = np.asarray(start, dtype=float)
    goal = np.asarray(goal, dtype=float)
    moves = np.asarray(moves, dtype=float).reshape(-1, 2)
    states = replay(model, start, moves)
    end = states[-1] if len(states) else start
    distance = float(np.linalg.norm(end - goal))
    if distance <= options.tolerance_mm:
        return moves, states, distance
    tree = RrtTree(end)
    finishing = RrtOptions(
        robostep_mm=options.robostep_mm,
        k=options.k,
        axis_only=options.axis_only,
        turn_mm=options.turn_mm,
        tolerance_mm=options.tolerance_mm,
        greedy=True,
        final_approach=True,
    )
    added = _descend(model, tree, 0, goal, finishing)
    if len(added) == 0:
        return moves, states, distance
    extra_moves, _ = tree.path_to(int(added[-1]))
    moves = np.concatenate([moves, extra_moves])
    states = np.concatenate([states, tree.nodes[added]])
    return moves, states, float(np.linalg.norm(states[-1] - goal))


def tree_meta(
    *,
    workspace_hash: str,
    radii: ArrayLike,
    contact: str,
    min_separation_mm: float,
    raster_mm: float | None,
    options: RrtOptions,
) -> dict:
    """What a saved tree records about the problem it was grown for (JSON-safe)."""
    return {
        "workspace_hash": workspace_hash,
        "radii": [float(r) for r in np.asarray(radii, dtype=float).reshape(-1)],
        "contact": contact,
        "min_separation_mm": float(min_separation_mm),
        "raster_mm": raster_mm,
        "robostep_mm": options.robostep_mm,
        "k": options.k,
        "axis_only": options.axis_only,
        "turn_mm": options.turn_mm,
    }


def check_tree_meta(tree: RrtTree, expected: dict, source: str = "tree") -> None:
    """Refuse a tree grown for another workspace, robots, contact model or move set (PlanError)."""
    problems = []
    for key, wanted in expected.items():
        have = tree.meta.get(key)
        if isinstance(wanted, list) and isinstance(have, list):
            same = len(wanted) == len(have) and np.allclose(wanted, have, rtol=0, atol=1e-9)
        elif isinstance(wanted, float) and isinstance(have, (int, float)):
            same = math.isclose(wanted, have, rel_tol=0, abs_tol=1e-9)
        else:
            same = wanted == have
        if not same:
            problems.append(f"{key} is {have!r} in the tree but {wanted!r} here")
    if problems:
        raise PlanError(f"{source} was grown for another problem: " + "; ".join(problems))
