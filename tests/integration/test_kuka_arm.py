"""The KST driver against the emulated arm on a real TCP socket, and the two arms as the run
engine's actuator group (`ArmPair`) against the emulated dEPM bench."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.errors import DeviceError, Disconnected
from rigctl.drivers.kuka_sunrise import KukaArm
from rigctl.emulators.depm import DepmBench
from rigctl.emulators.kuka.arm import EmulatedArm, SimClock
from rigctl.emulators.server import EmulatorServer
from rigctl.physics.kinematics import LBR_IIWA_14_R820
from rigctl.rigs.depm.actuators import ArmPair

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

SPEED = 4.0  # simulated seconds per real second: moves finish quickly, nothing else changes


@pytest.fixture
def bench():
    server = EmulatorServer()
    server.start()
    clock = SimClock(SPEED)
    emulated = EmulatedArm(server, name="arm1", clock=clock, servo_timeout_s=0.2)
    server.every(0.005, emulated.advance)
    try:
        yield server, emulated
    finally:
        server.stop()


def truth(server, emulated):
    return server.call(emulated.truth)


def connect(emulated, timeout_s=2.0):
    return KukaArm.open(emulated.url, name="arm1", timeout_s=timeout_s)


def test_ptp_move_arrives_where_asked(bench):
    server, emulated = bench
    arm = connect(emulated)
    target = np.radians([10, -5, 0, 20, 0, -10, 5])
    arm.move_to(target, relative_velocity=1.0, timeout_s=10)
    assert np.allclose(arm.joint_positions(), target, atol=1e-6)
    assert np.allclose(truth(server, emulated)["q"], target, atol=1e-9)
    arm.close()


def test_target_outside_limits_is_refused_by_the_robot(bench):
    server, emulated = bench
    arm = connect(emulated)  # no client-side limits: the robot's own check answers
    with pytest.raises(DeviceError, match="arm1: the robot refused"):
        arm.move_to(np.radians([0, 130, 0, 0, 0, 0, 0]), timeout_s=5)
    assert np.allclose(truth(server, emulated)["q"], 0.0)  # nothing moved
    arm.move_to(np.radians([1, 0, 0, 0, 0, 0, 0]), timeout_s=5)  # the session is still usable
    arm.close()


def test_silent_servo_stream_stops_the_arm(bench):
    server, emulated = bench
    arm = connect(emulated)
    arm.start_servo()
    target = np.zeros(7)
    for k in range(20):
        target[0] = math.radians(0.5 * k)
        measured = arm.servo(target)
    assert measured[0] > 0.0
    # go silent: the robot's watchdog (0.2 s simulated) stops the arm by itself
    wait_for(lambda: truth(server, emulated)["watchdog_tripped"], 5.0, "the servo watchdog")
    wait_for(lambda: truth(server, emulated)["mode"] == "idle", 5.0, "the arm at rest")
    state = truth(server, emulated)
    assert not any(state["qd"])
    with pytest.raises(DeviceError, match="no longer servoing"):
        arm.servo(target)
    arm.close()


def test_connection_loss_is_a_clear_fault_and_the_arm_stops(bench):
    server, emulated = bench
    arm = connect(emulated)
    arm.start_servo()
    arm.servo(np.radians([5, 0, 0, 0, 0, 0, 0]))
    emulated.endpoint.drop_link()
    with pytest.raises(Disconnected, match="arm1: link to the KST server lost"):
        arm.servo(np.radians([5, 0, 0, 0, 0, 0, 0]))
    wait_for(lambda: truth(server, emulated)["mode"] == "idle", 5.0, "the arm at rest")
    arm.close()  # never raises, even on a dead link
    emulated.endpoint.restore()
    again = connect(emulated)
    assert again.joint_positions().shape == (7,)
    again.close()


def test_stalled_joint_fails_the_move(bench):
    server, emulated = bench
    arm = connect(emulated)
    server.call(emulated.stall, 3)
    with pytest.raises(DeviceError, match="did not follow"):
        arm.move_to(np.radians([0, 0, 0, 10, 0, 0, 0]), timeout_s=10)
    arm.close()


def test_second_client_is_refused_while_one_is_connected(bench):
    server, emulated = bench
    arm = connect(emulated)
    with pytest.raises(Disconnected):
        connect(emulated, timeout_s=0.5)
    arm.close()


class ManualClock:
    """Simulated time that moves only when the test says so."""

    speed = 1.0

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t


def test_silence_while_the_emulator_itself_was_starved_is_not_the_clients():
    """The watchdog (0.2 s) counts stream silence only while the emulator's loop runs: a loop that
    could not run for 1 s (a loaded computer; the targets may wait unread in the socket) does not
    stop the arm, a client that sends nothing for 0.2 s while the loop ticks every 5 ms does."""
    with EmulatorServer() as server:
        clock = ManualClock()
        emulated = EmulatedArm(server, name="arm1", clock=clock, servo_timeout_s=0.2, tick_s=0.005)
        server.call(emulated.model.start_servo)

        def starved_for_one_second():
            emulated._advanced_real -= 1.0  # the last advance was 1 s ago (real time) ...
            clock.t += 1.0  # ... and 1 s of simulated time has passed since
            emulated.advance()
            return emulated.model.mode

        assert server.call(starved_for_one_second) == "servo"

        def ticks(n):
            for _ in range(n):  # the loop runs: one tick every 5 ms, no target comes
                clock.t += 0.005
                emulated.advance()
            return emulated.model.mode, emulated.model.watchdog_tripped

        assert server.call(ticks, 30) == ("servo", False)  # 0.15 s of silence
        mode, tripped = server.call(ticks, 12)  # 0.21 s
        assert tripped and mode in ("stopping", "idle")


def test_emergency_stop_from_another_thread_stops_the_servo_and_latches(bench):
    """The e-stop line goes out while a servo reply is still on its way; the reply is read as
    usual, the e-stop's own `done` is skipped, and nothing that moves the arm leaves again."""
    server, emulated = bench
    arm = connect(emulated)
    arm.start_servo()
    target = np.zeros(7)
    for k in range(30):
        target[1] = math.radians(0.5 * k)
        arm.servo(target)
    arm.send_servo(target)  # its reply is pending when the e-stop is written
    sender = threading.Thread(target=lambda: sent.append(arm.emergency_stop()))
    sent: list[bool] = []
    sender.start()
    sender.join()
    assert sent == [True]
    assert arm.read_servo().shape == (7,)
    wait_for(lambda: truth(server, emulated)["mode"] == "idle", 5.0, "the arm at rest")
    with pytest.raises(DeviceError, match="e-stop latched"):
        arm.start_servo()
    with pytest.raises(DeviceError, match="servo stream not started"):
        arm.send_servo(target)
    assert arm.wait_at_rest(2.0)
    np.testing.assert_allclose(arm.joint_positions(), truth(server, emulated)["q"], atol=1e-12)
    assert truth(server, emulated)["q"][1] > 0.0  # it stopped where it was, part of the way
    arm.close()


