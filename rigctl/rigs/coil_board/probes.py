"""`rigctl doctor`'s probe of the coil board (`RigKind.probes`): its handshake (firmware, channels,
watchdog) and its STATUS, whose outputs must read zero with nobody driving them."""

from __future__ import annotations

from rigctl.core.config import RigConfig
from rigctl.core.errors import RigError
from rigctl.rigs.base import Device


def board(rig: RigConfig, device: Device) -> str:
    from rigctl.drivers.coilboard import CoilBoard

    board = CoilBoard.from_settings(rig.board)
    try:
        hello, status = board.hello, board.status()
    finally:
        board.close()
    if any(status.outputs):
        raise RigError(f"outputs {list(status.outputs)} are not zero with nobody driving them",
                       device=device.name)
    return (f"firmware {hello.fw_major}.{hello.fw_minor}, {hello.channels} channels, watchdog "
            f"{hello.watchdog_ms} ms; outputs zero, {status.bad_frames} bad frames")
