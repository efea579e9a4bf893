"""Where the arms' servo targets come from, cycle by cycle: pure, no I/O and no clock of its own.

A run of a field-sequence plan streams one joint target per arm and cycle. The targets come from
three kinds of motion, all on the same servo:

- the *approach*: from wherever the arms stand to the plan's first pose, one arm after the other
  (by way of the candle pose when the direct way would break a constraint), each leg a straight
  line in joint space (`JointPath`) on a trapezoidal time law, all joints of an arm
  starting and stopping together as in a synchronised PTP move, timed so no joint exceeds the
  rig's speed fraction of its maximum speed, nor its acceleration fraction. It is checked against
  every safety constraint (`path_violations`) before anything moves;
- the *plan*: its PCHIP joint curves, on the plan's clock;
- a *rejoin*: after a hold that stopped the arms off the path (pause now holds the measured pose),
  a short `JointPath` of both arms back to the path where the clock stopped, before it runs on.

`Timeline` strings them together on one program clock that the caller advances by the time each
cycle stands for; a hold (pause, suspension) freezes the clock at a fixed pose.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from rigctl.physics.kinematics import ArmKinematics
from rigctl.plans.depm_safety import SafetyLimits, Violation, violations

TIMING_MARGIN = 0.02  # moves are timed this much slower than the limits allow
AT_POSE_RAD = 1e-9  # a hold this close to the path needs no rejoin


@dataclass(frozen=True)
class _Leg:
    """Every arm from `q_from` to `q_to` (A, 7) on one trapezoidal time law s(t) from 0 to 1 (all
    joints start and stop together, as a synchronised PTP move does): constant acceleration to a
    cruise rate, cruise, constant deceleration; the slowest joint sets both."""

    start_s: float
    q_from: np.ndarray
    q_to: np.ndarray
    rate: float  # cruise ds/dt, 1/s
    accel: float  # d2s/dt2, 1/s^2
    t_acc: float
    duration_s: float

    @classmethod
    def timed(cls, start_s: float, q_from: np.ndarray, q_to: np.ndarray, speed_caps: np.ndarray,
              accel_caps: np.ndarray) -> _Leg | None:
        delta = np.abs(q_to - q_from)
        moving = delta > 1e-12
        if not moving.any():
            return None
        rate = float(np.min(speed_caps[moving] / delta[moving])) / (1.0 + TIMING_MARGIN)
        accel = float(np.min(accel_caps[moving] / delta[moving])) / (1.0 + TIMING_MARGIN)
        if rate * rate / accel >= 1.0:  # never reaches the cruise rate: a triangle
            t_acc = float(np.sqrt(1.0 / accel))
            rate = accel * t_acc
            duration = 2.0 * t_acc
        else:
            t_acc = rate / accel
            duration = 1.0 / rate + t_acc
        return cls(start_s, q_from.copy(), q_to.copy(), rate, accel, t_acc, duration)

    def law(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """s, ds/dt, d2s/dt2 at times `t` from the leg's start (clamped to the leg)."""
        t = np.clip(t, 0.0, self.duration_s)
        a, v, ta, total = self.accel, self.rate, self.t_acc, self.duration_s
        rising, falling = t < ta, t > total - ta
        rest = total - t
        s = np.where(rising, 0.5 * a * t * t,
                     np.where(falling, 1.0 - 0.5 * a * rest * rest, 0.5 * a * ta * ta + v * (t - ta)))
        ds = np.where(rising, a * t, np.where(falling, a * rest, v))
        dds = np.where(rising, a, np.where(falling, -a, 0.0))
        return s, ds, dds


