"""Jogging the dual-EPM rig's magnets by hand (teleoperation, `rigctl.run.teleop`).

The operator gives a Cartesian velocity of the magnets (vx, vy, vz, each a fraction of
`JOG_MM_S`), and both EPM centres move by it together, their moment directions kept: each cycle,
each arm's joints step by the damped least-squares solution of its 6 x 7 task Jacobian (the EPM
centre's velocity, and no change of its moment direction, the flange x axis), taken by finite
differences of its forward kinematics. Every step is held to the arms' safety constraints before
it is sent (`rigctl.plans.depm_safety`): no joint faster than the rig's speed fraction of its
maximum (the step scaled down), no joint's speed changing faster than its acceleration cap, and a
pose that would leave a joint's range, enter the keep-out sphere or bring the EPMs too close is
not taken: the jog stops at the boundary (the record says which, once) and moves again only in a
direction that keeps them. With no input (let go, or the dead-man) the joints hold where they
are, which is the arms' rest.
"""

from __future__ import annotations

import numpy as np

from rigctl.core.config import RigConfig
from rigctl.run.certificate import Check
from rigctl.run.teleop import InputComponent, TeleopDrive

JOG_MM_S = 20.0
"""The magnets' Cartesian speed at full input (mm/s)."""

DAMPING = 1e-3  # damped least squares: bounded steps near a singular pose
FD_RAD = 1e-6  # the finite-difference step of the task Jacobian


class JogDrive(TeleopDrive):
    """The magnets' Cartesian jog (see the module docstring)."""

    mode = "jog"
    late = "skip"  # the arm servo: a target in the past is worthless
    components = tuple(
        InputComponent(f"v{axis}", "1", -1.0, 1.0,
                       f"the magnets' velocity along {axis}, a fraction of {JOG_MM_S:g} mm/s")
        for axis in "xyz")

    def __init__(self, rig: RigConfig) -> None:
        from rigctl.core.errors import ConfigError
        from rigctl.plans.depm import rig_from_settings
        from rigctl.rigs.depm.actuators import ArmPair
        from rigctl.rigs.depm.motion import caps
        from rigctl.rigs.depm.run import REAL_ARMS_REFUSED

        if rig.depm is None:
            raise ConfigError("a depm rig needs a [depm] table (arms, Hall board)")
        if not rig.emulated:  # a jog's direction and its checks come from the arm model
            raise ConfigError(REAL_ARMS_REFUSED)
        depm = rig_from_settings(rig.depm)
        self.arms, self.limits = depm.arms, depm.limits
        self.speed, self.accel = caps(self.arms, self.limits)  # (A, 7) rad/s, rad/s^2
        self.connect = ArmPair.connect
        self.rate_hz = rig.depm.servo_rate_hz
        self.dt = 1.0 / self.rate_hz
        self.q: np.ndarray | None = None  # (A, 7) rad, the pose commanded last
        self.qdot = np.zeros((len(self.arms), 7))
        self.blocked: str | None = None  # the constraint the jog stopped at, if it is stopped

    def connected(self, actuators) -> None:
        """Start from where the arms stand; LimitError if that pose breaks a constraint."""
        from rigctl.core.errors import LimitError
        from rigctl.plans.depm_safety import violations

        q = np.asarray(actuators.joint_positions(), dtype=float).reshape(len(self.arms), 7)
        found = violations(np.zeros(1), q[:, None, :], None, self.arms, self.limits)
        if found:
            raise LimitError(f"the arms stand where a safety constraint is broken: {found[0]}; "
                             "move them by a hold first", device=found[0].arm)
        self.start_at(q)

    def start_at(self, q: np.ndarray) -> None:
        self.q = np.array(q, dtype=float).reshape(len(self.arms), 7)
        self.qdot[:] = 0.0

    def task_jacobian(self, a: int, q: np.ndarray) -> np.ndarray:
        """(6, 7): the EPM centre's (m/rad) and its moment direction's change per joint."""
        arm = self.arms[a]
        p0, m0 = arm.epm_pose(q)
        jac = np.empty((6, 7))
        for j in range(7):
            dq = q.copy()
            dq[j] += FD_RAD
            p, m = arm.epm_pose(dq)
            jac[:3, j], jac[3:, j] = (p - p0) / FD_RAD, (m - m0) / FD_RAD
        return jac

    def step(self, values: np.ndarray | None) -> np.ndarray:
        from rigctl.plans.depm_safety import violations

        assert self.q is not None, "connected() first"
        if values is None:
            self.qdot[:] = 0.0
            self.blocked = None
            return self.q.ravel().copy()
        task = np.zeros(6)
        task[:3] = np.asarray(values, dtype=float) * JOG_MM_S * 1e-3  # m/s
        qdot = np.empty_like(self.qdot)
        for a in range(len(self.arms)):
            jac = self.task_jacobian(a, self.q[a])
            qdot[a] = jac.T @ np.linalg.solve(jac @ jac.T + DAMPING * np.eye(6), task)
        # no joint faster than its cap (the whole step scaled, so the direction is kept), and no
        # joint's speed changing faster than its acceleration cap
        qdot /= max(1.0, float(np.max(np.abs(qdot) / self.speed)))
        change = qdot - self.qdot
        qdot = self.qdot + change / max(1.0, float(np.max(np.abs(change) / (self.accel * self.dt))))
        q_next = self.q + qdot * self.dt
        found = violations(np.zeros(1), q_next[:, None, :], None, self.arms, self.limits)
        if found:
            self.blocked = str(found[0])
            self.qdot[:] = 0.0
        else:
            self.blocked = None
            self.q, self.qdot = q_next, qdot
        return self.q.ravel().copy()

    def at_rest(self) -> bool:
        return True  # the arms' rest is where they stand

    def checks(self) -> list[Check]:
        """None ahead: where a jog goes is not known before it is made; every cycle's pose is
        checked against every constraint before it is sent (the module docstring)."""
        return []


def teleop_drive(rig: RigConfig, mode: str | None) -> TeleopDrive:
    """The dual-EPM rig's teleoperation: "jog" (the magnets' Cartesian velocity)."""
    from rigctl.core.errors import ConfigError

    if mode in (None, "jog"):
        return JogDrive(rig)
    raise ConfigError(f"teleop: a depm rig steers in mode jog, not {mode!r}")
