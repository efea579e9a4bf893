"""The manual hold through the daemon on the coil board's and the arms' emulated benches (in this
process, the devices on real ptys and TCP sockets): what is held is read from the emulators' ground
truth (the SyRen outputs the board's wire carries, the arms' joints), refusals leave everything
where it was, and an e-stop during a hold ends it with the record's `safe` event; `rigctl hold` on
the six coils. The six-coil hold through the client (`set_field`): test_daemon_bench.py."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.client import CommandRefused
from rigctl.apps.testing import daemon_on, wait_for
from rigctl.core.record import read_events
from rigctl.emulators.bench import SixCoilBench
from rigctl.emulators.coilboard.bench import CoilBoardBench
from rigctl.emulators.depm import DepmBench


@pytest.fixture
def board(tmp_path):
    with daemon_on(CoilBoardBench(syren_startup_s=0.05), tmp_path / "runs") as served:
        yield served


@pytest.fixture
def arms(tmp_path):
    """The dual-EPM bench, its arms parked at 0."""
    with daemon_on(DepmBench(), tmp_path / "runs") as served:
        yield served


def hold_over(rig, timeout_s=30.0) -> Path:
    """Wait until the daemon has no run; the last run's record."""
    wait_for(lambda: rig.status()["run"] is None, timeout_s, "the hold ended")
    return Path(rig.status()["last_run"]["run"])


def events_of(run_dir: Path) -> list[str]:
    return [e["event"] for e in read_events(run_dir)]


# -- the coil board --------------------------------------------------------------------------------

def test_a_board_hold_drives_the_syren_outputs_and_release_zeroes_them(board):
    rig, backdoor, _ = board
    drive = [40, -20, 0, 100]
    reply = rig.hold({"drive": drive}, ramp_s=0.1)
    assert reply["setpoints"] == drive and reply["channels"] == ["+x", "-x", "+y", "-y"]
    # SyRen packetized serial: drive forward / backward at data/127 of full power
    expected = [v / 127 for v in drive]
    wait_for(lambda: np.allclose(backdoor.request("truth")["outputs"], expected, atol=1e-9),
             5.0, "the SyRen outputs at the held drive")
    status = rig.status()
    assert status["state"] == "running" and status["run"]["kind"] == "hold"
    assert status["hold"] == {"drive": [40.0, -20.0, 0.0, 100.0]}
    with pytest.raises(CommandRefused, match="cannot be paused: release it"):
        rig.pause()
    rig.hold({"drive": [-10, 0, 0, 0]}, ramp_s=0.05)  # retargeted while held
    wait_for(lambda: np.allclose(backdoor.request("truth")["outputs"], [-10 / 127, 0, 0, 0]),
             5.0, "the SyRen outputs at the new drive")
    assert rig.release(ramp_s=0.05)["released"] is True
    run_dir = hold_over(rig)
    assert backdoor.request("truth")["outputs"] == [0, 0, 0, 0]
    assert rig.status()["state"] == "idle" and rig.status()["hold"] is None
    assert {"hold", "release", "safe"} <= set(events_of(run_dir))
    summary = rig.run(run_dir.name)["summary"]
    assert summary["plan_kind"] == "hold" and summary["reached"] and summary["faults"] == []


def test_board_drive_beyond_its_limit_is_refused_before_anything_moves(board):
    rig, backdoor, runs = board
    with pytest.raises(CommandRefused) as refused:
        rig.hold({"drive": [0, 0, 128, 0]})  # the SyRen's full power is 127
    assert refused.value.code == "limit" and "+y" in refused.value.reason \
        and "127" in refused.value.reason
    with pytest.raises(CommandRefused) as refused:
        rig.hold({"drive": [0.5, 0, 0, 0]})
    assert refused.value.code == "limit" and "whole" in refused.value.reason
    with pytest.raises(CommandRefused) as refused:
        rig.hold({"field_mT": [1, 0, 0]})
    assert refused.value.code == "bad_args" and '"drive"' in refused.value.reason
    status = rig.status()
    assert status["state"] == "idle" and status["run"] is None and status["hold"] is None
    assert not runs.exists() or not any(runs.iterdir())  # no run was even started
    assert backdoor.request("truth")["outputs"] == [0, 0, 0, 0]


def test_an_estop_during_a_board_hold_ends_it_safe(board):
    rig, backdoor, _ = board
    rig.hold({"drive": [0, 90, 0, 0]}, ramp_s=0.05)
    wait_for(lambda: backdoor.request("truth")["outputs"][1] > 0.5, 5.0, "the coil driven")
    assert rig.estop()["state"] == "estopped"
    # the STOP has left; the SyRen packets follow on the 9600 baud wire within milliseconds
    wait_for(lambda: backdoor.request("truth")["outputs"] == [0, 0, 0, 0], 1.0, "outputs at 0")
    run_dir = hold_over(rig)
    assert "safe" in events_of(run_dir) and "unsafe" not in events_of(run_dir)
    assert rig.status()["hold"] is None
    assert rig.reset()["state"] == "idle"


# -- the arms ----------------------------------------------------------------------------------------

# LBR iiwa 14 R820 data sheet: A1..A7 at most 85, 85, 100, 75, 130, 135, 135 deg/s; the bench's
# speed fraction is 30 %
SPEED_CAP = np.radians([85, 85, 100, 75, 130, 135, 135]) * 0.3
POSE = [[0.2, 0.1, 0.0, -0.2, 0.0, 0.1, 0.0]] * 2  # near the parked candle (all joints 0)


