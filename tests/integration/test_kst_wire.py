"""The emulated KST server against a client that speaks the real wire format, written here the way
the KST MATLAB functions send it (`fprintf(t, theCommand)`: the line and LF) and read it (`fgets`,
numbers split at `_`), independently of rigctl's driver: every command the emulator answers beyond
the ones rigctl uses (docs/kuka-sunrise.md, "Every KST command").

Tool poses are checked against hand-worked poses and against the KST client's own forward
kinematics (`directKinematics.m`: modified DH with `constDhDataOf14R820.m`'s parameters), written
out in this file.
"""

from __future__ import annotations

import math
import socket

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.emulators.kuka.arm import EmulatedArm, SimClock
from rigctl.emulators.kuka.protocol import java_double
from rigctl.emulators.server import EmulatorServer

# no process started (the emulator serves a real socket from this process): the quick tier
pytestmark = pytest.mark.quick

# constDhDataOf14R820.m (KST client): modified DH, alfa(i) is the twist before joint i
KST_ALFA = (0.0, -math.pi / 2, math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, math.pi / 2)
KST_D_M = (0.36, 0.0, 0.42, 0.0, 0.4, 0.0, 0.126)


def kst_direct_kinematics(q):
    """directKinematics.m without a tool: T = prod RotX(alfa) RotZ(q) TransZ(d) (a = 0)."""
    pose = np.eye(4)
    for alfa, theta, d in zip(KST_ALFA, q, KST_D_M):
        ca, sa, ct, st = math.cos(alfa), math.sin(alfa), math.cos(theta), math.sin(theta)
        pose = pose @ np.array([[ct, -st, 0.0, 0.0],
                                [st * ca, ct * ca, -sa, -sa * d],
                                [st * sa, ct * sa, ca, ca * d],
                                [0.0, 0.0, 0.0, 1.0]])
    return pose


class MatlabLikeClient:
    """What the KST MATLAB functions do on their tcpip object: write a line, read lines."""

    def __init__(self, url: str) -> None:
        host, port = url.removeprefix("tcp://").rsplit(":", 1)
        self.sock = socket.create_connection((host, int(port)), timeout=5.0)
        self.reader = self.sock.makefile("rb")

    def ask(self, command: str) -> str:
        self.sock.sendall(command.encode("ascii") + b"\n")
        return self.fgets()

    def fgets(self) -> str:
        return self.reader.readline().decode("ascii").rstrip("\n")

    def numbers(self, command: str) -> list[float]:
        """getDoubleFromString.m: the numbers before each `_`."""
        reply = self.ask(command)
        assert reply.endswith("_"), reply
        return [float(field) for field in reply.split("_")[:-1]]

    def close(self) -> None:
        self.sock.sendall(b"end\n")
        self.reader.close()
        self.sock.close()


@pytest.fixture(scope="module")
def served():
    server = EmulatorServer()
    server.start()
    # a long stream watchdog: these tests pause between servo lines on a loaded computer
    emulated = EmulatedArm(server, name="arm1", clock=SimClock(1.0), servo_timeout_s=30.0)
    server.every(0.005, emulated.advance)
    try:
        yield server, emulated
    finally:
        server.stop()


@pytest.fixture
def client(served):
    server, emulated = served
    kst = MatlabLikeClient(emulated.url)
    try:
        yield kst
    finally:
        kst.close()
        # the next test's client waits for this one to be gone (one client at a time)
        wait_for(lambda: emulated.endpoint.connection_count == 0, timeout_s=5.0,
                 what="the client gone")


def place(served, q):
    """Put the joints at `q` (rad) by the backdoor, once a stopped servo has come to rest."""
    server, emulated = served
    wait_for(lambda: server.call(emulated.truth)["mode"] == "idle", timeout_s=5.0,
             what="the arm at rest")
    server.call(emulated.place, np.asarray(q, dtype=float))


def pose_mm_rad(pose):
    """x, y, z (mm) and KUKA's A, B, C (rad) of a 4x4 pose, for poses away from B = +-90 deg."""
    r = pose[:3, :3]
    return np.array([*(pose[:3, 3] * 1000.0), math.atan2(r[1, 0], r[0, 0]),
                     math.asin(-r[2, 0]), math.atan2(r[2, 1], r[2, 2])])


def test_java_double_strings():
    # outputs of Java's Double.toString for the same doubles
    assert [java_double(v) for v in (0.0, -0.0, 1.0, 100.0, 0.001, -0.00012, 1e-5, 1e7,
                                     12345678.9, 1306.0, 0.1 + 0.2)] == [
        "0.0", "-0.0", "1.0", "100.0", "0.001", "-1.2E-4", "1.0E-5", "1.0E7",
        "1.23456789E7", "1306.0", "0.30000000000000004"]


def test_torques_force_and_moment_of_a_contact_free_arm(served, client):
    place(served, np.radians([10, 20, -30, -60, 15, 45, 5]))
    assert client.ask("Torques_m_J") == "0.0_" * 7
    assert client.ask("Torques_ext_J") == "0.0_" * 7
    assert client.ask("Eef_force") == "0.0_0.0_0.0_"
    assert client.ask("Eef_moment") == "0.0_0.0_0.0_"


