"""The global-input model: every agent receives the same displacement, walls and other agents decide.

This is THE model of how agents move under a shared input (seed 000 Sec. II, seed 004 eq. 1). The
planners expand their trees with it, `check_plan` replays plans through it, and the emulated world
moves its robots with it, so all three agree on where an agent ends up.

Semantics, in terms of input progress s (mm of the commanded displacement already applied):

- an agent moves along the input direction u until it touches a surface (clearance == its radius);
- "slide" (rolling magnets, seed 000): while in contact and u points into the surface, the normal
  component of u is removed and the agent slides; a rounded surface (an obstacle's corner, a disk)
  is followed until u no longer points into it, and then the agent continues along u;
- "non-slip" (particles on rough walls, seed 004 eq. 1): while in contact and u points into the
  surface the agent does not move at all. A move exactly parallel to the wall is not "into" it.
- agents are discs that never overlap (centre distance >= r_i + r_j + min_separation): an agent
  pushed into a blocked agent stops against it, or slides around it.

Implementation. Contact with the walls is resolved exactly, event by event: free flight to the
first contact (solved on the contact surface's line or circle), sliding along a line or around a
circle in closed form (see `_arc_point`), and the transitions between them (wall ends, corners,
wedges). On a `ShapeWorkspace` every contact surface is a line or a circle, so a move applied in
pieces gives the whole move's result to ~1e-6 mm (measured: <= 2e-6 mm over random moves in
rect, polygon and disk workspaces). A workspace rasterized from shapes keeps each sample's
nearest wall piece and is just as exact for agents wider than about 1.5 pixels (measured: the
same end points to 1e-12 mm). A grid from a picture knows only its pixels: the same steps use the
interpolated normal, and agents end within about a pixel of where the drawn walls would put
them (inside corners are the worst).

Agent-agent contact is resolved after each sub-step (at most `substep_mm` of input, longer while
agents are far apart) by projecting overlapping pairs apart: an agent the walls hold stays, else
the one behind gives way. Sliding of one agent round another is therefore first order in the
sub-step. Configurations whose agents cannot reach a wall or each other during a move are
translated in one step, and so is every agent of the others that no wall can reach in a sub-step.
When several moves start from the same configuration (a planner's k directions from one node)
the walls are looked up once for it, not once per move, and a configuration no move can bring to
a wall is translated under all of them at once. On exact geometry two shortcuts skip events that
could not change anything: an agent whose whole straight path the workspace finds clear
(`Workspace.sweep_clear`) translates, and an agent sliding along a straight side slides the
rest of its input in one step when the workspace finds that side under the whole slide and
nothing else near (`Workspace.slide_clear`). A slide round a corner that runs onto
the straight side continuing it is solved in closed form (`_arc_meets_line`), not by bisection.

All work is vectorised over the batch; the Python loops run over event rounds and agent pairs,
never over configurations.
"""

from __future__ import annotations

import logging
import math
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import PlanError
from rigctl.plans.workspace import Workspace

log = logging.getLogger(__name__)

Contact = Literal["slide", "non-slip"]

# Positions agree to far better than this; "in contact" means clearance == radius within it (mm).
_CONTACT_TOL = 1e-7
# u . n below -_DIR_EPS means the input points into the surface.
_DIR_EPS = 1e-10
# Curvature (1/mm) below which a contact surface counts as straight.
_FLAT_CURVATURE = 1e-9
# On grids, a penetration whose surface normal turned less than this (cos) is curvature, not a corner.
_GRID_CORNER_COS = math.cos(math.radians(20.0))
_PAIR_ITERATIONS = 6
_TINY = 1e-300


