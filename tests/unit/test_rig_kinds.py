"""What each rig kind brings through its `RigKind` (issue 36): the rig file's model, the heating
windings, the stream host's patience and the doctor's probes. The figures expected are computed
here from the rig files' own numbers, not by the hooks under test."""

from __future__ import annotations

import pytest

from rigctl.apps.daemon.runhost import device_patience_s
from rigctl.core.config import RigConfig, RigInfo, load_rig, parse_rig
from rigctl.core.errors import ConfigError
from rigctl.physics.thermal import Windings
from rigctl.rigs import rig_kind
from rigctl.rigs.coil_board.settings import CoilBoardRig
from rigctl.rigs.depm.settings import DepmRig
from rigctl.rigs.doctor import probe_rig
from rigctl.rigs.six_coil.settings import SixCoilRig

MODELS = {"six-coil": SixCoilRig, "coil-board": CoilBoardRig, "depm": DepmRig}


@pytest.fixture(scope="module")
def templates(tmp_path_factory) -> dict[str, RigConfig]:
    """Each kind's `rigctl init` file, loaded as a lab's would be."""
    folder = tmp_path_factory.mktemp("rigs")
    rigs = {}
    for name in MODELS:
        path = folder / f"{name}.toml"
        path.write_text(rig_kind(name).template())
        rigs[name] = load_rig(path)
    return rigs


@pytest.mark.parametrize("kind", list(MODELS))
def test_a_rig_file_is_validated_with_its_kind_s_model(templates, kind) -> None:
    assert type(templates[kind]) is MODELS[kind]


def test_a_table_of_another_kind_is_refused_by_name() -> None:
    data = {"rig": {"kind": "coil-board"}, "board": {"url": "/dev/null"}, "magnets": {"radius_mm": 2}}
    with pytest.raises(ConfigError, match=r"^rig file: magnets: Extra inputs are not permitted$"):
        parse_rig(data)


def test_an_unknown_kind_names_the_installed_ones_in_one_line() -> None:
    with pytest.raises(ConfigError) as refused:
        parse_rig({"rig": {"kind": "maglev"}, "coils": []}, "lab.toml")
    assert str(refused.value) == ("lab.toml: rig.kind: rig kind 'maglev' is not installed; the "
                                  "installed kinds are coil-board, depm, six-coil")


def test_a_rig_of_a_kind_is_not_built_with_another_kind_s_model() -> None:
    with pytest.raises(ValueError, match="a six-coil rig is a rigctl.rigs.six_coil.settings.SixCoilRig"):
        RigConfig(rig=RigInfo(kind="six-coil"))


def test_the_six_coils_and_the_board_s_four_heat_and_the_arms_do_not(templates) -> None:
    six, board = templates["six-coil"], templates["coil-board"]
    windings = Windings.of_rig(six)
    assert windings.names == tuple(c.name for c in six.coils) and windings.volts_per_unit is None
    assert list(windings.resistance_ohm) == [c.resistance_ohm for c in six.coils]
    windings = Windings.of_rig(board)
    assert windings.names == tuple(board.board.coil_names)
    assert windings.volts_per_unit == pytest.approx(board.board.supply_V / 127)  # full drive: the supply
    assert Windings.of_rig(templates["depm"]) is None


def test_the_stream_host_waits_as_long_as_each_kind_s_devices_may_take(templates) -> None:
    six, board, depm = templates["six-coil"], templates["coil-board"], templates["depm"]
    assert device_patience_s(six) == six.stream.reply_timeout_s
    link = board.board  # a reconnect after an unplug, then every attempt of one request
    assert device_patience_s(board) == pytest.approx(
        max(board.stream.reply_timeout_s,
            link.reconnect_s + (link.retries + 1) * link.reply_timeout_s))
    assert device_patience_s(depm) == max(depm.stream.reply_timeout_s, depm.depm.reply_timeout_s)


def test_each_device_kind_of_every_rig_has_a_probe(templates) -> None:
    for name, rig in templates.items():
        kind = rig_kind(name)
        for device in kind.devices(rig):
            assert device.kind in kind.probes or device.kind == "camera", (name, device)


def test_a_device_no_probe_knows_is_a_failed_row_not_a_traceback(monkeypatch, templates) -> None:
    from dataclasses import replace

    from rigctl.core import registry
    from rigctl.rigs.base import Device

    kind = rig_kind("depm")
    odd = replace(kind, devices=lambda rig: [Device("gripper", "tcp://127.0.0.1:1", "gripper")])
    monkeypatch.setattr(registry, "_loaded", ({**registry.kinds(), "depm": odd}, {}))
    [row] = probe_rig(templates["depm"])
    assert not row.ok and row.detail == "gripper: rig kind depm has no doctor probe for a 'gripper'"
