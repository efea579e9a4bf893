"""The robot side of the KUKA Sunrise Toolbox (KST) protocol: ASCII lines, `_`-separated fields.

Source: the KST 1.7 server application that runs on the Sunrise cabinet (Safeea & Neto, "KUKA
Sunrise Toolbox: Interfacing Collaborative Robots with MATLAB", IEEE RAM 2019; the public
`KST-Kuka-Sunrise-Toolbox` repository, `MatlabToolboxServer.java`, `BackgroundTask.java`,
`PTPmotionClass.java`, `StateVariablesOfRobot.java`, and the MATLAB client functions). The
command table with each command's source is in docs/kuka-sunrise.md; in short:

    jRelVel_<v>_              -> done         relative joint velocity for PTP moves
    TFtrans_x_y_z_a_b_c_      -> done | nak   tool frame on the flange (mm, rad)
    jp_<q1>_..._<q7>_         -> done         joint target: PTP destination, or servo target
    doPTPinJS                 -> done, then done (motion finished) | nak (refused / failed)
    getJointsPositions        -> <q1>_..._<q7>_
    startDirectServoJoints    -> done
    jf_<q1>_..._<q7>_         -> (nothing)    servo target, fast mode
    jpJP_<q1>_..._<q7>_       -> <q1>_..._<q7>_  servo target, answered with the measured joints
    stopDirectServoJoints     -> done
    end                       -> (the server closes the connection)

Where this emulator differs from the real server (the guesses, also in the docs): an unknown or
malformed command is answered `nak` (the real server ignores it and the client hangs, or its
parser thread dies); `jpJP_` while servoing is off is answered `nak` instead of joint positions, so
a client sees at once that the stream watchdog has stopped the arm.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from rigctl.emulators.kuka.model import N_JOINTS, LbrArmModel, TargetRejected
from rigctl.emulators.server import Session

log = logging.getLogger(__name__)

ACK = "done"
NAK = "nak"


def format_joints(q: np.ndarray) -> str:
    """Joint angles the way the server writes them: each value followed by `_`."""
    return "".join(f"{float(v)!r}_" for v in q)


def parse_fields(line: str, count: int) -> np.ndarray:
    """The numbers after the command word of `cmd_v1_v2_..._`; ValueError unless exactly `count`."""
    fields = [f for f in line.split("_")[1:] if f != ""]
    if len(fields) != count:
        raise ValueError(f"expected {count} numbers, got {len(fields)}")
    return np.array([float(f) for f in fields])


class KstServer:
    """One arm's Sunrise application: commands from one client, replies through its `Session`."""

    def __init__(self, model: LbrArmModel, *, name: str = "arm",
                 before_command: Callable[[], None] | None = None) -> None:
        self.model = model
        self.name = name
        self.before_command = before_command or (lambda: None)
        self.tool_mm_rad = np.zeros(6)
        self._pending_target: np.ndarray | None = None
        self._session: Session | None = None
        self._ptp_waiting = 0  # PTP moves whose completion line is still owed to the client

    # -- SessionHandler -------------------------------------------------------------------------
    def connected(self, session: Session) -> None:
        self._session = session
        log.info("%s: client connected", self.name)

    def disconnected(self, session: Session) -> None:
        if session is self._session:
            self._session = None
            self.before_command()
            if self.model.mode in ("servo", "ptp"):
                log.warning("%s: client gone while moving; stopping the arm", self.name)
                self.model.stop()
            self._ptp_waiting = 0

    def received(self, session: Session, line: str) -> None:
        self.before_command()
        for reply in self._handle(session, line.strip()):
            session.send(reply)

    # -- completion of PTP moves (called after each simulation step) ----------------------------
    def deliver_completions(self) -> None:
        replies: list[str] = []
        self.deliver_completions_into(replies)
        if self._session is not None:
            for reply in replies:
                self._session.send(reply)

    # -- commands -------------------------------------------------------------------------------
    def _handle(self, session: Session, line: str) -> list[str]:
        """One command line -> the lines sent back: the first entry of `COMMANDS` whose word
        starts the line handles it; a malformed or refused one is answered `nak`."""
        for word, command in self.COMMANDS:
            if line.startswith(word):
                try:
                    return command(self, session, line)
                except (TargetRejected, ValueError) as err:
                    log.warning("%s: refused %r: %s", self.name, line[:80], err)
                    return [NAK]
        log.warning("%s: unknown command %r", self.name, line[:80])
        return [NAK]

    def _relative_velocity(self, session: Session, line: str) -> list[str]:
        self.model.set_relative_velocity(float(parse_fields(line, 1)[0]))
        return [ACK]

    def _tool_frame(self, session: Session, line: str) -> list[str]:
        self.tool_mm_rad = parse_fields(line, 6)
        return [ACK]

    def _servo_and_read(self, session: Session, line: str) -> list[str]:
        self.model.servo_to(parse_fields(line, N_JOINTS))
        return [format_joints(self.model.q)]

    def _servo_fast(self, session: Session, line: str) -> list[str]:
        model = self.model
        try:
            model.servo_to(parse_fields(line, N_JOINTS))
        except (TargetRejected, ValueError) as err:
            # KST: a bad fast-mode target ends the servo motion; nothing is sent back
            log.warning("%s: %s; direct servo stopped", self.name, err)
            if model.mode == "servo":
                model.stop()
        return []

    def _joint_target(self, session: Session, line: str) -> list[str]:
        target = parse_fields(line, N_JOINTS)
        if self.model.mode == "servo":
            self.model.servo_to(target)
        else:
            self._pending_target = target
        return [ACK]

    def _ptp(self, session: Session, line: str) -> list[str]:
        # the server acknowledges first, then moves; a refused move is its exception path
        if self._pending_target is None:
            return [ACK, NAK]
        try:
            self.model.start_ptp(self._pending_target)
        except TargetRejected as err:
            log.warning("%s: PTP refused: %s", self.name, err)
            return [ACK, NAK]
        self._ptp_waiting += 1
        replies = [ACK]
        if self.model.mode == "idle":  # zero-length move: finished already
            self.deliver_completions_into(replies)
        return replies

    def _read_joints(self, session: Session, line: str) -> list[str]:
        return [format_joints(self.model.q)]

    def _start_servo(self, session: Session, line: str) -> list[str]:
        self.model.start_servo()
        return [ACK]

    def _stop_servo(self, session: Session, line: str) -> list[str]:
        if self.model.mode == "servo":
            self.model.stop()
        return [ACK]

    def _end(self, session: Session, line: str) -> list[str]:
        if self.model.mode in ("servo", "ptp"):
            self.model.stop()
        session.close()
        return []

    COMMANDS: tuple[tuple[str, Callable[..., list[str]]], ...] = (
        ("jRelVel", _relative_velocity), ("TFtrans", _tool_frame), ("jpJP_", _servo_and_read),
        ("jf_", _servo_fast), ("jp_", _joint_target), ("doPTPinJS", _ptp),
        ("getJointsPositions", _read_joints), ("startDirectServoJoints", _start_servo),
        ("stopDirectServoJoints", _stop_servo), ("end", _end))
    """The command words of the module docstring's table, in the order they are tried."""

    def deliver_completions_into(self, replies: list[str]) -> None:
        for reached in self.model.collect_finished():
            if self._ptp_waiting > 0:
                self._ptp_waiting -= 1
                replies.append(ACK if reached else NAK)
