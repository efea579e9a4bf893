"""`rigctl doctor`'s probe of the coil board (`RigKind.probes`): its handshake (firmware, channels,
watchdog) and its STATUS, whose outputs must read zero with nobody driving them."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rigctl.core.errors import ConfigError, RigError
from rigctl.rigs.base import Device

if TYPE_CHECKING:
    from rigctl.rigs.coil_board.settings import CoilBoardRig


def board(rig: CoilBoardRig, device: Device) -> str:
    from rigctl.drivers.coilboard import CoilBoard

    if rig.board is None:  # a coil-board rig file always has one (CoilBoardRig's check)
        raise ConfigError("the rig has no [board] table: it is not a coil board")
    board = CoilBoard.from_settings(rig.board)
    try:
        hello, status = board.hello, board.status()
    finally:
        board.close()
    assert hello is not None  # from_settings opens the board, and opening shakes hands
    if any(status.outputs):
        raise RigError(f"outputs {list(status.outputs)} are not zero with nobody driving them",
                       device=device.name)
    return (f"firmware {hello.fw_major}.{hello.fw_minor}, {hello.channels} channels, watchdog "
            f"{hello.watchdog_ms} ms; outputs zero, {status.bad_frames} bad frames")
