"""The coil board's rig file: `[rig] kind = "coil-board"` adds its `[board]` table, the host link
(docs/coilboard-protocol.md, docs/coilboard-driver.md) and the coils it drives (`CoilBoardRig`,
the kind's `settings`).

Units: volts, ohms, seconds, SyRen drive units (-127..127), unless a key's name says otherwise.
"""

from __future__ import annotations

from pydantic import model_validator

from rigctl.core.config import CoilBoardSettings, RigConfig


class CoilBoardRig(RigConfig):
    """A coil-board rig file: every rig's tables and the board's."""

    board: CoilBoardSettings | None = None

    @model_validator(mode="after")
    def _has_board(self) -> CoilBoardRig:
        if self.board is None:
            raise ValueError("a coil-board rig needs a [board] table (at least its url)")
        return self
