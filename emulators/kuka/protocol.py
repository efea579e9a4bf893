"""The robot side of the KUKA Sunrise Toolbox (KST) protocol: ASCII lines, `_`-separated fields.

Source: the KST 1.7 server application that runs on the Sunrise cabinet (Safeea & Neto, "KUKA
Sunrise Toolbox: Interfacing Collaborative Robots with MATLAB", IEEE RAM 2019; the public
`KST-Kuka-Sunrise-Toolbox` repository, `MatlabToolboxServer.java`, `BackgroundTask.java`,
`PTPmotionClass.java`, `StateVariablesOfRobot.java`, `MediaFlangeFunctions.java`, and the MATLAB
client functions). Every command word the server parses, with its source line and whether it is
emulated, is in docs/kuka-sunrise.md ("Every KST command"); in short:

    jRelVel_<v>_              -> done         relative joint velocity for PTP moves
    TFtrans_x_y_z_a_b_c_      -> done | nak   tool frame on the flange (mm, rad)
    jp_<q1>_..._<q7>_         -> done         joint target: PTP destination, or servo target
    doPTPinJS                 -> done, then done (motion finished) | nak (refused / failed)
    getJointsPositions        -> <q1>_..._<q7>_
    Eef_pos                   -> x_y_z_a_b_c_ tool frame in the base frame (mm, rad)
    Eef_force / Eef_moment    -> fx_fy_fz_ / mx_my_mz_  external, at the tool: 0 (no contact)
    Torques_m_J / Torques_ext_J -> <t1>_..._<t7>_  measured / external joint torques: 0
    blueOn, blueOff, pin{1,2,11,12}{on,off} -> done   media flange outputs (state.MediaFlange)
    getPin{3,4,10,13,16}      -> 1 | 0, then an empty line (the server's "\n\n")
    handGuiding, preciseHandGuiding -> done   (the LTS server's bodies are commented out: no-ops)
    startDirectServoJoints    -> done
    jf_<q1>_..._<q7>_         -> (nothing)    servo target, fast mode
    jpJP_ / jpMT_ / jpExT_ / jpEEfP_ / jpEEfFrelEEF_ <q1>_..._<q7>_
                              -> servo target, answered with joints / measured torques /
                                 external torques / tool pose / tool force
    stopDirectServoJoints     -> done
    end                       -> (the server closes the connection)

Refused with `nak` (`REFUSED`): the Cartesian and conditional PTP moves, the Cartesian, velocity
and impedance servo modes and their stream commands; they need inverse kinematics on tool frames,
torque conditions or dynamics this emulator does not model, and a client is told at once rather
than left waiting for a motion that never comes.

Where this emulator differs from the real server (the guesses, also in the docs): an unknown or
malformed command is answered `nak` (the real server ignores it and the client hangs, or its
parser thread dies); `jpJP_` while servoing is off is answered `nak` instead of joint positions, so
a client sees at once that the stream watchdog has stopped the arm.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from decimal import Decimal

import numpy as np

from rigctl.emulators.kuka.model import N_JOINTS, LbrArmModel, TargetRejected
from rigctl.emulators.kuka.state import MediaFlange, robot_kinematics, tool_pose_mm_rad
from rigctl.emulators.server import Session

log = logging.getLogger(__name__)

ACK = "done"
NAK = "nak"


def java_double(value: float) -> str:
    """`value` as Java's `Double.toString` writes it (the server's number format): the shortest
    digits that read back to the same double, plain from 1e-3 up to 1e7 (`0.001`, `126.0`), else
    `d.dddE<n>` (`1.0E-5`, `1.2345E7`)."""
    x = float(value)
    if math.isnan(x):
        return "NaN"
    if math.isinf(x):
        return "Infinity" if x > 0 else "-Infinity"
    if x == 0.0:
        return "-0.0" if math.copysign(1.0, x) < 0 else "0.0"
    if 1e-3 <= abs(x) < 1e7:
        return repr(x)  # Python's repr is plain and shortest in this range, like Java's
    sign, digits, exponent = Decimal(repr(x)).as_tuple()
    text = "".join(map(str, digits)).rstrip("0") or "0"
    assert isinstance(exponent, int)
    power = exponent + len(digits) - 1
    return f"{'-' if sign else ''}{text[0]}.{text[1:] or '0'}E{power}"


def format_values(values: np.ndarray) -> str:
    """Numbers the way the server writes them (`StateVariablesOfRobot.java`): each followed by `_`."""
    return "".join(f"{java_double(v)}_" for v in values)


format_joints = format_values
"""Joint angles the way the server writes them."""


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
        self.kinematics = robot_kinematics()  # Eef_pos is in the robot's own base frame
        self.media_flange = MediaFlange()
        self._pending_target: np.ndarray | None = None
        self._session: Session | None = None
        self._ptp_waiting = 0  # PTP moves whose completion line is still owed to the client

    # -- SessionHandler -------------------------------------------------------------------------
    def connected(self, session: Session) -> None:
        self._session = session
        # each session is a new run of the server application, which starts with the default
        # tool, the flange itself (MatlabToolboxServer.run: "defaultToolEqualFlange")
        self.tool_mm_rad = np.zeros(6)
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
        """`jpJP_`, `jpMT_`, `jpExT_`, `jpEEfP_`, `jpEEfFrelEEF_`: a servo target, answered with
        the getter its suffix names (`BackgroundTask.updateJointsPositionArray`)."""
        self.model.servo_to(parse_fields(line, N_JOINTS))
        word = line.split("_", 1)[0]
        return self._state_reply(self.SERVO_REPLIES[word])

    SERVO_REPLIES = {"jpJP": "getJointsPositions", "jpMT": "Torques_m_J", "jpExT": "Torques_ext_J",
                     "jpEEfP": "Eef_pos", "jpEEfFrelEEF": "Eef_force"}
    """Servo-target words -> the getter whose reply answers them."""

    def _state_reply(self, getter: str) -> list[str]:
        """The reply line of a state getter (`StateVariablesOfRobot.java`)."""
        if getter == "getJointsPositions":
            return [format_values(self.model.q)]
        if getter in ("Torques_m_J", "Torques_ext_J"):
            # no dynamics and no contact: see emulators/kuka/state.py
            return [format_values(np.zeros(N_JOINTS))]
        if getter in ("Eef_force", "Eef_moment"):
            return [format_values(np.zeros(3))]  # nothing touches the emulated arm
        assert getter == "Eef_pos", getter
        return [format_values(tool_pose_mm_rad(self.kinematics, self.model.q, self.tool_mm_rad))]

    def _getter(self, session: Session, line: str) -> list[str]:
        for getter in ("Torques_m_J", "Torques_ext_J"):  # startsWith() in the server
            if line.startswith(getter):
                return self._state_reply(getter)
        if line in ("Eef_pos", "Eef_force", "Eef_moment"):  # equals() in the server
            return self._state_reply(line)
        raise ValueError("unknown state request")

    def _flange_output(self, session: Session, line: str) -> list[str]:
        flange = self.media_flange
        if line.startswith("blue"):
            flange.blue_led = line.startswith("blueOn")
            return [ACK]
        for pin in flange.outputs:  # "pin1on" is no prefix of "pin11on": any order will do
            for state, on in (("on", True), ("off", False)):
                if line.startswith(f"pin{pin}{state}"):
                    flange.outputs[pin] = on
                    return [ACK]
        raise ValueError("no such media flange output")

    def _flange_input(self, session: Session, line: str) -> list[str]:
        for pin in self.media_flange.inputs:
            if line.startswith(f"getPin{pin}"):
                # MediaFlangeFunctions' stopCharacter is "\n" + (char)10: an empty line follows
                return ["1" if self.media_flange.inputs[pin] else "0", ""]
        raise ValueError("no such media flange input")

    def _acknowledged_no_op(self, session: Session, line: str) -> list[str]:
        # handGuiding / preciseHandGuiding: the LTS server's bodies are commented out; it only acks
        return [ACK]

    def _refused(self, session: Session, line: str) -> list[str]:
        raise ValueError("not emulated: docs/kuka-sunrise.md, Every KST command")

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
        return self._state_reply("getJointsPositions")

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

    REFUSED = ("doPTPinCS", "doPTP!", "stDcEEf_", "stVelDcJoint_", "startSmartImpedneceJoints",
               "velJDC", "DcSe", "cArtixanPosition")
    """Command words the real server takes and this emulator answers `nak` (see the docstring)."""

    COMMANDS: tuple[tuple[str, Callable[..., list[str]]], ...] = (
        ("jRelVel", _relative_velocity), ("TFtrans", _tool_frame),
        ("jpJP_", _servo_and_read), ("jpMT_", _servo_and_read), ("jpExT_", _servo_and_read),
        ("jpEEfP_", _servo_and_read), ("jpEEfFrelEEF_", _servo_and_read),
        ("jf_", _servo_fast), ("jp_", _joint_target), ("doPTPinJS", _ptp),
        ("getJointsPositions", _read_joints), ("Eef", _getter), ("Torques_m_J", _getter),
        ("Torques_ext_J", _getter), ("blueOn", _flange_output), ("blueOff", _flange_output),
        ("pin", _flange_output), ("getPin", _flange_input),
        ("handGuiding", _acknowledged_no_op), ("preciseHandGuiding", _acknowledged_no_op),
        ("startDirectServoJoints", _start_servo), ("stopDirectServoJoints", _stop_servo),
        ("end", _end)) + tuple(zip(REFUSED, [_refused] * len(REFUSED)))
    """The command words of the module docstring's table, in the order they are tried."""

    def deliver_completions_into(self, replies: list[str]) -> None:
        for reached in self.model.collect_finished():
            if self._ptp_waiting > 0:
                self._ptp_waiting -= 1
                replies.append(ACK if reached else NAK)
