"""The coil board as the run engine's actuator group: four coil drives through one board.

One device (the Arduino and its four SyRen drivers) carries four channels, each coil's drive in
SyRen units (-max_command..max_command of full power, the caller's sense: the coil's pull). A
cycle is one SET; what the board's ACK reports applied is the measurement. The board has no output
switch: "energised" means its SyRens have finished their start-up (SYREN_READY), before which the
board sends them nothing. An e-stop goes out on the calling thread at once (the driver's
`emergency_stop`: a STOP frame under a wire-only lock, latched so that only zeros leave after
it). The end is a STOP whose ACK reports every output zero; that ACK is the confirmation. The
coils are stopped at once, not ramped: a pull that ramps down still pulls the particles, only
further from where the run left them. If this process dies, the board's 200 ms watchdog zeroes
the coils by itself.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from rigctl.core.channels import Channel
from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, DeviceTimeout, RigError
from rigctl.drivers.coilboard import CoilBoard
from rigctl.physics.thermal import Windings

if TYPE_CHECKING:
    from rigctl.rigs.coil_board.settings import CoilBoardRig

log = logging.getLogger(__name__)

SYREN_READY_TIMEOUT_S = 5.0  # the SyRens start 2 s after power-on; a board just plugged in too


def board_channels(rig: CoilBoardRig) -> list[Channel]:
    """Each coil's drive in SyRen units within the board's limit: the coil board's channels."""
    board = rig.board
    if board is None:
        return []
    return [Channel(name, "drive", -board.max_command, board.max_command, "board")
            for name in board.coil_names]


class BoardActuators:
    """The connected coil board of a rig (`connect`), as one actuator group of four channels."""

    def __init__(self, board: CoilBoard, channels: list[Channel], *,
                 syren_ready_timeout_s: float = SYREN_READY_TIMEOUT_S,
                 windings: Windings | None = None) -> None:
        self.board = board
        self.names = [board.name]
        self.syren_ready_timeout_s = syren_ready_timeout_s
        self.channels = channels  # `board_channels`
        # the coils the run's winding model watches, heated by the drive the board applies
        # (no current is measured: the SyRens drive a voltage)
        self.windings = windings
        self.measured = np.zeros(len(self.channels))

    @classmethod
    def connect(cls, rig: RigConfig, *, syren_ready_timeout_s: float = SYREN_READY_TIMEOUT_S
                ) -> BoardActuators:
        """Open the rig's [board] and handshake (the coils stay off); Disconnected or DeviceError
        naming the board if it cannot be opened."""
        from rigctl.rigs.coil_board.settings import coil_board_rig

        rig = coil_board_rig(rig)  # a run's `connect` is handed the rig as a RigConfig
        if rig.board is None:
            raise ConfigError("the rig has no [board] table: it is not a coil board")
        return cls(CoilBoard.from_settings(rig.board), board_channels(rig),
                   syren_ready_timeout_s=syren_ready_timeout_s, windings=Windings.of_board(rig.board))

    def energise(self) -> None:
        """Wait until the board reports its SyRen drivers ready (SYREN_READY), which it does once
        their start-up is over; DeviceTimeout naming the board if that takes longer than
        `syren_ready_timeout_s`."""
        deadline = time.monotonic() + self.syren_ready_timeout_s
        while not self.board.status().syren_ready:
            if time.monotonic() > deadline:
                raise DeviceTimeout("the board never reported its SyRen drivers ready "
                                    f"(SYREN_READY) within {self.syren_ready_timeout_s:g} s",
                                    device=self.board.name)
            time.sleep(0.05)  # a bounded poll of the board's own state, not of a server

    def cycle(self, setpoints: np.ndarray) -> np.ndarray:
        """One SET of the four drives (integers within +-max_command: anything else is refused
        with LimitError before it is sent, never rounded); returns what the board's ACK reports
        applied (4,), zeros after an e-stop whatever was asked."""
        ack = self.board.set([float(v) for v in setpoints])
        self.measured[:] = self.board.applied(ack)
        return self.measured

    def emergency_zero(self) -> list[str]:
        """E-stop from any thread: STOP at once, latched (only zeros are sent after it). Never
        raises; the board's name if the STOP could not be written (then its watchdog zeroes the
        coils within 200 ms of the last frame)."""
        return [] if self.board.emergency_stop() else [self.board.name]

    def zero_now(self) -> None:
        """On the stream thread after an e-stop: STOP again and wait for its ACK, best effort."""
        try:
            self.board.stop()
        except RigError as err:
            log.error("e-stop: %s", err)

    def stop(self, ramp_s: float) -> list[str]:
        """Stop the coils (at once whatever `ramp_s`, see the module docstring) and close the
        link. Never raises; the board's name unless its STOP ACK reported every output zero."""
        confirmed = False
        try:
            ack = self.board.stop()
            confirmed = all(v == 0 for v in ack.outputs)
            if not confirmed:
                log.error("%s: STOP answered with outputs %s", self.board.name, list(ack.outputs))
        except RigError as err:
            log.error("safe stop: %s", err)
        except Exception:  # the safe end must reach close() and report, whatever went wrong
            log.exception("%s: safe stop failed", self.board.name)
        try:
            self.board.close()
        except Exception:
            log.exception("%s: close failed", self.board.name)
        return [] if confirmed else [self.board.name]
