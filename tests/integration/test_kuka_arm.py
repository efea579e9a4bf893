"""The KST driver against the emulated arm on a real TCP socket."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.drivers.kuka_sunrise import KukaArm
from rigctl.emulators.kuka.arm import EmulatedArm, SimClock
from rigctl.emulators.server import EmulatorServer
from rigctl.errors import DeviceError, Disconnected
from rigctl.testing import wait_for

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
