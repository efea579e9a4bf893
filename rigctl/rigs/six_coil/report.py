"""What `rigctl report` draws differently for the six-coil rig: its supplies' panel title (a
record from before channels had groups has the coil currents, in amps, in no group)."""

from __future__ import annotations

from rigctl.rigs.base import ReportHooks

SUPPLIES = "coil currents (six supplies)"
REPORT = ReportHooks(group_titles={"supplies": SUPPLIES, "": SUPPLIES})
