"""`rigctl service install`: units a sysadmin accepts (issue 38, item 4).

The unit runs this environment's interpreter, opens only the devices and hosts the rig file names,
verifies with systemd's own checker and rates at most 2.0 in `systemd-analyze security` (the
figures systemd computes, not ours); `systemd/rigctl.service` is the command's output for the
documented install, so the file in the repository cannot drift from what the command writes.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rigctl.apps.cli.main import main
from rigctl.apps.cli.service import DEFAULT_VENV, allowed_addresses, device_classes, render
from rigctl.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
needs_systemd = pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                                   reason="systemd-analyze not installed (.ci/run installs it)")


def test_the_repositorys_unit_is_what_the_command_writes_for_the_documented_install():
    files = render(None, python=f"{DEFAULT_VENV}/bin/python3", operators=[])
    assert (ROOT / "systemd" / "rigctl.service").read_text() == files["etc/systemd/system/rigctl.service"]
    assert (ROOT / "systemd" / "rigctl.sysusers").read_text() == files["etc/sysusers.d/rigctl.conf"]


def test_serial_ports_and_cameras_become_their_device_classes():
    assert device_classes(["serial:///dev/ttyACM0?baud=115200"]) == ["char-ttyACM"]
    assert device_classes(["ASRL/dev/ttyUSB3::INSTR", "0"]) == ["char-ttyUSB", "char-video4linux"]
    # an adapter that is not plugged in: its by-id name does not say which driver it gets
    assert device_classes(["serial:///dev/serial/by-id/usb-FTDI_X-port0?baud=9600"]) == [
        "char-ttyACM", "char-ttyUSB"]
    assert device_classes(["tcp://192.168.1.11:5025", "http://10.0.0.2:8080/s.mjpg"]) == []


def test_addresses_are_loopback_the_devices_and_the_operators_networks():
    urls = ["tcp://192.168.1.11:5025", "TCPIP0::10.1.2.3::5025::SOCKET", "tcp://127.0.0.1:7000"]
    assert allowed_addresses(urls, ["tcp://127.0.0.1:5555"], []) == [
        "localhost", "192.168.1.11", "10.1.2.3"]
    assert allowed_addresses([], ["tcp://0.0.0.0:5555"], ["192.168.7.9/24"]) == [
        "localhost", "192.168.7.0/24"]
    with pytest.raises(ConfigError, match="--allow-from"):
        allowed_addresses([], ["tcp://0.0.0.0:5555"], [])
    with pytest.raises(ConfigError, match="does not resolve"):
        allowed_addresses(["tcp://no-such-host.invalid:5025"], [], [])


def test_each_template_rigs_unit_opens_what_its_devices_sit_on():
    six = render(_template("six-coil"), python="/x/bin/python3", operators=[])
    unit = six["etc/systemd/system/rigctl.service"]
    assert [f"192.168.1.{k}" for k in range(11, 17)] == re.findall(r"IPAddressAllow=(192\.\S+)", unit)
    assert re.findall(r"DeviceAllow=(\S+)", unit) == ["char-video4linux"]  # the camera, url = 0
    assert "SupplementaryGroups=video\n" in unit and "m rigctl video" in six["etc/sysusers.d/rigctl.conf"]
    board = render(_template("coil-board"), python="/x/bin/python3", operators=[])
    assert re.findall(r"DeviceAllow=(\S+)", board["etc/systemd/system/rigctl.service"]) == [
        "char-ttyACM", "char-video4linux"]


def _template(kind: str) -> str:
    return str(ROOT / "rigctl" / "rigs" / kind.replace("-", "_") / "template.toml")


def _exposure(unit: Path) -> float:
    out = subprocess.run(["systemd-analyze", "security", "--offline=yes", str(unit)],
                         capture_output=True, text=True, timeout=60).stdout
    return float(re.search(r"Overall exposure level for \S+: ([\d.]+)", out).group(1))


@needs_systemd
@pytest.mark.parametrize("kind", ["six-coil", "coil-board", "depm"])
def test_the_installed_unit_verifies_and_rates_at_most_2(tmp_path, capsys, kind):
    venv = Path(sys.prefix)
    assert main(["service", "install", "--venv", str(venv), "--rig", _template(kind),
                 "--root", str(tmp_path)]) == 0
    unit = tmp_path / "etc/systemd/system/rigctl.service"
    assert f"ExecStart={venv}/bin/python3 -m rigctl daemon" in unit.read_text()
    verify = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True,
                            timeout=60)
    assert verify.returncode == 0, verify.stderr
    assert _exposure(unit) <= 2.0


@needs_systemd
def test_the_bench_unit_rates_at_most_2():
    assert _exposure(ROOT / "systemd" / "rigctl-bench@.service") <= 2.0


def test_a_missing_environment_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["service", "install", "--venv", str(tmp_path / "nope"), "--root", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no bin/python3" in err[0]
