"""Contact corrections: fix the robots' relative error with a wall, then translate.

Under a shared input every robot moves alike in free space (or, with identified responses, each
by its own fixed linear map of the same total input), so a relative error between robots is out
of reach of any sequence of free moves. A wall is what breaks the symmetry (seed 000 Sec. II):
push the robots along an axis until one of them rests against a wall and slides or stops while
the others go on, and their relative position changes by the length pushed beyond that contact.
`correct_by_contact` searches that family exhaustively through the global-input model, in one
batched model call per stage: up to `pushes` axis pushes of every length on a grid, each followed
by the translation that best fits what is left (`GlobalInputModel.fit_translation`), scored by
the distance to the goals the model predicts, plus `length_cost` per mm pushed (a long slide
along a wall jitters more on a real rig). The zero push is a candidate, so a plain translation
is chosen when that is best.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigctl.plans.model import GlobalInputModel

AXES = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])


@dataclass(frozen=True)
class Correction:
    """moves (m, 2) mm (shared input), states (m, n, 2) mm after each, distance (mm, R^2n) of the
    last state to the goals."""

    moves: np.ndarray
    states: np.ndarray
    distance: float


def correct_by_contact(model: GlobalInputModel, start: np.ndarray, goals: np.ndarray, *,
                       max_push_mm: float = 120.0, step_mm: float = 0.5, pushes: int = 2,
                       keep: int = 24, length_cost: float = 0.002) -> Correction:
    """The best sequence of at most `pushes` axis pushes (lengths 0..max_push_mm by step_mm)
    and a final fitted translation from start (n, 2) mm towards goals (n, 2) mm, by the model.
    Each later stage extends the `keep` best sequences of the one before."""
    start = np.asarray(start, dtype=float)
    goals = np.asarray(goals, dtype=float)
    lengths = np.arange(step_mm, max_push_mm + 0.5 * step_mm, step_mm)
    candidates = (AXES[:, None, :] * lengths[None, :, None]).reshape(-1, 2)  # (c, 2)
    # sequences so far: their moves (s, k, 2), pushed length (s,), state (s, n, 2)
    moves = np.zeros((1, 0, 2))
    pushed = np.zeros(1)
    states = start[None]
    best = _finish(model, moves, pushed, states, goals, length_cost)
    for _ in range(pushes):
        after = model.apply(states[:, None], candidates[None])  # (s, c, n, 2)
        s, c = after.shape[:2]
        new_moves = np.concatenate([np.repeat(moves, c, axis=0),
                                    np.tile(candidates, (s, 1))[:, None]], axis=1)
        new_pushed = np.repeat(pushed, c) + np.tile(lengths, len(AXES) * s)
        new_states = after.reshape(s * c, *start.shape)
        scored = _finish(model, new_moves, new_pushed, new_states, goals, length_cost)
        if scored[0] < best[0]:
            best = scored
        # keep the sequences whose relative error (after the best translation) is smallest
        residual = goals - new_states
        offset = residual - model.free_displacement(model.fit_translation(residual))
        order = np.argsort(np.sqrt((offset ** 2).sum(axis=(1, 2))) + length_cost * new_pushed,
                           kind="stable")[:keep]
        moves, pushed, states = new_moves[order], new_pushed[order], new_states[order]
    _, seq, translation = _refine(model, start, goals, best, step_mm, length_cost)
    all_moves = np.concatenate([seq, translation[None]]) if np.any(translation) else seq
    all_moves = all_moves[np.hypot(*all_moves.T) > 0] if len(all_moves) else all_moves
    path = model.rollout(start, all_moves) if len(all_moves) else np.zeros((0,) + start.shape)
    end = path[-1] if len(path) else start
    return Correction(all_moves, path, float(np.linalg.norm(end - goals)))


def _finish(model: GlobalInputModel, moves: np.ndarray, pushed: np.ndarray, states: np.ndarray,
            goals: np.ndarray, length_cost: float) -> tuple[float, np.ndarray, np.ndarray]:
    """(score, moves (k, 2), translation (2,)) of the best of the sequences (s, k, 2) ending at
    states (s, n, 2) once each is followed by its fitted translation."""
    translation = model.fit_translation(goals - states)  # (s, 2)
    ends = model.apply(states, translation)
    distance = np.sqrt(((ends - goals) ** 2).sum(axis=(1, 2)))
    score = distance + length_cost * (pushed + np.hypot(*translation.T))
    i = int(np.argmin(score))
    return float(score[i]), moves[i], translation[i]


def _refine(model: GlobalInputModel, start: np.ndarray, goals: np.ndarray,
            best: tuple[float, np.ndarray, np.ndarray], step_mm: float, length_cost: float,
            points: int = 51) -> tuple[float, np.ndarray, np.ndarray]:
    """`best` with each push's length searched again within +-step_mm on a finer grid (the
    length pushed past a contact is the relative correction: the coarse grid's step is too
    coarse for it), push by push."""
    score, moves, translation = best
    moves = moves.copy()
    offsets = np.linspace(-step_mm, step_mm, points)
    for k in range(len(moves)):
        length = float(np.hypot(*moves[k]))
        if length == 0.0:
            continue
        axis = moves[k] / length
        trial = np.repeat(moves[None], points, axis=0)
        trial[:, k] = axis * np.maximum(length + offsets, 0.0)[:, None]
        states = np.repeat(start[None], points, axis=0)
        for j in range(len(moves)):
            states = model.apply(states, trial[:, j])
        pushed = np.hypot(trial[..., 0], trial[..., 1]).sum(axis=1)
        found = _finish(model, trial, pushed, states, goals, length_cost)
        if found[0] < score:
            score, moves, translation = found[0], found[1].copy(), found[2]
    return score, moves, translation