class GlobalInputModel:
    """Moves n disc agents by shared displacements through a workspace.

    radii: (n,) mm. contact: "slide" or "non-slip". min_separation_mm: extra gap kept between agents.
    substep_mm: the longest piece of input between agent-agent checks and between wall look-ups
    while sliding (default: a quarter of the smallest radius).

    gains (n,), headings_rad (n,): each agent's own response to the shared input, identified from
    tracking (`rigctl.physics.identify`): a move u takes agent i by gains[i] R(headings_rad[i]) u. None
    (the default), or all ones and zeros, is the shared displacement, computed exactly as without
    them. With them, every agent moves by its own displacement against the walls, and the agents
    meet one another in pieces of `substep_mm` while they are close enough to (the emulated
    world's rule: the one that moved towards the other gives way).
    """

    def __init__(
        self,
        workspace: Workspace,
        radii: ArrayLike,
        contact: Contact = "slide",
        min_separation_mm: float = 0.0,
        substep_mm: float | None = None,
        gains: ArrayLike | None = None,
        headings_rad: ArrayLike | None = None,
    ) -> None:
        self.workspace = workspace
        self.radii = np.asarray(radii, dtype=float).reshape(-1)
        if self.radii.size == 0 or np.any(self.radii <= 0):
            raise PlanError(f"agent radii must be > 0, got {self.radii.tolist()}")
        if contact not in ("slide", "non-slip"):
            raise PlanError(f"contact must be 'slide' or 'non-slip', got {contact!r}")
        if min_separation_mm < 0:
            raise PlanError(f"min_separation_mm must be >= 0, got {min_separation_mm}")
        self.contact: Contact = contact
        self.min_separation_mm = float(min_separation_mm)
        self.substep_mm = float(substep_mm) if substep_mm else float(self.radii.min()) / 4.0
        if self.substep_mm <= 0:
            raise PlanError(f"substep_mm must be > 0, got {substep_mm}")
        self.n = self.radii.size
        first, second = np.triu_indices(self.n, 1)
        self._pairs = list(zip(first.tolist(), second.tolist()))
        self._pair_first, self._pair_second = first, second
        self._reach = self.radii[first] + self.radii[second] + self.min_separation_mm
        self.gains = self._per_agent(gains, 1.0, "gains")
        self.headings_rad = self._per_agent(headings_rad, 0.0, "headings_rad")
        if np.any(self.gains <= 0):
            raise PlanError(f"gains must be > 0, got {self.gains.tolist()}")
        shared = np.all(self.gains == 1.0) and np.all(self.headings_rad == 0.0)
        c, s = np.cos(self.headings_rad), np.sin(self.headings_rad)
        # (n, 2, 2): agent i moves by response[i] @ u; None: the shared displacement
        self._single: list[GlobalInputModel] | None = None  # one-agent models, made when needed
        self._response = None if shared else self.gains[:, None, None] * np.stack(
            [np.stack([c, -s], axis=1), np.stack([s, c], axis=1)], axis=1)

    def _per_agent(self, values: ArrayLike | None, default: float, name: str) -> np.ndarray:
        if values is None:
            return np.full(self.n, default)
        out = np.asarray(values, dtype=float).reshape(-1)
        if out.shape != (self.n,) or not np.all(np.isfinite(out)):
            raise PlanError(f"{name}: one finite value per agent ({self.n}), got {out.tolist()}")
        return out

    def with_response(self, gains: ArrayLike | None, headings_rad: ArrayLike | None
                      ) -> GlobalInputModel:
        """The same model with these per-agent responses (None: the shared displacement)."""
        return GlobalInputModel(self.workspace, self.radii, self.contact, self.min_separation_mm,
                                self.substep_mm, gains=gains, headings_rad=headings_rad)

    def alone(self, i: int) -> GlobalInputModel:
        """Agent i alone in the workspace: the shared-input model of that one agent (made once)."""
        if self._single is None:
            self._single = [GlobalInputModel(self.workspace, [r], self.contact,
                                             substep_mm=self.substep_mm) for r in self.radii]
        return self._single[i]

    def free_displacement(self, moves: ArrayLike) -> np.ndarray:
        """Each agent's displacement (..., n, 2) mm under moves (..., 2) mm where nothing is in
        its way: the move itself, or its own response's image of it."""
        moves = np.asarray(moves, dtype=float)
        if self._response is None:
            return np.broadcast_to(moves[..., None, :], moves.shape[:-1] + (self.n, 2))
        return np.einsum("nij,...j->...ni", self._response, moves)

    def fit_translation(self, residual: ArrayLike) -> np.ndarray:
        """The move (..., 2) mm whose free displacements best fit residual (..., n, 2) mm (least
        squares): the mean residual, or sum_i A_i^T e_i / sum_i g_i^2 with responses A_i."""
        residual = np.asarray(residual, dtype=float)
        if self._response is None:
            return residual.mean(axis=-2)
        back = np.einsum("nji,...nj->...i", self._response, residual)  # sum_i A_i^T e_i
        return back / float(np.sum(self.gains ** 2))

    # Public API

    def apply(self, positions: ArrayLike, moves: ArrayLike) -> np.ndarray:
        """Apply one shared move to every configuration.

        positions (..., n, 2) mm, moves (..., 2) mm, batch dimensions broadcast -> (..., n, 2).
        """
        positions = np.asarray(positions, dtype=float)
        moves = np.asarray(moves, dtype=float)
        if positions.shape[-2:] != (self.n, 2):
            raise PlanError(f"positions must be (..., {self.n}, 2), got {positions.shape}")
        if moves.shape[-1:] != (2,):
            raise PlanError(f"moves must be (..., 2), got {moves.shape}")
        batch = np.broadcast_shapes(positions.shape[:-2], moves.shape[:-1])
        if self._response is not None:
            flat_p = np.broadcast_to(positions, batch + (self.n, 2)).reshape(-1, self.n, 2).copy()
            flat_d = np.broadcast_to(moves, batch + (2,)).reshape(-1, 2)
            return self._apply_per_agent(flat_p, flat_d).reshape(batch + (self.n, 2))
        configs = int(np.prod(positions.shape[:-2]))
        if configs < int(np.prod(batch)):
            return self._apply_shared(positions, moves, batch)
        flat_p = np.broadcast_to(positions, batch + (self.n, 2)).reshape(-1, self.n, 2).copy()
        flat_d = np.broadcast_to(moves, batch + (2,)).reshape(-1, 2)
        return self._apply_flat(flat_p, flat_d).reshape(batch + (self.n, 2))

    def _apply_shared(
        self, positions: np.ndarray, moves: np.ndarray, batch: tuple[int, ...]
    ) -> np.ndarray:
        """Several moves from each configuration (a planner trying k directions from a node):
        look the walls up once per configuration, not once per move, and translate at once
        every configuration that no move can bring to a wall."""
        config_of = np.arange(int(np.prod(positions.shape[:-2]))).reshape(positions.shape[:-2])
        config_of = np.broadcast_to(config_of, batch).reshape(-1)
        move_of = np.arange(int(np.prod(moves.shape[:-1]))).reshape(moves.shape[:-1])
        move_of = np.broadcast_to(move_of, batch).reshape(-1)
        configs = positions.reshape(-1, self.n, 2)
        flat_moves = moves.reshape(-1, 2)
        shared = _SharedLookup.of(self.workspace, configs)
        longest = float(np.hypot(flat_moves[:, 0], flat_moves[:, 1]).max(initial=0.0))
        still = np.all(shared.lower_bound - self.radii >= longest + _CONTACT_TOL, axis=1)
        result = positions + moves[..., None, :]  # (batch..., n, 2), fresh
        rows = np.flatnonzero(~still[config_of])
        if rows.size:
            flat = result.reshape(-1, self.n, 2)
            flat[rows] = self._apply_flat(
                configs[config_of[rows]], flat_moves[move_of[rows]],
                shared.take(config_of[rows]),
            )
        return result

    def rollout(self, start: ArrayLike, moves: ArrayLike) -> np.ndarray:
        """Positions after each move: start (n, 2), moves (m, 2) -> (m, n, 2), mm."""
        state = np.asarray(start, dtype=float).reshape(self.n, 2)
        moves = np.asarray(moves, dtype=float).reshape(-1, 2)
        states = np.empty((len(moves), self.n, 2))
        for index, move in enumerate(moves):
            state = self.apply(state, move)
            states[index] = state
        return states

    def is_free(self, positions: ArrayLike) -> np.ndarray:
        """(...) True where every agent fits the workspace and no two agents are too close.

        positions (..., n, 2) mm; tolerance 1e-7 mm.
        """
        p = np.asarray(positions, dtype=float)
        fits = np.all(self.workspace.clearance(p) >= self.radii - _CONTACT_TOL, axis=-1)
        if self.n > 1:
            gap = p[..., self._pair_second, :] - p[..., self._pair_first, :]
            distance = np.hypot(gap[..., 0], gap[..., 1])
            fits &= np.all(distance >= self._reach - _CONTACT_TOL, axis=-1)
        return fits

    # Whole moves

    def _apply_per_agent(self, p: np.ndarray, d: np.ndarray) -> np.ndarray:
        """p (B, n, 2) mm moved in place by the shared input d (B, 2) mm, each agent by its own
        response. The input is applied in pieces: a piece in which no agent can reach a wall
        (clearance lower bound) and no two can meet (their gap closes at |D_i - D_j| then) is a
        translation of each agent by its own displacement D_i; otherwise each agent meets the
        walls alone (a one-agent model, exact) over a piece short enough that no two agents can
        meet in it (their gap closes at most at |D_i| + |D_j|; `substep_mm` at the least), and
        an agent that would still overlap another keeps its place before the piece."""
        own = np.einsum("nij,bj->bni", self._response, d)  # (B, n, 2) per unit of input
        size = np.hypot(own[..., 0], own[..., 1])  # (B, n)
        longest = size.max(axis=1)
        left = np.where(longest > 0, 1.0, 0.0)  # fraction of the input still to apply
        first, second = self._pair_first, self._pair_second
        with np.errstate(divide="ignore", invalid="ignore"):
            relative = np.hypot(*(own[:, second] - own[:, first]).transpose(2, 0, 1))  # (B, pairs)
            together = size[:, first] + size[:, second]
        while True:
            rows = np.flatnonzero(left > 0)
            if rows.size == 0:
                return p
            before = p[rows]
            room = self.workspace.clearance_lower_bound(before) - self.radii  # (R, n)
            with np.errstate(divide="ignore", invalid="ignore"):
                to_wall = np.min(np.where(size[rows] > 0, room / size[rows], np.inf), axis=1)
                if self.n > 1:
                    gap = before[:, second] - before[:, first]
                    slack = np.hypot(gap[..., 0], gap[..., 1]) - self._reach
                    free_pairs = np.min(np.where(relative[rows] > 0,
                                                 0.5 * slack / relative[rows], np.inf), axis=1)
                    walled_pairs = np.min(np.where(together[rows] > 0,
                                                   0.5 * slack / together[rows], np.inf), axis=1)
                else:
                    free_pairs = walled_pairs = np.full(rows.size, np.inf)
            free = np.minimum(to_wall - _CONTACT_TOL, free_pairs)
            walled = np.maximum(self.substep_mm / longest[rows], walled_pairs)
            translate = free >= np.minimum(left[rows], walled)
            step = np.minimum(left[rows], np.where(translate, free, walled))
            piece = own[rows] * step[:, None, None]
            moved = before + piece
            hard = np.flatnonzero(~translate)
            if hard.size:
                for i in range(self.n):
                    single = self.alone(i)
                    moved[hard, i] = single._apply_flat(before[hard, i:i + 1].copy(),
                                                        piece[hard, i])[:, 0]
                if self.n > 1:
                    moved[hard] = self._give_way(moved[hard], before[hard], piece[hard])
            p[rows] = moved
            left[rows] = np.where(step >= left[rows], 0.0, left[rows] - step)

    def _give_way(self, moved: np.ndarray, before: np.ndarray, piece: np.ndarray) -> np.ndarray:
        """moved, changed in place and returned: where two agents of moved (B, n, 2) overlap, the one whose own piece
        (B, n, 2) pointed more towards the other goes back to `before`."""
        for _ in range(self.n):
            overlapping = False
            for (i, j), reach in zip(self._pairs, self._reach):
                gap = moved[:, j] - moved[:, i]
                rows = np.flatnonzero(np.hypot(gap[:, 0], gap[:, 1]) < reach - _CONTACT_TOL)
                if rows.size == 0:
                    continue
                overlapping = True
                towards = before[rows, j] - before[rows, i]
                i_gives = np.sum(piece[rows, i] * towards, axis=1) >= np.sum(
                    piece[rows, j] * -towards, axis=1)
                moved[rows[i_gives], i] = before[rows[i_gives], i]
                moved[rows[~i_gives], j] = before[rows[~i_gives], j]
            if not overlapping:
                break
        return moved

    def _apply_flat(
        self, p: np.ndarray, d: np.ndarray, shared: "_SharedLookup | None" = None
    ) -> np.ndarray:
        """p (B, n, 2) mm, moved in place by d (B, 2) mm; `shared`: the walls seen from p."""
        length = np.hypot(d[:, 0], d[:, 1])
        moving = np.flatnonzero(length > 0)
        if moving.size == 0:
            return p
        if shared is None:
            clearance = self.workspace.clearance_lower_bound(p[moving])
        else:
            clearance = shared.lower_bound[moving]
        # Agents that cannot reach a wall during the move translate rigidly; since they all move
        # alike, no pair can come closer either.
        agent_far = clearance - self.radii >= length[moving, None] + _CONTACT_TOL  # (B, n)
        far = np.all(agent_far, axis=1)
        hard = moving[~far]
        if hard.size:
            # Most of the rest only start near a wall and move along or away from it: the exact
            # sweep of each agent's straight path finds them (on exact geometry) and they
            # translate too. "slide" admits paths that touch the contact level to within its
            # tolerance (the model would slide them by at most that much); "non-slip" does not,
            # since an agent pushed into a wall by even a hair does not move at all.
            margin = -_CONTACT_TOL if self.contact == "slide" else _CONTACT_TOL
            clear = agent_far[~far]
            rows, agents = np.nonzero(~clear)
            clear[rows, agents] = self.workspace.sweep_clear(
                p[hard[rows], agents], d[hard[rows]], self.radii[agents] + margin
            )
            translates = clear.all(axis=1)
            far[~far] = translates
            hard = moving[~far]
            # (B, n): agents of the others whose whole straight path is clear of walls; they need
            # no wall events while the agents round them leave them on that path.
            on_path = clear[~translates]
        easy = moving[far]
        p[easy] += d[easy, None, :]
        if hard.size == 0:
            return p
        # Walls are handled exactly however long the step; agents meeting agents need sub-steps.
        # Two agents close in by at most twice the input, and only if a wall stops or turns one
        # of them; so a step of half the smallest gap between discs that a wall could bring
        # together cannot make any two meet: take that, or a sub-step once they are close.
        direction = d[hard] / length[hard, None]
        left = length[hard].copy()
        first = shared is not None  # the first sub-step starts where `shared` looked
        while True:
            going = np.flatnonzero(left > 0)
            if going.size == 0:
                break
            live = hard[going]
            step = left[going]
            if self.n > 1:
                gap = p[live][:, self._pair_second] - p[live][:, self._pair_first]
                slack = np.hypot(gap[..., 0], gap[..., 1]) - self._reach  # (B, pairs)
                if first:
                    room = shared.lower_bound[live] - self.radii
                else:
                    room = self.workspace.clearance_lower_bound(p[live]) - self.radii
                walled = (room < step[:, None]) & ~on_path[going]  # a wall may stop or turn it
                may_close = walled[:, self._pair_first] | walled[:, self._pair_second]
                slack = np.min(np.where(may_close, slack, np.inf), axis=1)
                step = np.minimum(step, np.maximum(self.substep_mm, 0.5 * slack))
            piece = direction[going] * step[:, None]
            before = p[live]
            # Only agents a wall could reach in this piece need the events; the others translate.
            moved = before + piece[:, None, :]
            if self.n > 1:
                rows, agents = np.nonzero((room < step[:, None] + _CONTACT_TOL) & ~on_path[going])
            else:
                rows, agents = np.arange(live.size), np.zeros(live.size, dtype=np.intp)
            if rows.size:
                moved[rows, agents] = self._wall_phase(
                    before[rows, agents],
                    piece[rows],
                    self.radii[agents],
                    shared.surface_of(live[rows], agents) if first else None,
                )
            first = False
            if self.n > 1:
                moved = self._pair_phase(moved, before, piece)
                # an agent the pair phase moved aside has left its swept path
                on_path[going] &= np.all(moved == before + piece[:, None, :], axis=2)
            p[live] = moved
            left[going] = np.where(step >= left[going], 0.0, left[going] - step)
        return p

    # Walls: exact events

    def _wall_phase(
        self,
        p: np.ndarray,
        d: np.ndarray,
        r: np.ndarray,
        surface: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Move single agents p (M, 2) by d (M, 2) against the walls only; radii r (M,);
        `surface`: the workspace's (clearance, normal, curvature) at p if already known.

        Each round, every agent with input left takes one step of its current mode (free flight,
        straight slide, slide round a circle) up to the next event, which is solved exactly and
        remembered for the next round's look-up.
        """
        ws = self.workspace
        h = self.substep_mm
        p = p.copy()
        progress = np.hypot(d[:, 0], d[:, 1])
        u = d / np.maximum(progress, _TINY)[:, None]
        memory = _EventMemory(len(p))
        stalls = np.zeros(len(p), dtype=int)
        limit = int(np.ceil(progress.max() / h)) * 4 + 40 if len(p) else 0
        for _ in range(limit):
            live = np.flatnonzero(progress > 0)
            if live.size == 0:
                break
            pp, ss, uu, rr = p[live], progress[live], u[live], r[live]
            if surface is not None:
                phi, nrm, kap = (value[live] for value in surface)
                surface = None
            else:
                phi, nrm, kap = ws.surface(pp)
            phi, nrm, kap, wedge = memory.recall(live, pp, phi, nrm, kap, rr)
            deep = phi < rr - _CONTACT_TOL
            if deep.any():  # started inside a wall (bad input or a grid's rounding): step out
                pp[deep] += (rr[deep] - phi[deep])[:, None] * nrm[deep]
                phi[deep] = rr[deep]
            contact = phi <= rr + _CONTACT_TOL
            wedge &= contact
            if wedge.any():
                w = np.flatnonzero(wedge)
                second_n, second_k = memory.second_of(live[w])
                nrm[w], kap[w], stuck = _choose_wedge_side(
                    uu[w], nrm[w], kap[w], np.ones(w.size, dtype=bool), second_n, second_k
                )
                ss[w[stuck]] = 0.0  # ss is this round's copy
            un = np.sum(uu * nrm, axis=1)
            pushing = contact & (un < -_DIR_EPS) & (ss > 0)
            if self.contact == "non-slip":
                ss = np.where(pushing, 0.0, ss)  # seed 004 eq. 1: pushed into a wall, it stays
                pushing[:] = False
            # On a grid the interpolated surfaces can disagree with each other by a hair, so an
            # agent may keep meeting the same contact without progress: step it by projection.
            stalled = (stalls[live] >= 3) & (ss > 0)
            modes = {
                self._step_projected: stalled,
                self._step_free: ~pushing & (ss > 0) & ~stalled,
                self._step_straight: pushing & (np.abs(kap) < _FLAT_CURVATURE) & ~stalled,
                self._step_round: pushing & (np.abs(kap) >= _FLAT_CURVATURE) & ~stalled,
            }
            new_p = pp.copy()
            new_s = ss.copy()
            for step_mode, chosen in modes.items():
                if chosen.any():
                    idx = np.flatnonzero(chosen)
                    end, used = step_mode(
                        pp[idx], ss[idx], uu[idx], rr[idx], phi[idx], nrm[idx], kap[idx],
                        memory, live[idx],
                    )
                    new_p[idx] = end
                    new_s[idx] = ss[idx] - used
            p[live] = new_p
            new_s = np.maximum(new_s, 0.0)
            stalls[live] = np.where(new_s < progress[live] - 1e-12, 0, stalls[live] + 1)
            progress[live] = new_s
        left = np.flatnonzero(progress > 0)
        if left.size:
            log.debug("wall phase: %d agents out of event rounds; finishing by projection", left.size)
            p[left] += progress[left, None] * u[left]
            p[left] = self._push_out(p[left], r[left])
        if not ws.exact_geometry:
            # Interpolated corners are slightly rounded; make sure nobody ends inside a wall.
            p = self._push_out(p, r)
        return p

    # One step of each mode: (a (K, 2), input left s (K,), direction u (K, 2), radius r (K,),
    # surface at a: clearance, normal, curvature) -> (end (K, 2), input used (K,)).

    def _step_projected(self, a, s, u, r, phi, n, k, memory, marks):
        """Fallback: move straight, then push back out of the wall ("slide"), or stop at the
        last free point on the way, found by bisection ("non-slip")."""
        step = np.minimum(s, self.substep_mm)
        if self.contact == "slide":
            return self._push_out(a + step[:, None] * u, r), step
        low, high = np.zeros(len(a)), step.copy()
        blocked = self.workspace.clearance(a + step[:, None] * u) < r - _CONTACT_TOL
        for _ in range(20 if blocked.any() else 0):
            mid = 0.5 * (low + high)
            ok = self.workspace.clearance(a + mid[:, None] * u) >= r - _CONTACT_TOL
            low, high = np.where(ok, mid, low), np.where(ok, high, mid)
        return a + np.where(blocked, low, step)[:, None] * u, step

    def _step_free(self, a, s, u, r, phi, n, k, memory, marks):
        """Straight along the input, to the first contact if there is one on the way."""
        # Nothing is nearer than the clearance: that much is safe, plus a sub-step to look ahead.
        step = np.minimum(s, np.maximum(phi - r, 0.0) + self.substep_mm)
        end = a + step[:, None] * u
        end_phi, end_n, end_k = self.workspace.surface(end)
        into = end_phi < r - _CONTACT_TOL
        into |= _clips_circle(a, u, step, end, end_phi, end_n, end_k, r)
        used = step.copy()
        if into.any():
            used[into], ref, ref_n, ref_k = self._first_contact(
                a[into], u[into], step[into], end_phi[into], end_n[into], end_k[into], r[into]
            )
            memory.touch(marks[into], ref, ref_n, ref_k)
        return a + used[:, None] * u, used

    def _step_straight(self, a, s, u, r, phi, n, k, memory, marks):
        """Slide along a straight wall with the normal part of the input removed."""
        v = u - np.sum(u * n, axis=1)[:, None] * n
        step = np.minimum(s, self.substep_mm)
        # Where the wall certainly runs under the whole rest of the slide and nothing else comes
        # near, slide it in one step (nothing can happen on the way).
        longer = np.flatnonzero(s > step)
        if longer.size:
            whole = self.workspace.slide_clear(
                a[longer], s[longer, None] * v[longer], r[longer], n[longer], _CONTACT_TOL
            )
            step[longer[whole]] = s[longer[whole]]
        end = a + step[:, None] * v
        end_phi, end_n, end_k = self.workspace.surface(end)
        used = step.copy()
        into = end_phi < r - _CONTACT_TOL
        if not self.workspace.exact_geometry:
            gentle = into & (np.sum(end_n * n, axis=1) > _GRID_CORNER_COS)
            end[gentle] += (r[gentle] - end_phi[gentle])[:, None] * end_n[gentle]
            into &= ~gentle
        if into.any():  # ran into a second surface: stop there, remember both
            beyond = end[into].copy()
            used[into] = self._first_contact(
                a[into], v[into], step[into], end_phi[into], end_n[into], end_k[into], r[into]
            )[0]
            end[into] = a[into] + used[into, None] * v[into]
            memory.wedge(marks[into], n[into], np.zeros(into.sum()))
            memory.touch(marks[into], beyond, end_n[into], end_k[into])
        off = (end_phi > r + _CONTACT_TOL) & (end_k > _FLAT_CURVATURE)
        if off.any():  # the wall ended: back to where the corner's circle begins, follow it next
            centre = end[off] - end_n[off] / end_k[off, None]
            vv = v[off]
            speed2 = np.maximum(np.sum(vv * vv, axis=1), _TINY)
            tangent = np.sum((centre - a[off]) * vv, axis=1) / speed2
            used[off] = np.clip(tangent, 0.0, step[off])
            end[off] = a[off] + used[off, None] * vv
            memory.corner(marks[off], centre, np.ones(off.sum()))
        return end, used

    def _step_round(self, a, s, u, r, phi, n, k, memory, marks):
        """Slide round a circle (a corner, a disk) in closed form until released or blocked."""
        ws = self.workspace
        centre = a - n / k[:, None]
        rho = 1.0 / k
        alpha = np.arctan2(u[:, 1], u[:, 0])
        lag = _wrap(alpha - np.arctan2(n[:, 1], n[:, 0]))  # input vs normal, |lag| > pi/2
        half = np.tan(lag / 2.0)
        head_on = np.abs(lag) > math.pi - 1e-12  # balanced on the circle: stays
        with np.errstate(divide="ignore", invalid="ignore"):
            release = np.where(rho > 0, rho * np.log(np.maximum(np.abs(half), 1.0)), np.inf)
        step = np.minimum(np.minimum(s, self.substep_mm), release)
        step = np.where(head_on, s, step)
        end = _arc_point(centre, rho, alpha, half, step)
        end[head_on] = a[head_on]
        end_phi, end_n, end_k = ws.surface(end)
        used = step.copy()
        into = (end_phi < r - _CONTACT_TOL) & ~head_on
        if not ws.exact_geometry:
            arc_n = (end - centre) / rho[:, None]
            gentle = into & (np.sum(end_n * arc_n, axis=1) > _GRID_CORNER_COS)
            end[gentle] += (r[gentle] - end_phi[gentle])[:, None] * end_n[gentle]
            into &= ~gentle
        if into.any():  # reached another surface on the way round: find where
            sub = np.flatnonzero(into)
            args = (centre[sub], rho[sub], alpha[sub], half[sub])
            low, high = np.zeros(sub.size), step[sub].copy()
            beyond = end[sub].copy()
            beyond_n, beyond_k = end_n[sub].copy(), np.zeros(sub.size)
            solved = np.zeros(sub.size, dtype=bool)
            if ws.exact_geometry:
                # Mostly the straight side that continues the corner's circle (a tangent): where
                # the arc meets that line's level set is closed form; the result is checked.
                line = np.flatnonzero(np.abs(end_k[sub]) < _FLAT_CURVATURE)
                meet, found, short = _arc_meets_line(
                    *(value[line] for value in args), step[sub[line]], end[sub[line]],
                    end_phi[sub[line]], end_n[sub[line]], r[sub[line]],
                )
                line, meet, short = line[found], meet[found], short[found]
                if line.size:
                    at = _arc_point(*(value[line] for value in args), meet)
                    # An arc that runs a hair (< the contact tolerance) inside the level r meets
                    # its tangent line that much inside too: that is still a meeting.
                    clear = ws.clearance(at) >= r[sub[line]] - 1e-3 * _CONTACT_TOL - short
                    low[line[clear]] = meet[clear]
                    solved[line[clear]] = True
            rest = np.flatnonzero(~solved)
            if rest.size:  # anything else: bisection on the arc
                rest_args = tuple(value[rest] for value in args)
                lo, hi = low[rest], high[rest]
                for _ in range(30):
                    mid = 0.5 * (lo + hi)
                    at = _arc_point(*rest_args, mid)
                    ok = ws.clearance(at) >= r[sub[rest]] - 1e-3 * _CONTACT_TOL
                    lo = np.where(ok, mid, lo)
                    hi = np.where(ok, hi, mid)
                low[rest] = lo
                beyond[rest] = _arc_point(*rest_args, hi)
                _, beyond_n[rest], beyond_k[rest] = ws.surface(beyond[rest])
            used[sub] = low
            end[sub] = _arc_point(*args, low)
            memory.wedge(marks[sub], (end[sub] - centre[sub]) / rho[sub, None], k[sub])
            memory.touch(marks[sub], beyond, beyond_n, beyond_k)
        return end, used

    def _first_contact(
        self,
        start: np.ndarray,
        velocity: np.ndarray,
        step: np.ndarray,
        end_phi: np.ndarray,
        end_n: np.ndarray,
        end_k: np.ndarray,
        r: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Where start + s * velocity, s in [0, step], first touches a surface (clearance == r).

        The end point's surface (a line or a circle through its level set) gives a first guess;
        if the guess lands short of that surface's actual extent, or inside an earlier one, the
        surface at the guess is solved next, keeping a bracket [free, inside]. On exact geometry
        this ends in a step or two; on grids it is Newton's method with a circle-aware step.
        Returns s (M,) and the touched surface: a point on its level set (M, 2), the normal (M, 2)
        and curvature (M,) there.
        """
        low = np.zeros(len(start))
        high = step.copy()
        ref_s, ref_phi, ref_n, ref_k = step.copy(), end_phi.copy(), end_n.copy(), end_k.copy()
        # The surface the final guess was solved on (at the contact point itself a look-up may
        # name another surface equally near): a point on its level set, normal, curvature.
        met_s, met_n, met_k = step.copy(), end_n.copy(), end_k.copy()
        at = step.copy()
        todo = np.arange(len(start))
        for _ in range(8):
            if todo.size == 0:
                break
            guess = _line_meets_level(
                start[todo], velocity[todo], ref_s[todo], ref_phi[todo], ref_n[todo],
                ref_k[todo], r[todo],
            )
            guess = np.where(np.isfinite(guess), guess, 0.5 * (low[todo] + high[todo]))
            guess = np.clip(guess, low[todo], high[todo])
            q = start[todo] + guess[:, None] * velocity[todo]
            phi, n, k = self.workspace.surface(q)
            at[todo] = guess
            inside = phi < r[todo] - _CONTACT_TOL
            short = phi > r[todo] + _CONTACT_TOL
            high[todo[inside]] = guess[inside]
            low[todo[short]] = guess[short]
            met_s[todo], met_n[todo], met_k[todo] = ref_s[todo], ref_n[todo], ref_k[todo]
            done = ~inside & ~short
            ref_s[todo] = guess
            ref_phi[todo], ref_n[todo], ref_k[todo] = phi, n, k
            # A bracket closed to rounding cannot improve: stop on its free side.
            closed = ~done & ((high[todo] - low[todo]) <= 1e-12 * np.maximum(step[todo], 1.0))
            at[todo[closed]] = low[todo[closed]]
            todo = todo[~done & ~closed]
        if todo.size:  # not pinned down by the surfaces (a grid's blended corner): bisect
            lo, hi = low[todo], high[todo]
            for _ in range(20):  # to 1e-6 of a sub-step
                mid = 0.5 * (lo + hi)
                q = start[todo] + mid[:, None] * velocity[todo]
                ok = self.workspace.clearance(q) >= r[todo] - _CONTACT_TOL
                lo = np.where(ok, mid, lo)
                hi = np.where(ok, hi, mid)
            at[todo] = lo
            met_s[todo] = hi
            beyond = start[todo] + hi[:, None] * velocity[todo]
            _, met_n[todo], met_k[todo] = self.workspace.surface(beyond)
        return at, start + met_s[:, None] * velocity, met_n, met_k

    def _push_out(self, p: np.ndarray, r: np.ndarray, rounds: int = 16) -> np.ndarray:
        """Project agents (M, 2) out of walls along the clearance gradient (corners need rounds)."""
        todo = np.arange(len(p))
        for _ in range(rounds):
            phi, n, _ = self.workspace.surface(p[todo])
            deep = phi < r[todo]
            if not deep.any():
                break
            todo, phi, n = todo[deep], phi[deep], n[deep]
            # Aim a hair beyond contact so rounding cannot leave the agent a hair inside.
            p[todo] += (r[todo] - phi + 0.1 * _CONTACT_TOL)[:, None] * n
        return p

    # Agents against agents

    def _pair_phase(self, p: np.ndarray, before: np.ndarray, piece: np.ndarray) -> np.ndarray:
        """Separate agents that overlap after a sub-step.

        p (B, n, 2): where the walls alone put each agent, from `before` (B, n, 2), for the
        sub-step's move `piece` (B, 2). An agent the walls held in place stays; otherwise the
        agent behind (along the input) gives way, since the one ahead was slowed by something it
        must not be pushed into. It steps back radially ("slide": it then slides round) or back
        along its own path to where it first touched ("non-slip"). A configuration that cannot be
        made free this way keeps its state from before the sub-step.
        """
        u = piece / np.maximum(np.hypot(piece[:, 0], piece[:, 1]), _TINY)[:, None]
        step = np.hypot(piece[:, 0], piece[:, 1])
        held = np.all(np.abs(p - before) <= 1e-12, axis=2)  # (B, n)
        corrected = np.zeros(len(p), dtype=bool)
        for _ in range(_PAIR_ITERATIONS):
            touched = np.zeros(len(p), dtype=bool)
            for (i, j), reach in zip(self._pairs, self._reach):
                gap = p[:, j] - p[:, i]
                dist = np.hypot(gap[:, 0], gap[:, 1])
                rows = np.flatnonzero(reach - dist > 0.1 * _CONTACT_TOL)
                if rows.size == 0:
                    continue
                touched[rows] = True
                g, dd, uu = gap[rows], dist[rows], u[rows]
                overlap = reach - dd
                across = np.stack([-uu[:, 1], uu[:, 0]], axis=1)  # coincident centres: side by side
                n_ij = np.where(dd[:, None] > 0, g / np.maximum(dd, _TINY)[:, None], across)
                ahead = np.sum(g * uu, axis=1)  # > 0: j is ahead of i
                held_i, held_j = held[rows, i], held[rows, j]
                give_i = ~held_i & (held_j | (ahead > 1e-9))
                give_j = ~held_j & (held_i | (ahead < -1e-9))
                split = ~give_i & ~give_j
                if self.contact == "non-slip":
                    # Back along its own (straight) path to where the two discs first touched.
                    sign = np.where(give_j, 1.0, -1.0)
                    along = sign * ahead
                    back = along + np.sqrt(np.maximum(along**2 - dd**2 + reach**2, 0.0))
                    back = np.clip(back, 0.0, step[rows])
                    p[rows[give_j], j] -= back[give_j, None] * uu[give_j]
                    p[rows[give_i], i] -= back[give_i, None] * uu[give_i]
                    w_i = w_j = np.where(split, 0.5, 0.0)
                else:
                    w_i = np.where(split, 0.5, give_i.astype(float))
                    w_j = np.where(split, 0.5, give_j.astype(float))
                p[rows, i] -= (overlap * w_i)[:, None] * n_ij
                p[rows, j] += (overlap * w_j)[:, None] * n_ij
            if not touched.any():
                break
            corrected |= touched
            rows = np.flatnonzero(touched)
            flat = self._push_out(p[rows].reshape(-1, 2), np.tile(self.radii, rows.size), 4)
            p[rows] = flat.reshape(-1, self.n, 2)
        rows = np.flatnonzero(corrected)
        if rows.size:
            jammed = rows[~self.is_free(p[rows]) & self.is_free(before[rows])]
            if jammed.size:
                log.debug("pair phase: %d configurations jammed; sub-step undone", jammed.size)
                p[jammed] = before[jammed]
        return p


class _SharedLookup:
    """The walls seen from configurations that several moves start from: per configuration
    (R, n) the clearance lower bound, the clearance, normal (R, n, 2) and curvature of each
    agent; `take` spreads them over the rows of `_apply_flat`."""

    def __init__(self, lower_bound, phi, normal, curvature) -> None:
        self.lower_bound = lower_bound
        self._phi, self._normal, self._curvature = phi, normal, curvature

    @classmethod
    def of(cls, workspace: Workspace, configs: np.ndarray) -> "_SharedLookup":
        """Look up configurations (P, n, 2) mm."""
        return cls(workspace.clearance_lower_bound(configs), *workspace.surface(configs))

    def take(self, index: np.ndarray) -> "_SharedLookup":
        """The lookups of configurations `index` (R,), one row each."""
        return _SharedLookup(self.lower_bound[index], self._phi[index], self._normal[index],
                             self._curvature[index])

    def surface_of(
        self, rows: np.ndarray, agents: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Clearance (M,), normal (M, 2), curvature (M,) of agent `agents` (M,) of row `rows` (M,)."""
        return self._phi[rows, agents], self._normal[rows, agents], self._curvature[rows, agents]


class _EventMemory:
    """What each agent (M of them) learned at its last event, used at its next look-up.

    - touch: the surface it just ran into. At the meeting point a look-up may report another
      surface equally near (a corner), or a grid may round the contact off; this one is right.
      Straight surfaces are kept as a normal, round ones as the circle's centre.
    - corner: a circle to follow next (a straight slide ran off the end of its wall).
    - wedge: the surface it was on when it ran into the touched one: two contacts at once.
    """

    def __init__(self, count: int) -> None:
        self.touched = np.zeros(count, dtype=bool)
        self.touch_normal = np.zeros((count, 2))
        self.circle = np.zeros(count, dtype=bool)
        self.circle_centre = np.zeros((count, 2))
        self.circle_sign = np.ones(count)
        self.wedged = np.zeros(count, dtype=bool)
        self.wedge_normal = np.zeros((count, 2))
        self.wedge_curvature = np.zeros(count)

    def touch(
        self, marks: np.ndarray, where: np.ndarray, normal: np.ndarray, curvature: np.ndarray
    ) -> None:
        """Agents `marks` now touch the surface seen at points `where` (normal, curvature there)."""
        round_ = np.abs(curvature) >= _FLAT_CURVATURE
        self.touched[marks[~round_]] = True
        self.touch_normal[marks[~round_]] = normal[~round_]
        centre = where[round_] - normal[round_] / curvature[round_, None]
        self.corner(marks[round_], centre, np.sign(curvature[round_]))

    def corner(self, marks: np.ndarray, centre: np.ndarray, sign: np.ndarray) -> None:
        self.circle[marks] = True
        self.circle_centre[marks] = centre
        self.circle_sign[marks] = sign

    def wedge(self, marks: np.ndarray, normal: np.ndarray, curvature: np.ndarray) -> None:
        self.wedged[marks] = True
        self.wedge_normal[marks] = normal
        self.wedge_curvature[marks] = curvature

    def second_of(self, live: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.wedge_normal[live], self.wedge_curvature[live]

    def recall(self, live, p, phi, normal, curvature, r):
        """Override the look-up at p (K, 2) for agents `live` that remember their surface; forget it.

        Returns clearance, normal, curvature and whether a second contact (a wedge) is remembered.
        """
        circle = self.circle[live]
        if circle.any():
            rel = p[circle] - self.circle_centre[live[circle]]
            dist = np.maximum(np.hypot(rel[:, 0], rel[:, 1]), _TINY)
            sign = self.circle_sign[live[circle]]
            normal[circle] = sign[:, None] * rel / dist[:, None]
            curvature[circle] = sign / dist
            phi[circle] = r[circle]
        touched = self.touched[live]
        if touched.any():
            normal[touched] = self.touch_normal[live[touched]]
            curvature[touched] = 0.0
            phi[touched] = r[touched]
        wedge = self.wedged[live].copy()
        self.circle[live] = self.touched[live] = self.wedged[live] = False
        return phi, normal, curvature, wedge

def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles in (-pi, pi]."""
    return np.pi - np.mod(np.pi - angle, 2.0 * np.pi)


def _arc_point(
    centre: np.ndarray, rho: np.ndarray, alpha: np.ndarray, half: np.ndarray, progress: np.ndarray
) -> np.ndarray:
    """Where an agent sliding on a circle is after `progress` mm of input.

    The agent sits at centre + rho * n(theta) (rho < 0 for a concave circle), the input points at
    angle alpha, lag = alpha - theta. Sliding keeps the tangential part of the input, so
    rho * dtheta/ds = sin(lag), i.e. dlag/ds = -sin(lag) / rho, whose solution is
    tan(lag / 2) = tan(lag0 / 2) * exp(-s / rho); `half` is tan(lag0 / 2).
    """
    lag = 2.0 * np.arctan(half * np.exp(-progress / rho))
    theta = alpha - lag
    return centre + rho[:, None] * np.stack([np.cos(theta), np.sin(theta)], axis=1)


def _arc_meets_line(
    centre: np.ndarray,
    rho: np.ndarray,
    alpha: np.ndarray,
    half: np.ndarray,
    step: np.ndarray,
    ref: np.ndarray,
    ref_phi: np.ndarray,
    ref_n: np.ndarray,
    r: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Input progress (M,) at which an agent sliding on a circle (see `_arc_point`) first reaches
    clearance r on a straight surface seen at ref (M, 2) (clearance ref_phi, normal ref_n),
    whether it does within [0, step], and by how much (mm, (M,), < `_CONTACT_TOL`) a circle that
    stays just inside the level r misses it (it then meets the line where the two are tangent).

    On the arc x = centre + rho e(theta) the line's clearance is
    ref_phi + n . (centre - ref) + rho cos(theta - theta_n), so the crossing angles are
    theta_n +- acos(q); a tangent line (q = 1 up to rounding) is met where the normals agree.
    The angle gives the progress through lag = alpha - theta: s = -rho log(tan(lag / 2) / half).
    """
    offset = ref_phi + np.sum(ref_n * (centre - ref), axis=1)
    q = (r - offset) / rho
    short = np.where(q > 1.0, np.abs(r - offset - rho), 0.0)
    found_level = short < _CONTACT_TOL
    q = np.clip(q, -1.0, 1.0)
    theta_n = np.arctan2(ref_n[:, 1], ref_n[:, 0])
    spread = np.arccos(q)
    best = np.full(len(centre), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for theta in (theta_n - spread, theta_n + spread):
            lag = _wrap(alpha - theta)
            ratio = np.tan(lag / 2.0) / half
            s = -rho * np.log(ratio)
            s = np.where(np.abs(s) < 1e-12 * np.maximum(step, 1.0), 0.0, s)
            fits = (ratio > 0) & np.isfinite(s) & (s >= 0.0) & (s <= step)
            best = np.where(fits & (s < best), s, best)
    found = np.isfinite(best) & found_level
    return np.where(found, best, 0.0), found, short


def _clips_circle(
    start: np.ndarray,
    u: np.ndarray,
    step: np.ndarray,
    end: np.ndarray,
    end_phi: np.ndarray,
    end_n: np.ndarray,
    end_k: np.ndarray,
    r: np.ndarray,
) -> np.ndarray:
    """True where a free segment that ends clear of the walls still grazed a rounded corner.

    Both ends can be clear while the middle cuts the contact circle of a corner; the circle is
    the one at the end point (centre end - n / k, radius 1/k + r - clearance).
    """
    convex = end_k > _FLAT_CURVATURE
    result = np.zeros(len(start), dtype=bool)
    if not convex.any():
        return result
    k = np.where(convex, end_k, 1.0)
    centre = end - end_n / k[:, None]
    level = 1.0 / k + (r - end_phi)
    along = np.clip(np.sum((centre - start) * u, axis=1), 0.0, step)
    closest = start + along[:, None] * u
    miss = np.hypot(*(closest - centre).T)
    return convex & (miss < level - _CONTACT_TOL)


def _choose_wedge_side(
    u: np.ndarray,
    normal: np.ndarray,
    curvature: np.ndarray,
    has_second: np.ndarray,
    second_normal: np.ndarray,
    second_curvature: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """In contact with two surfaces at once: slide along the one whose slide leaves the other, or stop.

    Returns the surface normal (M, 2) and curvature (M,) to use, and stuck (M,) bool.
    """
    normal = normal.copy()
    curvature = curvature.copy()
    distinct = has_second & (np.sum(normal * second_normal, axis=1) < 1.0 - 1e-12)
    u_a = np.sum(u * normal, axis=1)
    u_b = np.sum(u * second_normal, axis=1)
    slide_a = u - np.minimum(u_a, 0.0)[:, None] * normal
    slide_b = u - np.minimum(u_b, 0.0)[:, None] * second_normal
    ok_a = np.sum(slide_a * second_normal, axis=1) >= -_DIR_EPS
    ok_b = np.sum(slide_b * normal, axis=1) >= -_DIR_EPS
    use_b = distinct & ~ok_a & ok_b
    normal[use_b] = second_normal[use_b]
    curvature[use_b] = second_curvature[use_b]
    stuck = distinct & ~ok_a & ~ok_b
    return normal, curvature, stuck


def _line_meets_level(
    start: np.ndarray,
    velocity: np.ndarray,
    ref_s: np.ndarray,
    ref_phi: np.ndarray,
    ref_n: np.ndarray,
    ref_k: np.ndarray,
    r: np.ndarray,
) -> np.ndarray:
    """Progress s at which start + s * velocity reaches clearance r on the surface seen at s = ref_s.

    The surface's level sets are lines (curvature 0) or circles about ref - n / k; nan where the
    path misses it or runs parallel to it.
    """
    rate = np.sum(velocity * ref_n, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        on_line = ref_s + (r - ref_phi) / np.where(np.abs(rate) > _DIR_EPS, rate, np.nan)
    result = on_line
    curved = np.abs(ref_k) >= _FLAT_CURVATURE
    if curved.any():
        k = ref_k[curved]
        ref = start[curved] + ref_s[curved, None] * velocity[curved]
        centre = ref - ref_n[curved] / k[:, None]
        level = np.abs(1.0 / k + (r[curved] - ref_phi[curved]))
        w = start[curved] - centre
        vv = velocity[curved]
        a2 = np.maximum(np.sum(vv * vv, axis=1), _TINY)
        b = np.sum(w * vv, axis=1) / a2
        c = (np.sum(w * w, axis=1) - level**2) / a2
        disc = b * b - c
        root = np.sqrt(np.maximum(disc, 0.0))
        # Into a convex circle (the first crossing) or out of a concave one (the second).
        crossing = np.where(k > 0, -b - root, -b + root)
        result = result.copy()
        result[curved] = np.where(disc >= 0, crossing, np.nan)
    return result
