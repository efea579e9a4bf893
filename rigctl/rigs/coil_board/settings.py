"""The coil board's rig file: `[rig] kind = "coil-board"` adds its `[board]` table, the host link
(docs/coilboard-protocol.md, docs/coilboard-driver.md) and the coils it drives (`CoilBoardRig`,
the kind's `settings`).

Units: volts, ohms, seconds, SyRen drive units (-127..127), unless a key's name says otherwise.
"""

from __future__ import annotations

from pydantic import model_validator

from rigctl.core.config import CoilBoardSettings, RigConfig
from rigctl.core.errors import ConfigError


class CoilBoardRig(RigConfig):
    """A coil-board rig file: every rig's tables and the board's."""

    board: CoilBoardSettings | None = None

    @model_validator(mode="after")
    def _has_board(self) -> CoilBoardRig:
        if self.board is None:
            raise ValueError("a coil-board rig needs a [board] table (at least its url)")
        return self


def coil_board_rig(rig: RigConfig) -> CoilBoardRig:
    """`rig` as the coil-board rig it is (the kind's hooks are handed a `RigConfig`; a rig file of
    kind coil-board is always a `CoilBoardRig`), a ConfigError if it is of another kind."""
    if not isinstance(rig, CoilBoardRig):
        raise ConfigError(f"rig '{rig.rig.name}' is a {rig.rig.kind} rig, not a coil-board rig")
    return rig
