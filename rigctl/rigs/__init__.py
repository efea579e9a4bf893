"""The rig kinds: what differs between the six-coil manipulator, the coil board and the arms.

`KINDS` is the one registry: `rigctl execute`, `rigctl emulate`, the daemon and its stream
process look a rig kind up here instead of switching on its name."""

from __future__ import annotations

from rigctl.errors import ConfigError
from rigctl.rigs import coil_board, depm, six_coil
from rigctl.rigs.base import Device, RigKind

KINDS: dict[str, RigKind] = {k.name: k for k in (six_coil.KIND, coil_board.KIND, depm.KIND)}


def rig_kind(name: str) -> RigKind:
    try:
        return KINDS[name]
    except KeyError:
        raise ConfigError(f"rig kind {name!r} is not one of {', '.join(KINDS)}") from None


__all__ = ["KINDS", "Device", "RigKind", "rig_kind"]
