"""The KST driver against scripted byte exchanges, and the arm model stepped by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.apps.testing import ScriptedTransport
from rigctl.core.errors import DeviceError, DeviceTimeout, Disconnected, LimitError, ProtocolError
from rigctl.drivers.kuka_sunrise import KukaArm, format_joint_command, parse_joints
from rigctl.emulators.kuka.model import ArmLimits, LbrArmModel, TargetRejected
from rigctl.emulators.kuka.protocol import parse_fields

Q = np.array([0.1, -0.2, 0.3, -0.4, 0.5, -0.6, 0.7])
Q_WIRE = b"0.1_-0.2_0.3_-0.4_0.5_-0.6_0.7_"


def arm(steps, **kw):
    transport = ScriptedTransport(steps)
    return KukaArm(transport, name="arm1", **kw), transport


def test_joint_command_format_matches_kst():
    assert format_joint_command("jp", Q).encode() == b"jp_" + Q_WIRE
    assert format_joint_command("jp", np.array([-0.0] * 7)) == "jp_" + "0.0_" * 7
    # a target exactly at a joint limit goes out exactly, never rounded past it
    limit = -math.radians(170.0)
    sent = format_joint_command("jp", np.array([0, 0, 0, 0, limit, 0, 0]))
    assert float(sent.split("_")[5]) == limit


def test_parse_joints_accepts_java_double_strings():
    q = parse_joints("0.1_-1.0E-5_3.0_0.0_1.2345678901234_-2.0_1.0_\n")
    assert q[1] == pytest.approx(-1e-5) and q[4] == pytest.approx(1.2345678901234)
    with pytest.raises(ValueError):
        parse_joints("0.1_0.2_")


def test_read_joints():
    a, t = arm([(b"getJointsPositions\n", b"0.1_-0.2_0.3_-0.4_0.5_-0.6_0.7_\n")])
    assert np.allclose(a.joint_positions(), Q)
    t.assert_done()


def test_blocking_move_sends_the_kst_sequence():
    a, t = arm([
        (b"jRelVel_0.3_\n", b"done\n"),
        (b"jp_" + Q_WIRE + b"\n", b"done\n"),
        (b"doPTPinJS\n", b"done\n"),
        (None, b"done\n"),  # arrival, sent later by the robot
    ])
    a.move_to(Q, relative_velocity=0.3)
    t.assert_done()


def test_refused_move_is_a_device_error_naming_the_arm():
    a, t = arm([
        (b"jp_" + Q_WIRE + b"\n", b"done\n"),
        (b"doPTPinJS\n", b"done\n"),
        (None, b"nak\n"),
    ])
    with pytest.raises(DeviceError, match="arm1: the robot refused"):
        a.move_to(Q)
    t.assert_done()


def test_move_that_never_arrives_times_out():
    a, t = arm([
        (b"jp_" + Q_WIRE + b"\n", b"done\n"),
        (b"doPTPinJS\n", b"done\n"),
    ])
    with pytest.raises(DeviceTimeout, match="arm1: no arrival"):
        a.move_to(Q, timeout_s=0.01)
    t.assert_done()


def test_limits_checked_before_any_io():
    limits = np.array([[-1.0, 1.0]] * 7)
    a, t = arm([], joint_limits_rad=limits)
    with pytest.raises(LimitError, match="A4"):
        a.move_to(np.array([0, 0, 0, 1.5, 0, 0, 0.0]))
    with pytest.raises(LimitError):
        a.set_relative_velocity(1.5)
    t.assert_done()  # nothing was written


def test_servo_stream_checks_every_reply():
    a, t = arm([
        (b"startDirectServoJoints\n", b"done\n"),
        (b"jpJP_" + Q_WIRE + b"\n", b"0.1_-0.2_0.3_-0.4_0.5_-0.6_0.7_\n"),
        (b"jpJP_" + Q_WIRE + b"\n", b"nak\n"),
    ])
    a.start_servo()
    assert np.allclose(a.servo(Q), Q)
    with pytest.raises(DeviceError, match="no longer servoing"):
        a.servo(Q)
    assert not a.servoing
    t.assert_done()


def test_garbage_reply_is_a_protocol_error_and_next_command_resynchronises():
    a, t = arm([
        (b"getJointsPositions\n", b"hello\n"),
        (b"getJointsPositions\n", b"0.1_-0.2_0.3_-0.4_0.5_-0.6_0.7_\n"),
    ])
    with pytest.raises(ProtocolError):
        a.joint_positions()
    assert np.allclose(a.joint_positions(), Q)
    assert t.discards == 1
    t.assert_done()


def test_lost_link_is_disconnected_naming_the_arm():
    a, t = arm([(b"getJointsPositions\n", Disconnected("connection reset by tcp://x"))])
    with pytest.raises(Disconnected, match="arm1"):
        a.joint_positions()


def test_stop_servo_skips_a_late_servo_reply():
    a, t = arm([
        (b"startDirectServoJoints\n", b"done\n"),
        (b"jpJP_" + Q_WIRE + b"\n", None),  # its reply comes too late for the cycle
        (b"stopDirectServoJoints\n", b"0.1_-0.2_0.3_-0.4_0.5_-0.6_0.7_\ndone\n"),
    ])
    a.start_servo()
    with pytest.raises(DeviceTimeout):
        a.servo(Q)
    a.stop_servo()
    t.assert_done()


def test_close_stops_the_servo_and_ends_the_session():
    a, t = arm([
        (b"startDirectServoJoints\n", b"done\n"),
        (b"stopDirectServoJoints\n", b"done\n"),
        (b"end\n", None),
    ])
    a.start_servo()
    a.close()
    a.close()  # idempotent
    t.assert_done()
    assert t.closed


def test_server_field_parser():
    assert parse_fields("jRelVel_0.25_", 1).tolist() == [0.25]
    with pytest.raises(ValueError):
        parse_fields("jp_1_2_3_", 7)


# -- the model ------------------------------------------------------------------------------------


def run(model: LbrArmModel, seconds: float, dt: float = 1e-3) -> None:
    for _ in range(int(round(seconds / dt))):
        model.step(dt)


def test_ptp_duration_is_the_trapezoid_of_the_slowest_joint():
    limits = ArmLimits(np.full(7, -3.0), np.full(7, 3.0), np.full(7, 1.0), np.full(7, 2.0))
    model = LbrArmModel(limits=limits)
    model.set_relative_velocity(0.5)
    target = np.array([1.0, 0.5, 0, 0, 0, 0, 0])
    model.start_ptp(target)
    # joint 1 limits: v = 0.5 rad/s, a = 2 rad/s^2 over 1 rad: t = 1/v + v/a = 2.25 s
    run(model, 2.2)
    assert model.mode == "ptp"
    # joints move together: joint 2 is always half of joint 1
    assert model.q[1] == pytest.approx(0.5 * model.q[0])
    run(model, 0.06)
    assert model.mode == "idle" and np.allclose(model.q, target)
    assert model.collect_finished() == [True]


def test_targets_outside_limits_are_rejected():
    model = LbrArmModel()
    with pytest.raises(TargetRejected, match="A2"):
        model.start_ptp(np.array([0, math.radians(121), 0, 0, 0, 0, 0]))
    assert model.mode == "idle"


def test_servo_tracks_within_speed_limit_and_watchdog_stops_it():
    model = LbrArmModel(servo_timeout_s=0.2)
    vmax = model.limits.max_speed_rad_s[0]
    model.start_servo()
    model.servo_to(np.array([1.0, 0, 0, 0, 0, 0, 0]))
    peak = 0.0
    for _ in range(150):
        model.step(1e-3)
        peak = max(peak, abs(model.qd[0]))
    assert peak <= vmax + 1e-9
    run(model, 0.1)  # 0.25 s without a new target: the watchdog has fired
    assert model.watchdog_tripped
    run(model, 2.0)
    assert model.mode == "idle" and not np.any(model.qd)
    assert model.q[0] < 1.0  # it stopped short of the target
    with pytest.raises(TargetRejected, match="watchdog"):
        model.servo_to(np.zeros(7))


def test_stalled_joint_makes_the_ptp_fail():
    model = LbrArmModel()
    model.stall(2)
    model.start_ptp(np.array([0, 0, 0.2, 0, 0, 0, 0.0]))
    run(model, 5.0)
    assert model.collect_finished() == [False]
    assert model.q[2] == 0.0


def test_a_stopped_arm_comes_to_rest_whatever_the_steps_lengths():
    # the emulator steps its model to the backdoor's and the client's calls: steps of any length up
    # to the physics step. A stop brakes at full deceleration, v / a seconds, and is then at rest.
    rng = np.random.default_rng(3)
    model = LbrArmModel()
    model.start_servo()
    for k in range(100):  # a 50 Hz stream, 2 mrad a set point: moving at about 0.1 rad/s
        model.servo_to(np.full(7, 2e-3 * (k + 1)))
        model.step(0.02)
    speed = np.abs(model.qd).max()
    assert speed > 0.01
    model.stop()
    braking_s = speed / model.limits.max_accel_rad_s2.min()
    elapsed = 0.0
    while model.mode != "idle" and elapsed < braking_s + 1.0:
        dt = float(rng.uniform(1e-5, 4e-3))
        model.step(dt)
        elapsed += dt
    assert model.mode == "idle" and not np.any(model.qd)
    assert elapsed < braking_s + 0.1
