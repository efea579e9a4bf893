"""Driver for a KUKA LBR arm through the KUKA Sunrise Toolbox (KST) server on the robot's cabinet.

The KST server application listens on TCP port 30001 and speaks ASCII lines, fields separated by
`_` (docs/kuka-sunrise.md has the command table and its sources). This driver uses:

- `jRelVel_<v>_` -> `done`: relative joint velocity of point-to-point moves;
- `jp_<q1>_..._<q7>_` -> `done` then `doPTPinJS` -> `done` (accepted) ... `done` (arrived) or
  `nak` (refused or failed): a blocking joint-space move with a deadline;
- `getJointsPositions` -> `<q1>_..._<q7>_`: the measured joints;
- `startDirectServoJoints` -> `done`, then one `jpJP_<q1>_..._<q7>_` per cycle, answered with the
  measured joints (every cycle is checked, so a dead robot is noticed within one timeout), then
  `stopDirectServoJoints` -> `done`;
- `end`: the server closes the session.

Angles in rad, sent with full double precision. Every reply is checked; a silent robot raises `DeviceTimeout`, a lost link
`Disconnected`, a `nak` `DeviceError`, garbage `ProtocolError`; all name the arm. After a timeout the
next command first discards whatever is pending, so a late reply is never taken for a new answer.
`close()` stops a running servo stream and ends the session; it never raises.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from rigctl.errors import (
    ConfigError,
    DeviceError,
    DeviceTimeout,
    Disconnected,
    LimitError,
    ProtocolError,
    RigError,
)
from rigctl.transport import Transport, open_transport

log = logging.getLogger(__name__)

N_JOINTS = 7
KST_PORT = 30001
TERMINATOR = b"\n"
MAX_REPLY_BYTES = 512
ACK, NAK = "done", "nak"
MAX_LATE_REPLIES = 4


def format_joint_command(command: str, q: np.ndarray) -> str:
    """`command_<q1>_..._<q7>_` with every digit of each double (the server parses them with
    Java's `Double.parseDouble`). KST's MATLAB client sends 5 decimals; rounding like that can push
    a target planned exactly at a joint limit past it, and the robot refuses it."""
    return command + "_" + "".join(f"{float(v) + 0.0!r}_" for v in q)


def parse_joints(reply: str) -> np.ndarray:
    """Seven angles from `<q1>_..._<q7>_`; ValueError otherwise."""
    fields = [f for f in reply.strip().split("_") if f != ""]
    if len(fields) != N_JOINTS:
        raise ValueError(f"expected {N_JOINTS} joint values, got {len(fields)}")
    q = np.array([float(f) for f in fields])
    if not np.all(np.isfinite(q)):
        raise ValueError("joint values are not finite")
    return q


class KukaArm:
    """One LBR arm behind a KST server.

    `joint_limits_rad` (shape (7, 2)), when given, is checked before anything is sent (LimitError);
    without it only the robot's own check applies (a refused target comes back as `nak`).
    """

    def __init__(self, transport: Transport, *, name: str, timeout_s: float = 1.0,
                 joint_limits_rad: np.ndarray | None = None) -> None:
        if timeout_s <= 0:
            raise ConfigError(f"timeout_s must be positive, got {timeout_s}", device=name)
        self.name = name
        self.timeout_s = float(timeout_s)
        self.joint_limits_rad = None if joint_limits_rad is None else np.asarray(joint_limits_rad, float)
        self._transport = transport
        self._stale = False
        self._servoing = False
        self._closed = False

    @classmethod
    def open(cls, url: str, *, name: str, timeout_s: float = 1.0,
             joint_limits_rad: np.ndarray | None = None) -> "KukaArm":
        """Connect to the KST server at `url` and check it answers (reads the joints once)."""
        try:
            transport = open_transport(url, timeout_s=timeout_s)
        except Disconnected as err:
            raise Disconnected(f"cannot connect to the KST server: {err}", device=name) from None
        arm = cls(transport, name=name, timeout_s=timeout_s, joint_limits_rad=joint_limits_rad)
        try:
            arm.joint_positions()
        except RigError:
            arm._transport.close()
            raise
        return arm

    # -- wire ------------------------------------------------------------------------------------
    def _write(self, command: str) -> None:
        if self._closed:
            raise Disconnected("the arm's session is closed", device=self.name)
        if self._stale:
            self._transport.discard_input()
            self._stale = False
        try:
            self._transport.write(command.encode("ascii") + TERMINATOR)
        except Disconnected as err:
            raise Disconnected(f"link to the KST server lost ({err})", device=self.name) from None
        except DeviceTimeout as err:
            self._stale = True
            raise DeviceTimeout(str(err), device=self.name) from None

    def _read(self, timeout_s: float | None = None, what: str = "a reply") -> str:
        timeout = self.timeout_s if timeout_s is None else timeout_s
        try:
            raw = self._transport.read_until(TERMINATOR, timeout_s=timeout, max_bytes=MAX_REPLY_BYTES)
        except Disconnected as err:
            raise Disconnected(f"link to the KST server lost ({err})", device=self.name) from None
        except DeviceTimeout:
            self._stale = True
            raise DeviceTimeout(f"no {what} within {timeout:g} s", device=self.name) from None
        except ProtocolError as err:
            self._stale = True
            raise ProtocolError(str(err), device=self.name) from None
        try:
            return raw.decode("ascii").strip()
        except UnicodeDecodeError:
            self._stale = True
            raise ProtocolError(f"reply is not ASCII: {raw[:40]!r}", device=self.name) from None

    def _expect_ack(self, command: str, reply: str) -> None:
        if reply == ACK:
            return
        if reply == NAK:
            raise DeviceError(f"the robot refused {command.split('_')[0]!r} (nak)", device=self.name)
        self._stale = True
        raise ProtocolError(f"expected 'done' after {command.split('_')[0]!r}, got {reply[:60]!r}",
                            device=self.name)

    def _command(self, command: str) -> None:
        self._write(command)
        self._expect_ack(command, self._read(what="acknowledgement"))

    def _joints_reply(self, command: str) -> np.ndarray:
        reply = self._read(what="joint positions")
        if reply == NAK:
            raise DeviceError(f"the robot refused {command.split('_')[0]!r} (nak)", device=self.name)
        try:
            return parse_joints(reply)
        except ValueError as err:
            self._stale = True
            raise ProtocolError(f"bad joint positions {reply[:80]!r}: {err}", device=self.name) from None

    def _check_target(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
            raise LimitError(f"a joint target is {N_JOINTS} finite angles (rad), got {q.tolist()}",
                             device=self.name)
        if self.joint_limits_rad is not None:
            low, high = self.joint_limits_rad[:, 0], self.joint_limits_rad[:, 1]
            bad = np.flatnonzero((q < low) | (q > high))
            if len(bad):
                j = int(bad[0])
                raise LimitError(
                    f"joint A{j + 1} target {math.degrees(q[j]):.2f} deg is outside "
                    f"[{math.degrees(low[j]):.1f}, {math.degrees(high[j]):.1f}] deg; nothing sent",
                    device=self.name)
        return q

    # -- commands --------------------------------------------------------------------------------
    def joint_positions(self) -> np.ndarray:
        """The measured joint angles, shape (7,), rad."""
        self._write("getJointsPositions")
        return self._joints_reply("getJointsPositions")

    def set_relative_velocity(self, value: float) -> None:
        """Relative joint velocity for point-to-point moves, in (0, 1]."""
        if not 0.0 < value <= 1.0:
            raise LimitError(f"relative velocity must be in (0, 1], got {value}", device=self.name)
        self._command(f"jRelVel_{value:.6g}_")

    def move_to(self, q: np.ndarray, *, relative_velocity: float | None = None,
                timeout_s: float = 60.0) -> None:
        """Point-to-point move in joint space; returns once the robot reports arrival.

        DeviceError if the robot refuses the target (outside its limits) or does not arrive,
        DeviceTimeout if no arrival within `timeout_s`.
        """
        if self._servoing:
            raise DeviceError("stop the servo stream before a point-to-point move", device=self.name)
        q = self._check_target(q)
        if relative_velocity is not None:
            self.set_relative_velocity(relative_velocity)
        self._command(format_joint_command("jp", q))
        self._command("doPTPinJS")
        reply = self._read(timeout_s, what="arrival")
        if reply == NAK:
            raise DeviceError(
                "the robot refused or aborted the move (nak): target outside its joint limits, "
                "or a joint did not follow", device=self.name)
        self._expect_ack("doPTPinJS", reply)

    def start_servo(self) -> None:
        """Enter direct-servo mode: from now on `servo(q)` streams joint targets."""
        self._command("startDirectServoJoints")
        self._servoing = True

    def servo(self, q: np.ndarray) -> np.ndarray:
        """Send one servo target and return the measured joints (one round trip)."""
        if not self._servoing:
            raise DeviceError("servo stream not started (start_servo)", device=self.name)
        q = self._check_target(q)
        command = format_joint_command("jpJP", q)
        self._write(command)
        try:
            return self._joints_reply(command)
        except DeviceError as err:
            self._servoing = False
            raise DeviceError(f"{err.args[0]}: the robot is no longer servoing (its stream "
                              "watchdog stopped it, or the target was refused)",
                              device=self.name) from None

    def stop_servo(self) -> None:
        """Leave direct-servo mode (the arm holds where it is).

        A servo reply that came too late for its cycle may still be on the line: joint-position
        lines before the acknowledgement are skipped (at most a few)."""
        self._servoing = False
        self._write("stopDirectServoJoints")
        for _ in range(MAX_LATE_REPLIES):
            reply = self._read(what="acknowledgement")
            try:
                parse_joints(reply)
            except ValueError:
                break
        self._expect_ack("stopDirectServoJoints", reply)

    @property
    def servoing(self) -> bool:
        return self._servoing

    def close(self) -> None:
        """Stop a servo stream, end the session and close the link; never raises."""
        if self._closed:
            return
        try:
            if self._servoing:
                self.stop_servo()
            self._write("end")
        except RigError as err:
            log.warning("%s: clean stop incomplete: %s", self.name, err)
        finally:
            self._closed = True
            self._transport.close()