@dataclass
class JointPath:
    """Straight joint-space legs one after another (`at(t)` -> (A, 7) rad); at rest at both ends
    of every leg. Before the first leg and after the last it holds the end poses."""

    q_from: np.ndarray
    legs: list[_Leg] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return self.legs[-1].start_s + self.legs[-1].duration_s if self.legs else 0.0

    @property
    def q_to(self) -> np.ndarray:
        return self.legs[-1].q_to if self.legs else self.q_from

    def at(self, t: float) -> np.ndarray:
        return self.sample(np.array([t]))[0][:, 0]

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joints, speeds and accelerations (A, T, 7) at times (T,)."""
        t = np.asarray(t, dtype=float)
        q = np.repeat(self.q_from[:, None, :], len(t), axis=1).astype(float)
        qd = np.zeros_like(q)
        qdd = np.zeros_like(q)
        for leg in self.legs:  # in order: a later leg takes over from its start
            delta = (leg.q_to - leg.q_from)[:, None, :]
            local = t - leg.start_s
            begun = local >= 0.0
            inside = begun & (local <= leg.duration_s)
            s, ds, dds = leg.law(local)
            q[:, begun] = leg.q_from[:, None, :] + delta * s[begun][None, :, None]
            qd[:, inside] = delta * ds[inside][None, :, None]
            qdd[:, inside] = delta * dds[inside][None, :, None]
        return q, qd, qdd


def joint_path(q_from: np.ndarray, q_to: np.ndarray, speed_caps: np.ndarray,
               accel_caps: np.ndarray, *, one_at_a_time: bool) -> JointPath:
    """From `q_from` to `q_to` (A, 7): every arm together, or one arm after the other (in order;
    an arm already there adds no leg). Caps (A, 7) or (7,), rad/s and rad/s^2."""
    q_to = np.asarray(q_to, dtype=float)
    groups = [[a] for a in range(len(q_to))] if one_at_a_time else [list(range(len(q_to)))]
    return waypoint_path(q_from, [(arms, q_to[arms]) for arms in groups], speed_caps, accel_caps)


def waypoint_path(q_from: np.ndarray, moves: Sequence[tuple[list[int], np.ndarray]],
                  speed_caps: np.ndarray, accel_caps: np.ndarray) -> JointPath:
    """From `q_from` (A, 7), one leg per move in turn: the arms it names to its joints (a move
    that changes nothing adds no leg)."""
    q_from = np.asarray(q_from, dtype=float)
    speed_caps = np.broadcast_to(speed_caps, q_from.shape)
    accel_caps = np.broadcast_to(accel_caps, q_from.shape)
    path = JointPath(q_from.copy())
    q, t = q_from.copy(), 0.0
    for arms, target in moves:
        nxt = q.copy()
        nxt[arms] = target
        leg = _Leg.timed(t, q, nxt, speed_caps, accel_caps)
        if leg is not None:
            path.legs.append(leg)
            t += leg.duration_s
        q = nxt
    return path


def caps(arms: Sequence[ArmKinematics], limits: SafetyLimits) -> tuple[np.ndarray, np.ndarray]:
    """Per arm and joint (A, 7): the speed and acceleration the safety limits allow."""
    speed = np.array([limits.speed_fraction * arm.model.max_speed for arm in arms])
    accel = np.array([limits.accel_fraction * arm.model.max_accel for arm in arms])
    return speed, accel


def approach_path(q_now: np.ndarray, q_start: np.ndarray, arms: Sequence[ArmKinematics],
                  limits: SafetyLimits) -> JointPath:
    """From where the arms stand (A, 7) to the plan's first pose, one arm after the other: the
    first of these that keeps every constraint (else the first, whose breaches the caller
    reports): in the rig's order; in the other order; each arm back to the candle (all joints
    0, straight up, far from the workspace) first, then each to its start, in either order. A
    straight line in joint space from where a plan ended to where the next begins can cut the
    keep-out sphere that a retreat goes around."""
    speed, accel = caps(arms, limits)
    q_start = np.asarray(q_start, dtype=float)
    candle = np.zeros(q_start.shape[1])
    candidates = []
    for order in (list(range(len(q_start))), list(range(len(q_start)))[::-1]):
        candidates.append([([a], q_start[a]) for a in order])
    for order in (list(range(len(q_start))), list(range(len(q_start)))[::-1]):
        candidates.append([([a], candle) for a in order] + [([a], q_start[a]) for a in order])
    paths = [waypoint_path(q_now, moves, speed, accel) for moves in candidates]
    return next((p for p in paths if not path_violations(p, arms, limits)), paths[0])


def path_violations(path: JointPath, arms: Sequence[ArmKinematics],
                    limits: SafetyLimits) -> list[Violation]:
    """Every constraint `path` breaks (positions, speeds and accelerations sampled every
    `check_step_s` and at every leg's ends), times from the path's start."""
    ends = [0.0] + [leg.start_s + leg.duration_s for leg in path.legs]
    t = np.union1d(np.arange(0.0, path.duration_s, limits.check_step_s), ends)
    q, qd, qdd = path.sample(t)
    return violations(t, q, qd, arms, limits, qdd)


class Timeline:
    """The approach, then the plan's curves, on one program clock (s, the plan's seconds).

    `advance(dt)` moves the clock by `dt` (unless held) and returns the target (A, 7); `hold(q)`
    freezes it at pose `q`; `release()` lets it run again, first rejoining the path by a
    `JointPath` of both arms if the hold was off it. `finished` once the target at the plan's
    end has been handed out."""

    def __init__(self, approach: JointPath, curves: Sequence[Callable[[float], np.ndarray]],
                 t_start_s: float, t_end_s: float, speed_caps: np.ndarray,
                 accel_caps: np.ndarray) -> None:
        self.approach = approach
        self.curves = list(curves)
        self.t_start_s, self.t_end_s = float(t_start_s), float(t_end_s)
        self.speed_caps, self.accel_caps = speed_caps, accel_caps
        self.t = 0.0  # program clock: the approach on [0, approach.duration_s), then the plan
        self.held: np.ndarray | None = None
        self.rejoin: JointPath | None = None
        self._rejoin_t = 0.0
        self.finished = False
        self.rejoins = 0
        # (plan time t, the plan's pose) -> the pose to send, if not None (the Hall correction)
        self.correct: Callable[[float, np.ndarray], np.ndarray] | None = None

    @property
    def in_approach(self) -> bool:
        return self.t < self.approach.duration_s

    @property
    def plan_time_s(self) -> float:
        """The plan's clock now (before its start while approaching)."""
        return self.t_start_s + self.t - self.approach.duration_s

    def pose_at_clock(self) -> np.ndarray:
        if self.in_approach:
            return self.approach.at(self.t)
        t = min(self.plan_time_s, self.t_end_s)
        pose = np.array([curve(t) for curve in self.curves])
        return pose if self.correct is None else self.correct(t, pose)

    def hold(self, pose: np.ndarray) -> None:
        if self.held is None:
            self.held = np.array(pose, dtype=float).reshape(len(self.curves), -1)

    def release(self) -> None:
        if self.held is None:
            return
        held, self.held = self.held, None
        on_path = self.rejoin.at(self._rejoin_t) if self.rejoin is not None else self.pose_at_clock()
        if np.max(np.abs(held - on_path)) > AT_POSE_RAD:
            # back to where the path was left (a rejoin interrupted by a hold is replaced)
            target = self.rejoin.q_to if self.rejoin is not None else self.pose_at_clock()
            self.rejoin = joint_path(held, target, self.speed_caps, self.accel_caps,
                                     one_at_a_time=False)
            self._rejoin_t = 0.0
            self.rejoins += 1

    def advance(self, dt: float) -> np.ndarray:
        if self.held is not None:
            return self.held.copy()
        if self.rejoin is not None:
            self._rejoin_t += dt
            if self._rejoin_t < self.rejoin.duration_s:
                return self.rejoin.at(self._rejoin_t)
            dt = self._rejoin_t - self.rejoin.duration_s  # the rest of this cycle is the path's
            self.rejoin = None
        self.t += dt
        if self.plan_time_s >= self.t_end_s:
            self.finished = True
        return self.pose_at_clock()