@pytest.fixture
def depm_bench():
    with DepmBench(speed=SPEED) as emulated:
        yield emulated


def arm_truth(emulated: DepmBench) -> dict:
    return {a.name: emulated.server.call(a.truth) for a in emulated.arms}


def test_arm_pair_channels_and_a_servo_cycle(depm_bench):
    pair = ArmPair.connect(depm_bench.rig)
    try:
        names = [c.name for c in pair.channels]
        assert names == [f"{arm}_q{j}" for arm in ("left", "right") for j in range(1, 8)]
        first = pair.channels[0]
        assert (first.unit, first.group) == ("rad", "left")
        assert first.low == pytest.approx(-math.radians(170)) and \
            first.high == pytest.approx(math.radians(170))
        assert pair.channels[8].high == pytest.approx(math.radians(120))  # right A2
        np.testing.assert_allclose(pair.joint_positions(), 0.0)
        pair.energise()
        target = np.zeros(14)
        for k in range(40):
            target[7 + 3] = -math.radians(0.25 * k)  # right A4 moves, everything else holds
            measured = pair.cycle(target)
        assert measured.shape == (14,)
        assert measured[10] < 0 and not np.any(measured[:10]) and not np.any(measured[11:])
        truth_now = arm_truth(depm_bench)
        assert truth_now["right"]["mode"] == "servo" and truth_now["left"]["q"] == [0.0] * 7
    finally:
        assert pair.stop(0.5) == []  # both confirmed at rest
    wait_for(lambda: all(t["connections"] == 0 for t in arm_truth(depm_bench).values()), 5.0,
             "both sessions closed")
    assert all(t["mode"] == "idle" for t in arm_truth(depm_bench).values())


def test_arm_pair_emergency_zero_stops_both_and_sends_nothing_after(depm_bench):
    pair = ArmPair.connect(depm_bench.rig)
    pair.energise()
    target = np.zeros(14)
    for k in range(40):
        target[1] = target[8] = math.radians(0.3 * k)  # both A2 moving
        pair.cycle(target)
    unreached: list = []
    stopper = threading.Thread(target=lambda: unreached.extend(pair.emergency_zero()))
    stopper.start()
    stopper.join()
    assert unreached == []
    # (a state the emulator reaches, not a deadline: on a loaded machine its loop runs late)
    wait_for(lambda: all(t["mode"] == "idle" for t in arm_truth(depm_bench).values()), 30.0,
             "both arms at rest")
    at_rest = {name: t["q"] for name, t in arm_truth(depm_bench).items()}
    last = pair.cycle(target + 0.1)  # latched: nothing is sent, the last measurement comes back
    assert last.shape == (14,)
    pair.zero_now()
    assert pair.stop(0.0) == []
    after = arm_truth(depm_bench)
    assert {name: t["q"] for name, t in after.items()} == at_rest  # nothing moved them since
    # stopped between the start (on a loaded machine the servo may not have left it before the stop
    # came) and the last target plus A2's braking distance from its full speed: the servo follows
    # the targets with their feed-forward speed, and a stop brakes from whatever speed it finds
    # (a loaded machine bunches the cycles, so that speed can reach the data sheet's 85 deg/s)
    a2 = 1
    braking = LBR_IIWA_14_R820.max_speed[a2] ** 2 / (2 * LBR_IIWA_14_R820.max_accel[a2])
    assert all(0.0 <= t["q"][a2] < math.radians(0.3 * 39) + braking + 1e-9
               for t in after.values()), after
