"""A GRBL 1.1h controller as a pure model: its states, its planner and one stepper axis, no I/O.

The spinner's stepper is GRBL's X axis configured in degrees (`$100` steps per degree, `$110` the
maximum rate in degrees per minute, `$120` the acceleration in degrees per s^2), so a jog's feed
`F` is a rotation rate in degrees per minute. The model follows GRBL's documented behaviour
(gnea/grbl doc/markdown: interface.md, commands.md, jogging.md; protocol.c for the hold and
jog-cancel state changes):

- the planner holds up to `PLANNER_BLOCKS` (15) motions; a block's feed is clamped to `$110`; the
  axis accelerates and decelerates at `$120` and plans to stop at the end of what is queued (it
  never runs faster than it can stop within the queued distance), through junctions of the same
  direction without slowing (one axis: collinear), to a stop where the direction reverses;
- `Idle`, `Run`, `Jog`, `Hold:0/1`, `Alarm`; a feed hold decelerates to `Hold:0` (from `Idle`
  at once); in `Jog` a hold or a jog cancel decelerates and then flushes every queued jog, back
  to `Idle`; cycle start resumes a completed hold; a soft reset stops at once, flushes, and
  raises alarm 3 if the axis was moving (or a hold was still decelerating), else keeps `Idle`;
- `$X` leaves `Alarm`.

Only `step(dt)` advances time (integrated in sub-steps of `SUBSTEP_S`), so tests drive it by hand.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

PLANNER_BLOCKS = 15  # BLOCK_BUFFER_SIZE 16 on an ATmega328p, one kept free: `Bf:15,128` when empty
SUBSTEP_S = 0.001
ALARM_ABORT_CYCLE = 3  # "Reset while in motion. Grbl cannot guarantee position."

# $$ as GRBL 1.1h prints it (interface.md), X configured for the spinner: 3200 microsteps per
# turn (200-step motor at 1/16) is 8.889 steps/degree; 5 turns/s = 108000 degrees/min; 7200
# degrees/s^2 (20 turns/s^2). The integer settings print without decimals.
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0, 20: 0, 21: 0,
    22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 3200 / 360, 101: 250.0, 102: 250.0, 110: 108000.0, 111: 500.0, 112: 500.0,
    120: 7200.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0}
INTEGER_SETTINGS = {0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32}


@dataclass
class Block:
    """One planned motion of the X axis: what is left of it (degrees, signed) and its feed
    (degrees/s, already clamped to the axis's maximum rate)."""

    remaining_deg: float
    feed_deg_s: float
    jog: bool


class GrblMachine:
    """The controller's state and its axis. `settings` is the `$$` table (number -> value)."""

    def __init__(self, settings: dict[int, float] | None = None) -> None:
        self.settings = dict(DEFAULT_SETTINGS if settings is None else settings)
        self.position_deg = 0.0
        self.speed_deg_s = 0.0  # >= 0, along the current block's direction
        self.direction = 1.0
        self.queue: deque[Block] = deque()
        self.state = "Idle"
        self.holding = False  # a feed hold (or jog cancel) is decelerating or complete
        self.jog_cancel = False
        self.time_s = 0.0

    # -- settings -------------------------------------------------------------------------------
    @property
    def steps_per_deg(self) -> float:
        return self.settings[100]

    @property
    def max_rate_deg_s(self) -> float:
        return self.settings[110] / 60.0

    @property
    def accel_deg_s2(self) -> float:
        return self.settings[120]

    @property
    def moving(self) -> bool:
        return self.speed_deg_s > 0.0

    @property
    def rate_hz(self) -> float:
        """Signed turns per second of the axis now."""
        return self.direction * self.speed_deg_s / 360.0

    def machine_position_deg(self) -> float:
        """MPos as GRBL reports it: the position in whole steps (its int32 step counter)."""
        return round(self.position_deg * self.steps_per_deg) / self.steps_per_deg

    # -- commands (the wire's protocol calls these) ---------------------------------------------
    @property
    def planner_full(self) -> bool:
        return len(self.queue) >= PLANNER_BLOCKS

    def jog(self, delta_deg: float, feed_deg_min: float) -> None:
        """Queue an incremental jog (the caller checked the state is Idle or Jog and the planner
        has room); a zero-length jog is accepted and does nothing, as in GRBL. One that arrives
        while a jog cancel decelerates is queued, then flushed with the rest (protocol.c)."""
        if delta_deg == 0.0:
            return
        self.queue.append(Block(delta_deg, min(feed_deg_min / 60.0, self.max_rate_deg_s), True))
        if self.state == "Idle":
            self.state = "Jog"

    def feed_hold(self) -> None:
        """`!`: decelerate to a hold; in Jog it cancels the jog; in Idle the hold is complete."""
        if self.state in ("Alarm",):
            return
        if self.state == "Jog":
            self.jog_cancel_now()
        elif self.state in ("Idle", "Run"):
            self.state = "Hold"
            self.holding = True

    def jog_cancel_now(self) -> None:
        """0x85: only in Jog: decelerate, then flush every jog and go Idle."""
        if self.state == "Jog" and not self.jog_cancel:
            self.holding = True
            self.jog_cancel = True

    def cycle_start(self) -> None:
        """`~`: resume a completed hold (Run if blocks are left, else Idle); otherwise ignored."""
        if self.state == "Hold" and not self.moving:
            self.holding = False
            self.state = "Run" if self.queue else "Idle"

    def soft_reset(self) -> bool:
        """0x18: stop at once and flush; True if this raised alarm 3 (it was moving, or a hold
        was still decelerating): GRBL cannot vouch for the position then."""
        alarm = self.moving or (self.state in ("Run", "Jog") and bool(self.queue))
        self.queue.clear()
        self.speed_deg_s = 0.0
        self.holding = self.jog_cancel = False
        if alarm or self.state == "Alarm":
            self.state = "Alarm"
        else:
            self.state = "Idle"
        return alarm

    def unlock(self) -> None:
        """`$X`: leave the alarm state (the position may be off: a rotor does not care)."""
        if self.state == "Alarm":
            self.state = "Idle"

    # -- time ----------------------------------------------------------------------------------
    def step(self, dt_s: float) -> None:
        """Advance `dt_s` seconds of motion."""
        while dt_s > 1e-12:
            h = min(SUBSTEP_S, dt_s)
            self._substep(h)
            dt_s -= h
            self.time_s += h

    def _substep(self, h: float) -> None:
        a = self.accel_deg_s2
        if self.holding:
            self.speed_deg_s = max(0.0, self.speed_deg_s - a * h)
        elif self.queue and self.state in ("Run", "Jog"):
            self.speed_deg_s = min(self.speed_deg_s + a * h, self._allowed_speed())
        if self.speed_deg_s > 0.0 and self.queue:
            self._advance(self.speed_deg_s * h)
        elif self.speed_deg_s > 0.0:  # nothing left to run on
            self.speed_deg_s = 0.0
        if self.speed_deg_s == 0.0:
            self._settled()

    def _allowed_speed(self) -> float:
        """The fastest the axis may go now and still meet every block's feed and stop at the end
        of the queued run in this direction (v^2 = v_i^2 + 2 a d)."""
        a = self.accel_deg_s2
        sign = math.copysign(1.0, self.queue[0].remaining_deg)
        if self.speed_deg_s > 0.0 and sign != self.direction:
            return 0.0  # the queue reverses under us: stop first
        allowed, ahead = math.inf, 0.0
        for block in self.queue:
            if math.copysign(1.0, block.remaining_deg) != sign:
                break
            allowed = min(allowed, math.sqrt(block.feed_deg_s ** 2 + 2.0 * a * ahead))
            ahead += abs(block.remaining_deg)
        return min(allowed, math.sqrt(2.0 * a * ahead))

    def _advance(self, distance_deg: float) -> None:
        if self.speed_deg_s > 0.0 and not self.holding:
            self.direction = math.copysign(1.0, self.queue[0].remaining_deg)
        while distance_deg > 0.0 and self.queue:
            block = self.queue[0]
            if math.copysign(1.0, block.remaining_deg) != self.direction:
                self.speed_deg_s = 0.0  # a reversal: the planner stops at the junction
                return
            step = min(distance_deg, abs(block.remaining_deg))
            self.position_deg += self.direction * step
            block.remaining_deg -= self.direction * step
            distance_deg -= step
            if abs(block.remaining_deg) < 1e-9:
                self.queue.popleft()
        if not self.queue and not self.holding:
            self.speed_deg_s = 0.0  # the queued run ended (planned to stop there)

    def _settled(self) -> None:
        """Stopped: a hold is complete, a jog cancel flushes to Idle, a finished cycle is Idle."""
        if self.jog_cancel:
            self.queue.clear()
            self.holding = self.jog_cancel = False
            self.state = "Idle"
        elif self.state in ("Run", "Jog") and not self.queue:
            self.state = "Idle"

    def status_state(self) -> str:
        """The first field of a status report: `Hold:0` once a hold is complete, `Hold:1` while it
        decelerates; a jog cancel still reports `Jog` (report.c)."""
        if self.state == "Hold":
            return "Hold:1" if self.moving else "Hold:0"
        return self.state
