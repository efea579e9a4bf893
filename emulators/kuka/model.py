"""A KUKA LBR iiwa arm's joints as the Sunrise controller moves them: pure state, `step(dt)`, no I/O.

Two ways to move, as through the KUKA Sunrise Toolbox (docs/kuka-sunrise.md):

- point to point (`start_ptp`): a straight line in joint space, every joint starting and stopping
  together (Sunrise's synchronised PTP), on a trapezoidal speed profile whose cruise speed is the
  relative velocity (`jRelVel`) times each joint's maximum speed;
- direct servo (`start_servo`, `servo_to`): each joint tracks the latest target within its speed
  and acceleration limits. A stream that goes silent for `servo_timeout_s` stops the arm (the
  joints decelerate to rest and servoing ends until it is started again): the watchdog rigctl's
  safety rules ask of every link.

Targets outside the joint limits are refused (`TargetRejected`) before anything moves. A stalled
joint (`stall(i)`, a backdoor fault) stops following commands; the others carry on, so the motion
ends away from the target and a PTP reports failure.

Joint limits and speeds default to the LBR iiwa 14 R820 data sheet values (`rigctl.physics.kinematics`);
the accelerations are not published and are a guess (docs/kuka-sunrise.md). Angles in rad, time in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rigctl.physics.kinematics import LBR_IIWA_14_R820, N_JOINTS, ArmModel

SERVO_TIMEOUT_S = 0.5
PTP_REACHED_RAD = math.radians(0.1)  # KST's own "reached" clearance for conditional PTP moves
# a joint this close to a standing set point, and slow enough to stop within one 4 ms step, is at
# rest there: without it the discrete tracker chatters round the point (microradians, mrad/s) for
# as long as the steps' lengths vary, and a stopped arm takes seconds to report "idle"
SETTLED_RAD = 1e-5
SETTLE_STEP_S = 4e-3


class TargetRejected(ValueError):
    """A joint target the controller refuses (outside the limits, wrong size, not finite)."""


@dataclass(frozen=True)
class ArmLimits:
    lower_rad: np.ndarray
    upper_rad: np.ndarray
    max_speed_rad_s: np.ndarray
    max_accel_rad_s2: np.ndarray

    @classmethod
    def of(cls, model: ArmModel) -> "ArmLimits":
        return cls(model.lower_rad, model.upper_rad, model.max_speed, model.max_accel)

    @classmethod
    def iiwa14(cls) -> "ArmLimits":
        return cls.of(LBR_IIWA_14_R820)


class _PtpProfile:
    """q(t) = q0 + (q1 - q0) s(t), s a trapezoid from 0 to 1 limited by the slowest joint."""

    def __init__(self, q0: np.ndarray, q1: np.ndarray, speed: np.ndarray, accel: np.ndarray) -> None:
        self.q0, self.q1 = q0.copy(), q1.copy()
        delta = np.abs(q1 - q0)
        moving = delta > 1e-12
        if not moving.any():
            self.v = self.a = 1.0
            self.duration = 0.0
            self.t_acc = 0.0
            return
        self.v = float(np.min(speed[moving] / delta[moving]))  # ds/dt limit
        self.a = float(np.min(accel[moving] / delta[moving]))  # d2s/dt2 limit
        if self.v * self.v / self.a >= 1.0:  # never reaches cruise: a triangle
            self.t_acc = math.sqrt(1.0 / self.a)
            self.v = self.a * self.t_acc
            self.duration = 2.0 * self.t_acc
        else:
            self.t_acc = self.v / self.a
            self.duration = 1.0 / self.v + self.t_acc

    def s(self, t: float) -> tuple[float, float]:
        """Path parameter and its rate at time t."""
        if t >= self.duration:
            return 1.0, 0.0
        if t < self.t_acc:
            return 0.5 * self.a * t * t, self.a * t
        t_dec = self.duration - self.t_acc
        if t <= t_dec:
            return 0.5 * self.a * self.t_acc**2 + self.v * (t - self.t_acc), self.v
        rest = self.duration - t
        return 1.0 - 0.5 * self.a * rest * rest, self.a * rest


class LbrArmModel:
    """The joints of one arm. Modes: "idle", "ptp", "servo"; `time_s` is simulated time."""

    def __init__(self, q0: np.ndarray | None = None, *, limits: ArmLimits | None = None,
                 servo_timeout_s: float = SERVO_TIMEOUT_S) -> None:
        self.limits = limits or ArmLimits.iiwa14()
        self.q = np.zeros(N_JOINTS) if q0 is None else np.asarray(q0, dtype=float).copy()
        self.check_target(self.q)
        self.qd = np.zeros(N_JOINTS)
        self.mode = "idle"
        self.time_s = 0.0
        self.relative_velocity = 1.0
        self.servo_timeout_s = servo_timeout_s
        self.servo_target = self.q.copy()
        self._interp_from = self.q.copy()  # the set point moves from here to servo_target
        self._interp_t0 = 0.0
        self._interp_period = 1.0
        self.watchdog_tripped = False
        self.stalled: set[int] = set()
        self._ptp: _PtpProfile | None = None
        self._ptp_start_s = 0.0
        self._last_servo_s = 0.0
        self._finished: list[bool] = []  # PTP results not yet collected: True reached

    # -- commands -------------------------------------------------------------------------------
    def check_target(self, q: np.ndarray) -> np.ndarray:
        """The target as an array; TargetRejected naming the first joint out of its limits."""
        q = np.asarray(q, dtype=float)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
            raise TargetRejected(f"a joint target is {N_JOINTS} finite angles, got {q.tolist()}")
        low, high = self.limits.lower_rad, self.limits.upper_rad
        bad = np.flatnonzero((q < low - 1e-12) | (q > high + 1e-12))
        if len(bad):
            j = int(bad[0])
            raise TargetRejected(
                f"joint A{j + 1} target {math.degrees(q[j]):.2f} deg outside "
                f"[{math.degrees(low[j]):.1f}, {math.degrees(high[j]):.1f}] deg")
        return q

    def set_relative_velocity(self, value: float) -> None:
        if not 0.0 < value <= 1.0:
            raise TargetRejected(f"relative velocity must be in (0, 1], got {value}")
        self.relative_velocity = float(value)

    def start_ptp(self, target: np.ndarray) -> None:
        target = self.check_target(target)
        if self.mode != "idle":
            raise TargetRejected(f"cannot start a PTP motion while in {self.mode} mode")
        self._ptp = _PtpProfile(self.q, target, self.limits.max_speed_rad_s * self.relative_velocity,
                                self.limits.max_accel_rad_s2)
        self._ptp_start_s = self.time_s
        self.mode = "ptp"
        if self._ptp.duration == 0.0:
            self._end_ptp()

    def start_servo(self) -> None:
        if self.mode == "ptp":
            raise TargetRejected("cannot start direct servo during a PTP motion")
        self.mode = "servo"
        self.servo_target = self.q.copy()
        self._interp_from = self.q.copy()
        self.watchdog_tripped = False
        self._last_servo_s = self.time_s

    def servo_to(self, target: np.ndarray) -> None:
        if self.mode != "servo":
            why = " (stopped by the stream watchdog)" if self.watchdog_tripped else ""
            raise TargetRejected(f"direct servo is not running{why}")
        target = self.check_target(target)
        # like DirectServo, the controller interpolates from where its set point is to the new
        # target over one stream period (never beyond the target, so a late message is safe)
        period = min(max(self.time_s - self._last_servo_s, 1e-3), self.servo_timeout_s)
        self._interp_from = self._set_point()
        self._interp_t0, self._interp_period = self.time_s, period
        self.servo_target = target
        self._last_servo_s = self.time_s

    def discount_silence(self, sim_s: float) -> None:
        """Do not count the next `sim_s` of stream silence against the watchdog (the emulator
        itself could not listen then)."""
        self._last_servo_s += max(sim_s, 0.0)

    def stop(self) -> None:
        """End any motion: the joints decelerate to rest at their limits (a servo hold)."""
        if self.mode == "ptp":
            self._finished.append(False)
            self._ptp = None
        self.mode = "stopping"
        self.servo_target = self._stopping_point()
        self._interp_from = self.servo_target.copy()

    def stall(self, joint: int) -> None:
        if not 0 <= joint < N_JOINTS:
            raise ValueError(f"joint index must be 0..{N_JOINTS - 1}, got {joint}")
        self.stalled.add(joint)
        self.qd[joint] = 0.0

    def unstall(self) -> None:
        self.stalled.clear()

    def collect_finished(self) -> list[bool]:
        """PTP motions that ended since the last call: True if the target was reached."""
        done, self._finished = self._finished, []
        return done

    # -- time -----------------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        if dt <= 0:
            return
        self.time_s += dt
        if self.mode == "servo" and self.time_s - self._last_servo_s > self.servo_timeout_s:
            self.watchdog_tripped = True
            self.stop()
        if self.mode == "ptp":
            assert self._ptp is not None
            s, s_rate = self._ptp.s(self.time_s - self._ptp_start_s)
            q_new = self._ptp.q0 + (self._ptp.q1 - self._ptp.q0) * s
            qd_new = (self._ptp.q1 - self._ptp.q0) * s_rate
            for j in self.stalled:
                q_new[j], qd_new[j] = self.q[j], 0.0
            self.q, self.qd = q_new, qd_new
            if self.time_s - self._ptp_start_s >= self._ptp.duration:
                self._end_ptp()
        elif self.mode in ("servo", "stopping"):
            self._track(dt)
            if self.mode == "stopping" and not np.any(self.qd):
                self.mode = "idle"

    def _set_point(self) -> np.ndarray:
        """Where the interpolator is now between the previous set point and `servo_target`."""
        f = min(max((self.time_s - self._interp_t0) / self._interp_period, 0.0), 1.0)
        return self._interp_from + (self.servo_target - self._interp_from) * f

    def _track(self, dt: float) -> None:
        """Each joint follows the interpolated set point: its feed-forward speed plus a correction
        as fast as the speed limit and the braking distance allow, within the acceleration limit."""
        lim = self.limits
        set_point = self._set_point()
        moving = self.time_s - self._interp_t0 < self._interp_period
        rate = (self.servo_target - self._interp_from) / self._interp_period if moving else 0.0
        error = set_point - self.q
        correction = np.sign(error) * np.minimum(
            np.sqrt(2.0 * lim.max_accel_rad_s2 * np.abs(error)), np.abs(error) / dt)
        wanted = np.clip(rate + correction, -lim.max_speed_rad_s, lim.max_speed_rad_s)
        change = np.clip(wanted - self.qd, -lim.max_accel_rad_s2 * dt, lim.max_accel_rad_s2 * dt)
        qd = self.qd + change
        q = self.q + 0.5 * (self.qd + qd) * dt
        arrived = ((np.abs(self.servo_target - q) < SETTLED_RAD)
                   & (np.abs(qd) <= lim.max_accel_rad_s2 * SETTLE_STEP_S) & (not moving))
        q[arrived], qd[arrived] = self.servo_target[arrived], 0.0
        for j in self.stalled:
            q[j], qd[j] = self.q[j], 0.0
        self.q = np.clip(q, lim.lower_rad, lim.upper_rad)
        self.qd = qd

    def _stopping_point(self) -> np.ndarray:
        """Where each joint comes to rest braking at full deceleration from its current speed."""
        a = self.limits.max_accel_rad_s2
        return np.clip(self.q + self.qd * np.abs(self.qd) / (2.0 * a),
                       self.limits.lower_rad, self.limits.upper_rad)

    def _end_ptp(self) -> None:
        assert self._ptp is not None
        reached = bool(np.all(np.abs(self.q - self._ptp.q1) <= PTP_REACHED_RAD))
        self.qd = np.zeros(N_JOINTS)
        self._ptp = None
        self.mode = "idle"
        self._finished.append(reached)
