"""The six-coil rig's part in the fault campaign (`rigctl faults`, `rigctl.rigs.faults`): two
magnets moved twice (plans/examples/fig4-quick.json), driving while any coil carries over 0.5 A,
safe when every coil current is under 50 mA, a frozen camera to suspend a run."""

from __future__ import annotations

import json
from importlib.resources import files

from rigctl.core.config import RigConfig
from rigctl.rigs.faults import STREAM_PROCESS, Fault, FaultProfile

SAFE_CURRENT_A = 0.05
DRIVING_CURRENT_A = 0.5


def quick_plan() -> dict:
    """Two magnets, two moves (about 5 s of streaming): plans/examples/fig4-quick.json."""
    return json.loads((files("rigctl.plans") / "examples" / "fig4-quick.json").read_text())


def _tune(rig: RigConfig) -> RigConfig:
    # a watchdog that tolerates a loaded machine: a run faulted by a scheduling gap says nothing
    # about the fault injected (a dropped link still stops it at once, a stalled one in 0.5 s)
    return rig.model_copy(update={"stream": rig.stream.model_copy(update={"reply_timeout_s": 0.5})})


def fault_profile() -> FaultProfile:
    return FaultProfile(
        plan=quick_plan,
        driving=lambda t: max(abs(c) for c in t["currents_A"].values()) > DRIVING_CURRENT_A,
        safe=lambda t: all(abs(c) < SAFE_CURRENT_A for c in t["currents_A"].values()),
        safe_means="every coil current under 50 mA",
        suspend_with=Fault("camera", "freeze"),
        tune=_tune,
        unsafe_detail=lambda t: {"currents_A": t["currents_A"]},
        quick=(("daemon", "x+:drop_link", "before"), ("daemon", "x+:stall", "moving"),
               ("daemon", "x+:overtemp", "paused"), ("daemon", "camera:drop_link", "suspended"),
               ("daemon", f"{STREAM_PROCESS}:sigkill", "moving"),
               ("daemon", f"{STREAM_PROCESS}:sigstop", "moving"),
               ("execute", "camera:freeze", "moving")))
