"""What a rig kind tells the fault campaign (`rigctl faults`, `rigctl.apps.faults`) about itself.

The campaign is the same for every rig: start the kind's emulated bench, ask its backdoor which
faults it has, inject each at each phase of a short run and watch the emulator's truth until every
device is safe. What differs per kind is small and lives with the kind, as a `FaultProfile` its
`RigKind.faults` builds: the short plan, when its devices drive and when they are safe (read from
the bench's `truth`, never from rigctl), what suspends a run, the quick campaign's cells, and how
to put the bench back where the plan starts. Kept here, below the applications, so that a kind
builds its profile without importing them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rigctl.core.config import RigConfig

STREAM_PROCESS = "stream process"
"""The device of the daemon's own faults (SIGKILL and SIGSTOP of its stream process)."""
POLL_S = 0.01


@dataclass(frozen=True)
class Fault:
    """One fault: a bench device's backdoor kind (with its arguments), or a signal to the
    daemon's stream process; `clear` is what ends it (a backdoor kind, or "SIGCONT")."""

    device: str
    kind: str
    args: tuple[tuple[str, Any], ...] = ()
    clear: str | None = "restore"

    @property
    def label(self) -> str:
        return f"{self.device}:{self.kind}"


def _as_is(truth: dict) -> dict:
    return truth


@dataclass(frozen=True)
class FaultProfile:
    """What differs per rig kind: its short plan (a plan document), the rig file the campaign runs
    it with (`tune`), when its devices drive something and when they are safe (the emulator's
    `truth`), what "safe" means in words, what suspends a run (a fault that holds the field: None
    where the rig has nothing that suspends), the quick campaign's cells, how to put the bench back
    where the plan starts (`reset`, given what has `request`: a backdoor), and the part of the
    truth that shows a device not safe (`unsafe_detail`)."""

    plan: Callable[[], dict]
    driving: Callable[[dict], bool]
    safe: Callable[[dict], bool]
    safe_means: str
    suspend_with: Fault | None
    quick: tuple[tuple[str, str, str], ...]  # (path, fault label, phase) of the quick campaign
    reset: Callable[[Any], None] = lambda backdoor: None
    tune: Callable[[RigConfig], RigConfig] = lambda rig: rig
    unsafe_detail: Callable[[dict], dict] = _as_is


def wait_until(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll `condition` every `POLL_S` until it holds; TimeoutError naming `what` after
    `timeout_s` (a bench is another process: its state is only seen by asking)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(POLL_S)
