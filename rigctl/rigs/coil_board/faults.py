"""The coil board's part in the fault campaign (`rigctl faults`, `rigctl.rigs.faults`): two
particles moved 8 mm to the right in closed loop, driving while any SyRen output is not 0, safe
when every output is 0, a frozen camera to suspend a run."""

from __future__ import annotations

from rigctl.rigs.faults import Fault, FaultProfile


def quick_plan() -> dict:
    """Two particles 8 mm to the right on the board (closed loop through the camera)."""
    return {"schema": "rigctl.plan/1", "kind": "global-moves", "rig": "coil-board",
            "name": "faults: to the right",
            "workspace": {"boundary": {"disk": [0.0, 0.0, 23.0]}, "obstacles": []},
            "agents": [{"start": [-4.0, -5.0], "goal": [4.0, -5.0], "radius": 0.5},
                       {"start": [-4.0, 5.0], "goal": [4.0, 5.0], "radius": 0.5}],
            "moves": [[8.0, 0.0]], "tolerance_mm": 1.0, "min_separation_mm": 0.0}


def fault_profile() -> FaultProfile:
    return FaultProfile(
        plan=quick_plan,
        driving=lambda t: any(t["outputs"]),
        safe=lambda t: not any(t["outputs"]),
        safe_means="every SyRen output 0",
        suspend_with=Fault("camera", "freeze"),
        unsafe_detail=lambda t: {"outputs": t["outputs"]},
        quick=(("daemon", "board:stall", "moving"),))
