"""The progress line every run shows on a terminal (or a line per move elsewhere)."""

from __future__ import annotations

import time
from typing import TextIO


class Progress:
    """One status line on a terminal (rewritten in place), or a line per move elsewhere."""

    def __init__(self, out: TextIO | None, n_moves: int, duration_s: float) -> None:
        self.out = out
        self.n_moves = n_moves
        self.duration_s = duration_s
        self.tty = bool(out is not None and out.isatty())
        self._last_move = -2
        self._last_draw = 0.0

    def update(self, move: int, t_s: float, what: str | None = None) -> None:
        """`t_s` s into the run, in `move` (-1: a ramp or hold, not a line of its own off a
        terminal). `what` names the stage for runs whose stages are not global moves (a pair
        run's segments and hold); a new line off a terminal still comes only with a new `move`."""
        if self.out is None:
            return
        now = time.monotonic()
        if move == self._last_move and (not self.tty or now - self._last_draw < 0.2):
            return
        new_move = move != self._last_move
        self._last_move, self._last_draw = move, now
        what = what or self._move_name(move)
        planned = f" / {self.duration_s:.1f} s planned" if self.duration_s else ""  # 0: unknown
        line = f"  {what:<14} {t_s:6.1f} s{planned}"
        if self.tty:
            self.out.write("\r" + line.ljust(50))
            self.out.flush()
        elif new_move and move >= 0:
            self.out.write(line + "\n")

    def _move_name(self, move: int) -> str:
        if move < 0:
            return "ramp/hold"
        if move < self.n_moves:
            return f"move {move + 1}/{self.n_moves}"
        return f"correction {move + 1 - self.n_moves}"  # spliced in by the closed loop's re-plans

    def done(self) -> None:
        if self.out is not None and self.tty:
            self.out.write("\n")


