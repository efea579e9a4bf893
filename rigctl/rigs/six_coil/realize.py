"""Realize global moves on the six-coil rig: a list of planar moves becomes a field program U(t).

The robots are radially magnetised cylinders lying on the floor of the workspace (seed 000
Sec. V). They align with a 3 mT field; rotating the field about a horizontal axis u rolls them,
rotating it about z turns them. Workspace frame xyz, z up, lengths in mm.

A move d (in the xy plane) is realized as

1. steering (seed 000 eq. 2): B stays horizontal and turns about z at `field.steering_deg_per_s`
   from its present direction h to e0 = +-d_hat, whichever sign is nearer (so <= 90 degrees);
2. rolling (seed 000 eq. 1 written in xyz): with u = z_hat x d_hat,
   B(alpha) = B0 (cos(alpha) e0 + sin(alpha) (u x e0)), alpha from 0 to 2 pi N, at
   `field.rolling_turns_per_s`. A cylinder of radius R rolling by alpha about u moves its centre by
   R alpha (u x z_hat) = R alpha d_hat, so N = |d| / (2 pi R) must be a whole number of turns;
3. a hold of `field.hold_s` at B0 e0, so the coils settle before the next move;
4. with `field.rest_s` (the pre-flight certificate says how long a plan needs), between moves
   the field ramps to zero, stays off that long (the coils cool, the magnets lie still) and ramps
   back up along the same direction.

With whole turns (`field.whole_turns`, the default and the paper's hardware) rolling starts and
ends with B = B0 e0, horizontal, so the field is continuous from one move to the next. Without it a
move of N + f turns (the closed loop's corrections) ends with B tilted out of the floor plane by the
roll: B = B0 (cos(theta) h + sin(theta) z) with h horizontal. The next steering turns h about z and
keeps theta (the magnet keeps lying on the floor and turns about z), and the next roll starts at the
angle theta in its own rolling plane, so the field stays continuous; a move is then any length. The
program starts with a ramp of |B| from 0 to B0 along `field.initial_heading_deg` and ends,
after the last move's hold, with a ramp back to 0 (and one final sample at exactly 0).

Every phase lasts a whole number of sample periods at `stream.rate_hz`, rounded up, so phase
boundaries fall on samples and the configured speeds are upper bounds, never exceeded.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from rigctl.core.errors import ConfigError, PlanError
from rigctl.plans.schema import MAX_DURATION_S, MAX_PROGRAM_SAMPLES

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

logger = logging.getLogger(__name__)

HOLD = 0
"""`FieldProgram.kind` of ramp and hold samples (field magnitude changes or nothing moves)."""
STEERING = 1
"""`FieldProgram.kind` of steering samples (B turns about z, seed 000 eq. 2)."""
ROLLING = 2
"""`FieldProgram.kind` of rolling samples (B turns about u, seed 000 eq. 1)."""

NO_MOVE = -1
"""`FieldProgram.segment` of samples that belong to no move (ramps, holds)."""

WHOLE_TURN_TOLERANCE = 1e-3
"""How far (in turns) a move may be from a whole number of turns of the magnets."""

_Z_HAT = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class FieldProgram:
    """A sampled field program: what the coils must produce at the workspace centre.

    Attributes
    ----------
    t_s : (T,) float
        Sample times in s, from 0, uniform at `rate_hz`.
    field_T : (T, 3) float
        Flux density in tesla, workspace frame.
    segment : (T,) int
        Index (0-based, as in the moves array) of the plan move a sample belongs to;
        `NO_MOVE` (-1) for ramps and holds.
    kind : (T,) uint8
        `HOLD` (0) for ramp/hold, `STEERING` (1), `ROLLING` (2).
    rate_hz : float
        Sample rate in Hz.
    move_spans : (m, 2) int or None
        `[start, end)` sample indices of each move including its hold (see `move_end_index`).
        Optional so other realizers may leave it out; then it is derived from `segment`.
    """

    t_s: np.ndarray
    field_T: np.ndarray
    segment: np.ndarray
    kind: np.ndarray
    rate_hz: float
    move_spans: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.t_s)
        if self.field_T.shape != (n, 3) or self.segment.shape != (n,) or self.kind.shape != (n,):
            raise ValueError(
                f"field program arrays disagree: t_s {self.t_s.shape}, field_T "
                f"{self.field_T.shape}, segment {self.segment.shape}, kind {self.kind.shape}"
            )

    @property
    def n_moves(self) -> int:
        """Number of plan moves the program was realized from."""
        if self.move_spans is not None:
            return len(self.move_spans)
        return int(self.segment.max(initial=NO_MOVE)) + 1

    @property
    def duration_s(self) -> float:
        """Time of the last sample, in s."""
        return float(self.t_s[-1]) if len(self.t_s) else 0.0

    def move_end_index(self, i: int) -> int:
        """Sample index where move `i` (including its hold) is over.

        Samples `[0, j)` cover everything up to and including move i's hold; `t_s[j]` is the time
        at which the robots should be at rest in the move's expected end state. A zero move has
        only its hold. Without `move_spans` this is one past the move's last own sample.
        """
        if not 0 <= i < self.n_moves:
            raise IndexError(f"move {i} is not in this program ({self.n_moves} moves)")
        if self.move_spans is not None:
            return int(self.move_spans[i, 1])
        own = np.flatnonzero(self.segment == i)
        if own.size == 0:
            raise IndexError(f"move {i} has no samples in this program")
        return int(own[-1]) + 1

    def describe_sample(self, index: int) -> str:
        """What sample `index` is part of, for messages: 'move 3', 'the hold after move 3',
        'the start ramp' or 'the end ramp'."""
        seg = int(self.segment[index])
        if seg != NO_MOVE:
            return f"move {seg}"
        if self.move_spans is not None:
            if len(self.move_spans) == 0:
                return "the ramp and hold of a plan without moves"
            if index < self.move_spans[0, 0]:
                return "the start ramp"
            if index >= self.move_spans[-1, 1]:
                return "the end ramp"
            j = int(np.searchsorted(self.move_spans[:, 1], index, side="right"))
            return f"the hold after move {j}"
        before = np.flatnonzero(self.segment[:index] != NO_MOVE)
        if before.size == 0:
            return "the start ramp"
        return f"the hold after move {int(self.segment[before[-1]])}"


def _samples(duration_s: float, rate_hz: float) -> int:
    """Whole number of sample periods covering `duration_s` (rounded up; 1e-9 absorbs fp noise)."""
    return max(0, math.ceil(duration_s * rate_hz - 1e-9))


def _check_moves(moves: np.ndarray, radius_mm: float) -> np.ndarray:
    """Whole turns per move, shape (m,) int; PlanError for a move that is not whole turns."""
    per_turn_mm = 2.0 * math.pi * radius_mm
    lengths = np.linalg.norm(moves, axis=1)
    turns = lengths / per_turn_mm
    whole = np.rint(turns)
    for i, (length, t, n) in enumerate(zip(lengths, turns, whole)):
        if abs(t - n) > WHOLE_TURN_TOLERANCE:
            raise PlanError(
                f"move {i}: {length:.2f} mm is {t:.2f} turns of the {radius_mm:.2f} mm magnet "
                f"({per_turn_mm:.2f} mm per turn); rolling uses whole turns (seed 000 Sec. V-a): "
                f"make moves multiples of {per_turn_mm:.2f} mm or change magnets.radius_mm"
            )
    return whole.astype(int)


def realize_global_moves(
    moves_mm: ArrayLike, rig: SixCoilRig, *, start_field_T: ArrayLike | None = None
) -> FieldProgram:
    """Turn global moves into the six-coil rig's field program.

    Parameters
    ----------
    moves_mm : (m, 2) array
        Displacements in mm in the workspace xy plane, one per plan move, executed in order.
        Each must be a whole number of turns of the magnets (2 pi `magnets.radius_mm` mm per
        turn, tolerance 1e-3 turn); a zero move is realized as a hold only.
    rig : SixCoilRig
        Uses `field` (b0_mT, speeds, ramp_s, hold_s, initial_heading_deg, whole_turns),
        `magnets.radius_mm` and `stream.rate_hz`.
    start_field_T : (3,) array, optional
        The field the coils hold now (magnitude b0): the program starts there, without the start
        ramp (a re-planned program spliced into a running one).

    Returns
    -------
    FieldProgram
        Sampled at `stream.rate_hz`, starting and ending at zero field.

    Raises
    ------
    PlanError
        Moves of the wrong shape, not finite, or not whole turns (message names the move).
    ConfigError
        `field.b0_mT` below `magnets.min_field_mT`, so the magnets would not follow.
    """
    moves = np.asarray(moves_mm, dtype=float)
    turns = _turns_of(moves, rig)
    fs = rig.field
    rate = rig.stream.rate_hz
    b0 = fs.b0_mT * 1e-3
    n_ramp = _samples(fs.ramp_s, rate)
    n_hold = _samples(fs.hold_s, rate)
    _check_size(turns, rig)

    fields: list[np.ndarray] = []
    segments: list[np.ndarray] = []
    kinds: list[np.ndarray] = []
    move_spans: list[tuple[int, int]] = []
    count = 0

    def emit(field: np.ndarray, segment: int, kind: int) -> None:
        nonlocal count
        fields.append(field)
        segments.append(np.full(len(field), segment, dtype=int))
        kinds.append(np.full(len(field), kind, dtype=np.uint8))
        count += len(field)

    heading = math.radians(fs.initial_heading_deg)
    h = np.array([math.cos(heading), math.sin(heading), 0.0])
    tilt = 0.0  # B = b0 (cos(tilt) h + sin(tilt) z), h horizontal

    ramp = np.arange(n_ramp) / max(n_ramp, 1)
    if start_field_T is None:
        emit(b0 * ramp[:, None] * h, NO_MOVE, HOLD)
    else:
        b_start = np.asarray(start_field_T, dtype=float).reshape(3)
        horizontal = math.hypot(b_start[0], b_start[1])
        if horizontal > 1e-12 * max(float(np.linalg.norm(b_start)), 1e-300):
            h = np.array([b_start[0] / horizontal, b_start[1] / horizontal, 0.0])
        tilt = math.atan2(float(b_start[2]), horizontal)

    def field_now() -> np.ndarray:
        return b0 * (math.cos(tilt) * h + math.sin(tilt) * _Z_HAT)

    for i, (d, n_turns) in enumerate(zip(moves, turns)):
        move_start = count
        if n_turns > 0:
            steer, roll, h, tilt = _steer_and_roll(i, d, n_turns, h, tilt, fs, rate)
            emit(b0 * steer, i, STEERING)
            emit(b0 * roll, i, ROLLING)
        else:
            logger.debug("move %d is zero: hold only", i)
        emit(np.repeat(field_now()[None, :], n_hold, axis=0), NO_MOVE, HOLD)
        move_spans.append((move_start, count))
        if fs.rest_s > 0 and i < len(moves) - 1:  # the coils cool: off, then back where it was
            emit((1.0 - ramp)[:, None] * field_now(), NO_MOVE, HOLD)
            emit(np.zeros((_samples(fs.rest_s, rate), 3)), NO_MOVE, HOLD)
            emit(ramp[:, None] * field_now(), NO_MOVE, HOLD)

    if len(moves) == 0:
        emit(np.repeat(field_now()[None, :], n_hold, axis=0), NO_MOVE, HOLD)
    emit((1.0 - ramp)[:, None] * field_now(), NO_MOVE, HOLD)
    emit(np.zeros((1, 3)), NO_MOVE, HOLD)

    field = np.concatenate(fields)
    if len(field) > MAX_DURATION_S * rate:
        raise PlanError(f"moves: the field program lasts {len(field) / rate:.0f} s; at most "
                        f"{MAX_DURATION_S:g} s (fewer or shorter moves)")
    return FieldProgram(
        t_s=np.arange(len(field)) / rate,
        field_T=field,
        segment=np.concatenate(segments),
        kind=np.concatenate(kinds),
        rate_hz=rate,
        move_spans=np.array(move_spans, dtype=int).reshape(-1, 2),
    )


def _turns_of(moves: np.ndarray, rig: SixCoilRig) -> np.ndarray:
    """Turns of the magnets (m,) for moves (m, 2) mm: checked whole with `field.whole_turns`.
    PlanError for moves of the wrong shape or not finite, ConfigError for a field too weak for
    the magnets to follow."""
    if moves.ndim != 2 or moves.shape[1] != 2:
        raise PlanError(
            f"moves must be an (m, 2) array of xy displacements in mm, got shape {moves.shape}"
        )
    if not np.isfinite(moves).all():
        bad = int(np.flatnonzero(~np.isfinite(moves).all(axis=1))[0])
        raise PlanError(f"move {bad}: displacement {moves[bad].tolist()} is not finite")
    fs = rig.field
    if fs.b0_mT < rig.magnets.min_field_mT:
        raise ConfigError(
            f"field.b0_mT {fs.b0_mT} is below magnets.min_field_mT {rig.magnets.min_field_mT}: "
            "the magnets would not follow the field"
        )
    if fs.whole_turns:
        return _check_moves(moves, rig.magnets.radius_mm).astype(float)
    return np.linalg.norm(moves, axis=1) / (2.0 * math.pi * rig.magnets.radius_mm)


def _check_size(turns: np.ndarray, rig: SixCoilRig) -> None:
    """PlanError if the program of moves of `turns` (m,) could exceed MAX_PROGRAM_SAMPLES: an
    upper bound on its samples, before anything is allocated."""
    fs, rate = rig.field, rig.stream.rate_hz
    n_ramp, n_hold = _samples(fs.ramp_s, rate), _samples(fs.hold_s, rate)
    steer_rad_per_s = math.radians(fs.steering_deg_per_s)
    most = (turns.sum() / fs.rolling_turns_per_s + len(turns) * (math.pi / steer_rad_per_s)) * rate \
        + (len(turns) + 2) * (n_hold + 1) + 2 * n_ramp
    if fs.rest_s > 0:
        most += len(turns) * (_samples(fs.rest_s, rate) + 2 * n_ramp)
    if most > MAX_PROGRAM_SAMPLES:
        raise PlanError(f"moves: up to {most:.3g} samples of field program at {rate:g} Hz; "
                        f"at most {MAX_PROGRAM_SAMPLES} (fewer or shorter moves)")


def _steer_and_roll(i: int, d: np.ndarray, n_turns: float, h: np.ndarray, tilt: float, fs,
                    rate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Move `i`, d (2,) mm of `n_turns` turns, from the field's horizontal direction `h` (3,) and
    its `tilt` (rad) out of the floor: the field's directions (unit, (n, 3)) steering, then
    rolling (module docstring, 1 and 2), and `h` and `tilt` after it."""
    steer_rad_per_s = math.radians(fs.steering_deg_per_s)
    d_hat = np.array([d[0], d[1], 0.0]) / math.hypot(d[0], d[1])
    u = np.cross(_Z_HAT, d_hat)
    e0 = d_hat if h @ d_hat >= 0.0 else -d_hat

    # steering: turn h into e0 the short way about z, keeping the vertical part
    phi = math.atan2(h[0] * e0[1] - h[1] * e0[0], h @ e0)
    n_steer = _samples(abs(phi) / steer_rad_per_s, rate)
    start = math.atan2(h[1], h[0])
    angles = start + phi * np.arange(n_steer) / max(n_steer, 1)
    steer = np.stack([np.cos(tilt) * np.cos(angles), np.cos(tilt) * np.sin(angles),
                      np.full(n_steer, math.sin(tilt))], axis=1)

    # rolling: n_turns about u, from the angle alpha0 at which B now stands in the
    # rolling plane (0 when B is horizontal, e.g. after whole turns)
    w = np.cross(u, e0)  # +-z
    alpha0 = math.atan2(math.sin(tilt) * float(w @ _Z_HAT), math.cos(tilt))
    n_roll = max(1, _samples(n_turns / fs.rolling_turns_per_s, rate))
    alpha = alpha0 + 2.0 * math.pi * n_turns * np.arange(n_roll) / n_roll
    roll = np.cos(alpha)[:, None] * e0 + np.sin(alpha)[:, None] * w
    end = alpha0 + 2.0 * math.pi * n_turns
    end_b = math.cos(end) * e0 + math.sin(end) * w
    if fs.whole_turns or abs(math.cos(end)) < 1e-12:
        h = e0
    else:
        h = e0 if math.cos(end) > 0 else -e0
    tilt = math.atan2(float(end_b[2]), abs(math.cos(end)))
    if fs.whole_turns:
        tilt = 0.0
    logger.debug("move %d: %.3f turns along %s, steering %.1f deg", i, n_turns, d_hat[:2],
                 math.degrees(phi))
    return steer, roll, h, tilt
