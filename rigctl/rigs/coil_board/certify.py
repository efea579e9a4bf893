"""The coil board's pre-flight checks (`rigctl.run.certificate`). A coil-board run is closed loop: a
move lasts until the camera sees it done, so its currents are not known before it starts. What is
known bounds it: the drive of a move against the board's range; every coil at that drive for the
longest run the settings allow (`max_moves` x `move_timeout_s`), the winding heated by V^2 / R(T)
(the SyRens put a share of their supply on the coil); the host link at its baud rate and the SyRen
bus at 9600 baud per stream cycle; the plan's size and the run's longest duration."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from rigctl.core.transport import parse_url
from rigctl.drivers.coilboard_frame import (
    ACK,
    MIN_FRAME_BYTES,
    REPLY_PAYLOAD_BYTES,
    REQUEST_PAYLOAD_BYTES,
    SET,
)
from rigctl.physics.thermal import Windings, step_voltage, voltage_steady_C
from rigctl.plans.schema import MAX_DURATION_S
from rigctl.run.certificate import Check, ceiling, link_checks, serial_seconds, size_checks

if TYPE_CHECKING:
    from rigctl.rigs.coil_board.settings import CoilBoardRig

SYREN_BAUD = 9600  # firmware/coilboard/syren.h
SYREN_PACKET_BYTES = 4  # address, command, data, checksum (SyRen packetized serial)


def drive_for_limit(w: Windings, supply_V: float, max_command: int) -> int:
    """The largest drive (1..max_command) whose steady winding temperature stays below every
    winding's limit (0 if none)."""
    best = 0
    for drive in range(1, max_command + 1):
        if (voltage_steady_C(np.full(len(w.names), supply_V * drive / 127), w) < w.limit_C).all():
            best = drive
    return best


def board_checks(rig: CoilBoardRig, settings, n_moves: int) -> list[Check]:
    """Every check of a coil-board run with `settings` (`CoilBoardRunSettings`; its rate_hz None:
    the rig file's `[board] rate_hz`) of a plan of `n_moves` moves."""
    board = rig.board
    assert board is not None
    rate_hz = settings.rate_hz or board.rate_hz
    checks = [ceiling("drive", "every coil", settings.drive, board.max_command, "SyRen units",
                      "a move's stronger coil; the board refuses more")]
    w = Windings.of_board(board)
    volts = np.full(len(w.names), settings.drive * w.volts_per_unit)
    longest = settings.max_moves * settings.move_timeout_s
    temperature = np.array(w.ambient_C, dtype=float)
    step = float(w.time_constant_s.min()) / 200
    for _ in range(int(np.ceil(longest / step))):
        temperature = step_voltage(temperature, volts, step, w)
    steady = voltage_steady_C(volts, w)
    for j, name in enumerate(w.names):
        if temperature[j] < w.limit_C[j]:
            detail = (f"{settings.drive}/127 of {board.supply_V:g} V held {longest:.0f} s "
                      f"(max_moves x move_timeout_s); steady {steady[j]:.1f} C")
        else:
            detail = (f"at drive {settings.drive} a coil held on for the run's longest "
                      f"{longest:.0f} s passes {w.limit_C[j]:.0f} C; a drive of at most "
                      f"{drive_for_limit(w, board.supply_V, board.max_command)} (board.max_command) "
                      "never does")
        checks.append(ceiling("winding temperature", f"coil {name}", temperature[j],
                              w.limit_C[j], "C", detail))
    scheme, _, baud = parse_url(board.url)
    baud = baud if scheme == "serial" and "baud=" in board.url else board.baud
    host_bytes = 2 * MIN_FRAME_BYTES + REQUEST_PAYLOAD_BYTES[SET] + REPLY_PAYLOAD_BYTES[ACK]
    checks += link_checks({f"host link ({baud} baud, SET + ACK)": serial_seconds(host_bytes, baud)},
                          rate_hz)
    # the firmware refreshes the SyRens on its own: the bus must keep up with the SETs, no more
    bus = serial_seconds(len(board.coil_names) * SYREN_PACKET_BYTES, SYREN_BAUD)
    checks += link_checks({f"SyRen bus ({SYREN_BAUD} baud, a packet per coil)": bus},
                          rate_hz, share=1.0)
    checks += size_checks(n_moves, settings.max_moves, longest, MAX_DURATION_S, unit="moves")
    return checks