def truth_q(backdoor) -> np.ndarray:
    arms = backdoor.request("truth")["arms"]
    return np.array([arms[name]["q"] for name in ("left", "right")])


def at_rest(backdoor) -> bool:
    return all(max(abs(v) for v in arm["qd"]) < 1e-3
               for arm in backdoor.request("truth")["arms"].values())


def test_an_arm_pose_is_reached_and_stays_after_release(arms):
    rig, backdoor, _ = arms
    ramp_s, rate_hz = 1.0, 50.0  # the bench's servo rate
    reply = rig.hold({"joints_rad": POSE}, ramp_s=ramp_s)
    assert len(reply["setpoints"]) == 14
    # the ramp steps each joint by at most |dq| / (ramp_s * rate) per cycle; once the last
    # target is held the servo has no reason to be further off than one such step
    tolerance = np.max(np.abs(POSE)) / (ramp_s * rate_hz)
    # settled there, not passing through: released mid-motion the arms brake to a stop a braking
    # distance further on (the controller's stop, not the hold's doing)
    wait_for(lambda: at_rest(backdoor) and np.max(np.abs(truth_q(backdoor) - POSE)) < tolerance,
             ramp_s + 5.0, "the arms at rest at the held pose")
    assert rig.status()["hold"] == {"joints_rad": POSE}
    rig.release()
    run_dir = hold_over(rig)
    assert "safe" in events_of(run_dir)
    wait_for(lambda: at_rest(backdoor), 5.0, "the arms at rest")
    assert np.max(np.abs(truth_q(backdoor) - POSE)) < tolerance  # the rest: where they stood


def test_arm_poses_beyond_a_joint_limit_or_too_fast_are_refused_before_anything_moves(arms):
    rig, backdoor, _ = arms
    beyond = [[3.0, 0, 0, 0, 0, 0, 0], [0] * 7]  # A1 reaches +-170 deg = 2.967 rad
    with pytest.raises(CommandRefused) as refused:
        rig.hold({"joints_rad": beyond}, ramp_s=10.0)
    assert refused.value.code == "limit" and "A1" in refused.value.reason \
        and "outside its range" in refused.value.reason
    # from the parked pose, A4's 0.2 rad at 22.5 deg/s takes 0.509 s: 0.1 s is too fast (checked
    # in the stream process once the arms' joints are read, before they servo)
    needed_s = float(np.max(np.abs(np.array(POSE)) / SPEED_CAP))
    assert math.isclose(needed_s, 0.2 / math.radians(22.5))
    with pytest.raises(CommandRefused) as refused:
        rig.hold({"joints_rad": POSE}, ramp_s=0.1)
    assert refused.value.code == "limit" and f"ramp_s >= {needed_s:.2f} s" in refused.value.reason
    with pytest.raises(CommandRefused) as refused:
        rig.hold({"joints_rad": POSE[0]})
    assert refused.value.code == "bad_args"
    status = rig.status()
    assert status["state"] == "idle" and status["run"] is None
    assert np.max(np.abs(truth_q(backdoor))) == 0.0  # still parked
    assert all(arm["mode"] == "idle" for arm in backdoor.request("truth")["arms"].values())


def test_an_estop_during_an_arm_hold_ends_it_safe(arms):
    rig, backdoor, _ = arms
    rig.hold({"joints_rad": POSE}, ramp_s=3.0)
    wait_for(lambda: np.max(np.abs(truth_q(backdoor))) > 0.02, 5.0, "the arms moving")
    assert rig.estop()["state"] == "estopped"
    run_dir = hold_over(rig)
    assert "safe" in events_of(run_dir) and "unsafe" not in events_of(run_dir)
    wait_for(lambda: at_rest(backdoor), 5.0, "the arms at rest")
    assert np.max(np.abs(truth_q(backdoor) - POSE)) > 0.01  # stopped on the way, not at the pose
    assert rig.reset()["state"] == "idle"


# -- rigctl hold -------------------------------------------------------------------------------------

def test_rigctl_hold_holds_refuses_with_exit_2_and_releases(tmp_path):
    with daemon_on(SixCoilBench(), tmp_path / "runs") as (rig, backdoor, _):
        endpoint = rig.endpoint

        def hold(*args):
            return subprocess.run([sys.executable, "-m", "rigctl", "hold", "--connect", endpoint,
                                   *args], check=False, capture_output=True, text=True,
                                  timeout=60)

        held = hold("--field-mT", "1", "0", "0", "--ramp-s", "0.05")
        assert held.returncode == 0
        assert held.stdout.startswith("holding {'field_mT': [1.0, 0.0, 0.0]}")
        wait_for(lambda: backdoor.request("truth")["currents_A"]["x+"] > 0.1, 5.0, "x+ driven")
        refused = hold("--field-mT", "0", "0", "10")  # 32.6 A per z coil, over its 20 A
        assert refused.returncode == 2 and refused.stderr.startswith("refused: ")
        assert len(refused.stderr.strip().splitlines()) == 1
        released = hold("--release")
        assert released.returncode == 0 and released.stdout.startswith("released")
        hold_over(rig)
        wait_for(lambda: all(abs(a) < 0.05 for a in backdoor.request("truth")["currents_A"].values()),
                 5.0, "every current under 50 mA (the coils' L/R decay)")
