"""What the KST server's state getters report, computed from the emulated arm's joints.

The real server (KST 1.7, `StateVariablesOfRobot.java`) asks the Sunrise controller; the emulator
answers what it can compute honestly (docs/kuka-sunrise.md, "Every KST command"):

- the pose of the attached tool frame (`Eef_pos`): forward kinematics of the LBR iiwa 14 R820
  (`rigctl.physics.kinematics.ArmKinematics`, the arm at the origin of its own base frame, with
  the robot's own twist angles, `LBR_IIWA_14_KUKA_AXES` below) followed by the tool transform
  `TFtrans_x_y_z_a_b_c_` set, reported as KUKA does: x, y, z in mm in the robot's base frame and
  the A, B, C angles in rad, R = Rz(A) Ry(B) Rx(C);
- joint torques (`Torques_m_J`, `Torques_ext_J`) and the external force and moment at the tool
  (`Eef_force`, `Eef_moment`): the emulated arm has no dynamics and nothing touches it, so the
  external ones are exactly 0; the measured ones are those of a gravity-free arm at rest, also 0
  (a real arm measures its links' weight there: tens of N m on A2 and A4);
- the media flange (`MediaFlange`): the blue LED and the four outputs as state the backdoor reads,
  and the five inputs, which the backdoor sets (the real noFlange server answers 1 for every input).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from rigctl.physics.kinematics import LBR_IIWA_14_R820, ArmKinematics

LBR_IIWA_14_KUKA_AXES = dataclasses.replace(
    LBR_IIWA_14_R820, alpha_rad=(-np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, np.pi / 2, 0.0))
"""The LBR iiwa 14 R820 with the twist angles of KUKA's own axes: standard DH
alpha = (-90, 90, 90, -90, -90, 90, 0) deg, the same chain as the KST client's modified-DH
`constDhDataOf14R820.m` (alfa = 0, -90, 90, 90, -90, -90, 90) and the iiwa_stack URDF: at the
zero pose A2 turns about +y and A4 about -y. `rigctl.physics.kinematics.LBR_IIWA_14_R820`
alternates the twists (-90, 90, -90, 90, ...), which turns A4 about +y: the same positions for
A4 = 0, the mirror image of the forearm's bend otherwise. The emulator answers `Eef_pos` as the
robot would."""

FLANGE_OUTPUT_PINS = (1, 2, 11, 12)
"""X3 outputs the server switches (`pin1on` ... `pin12off`, `MediaFlangeFunctions.java`)."""
FLANGE_INPUT_PINS = (3, 4, 10, 13, 16)
"""X3 inputs the server reads (`getPin3` ... `getPin16`)."""


@dataclass
class MediaFlange:
    """The media flange's LED and X3 pins. Outputs start off; inputs read 1 (as the real
    noFlange server answers) until the backdoor sets them."""

    blue_led: bool = False
    outputs: dict[int, bool] = field(default_factory=lambda: dict.fromkeys(FLANGE_OUTPUT_PINS, False))
    inputs: dict[int, bool] = field(default_factory=lambda: dict.fromkeys(FLANGE_INPUT_PINS, True))

    def truth(self) -> dict:
        return {"blue_led": self.blue_led, "outputs": dict(self.outputs), "inputs": dict(self.inputs)}


def abc_transform(xyz_mm: np.ndarray, abc_rad: np.ndarray) -> np.ndarray:
    """4x4 transform of a KUKA frame (x, y, z in mm, A, B, C in rad), translation in m."""
    a, b, c = (float(v) for v in abc_rad)
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), math.sin(c)
    rz = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cc, -sc], [0.0, sc, cc]])
    pose = np.eye(4)
    pose[:3, :3] = rz @ ry @ rx
    pose[:3, 3] = np.asarray(xyz_mm, dtype=float) / 1000.0
    return pose


def kuka_abc(rotation: np.ndarray) -> tuple[float, float, float]:
    """A, B, C (rad) of a rotation matrix, R = Rz(A) Ry(B) Rx(C), B in [-pi/2, pi/2]. At B = +-pi/2
    only A - C (or A + C) is defined: C is then reported 0."""
    r = rotation
    b = math.atan2(-r[2, 0], math.hypot(r[0, 0], r[1, 0]))
    if math.hypot(r[0, 0], r[1, 0]) < 1e-12:
        a, c = math.atan2(-r[0, 1], r[1, 1]), 0.0
    else:
        a, c = math.atan2(r[1, 0], r[0, 0]), math.atan2(r[2, 1], r[2, 2])
    return a + 0.0, b + 0.0, c + 0.0  # + 0.0: an angle of -0.0 is reported as 0.0


def robot_kinematics() -> ArmKinematics:
    """The arm at the origin of its own base frame, with KUKA's axes (`LBR_IIWA_14_KUKA_AXES`)."""
    return ArmKinematics(model=LBR_IIWA_14_KUKA_AXES)


def tool_pose_mm_rad(kinematics: ArmKinematics, q: np.ndarray, tool_mm_rad: np.ndarray) -> np.ndarray:
    """The tool frame's pose in the robot's base frame as `Eef_pos` reports it:
    (x, y, z in mm, A, B, C in rad), shape (6,). `tool_mm_rad` is the flange->tool frame (6,)."""
    pose = kinematics.flange(q) @ abc_transform(tool_mm_rad[:3], tool_mm_rad[3:])
    return np.array([*(pose[:3, 3] * 1000.0), *kuka_abc(pose[:3, :3])])
