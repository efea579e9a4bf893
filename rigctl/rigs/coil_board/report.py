"""What `rigctl report` draws differently for the coil board: its drive panel's title, and its
records from before channels had units, whose SyRen drive values were written as amps."""

from __future__ import annotations

from pathlib import Path

from rigctl.core.channels import Channel
from rigctl.rigs.base import ReportHooks

DEFAULT_MAX_COMMAND = 127  # the SyRen's full scale, the [board] table's default


def old_channels(channels: list[Channel], run_dir: Path) -> list[Channel]:
    """A record whose channels all say amps with no limit and no group (written before channels
    had units): the board's drive values, limited by its rig file's `max_command`."""
    if not all(c.unit == "A" and c.low is None and not c.group for c in channels):
        return channels
    limit = _max_command(run_dir)
    return [Channel(c.name, "drive", -limit, limit, "board") for c in channels]


def _max_command(run_dir: Path) -> float:
    import tomllib

    try:
        rig = tomllib.loads((run_dir / "rig.toml").read_text())
        return float(rig.get("board", {}).get("max_command", DEFAULT_MAX_COMMAND))
    except (OSError, ValueError):  # tomllib.TOMLDecodeError is a ValueError
        return float(DEFAULT_MAX_COMMAND)


REPORT = ReportHooks(group_titles={"board": "coil board drive (SyRen)"}, old_channels=old_channels)