def test_eef_pos_at_hand_worked_poses(served, client):
    assert client.ask("TFtrans_0_0_0_0_0_0_") == "done"
    place(served, np.zeros(7))
    # candle: the flange 360 + 420 + 400 + 126 mm above the base, axes as the base's
    assert client.ask("Eef_pos") == "0.0_0.0_1306.0_0.0_0.0_0.0_"
    # A2 at +45 deg tilts everything above the shoulder (946 mm) towards +x about +y
    place(served, np.radians([0, 45, 0, 0, 0, 0, 0]))
    s = math.sqrt(0.5)
    assert np.allclose(client.numbers("Eef_pos"), [946 * s, 0, 360 + 946 * s, 0, math.pi / 4, 0],
                       atol=1e-9)
    # A4 at +60 deg turns the forearm (526 mm from the elbow at 780 mm) about -y: towards -x
    place(served, np.radians([0, 0, 0, 60, 0, 0, 0]))
    assert np.allclose(client.numbers("Eef_pos"),
                       [-526 * math.sin(math.pi / 3), 0, 780 + 526 * 0.5, 0, -math.pi / 3, 0],
                       atol=1e-9)


def test_eef_pos_matches_the_kst_clients_forward_kinematics(served, client):
    tool_mm_rad = (12.5, -30.0, 85.0, 0.3, -0.2, 0.1)
    assert client.ask("TFtrans_" + "".join(f"{v}_" for v in tool_mm_rad)) == "done"
    # the tool frame as attachToolToFlange.m documents it: x, y, z mm then A, B, C rad
    x, y, z, a, b, c = tool_mm_rad
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rx = np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])
    tool = np.eye(4)
    tool[:3, :3], tool[:3, 3] = rz @ ry @ rx, np.array([x, y, z]) / 1000.0
    rng = np.random.default_rng(38)
    for _ in range(5):
        q = rng.uniform(-1.0, 1.0, 7) * np.radians([160, 110, 160, 110, 160, 110, 170])
        place(served, q)
        expected = pose_mm_rad(kst_direct_kinematics(q) @ tool)
        assert np.allclose(client.numbers("Eef_pos"), expected, atol=1e-9)
        assert np.allclose(client.numbers("getJointsPositions"), q, atol=0)


def test_servo_targets_are_answered_by_the_getter_their_word_names(served, client):
    q = np.radians([5, 10, 15, -20, 25, 30, -35])
    place(served, q)
    wire = "".join(f"{float(v)!r}_" for v in q)
    assert client.ask("startDirectServoJoints") == "done"
    assert client.ask("jpMT_" + wire) == "0.0_" * 7
    assert client.ask("jpExT_" + wire) == "0.0_" * 7
    assert client.ask("jpEEfFrelEEF_" + wire) == "0.0_0.0_0.0_"
    eef = client.numbers("jpEEfP_" + wire)
    assert np.allclose(eef, pose_mm_rad(kst_direct_kinematics(q)), atol=1e-6)
    assert np.allclose(client.numbers("jpJP_" + wire), q, atol=1e-9)
    assert client.ask("stopDirectServoJoints") == "done"
    # servoing over, a servo target is refused rather than answered with a stale state
    assert client.ask("jpMT_" + wire) == "nak"


def test_media_flange_outputs_are_state_and_inputs_are_read(served, client):
    server, emulated = served
    assert client.ask("blueOn") == "done"
    for command in ("pin1on", "pin11on", "pin12on"):
        assert client.ask(command) == "done"
    flange = server.call(emulated.truth)["media_flange"]
    assert flange["blue_led"] is True
    assert flange["outputs"] == {1: True, 2: False, 11: True, 12: True}
    assert client.ask("blueOff") == "done"
    assert client.ask("pin11off") == "done"
    flange = server.call(emulated.truth)["media_flange"]
    assert flange["blue_led"] is False and flange["outputs"][11] is False
    assert flange["outputs"][1] is True  # pin11off leaves pin 1 alone
    # getPinN: the state, then the empty line of the server's "\n\n" terminator
    assert client.ask("getPin10") == "1"
    assert client.fgets() == ""
    server.call(emulated.set_flange_input, 10, False)
    assert client.ask("getPin10") == "0"
    assert client.fgets() == ""
    assert client.ask("getPin16") == "1"
    assert client.fgets() == ""
    with pytest.raises(ValueError, match="no input pin 7"):
        server.call(emulated.set_flange_input, 7, True)
    server.call(emulated.set_flange_input, 10, True)


def test_hand_guiding_is_acknowledged_as_the_lts_server_does(served, client):
    assert client.ask("handGuiding") == "done"
    assert client.ask("preciseHandGuiding_1.0_0_0_0.1_") == "done"


@pytest.mark.parametrize("command", [
    "doPTPinCS", "doPTPinCSRelEEF", "doPTPinCSRelBase", "doPTPinCSCircle1_",
    "doPTP!inJS_4_-10_10_", "doPTP!inCS_4_-10_10_", "doPTP!CSCircle1_4_-10_10_",
    "stDcEEf_", "stVelDcJoint_", "startSmartImpedneceJoints_0.5_0_0_0.1_1000_100_0.5_",
    "velJDC_0_0_0_0_0_0_0_", "DcSeCar_400_0_600_0_0_0_", "cArtixanPosition_400_0_600_0_0_0_",
    "Eef_pos_", "getPin7", "pin5on"])
def test_motion_and_unknown_commands_not_emulated_are_refused(served, client, command):
    q = np.radians([0, 30, 0, -60, 0, 90, 0])
    place(served, q)
    assert client.ask(command) == "nak"
    server, emulated = served
    truth = server.call(emulated.truth)
    assert truth["mode"] == "idle" and np.allclose(truth["q"], q, atol=0)
    assert client.ask("getJointsPositions").count("_") == 7  # the link still in step
