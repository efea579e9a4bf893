"""What a run does on an emulated bench: place the agents (the workspace sent to another
process), read ground truth through the bench's backdoor."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rigctl.emulators.backdoor import BackdoorClient
from rigctl.errors import RigError
from rigctl.plans.schema import Plan


def portable_workspace(plan: Plan) -> dict:
    """The plan's workspace as JSON for another process: an image path made absolute."""
    workspace = plan.workspace.model_dump(mode="json", exclude_none=True)
    if "image" in workspace and plan.base_dir is not None:
        workspace["image"] = str((Path(plan.base_dir) / workspace["image"]).resolve())
    return workspace



def truth_of(backdoor: BackdoorClient | None) -> np.ndarray:
    if backdoor is None:
        raise RigError("no emulator backdoor", device="bench backdoor")
    return np.array(backdoor.request("truth")["agents"], dtype=float)


