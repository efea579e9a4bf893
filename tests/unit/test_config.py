"""The rig file loader (`rigctl.core.config`): every device URL checked at load, with the field path and
what to write instead; the tables a rig file carries are those of its kind."""

from __future__ import annotations

import subprocess
import sys
import tomllib

import pytest

from rigctl.core.config import (
    CameraSettings,
    CoilBoardSettings,
    RigInfo,
    default_six_coil_coils,
    dump_rig,
    load_rig,
    parse_rig,
)
from rigctl.core.errors import ConfigError
from rigctl.rigs.coil_board.settings import CoilBoardRig


def six_coil(**tables) -> dict:
    coils = [c.model_dump(mode="json") for c in default_six_coil_coils()]
    return {"rig": {"kind": "six-coil"}, "coils": coils, **tables}


def test_a_bad_coil_url_names_its_field_path_and_what_to_write(tmp_path) -> None:
    data = six_coil()
    data["coils"][2]["url"] = "COM3"
    with pytest.raises(ConfigError) as info:
        parse_rig(data, "six.toml")
    assert str(info.value) == ("six.toml: coils[2].url: 'COM3' is not a device URL; write "
                               "serial:///dev/ttyUSB0?baud=9600 or tcp://HOST:PORT")


@pytest.mark.parametrize("url", ["htp:/typo", "tcp://:5025", "tcp://10.0.0.1:70000", "ASRL2::INSTR"])
def test_every_table_s_device_urls_are_checked(url) -> None:
    depm = {"arm_urls": ["tcp://172.31.1.147:30001", url], "arm_positions_mm": [[0, 0, 0]] * 2,
            "arm_rpy_deg": [[0, 0, 0]] * 2, "epm_moment_Am2": 970.0,
            "hall_url": "tcp://10.0.0.20:30010"}
    cases = {
        "board.url": {"rig": {"kind": "coil-board"}, "board": {"url": url}},
        "depm.arm_urls[1]": {"rig": {"kind": "depm"}, "depm": depm},
        "depm.hall_url": {"rig": {"kind": "depm"}, "depm": {**depm, "arm_urls": [
            "tcp://172.31.1.147:30001"] * 2, "hall_url": url}},
        "camera.url": six_coil(camera={"url": url}),
        "emulation.backdoor": six_coil(emulation={"backdoor": url}),
    }
    for where, data in cases.items():
        with pytest.raises(ConfigError) as info:
            parse_rig(data, "rig.toml")
        assert str(info.value).startswith(f"rig.toml: {where}: {url!r}"), str(info.value)


@pytest.mark.parametrize("url", ["TCPIP::10.0.0.11::5025::SOCKET", "TCPIP0::bop1::5025::SOCKET",
                                 "ASRL/dev/ttyUSB0::INSTR", "serial:///dev/ttyS0?baud=9600",
                                 "tcp://10.0.0.11:5025", "/dev/pts/4"])
def test_supply_urls_of_every_accepted_form_load(url) -> None:
    data = six_coil()
    data["coils"][0]["url"] = url
    assert parse_rig(data).coils[0].url == url


@pytest.mark.parametrize("source", [0, "0", "/dev/video0", "http://10.0.0.5:8080/stream.mjpg",
                                    "https://cam.lab/live", "runs/fig4.mp4"])
def test_camera_sources_as_labs_write_them(tmp_path, source) -> None:
    path = tmp_path / "rig.toml"
    rig = parse_rig(six_coil(camera={"url": source}))
    path.write_text(dump_rig(rig))
    assert load_rig(path).camera.url == str(source)


def test_a_bad_url_exits_2_before_any_connection(tmp_path) -> None:
    data = six_coil()
    data["coils"][4]["url"] = "htp:/typo"
    rig = tmp_path / "rig.toml"
    import tomli_w

    rig.write_text(tomli_w.dumps(data))
    done = subprocess.run([sys.executable, "-m", "rigctl", "doctor", "--rig", str(rig)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert "coils[4].url: 'htp:/typo' is not a device URL" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_coil_board_rig_file_has_only_its_own_tables() -> None:
    rig = CoilBoardRig(rig=RigInfo(kind="coil-board"), board=CoilBoardSettings(url="/dev/pts/3"),
                    camera=CameraSettings(url="0"))
    written = tomllib.loads(dump_rig(rig))
    assert set(written) == {"rig", "stream", "board", "camera", "preflight"}  # every kind reads [preflight]
    assert parse_rig(written) == rig


def test_a_six_coil_rig_file_keeps_its_tables() -> None:
    rig = parse_rig(six_coil())
    written = tomllib.loads(dump_rig(rig))
    assert {"field", "magnets", "coils"} <= set(written)
    assert parse_rig(written) == rig
