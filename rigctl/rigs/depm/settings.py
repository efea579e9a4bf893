"""The dual-EPM rig's file: `[rig] kind = "depm"` adds its `[depm]` table, the two arms, their
magnets, the Hall board and the safety limits (`DepmRig`, the kind's `settings`).

Units: mm, degrees, A m^2, mT, seconds, unless a key's name says otherwise.
"""

from __future__ import annotations

from rigctl.core.config import DepmSettings, RigConfig


class DepmRig(RigConfig):
    """A dual-EPM rig file: every rig's tables and `[depm]` (None: a rig file without one, which
    the kind's runs, hold and probes refuse)."""

    depm: DepmSettings | None = None
