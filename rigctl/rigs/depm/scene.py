"""What the console's "arms" scene draws of a dual-EPM rig: each arm's name and base pose, the
keep-out sphere and the EPMs' size, from the rig file's [depm] table. The console turns the arms'
measured joints into the sketch itself (`rigctl.apps.console.scene.ArmsSketch`)."""

from __future__ import annotations

from rigctl.core.config import RigConfig


def arms_scene(rig: RigConfig) -> dict:
    """{"arms": [{"name", "position_mm" (3,), "rpy_deg" (3,)}], "keep_out_mm", "epm_radius_mm"};
    no arms for a rig file without a [depm] table."""
    depm = rig.depm
    if depm is None:
        return {"arms": [], "keep_out_mm": 0.0, "epm_radius_mm": 0.0}
    return {"arms": [{"name": name, "position_mm": list(position), "rpy_deg": list(rpy)}
                     for name, position, rpy in zip(depm.arm_names, depm.arm_positions_mm,
                                                    depm.arm_rpy_deg)],
            "keep_out_mm": float(depm.keep_out_radius_mm),
            "epm_radius_mm": float(depm.epm_radius_mm)}
