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

Angles in rad, sent with full double precision. Every reply is checked; a silent robot raises
`DeviceTimeout`, a lost link
`Disconnected`, a `nak` `DeviceError`, garbage `ProtocolError`; all name the arm. After a timeout the
next command first discards whatever is pending, so a late reply is never taken for a new answer.
`close()` stops a running servo stream and ends the session; it never raises.

A servo cycle of two arms overlaps their round trips: `send_servo` to each, then `read_servo` from
each (`servo` is the two in one).

E-stop does not wait for the stream thread: `emergency_stop` may be called from any thread, even
while the stream thread waits for a servo reply. KST has no "stop now" of its own beyond ending the
servo motion, so that is what it sends (`stopDirectServoJoints`: the robot brakes and holds where
it is); it latches, so no further target, PTP move or servo start leaves this driver. The `done`
that answers it is owed: whichever read comes next skips it. A lock keeps the two threads' lines
from interleaving on the wire. KST has no speed query either: `wait_at_rest` confirms rest by
reading the joints until two reads a moment apart agree.
"""

from __future__ import annotations

import logging
import math
import threading
import time

import numpy as np

from rigctl.core.errors import (
    ConfigError,
    DeviceError,
    DeviceTimeout,
    Disconnected,
    LimitError,
    ProtocolError,
    RigError,
)
from rigctl.core.transport import Transport, open_transport

log = logging.getLogger(__name__)

N_JOINTS = 7
KST_PORT = 30001
TERMINATOR = b"\n"
MAX_REPLY_BYTES = 512
ACK, NAK = "done", "nak"
MAX_LATE_REPLIES = 4
AT_REST_RAD = 1e-5  # two joint reads this close (every joint): the arm is at rest
AT_REST_INTERVAL_S = 0.05
MOTION_COMMANDS = ("jp_", "jpJP_", "jf_", "doPTPinJS", "startDirectServoJoints", "jRelVel_")


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
        self._wire = threading.Lock()  # the e-stop thread's line and the stream's never interleave
        self._estopped = False  # latched by emergency_stop: no motion command leaves any more
        self._owed_acks = 0  # `done`s answering e-stops, not yet read
        self._awaiting_servo = False

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
        with self._wire:
            if self._estopped and command.startswith(MOTION_COMMANDS):
                raise DeviceError(f"e-stop latched: {command.split('_')[0]!r} not sent (the arm "
                                  "stays stopped; connect again to move it)", device=self.name)
            if self._stale:
                self._transport.discard_input()
                self._stale = False
                self._owed_acks = 0  # gone with the discarded input, or a stray `done` later
            try:
                self._transport.write(command.encode("ascii") + TERMINATOR)
            except Disconnected as err:
                raise Disconnected(f"link to the KST server lost ({err})", device=self.name) from None
            except DeviceTimeout as err:
                self._stale = True
                raise DeviceTimeout(str(err), device=self.name) from None

    def _reply(self, timeout_s: float | None = None, what: str = "a reply") -> str:
        """The next reply, past the `done`s that answered e-stops sent meanwhile."""
        while True:
            reply = self._read(timeout_s, what)
            with self._wire:
                if reply == ACK and self._owed_acks > 0:
                    self._owed_acks -= 1
                    continue
            return reply

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
        self._expect_ack(command, self._reply(what="acknowledgement"))

    def _joints_reply(self, command: str) -> np.ndarray:
        reply = self._reply(what="joint positions")
        for _ in range(MAX_LATE_REPLIES):
            if reply != ACK:
                break
            # a stray acknowledgement (an e-stop's, after its owed count was lost with
            # discarded input): never a joint position
            reply = self._reply(what="joint positions")
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
        reply = self._reply(timeout_s, what="arrival")
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
        self.send_servo(q)
        return self.read_servo()

    def send_servo(self, q: np.ndarray) -> None:
        """Send one servo target; `read_servo` takes its answer (another arm's round trip may
        run in between)."""
        if not self._servoing:
            raise DeviceError("servo stream not started (start_servo)", device=self.name)
        if self._awaiting_servo:
            raise RuntimeError(f"{self.name}: read_servo() must follow each send_servo()")
        q = self._check_target(q)
        self._write(format_joint_command("jpJP", q))
        self._awaiting_servo = True

    def read_servo(self) -> np.ndarray:
        """The measured joints (7,) rad answering the last `send_servo`."""
        if not self._awaiting_servo:
            raise RuntimeError(f"{self.name}: read_servo() without send_servo()")
        try:
            return self._joints_reply("jpJP")
        except DeviceError as err:
            self._servoing = False
            raise DeviceError(f"{err.args[0]}: the robot is no longer servoing (its stream "
                              "watchdog stopped it, or the target was refused)",
                              device=self.name) from None
        finally:
            self._awaiting_servo = False

    def stop_servo(self) -> None:
        """Leave direct-servo mode (the arm holds where it is).

        A servo reply that came too late for its cycle may still be on the line: joint-position
        lines before the acknowledgement are skipped (at most a few)."""
        self._servoing = False
        self._awaiting_servo = False
        self._write("stopDirectServoJoints")
        for _ in range(MAX_LATE_REPLIES):
            reply = self._reply(what="acknowledgement")
            try:
                parse_joints(reply)
            except ValueError:
                break
        self._expect_ack("stopDirectServoJoints", reply)

    @property
    def servoing(self) -> bool:
        return self._servoing

    @property
    def estopped(self) -> bool:
        return self._estopped

    def emergency_stop(self) -> bool:
        """E-stop, from any thread: end the servo motion now (the robot brakes and holds where it
        is) and latch (no further target, move or servo start is sent). Never raises; returns
        False when the line could not be sent (a dead link, logged: the robot's own stream
        watchdog, or its safety controller, must stop it then)."""
        try:
            with self._wire:
                self._estopped = True
                self._servoing = False
                if self._closed:
                    return False
                try:
                    self._transport.write(b"stopDirectServoJoints" + TERMINATOR)
                except (RigError, OSError) as err:
                    log.error("%s: e-stop could not be sent (%s)", self.name, err)
                    return False
                self._owed_acks += 1
            return True
        except Exception:  # never raise on the e-stop path
            log.exception("%s: e-stop failed", self.name)
            return False

    def wait_at_rest(self, timeout_s: float = 5.0) -> bool:
        """Whether the arm is at rest: the joints read twice, AT_REST_INTERVAL_S apart, agree
        within AT_REST_RAD, within `timeout_s`. Never raises (a dead link: False, logged)."""
        deadline = time.monotonic() + timeout_s
        try:
            previous = self.joint_positions()
            while True:
                time.sleep(AT_REST_INTERVAL_S)
                q = self.joint_positions()
                if np.max(np.abs(q - previous)) <= AT_REST_RAD:
                    return True
                if time.monotonic() > deadline:
                    log.error("%s: still moving %.3g rad after %g s", self.name,
                              float(np.max(np.abs(q - previous))), timeout_s)
                    return False
                previous = q
        except RigError as err:
            log.error("%s: rest not confirmed: %s", self.name, err)
            return False

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

