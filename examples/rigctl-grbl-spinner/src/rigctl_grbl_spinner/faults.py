"""What the fault campaign (`rigctl faults`) needs of the spinner: a short plan, and when the
rotor turns and when it is at rest, read from the emulated bench's truth (never from rigctl)."""

from __future__ import annotations

SAFE_RATE_HZ = 0.001  # at rest: GRBL's reported speed is whole degrees per minute


def quick_plan() -> dict:
    """Two seconds at 2 turns/s, then one at -1 turn/s."""
    return {"schema": "rigctl.plan/1", "kind": "spin-sequence", "rig": "grbl-spinner",
            "name": "faults: spin", "segments": [{"rate_hz": 2.0, "duration_s": 2.0},
                                                 {"rate_hz": -1.0, "duration_s": 1.0}],
            "tolerance_hz": 0.1}


def fault_profile():
    from rigctl.rigs.faults import FaultProfile

    return FaultProfile(
        plan=quick_plan,
        driving=lambda t: abs(t["rate_hz"]) > 0.5,
        safe=lambda t: abs(t["rate_hz"]) < SAFE_RATE_HZ,
        safe_means="the rotor at rest",
        suspend_with=None,
        quick=(("daemon", "grbl:stall", "moving"),),
        unsafe_detail=lambda t: {"rate_hz": t["rate_hz"], "state": t["state"]})
