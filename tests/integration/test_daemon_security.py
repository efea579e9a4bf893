"""Binding rules and the CURVE allow-list: loopback by default, keys for anything else, and a client
whose key is not allowed gets nothing at all, not even `status` or telemetry."""

import os
import socket

import pytest

from rigctl.apps.client import DaemonUnreachable, Rig, Telemetry
from rigctl.apps.daemon.keys import allow, new_keypair
from rigctl.apps.daemon.messages import is_loopback_endpoint
from rigctl.apps.daemon.sdnotify import SystemdNotifier
from rigctl.apps.daemon.server import Daemon
from rigctl.core.config import RigInfo, default_six_coil_coils
from rigctl.core.errors import ConfigError
from rigctl.rigs.six_coil.settings import SixCoilRig

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick

RIG = SixCoilRig(rig=RigInfo(kind="six-coil", name="secure rig"), coils=default_six_coil_coils())
LOOPBACK = dict(command="tcp://127.0.0.1:0", telemetry="tcp://127.0.0.1:0", events="tcp://127.0.0.1:0")


@pytest.mark.parametrize("endpoint, loopback", [
    ("tcp://127.0.0.1:7810", True), ("tcp://127.3.4.5:1", True), ("tcp://localhost:1", True),
    ("tcp://[::1]:7810", True), ("ipc:///run/rigctl/cmd", True), ("tcp://*:7810", False),
    ("tcp://0.0.0.0:7810", False), ("tcp://192.168.1.20:7810", False), ("tcp://eth0:7810", False),
])
def test_which_endpoints_count_as_loopback(endpoint, loopback):
    assert is_loopback_endpoint(endpoint) is loopback


def test_a_non_loopback_bind_without_keys_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="CURVE"):
        Daemon(RIG, command="tcp://0.0.0.0:0", telemetry="tcp://127.0.0.1:0",
               events="tcp://127.0.0.1:0", runs_dir=tmp_path)


@pytest.fixture
def keys(tmp_path):
    server_public, server_secret = new_keypair(tmp_path / "server", "daemon")
    alice_public, alice_secret = new_keypair(tmp_path / "operators", "alice")
    mallory_public, mallory_secret = new_keypair(tmp_path / "others", "mallory")
    allowed = tmp_path / "allowed"
    allow(alice_public, allowed)
    assert oct(os.stat(alice_secret).st_mode & 0o777) == "0o600"
    return dict(server_public=server_public, server_secret=server_secret, allowed=allowed,
                alice=alice_secret, mallory=mallory_secret)


def test_only_allowed_operator_keys_get_any_reply(keys, tmp_path):
    # bound on all interfaces: allowed because keys are configured
    daemon = Daemon(RIG, command="tcp://0.0.0.0:0", telemetry="tcp://0.0.0.0:0",
                    events="tcp://0.0.0.0:0", runs_dir=tmp_path,
                    server_key=keys["server_secret"], allowed_keys=keys["allowed"])
    endpoints = daemon.start_thread()
    port = endpoints.command.rsplit(":", 1)[1]
    endpoint = f"tcp://127.0.0.1:{port}"
    try:
        with Rig(endpoint, server_key=keys["server_public"], client_key=keys["alice"]) as alice:
            assert alice.status()["state"] == "idle"
        with Rig(endpoint, server_key=keys["server_public"], client_key=keys["mallory"],
                 timeout_s=0.3, retries=1) as mallory:
            with pytest.raises(DaemonUnreachable):
                mallory.status()
        with Rig(endpoint, timeout_s=0.3, retries=0) as anonymous:  # no CURVE at all
            with pytest.raises(DaemonUnreachable):
                anonymous.ping()
        # telemetry: alice hears the state heartbeat, mallory hears nothing
        events_port = endpoints.events.rsplit(":", 1)[1]
        data_port = endpoints.telemetry.rsplit(":", 1)[1]
        from rigctl.apps.client import _Curve

        heard = {}
        for who in ("alice", "mallory"):
            with Telemetry(f"tcp://127.0.0.1:{data_port}", f"tcp://127.0.0.1:{events_port}",
                           ["state"], curve=_Curve(keys["server_public"], keys[who])) as feed:
                heard[who] = feed.receive(timeout_s=2.5)
        assert heard["alice"] is not None and heard["alice"].state.value == "idle"
        assert heard["mallory"] is None
    finally:
        daemon.stop()


def test_ready_and_watchdog_go_to_the_notify_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(path)
    listener.settimeout(5)
    notifier = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "300000"})
    assert notifier.watchdog_s == pytest.approx(0.3)
    daemon = Daemon(RIG, runs_dir=tmp_path, notifier=notifier, **LOOPBACK)
    daemon.start_thread()
    try:
        messages = [listener.recv(4096).decode()]
        assert "READY=1" in messages[0]
        while not any("WATCHDOG=1" in m for m in messages):
            messages.append(listener.recv(4096).decode())
    finally:
        daemon.stop()
        listener.close()


def test_the_allow_list_is_read_again_when_its_folder_changes(keys, tmp_path):
    """Revoking a key needs no restart: removed, its open connection is refused (`forbidden`)
    and a new one gets nothing; a key added gets in."""
    from rigctl.apps.client import CommandRefused
    from rigctl.apps.daemon.keys import ALLOW_LIST_POLL_S
    from rigctl.apps.testing import wait_for

    daemon = Daemon(RIG, runs_dir=tmp_path, server_key=keys["server_secret"],
                    allowed_keys=keys["allowed"], **LOOPBACK)
    endpoint = daemon.start_thread().command
    curve = dict(server_key=keys["server_public"])
    try:
        with Rig(endpoint, **curve, client_key=keys["mallory"], timeout_s=0.3, retries=0) as m:
            with pytest.raises(DaemonUnreachable):
                m.status()
        allow(keys["mallory"].with_suffix(".key"), keys["allowed"])  # mallory let in
        wait_for(lambda: len(daemon.curve.allowed) == 2, 5 * ALLOW_LIST_POLL_S + 5, "re-read")
        with Rig(endpoint, **curve, client_key=keys["mallory"]) as m:
            assert m.status()["state"] == "idle"
        with Rig(endpoint, **curve, client_key=keys["alice"]) as alice:
            assert alice.status()["state"] == "idle"  # connected while allowed
            (keys["allowed"] / "alice.key").unlink()  # revoked
            wait_for(lambda: len(daemon.curve.allowed) == 1, 5 * ALLOW_LIST_POLL_S + 5,
                     "re-read")
            with pytest.raises(CommandRefused) as refused:
                alice.status()
            assert refused.value.code == "forbidden"
        with Rig(endpoint, **curve, client_key=keys["alice"], timeout_s=0.3, retries=0) as again:
            with pytest.raises(DaemonUnreachable):
                again.status()
    finally:
        daemon.stop()
