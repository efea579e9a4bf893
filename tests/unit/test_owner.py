"""One owner per rig: the device locks of `rigctl.rigs.owner`, across real processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from rigctl.core.config import RigConfig, RigInfo, default_six_coil_coils, dump_rig
from rigctl.rigs.owner import RigInUse, RigLock, holder_of
from rigctl.rigs.six_coil.settings import SixCoilRig

HOLD = textwrap.dedent("""
    import sys, time
    from rigctl.core.config import load_rig
    from rigctl.rigs.owner import RigLock
    with RigLock(load_rig(sys.argv[1]), "rigctl daemon"):
        print("held", flush=True)
        time.sleep(60)
""")


def six_coil_rig(port0: int) -> RigConfig:
    coils = [c.model_copy(update={"url": f"tcp://127.0.0.1:{port0 + i}"})
             for i, c in enumerate(default_six_coil_coils())]
    return SixCoilRig(rig=RigInfo(kind="six-coil", name="test"), coils=coils)


@pytest.fixture(autouse=True)
def lock_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGCTL_LOCK_DIR", str(tmp_path / "locks"))
    return tmp_path / "locks"


def hold_in_child(rig: RigConfig, tmp_path) -> subprocess.Popen:
    path = tmp_path / f"rig-{time.monotonic_ns()}.toml"
    path.write_text(dump_rig(rig))
    child = subprocess.Popen([sys.executable, "-c", HOLD, str(path)], stdout=subprocess.PIPE,
                             text=True, env=os.environ.copy())
    assert child.stdout.readline().strip() == "held"
    return child


def test_a_second_owner_is_refused_naming_the_first(tmp_path):
    child = hold_in_child(six_coil_rig(40000), tmp_path)
    try:
        with pytest.raises(RigInUse) as refused:
            RigLock(six_coil_rig(40000), "rigctl execute").acquire()
        assert f"rigctl daemon, pid {child.pid}" in str(refused.value)
        held = holder_of(six_coil_rig(40000))
        assert held is not None and held.pid == child.pid and held.owner == "rigctl daemon"
    finally:
        child.kill()
        child.wait()


def test_sharing_one_device_is_owning_the_same_rig(tmp_path):
    child = hold_in_child(six_coil_rig(40000), tmp_path)
    try:
        overlapping = six_coil_rig(40005)  # its first supply is the other rig's last
        with pytest.raises(RigInUse):
            RigLock(overlapping, "rigctl execute").acquire()
        with RigLock(six_coil_rig(40006), "rigctl execute"):  # disjoint: its own rig
            pass
    finally:
        child.kill()
        child.wait()


def test_a_lock_left_by_a_killed_process_is_taken_over(tmp_path):
    child = hold_in_child(six_coil_rig(40000), tmp_path)
    child.send_signal(signal.SIGKILL)
    child.wait()
    assert holder_of(six_coil_rig(40000)) is None
    with RigLock(six_coil_rig(40000), "rigctl execute") as lock:
        assert holder_of(six_coil_rig(40000)).pid == os.getpid()
    lock.release()
    assert holder_of(six_coil_rig(40000)) is None


def test_rigctl_execute_on_an_owned_rig_exits_2_before_connecting(tmp_path):
    rig = six_coil_rig(40000)  # nothing listens on these ports: a connect would fail with exit 3
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(dump_rig(rig))
    plan = os.path.join(os.path.dirname(__file__), "..", "..", "plans", "examples", "fig4-quick.json")
    child = hold_in_child(rig, tmp_path)
    try:
        done = subprocess.run([sys.executable, "-m", "rigctl", "execute", plan, "--rig",
                               str(rig_file), "--runs", str(tmp_path / "runs")],
                              capture_output=True, text=True, timeout=60)
    finally:
        child.kill()
        child.wait()
    assert done.returncode == 2, done.stderr
    assert f"rig in use by rigctl daemon, pid {child.pid}" in done.stderr
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "runs").exists()


def test_the_locks_are_every_users_whatever_the_umask(lock_dir):
    """The daemon runs as its own user under umask 0027 (the unit's); an operator's `rigctl
    execute` or `estop --rig` must still open the same lock files."""
    import stat

    old = os.umask(0o027)
    try:
        with RigLock(six_coil_rig(40100), "rigctl daemon"):
            pass
    finally:
        os.umask(old)
    assert stat.S_IMODE(lock_dir.stat().st_mode) == 0o1777
    files = list(lock_dir.iterdir())
    assert len(files) == 6 and all(stat.S_IMODE(f.stat().st_mode) == 0o666 for f in files)


@pytest.mark.skipif(not os.path.isdir("/run/lock"), reason="no /run/lock on this machine")
def test_the_default_lock_folder_is_the_machines_not_tmp(monkeypatch):
    """A unit's PrivateTmp= gives the daemon a /tmp of its own: locks there are invisible to an
    operator's rigctl."""
    from pathlib import Path

    from rigctl.rigs.owner import lock_dir

    monkeypatch.delenv("RIGCTL_LOCK_DIR")
    assert lock_dir() == Path("/run/lock/rigctl")
