"""Channels: what a run commands and measures, each with its name, unit and limits.

A run describes its channels once (the actuators' own: six supply currents in A, four SyRen drive
values, fourteen joint angles in rad); the record's columns, the daemon's telemetry and the report
are typed by them, so amps, drive units and radians each say what they are. A column is named
`cmd_<name>_<unit>` / `meas_<name>_<unit>` (`cmd_X1_A`, `meas_px_drive`, `cmd_L_q3_rad`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Channel:
    """One commanded-and-measured value. `group` gathers channels drawn in one panel (a device or
    an arm); `low`/`high` are its limits in `unit` (None: none)."""

    name: str
    unit: str
    low: float | None = None
    high: float | None = None
    group: str = ""

    def column(self, prefix: str) -> str:
        return f"{prefix}_{self.name}_{self.unit}"

    def as_dict(self) -> dict:
        return asdict(self)


def channels_from_dicts(items: list[dict]) -> list[Channel]:
    return [Channel(**item) for item in items]


def symmetric(names: list[str], unit: str, limits: list[float], group: str = "") -> list[Channel]:
    """Channels of +-limit each (a bipolar supply, a motor driver)."""
    return [Channel(n, unit, -abs(lim), abs(lim), group) for n, lim in zip(names, limits)]
