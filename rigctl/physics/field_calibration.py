"""A six-coil rig's field calibration: each coil's fitted loop, as a file a lab can reuse.

The rig file describes each coil as a circular loop (`centre_mm`, `axis`, `loop_radius_mm`,
`turns`); a real coil is never where the drawing puts it, nor as strong. A calibration
(`rigctl calibrate field`, `rigctl.rigs.six_coil.field_fit`) measures the field with a Hall
probe and fits, per coil, a gain (field per ampere x g), an offset of the loop's centre and the
misalignment of its axis. The allocator then takes its actuation matrix from the fitted loops
(`rigctl.physics.coils`) whenever the rig file names the calibration (`field_calibration = "FILE.yaml"`).

File format: YAML in the layout of ETH MSRL's mag_manip / Tesla calibration files (SI units,
a `Coil_List` naming one top-level mapping per coil), because that is the format the magnetic
manipulation community already exchanges; the per-coil entries are this rig's loop model (centre,
axis, radius, turns, gain) rather than mag_manip's multipole coefficients, so any Biot-Savart loop
code reproduces the field, and `Actuation_Matrix` (3 x n, T/A at the workspace centre) serves a
lab that only wants the linear map there. Unknown keys are refused: a misspelt key is an error.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from rigctl.core.errors import ConfigError

FORMAT = "rigctl-loop-v1"
"""`Calibration_Model`: which per-coil model the file holds (a reader checks it)."""


class CoilFit(BaseModel):
    """One coil's fitted loop (SI units) and the fit's one-sigma uncertainties."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    centre_m: tuple[float, float, float] = Field(alias="Loop_Centre")
    axis: tuple[float, float, float] = Field(alias="Loop_Axis")
    radius_m: float = Field(gt=0, alias="Loop_Radius")
    turns: int = Field(gt=0, alias="Turns")
    gain: float = Field(gt=0, alias="Gain", description="field per ampere x this")
    offset_m: tuple[float, float, float] = Field(
        alias="Offset", description="fitted centre minus the rig file's centre")
    tilt_rad: float = Field(ge=0, alias="Misalignment",
                            description="angle between the fitted axis and the rig file's")
    sigma: dict[str, float] = Field(default_factory=dict, alias="Sigma",
                                    description="one-sigma of gain, offset (m) and tilt (rad)")


class FieldCalibration(BaseModel):
    """A whole calibration file; `source` is where it was read from (not in the file)."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    name: str = Field(alias="Calibration_Name")
    model: str = Field(default=FORMAT, alias="Calibration_Model")
    workspace_m: tuple[float, float, float, float, float, float] = Field(
        alias="Workspace_Dimensions", description="xmin, xmax, ymin, ymax, zmin, zmax of the probe")
    coil_list: list[str] = Field(alias="Coil_List")
    coils: dict[str, CoilFit]
    actuation_matrix: list[list[float]] = Field(alias="Actuation_Matrix")
    fit: dict = Field(default_factory=dict, alias="Fit",
                      description="residuals, patterns, probe points, duration")
    source: str | None = Field(default=None, exclude=True)

    def coil(self, name: str) -> CoilFit:
        try:
            return self.coils[name]
        except KeyError:
            raise ConfigError(f"field calibration {self.source or self.name} has no coil {name!r} "
                              f"(it has {', '.join(self.coil_list)})") from None

    def to_yaml(self) -> str:
        data: dict[str, Any] = {"Calibration_Name": self.name, "Calibration_Model": self.model,
                "Workspace_Dimensions": list(self.workspace_m), "Coil_List": list(self.coil_list)}
        for name in self.coil_list:
            data[name] = self.coils[name].model_dump(by_alias=True, mode="json")
        data["Actuation_Matrix"] = self.actuation_matrix
        data["Fit"] = self.fit
        head = ("# rigctl field calibration (rigctl calibrate field); mag_manip-style layout, SI "
                "units.\n# Per coil: the fitted loop (centre m, unit axis, radius m, turns) whose "
                "field per ampere\n# is Gain x that of the loop; Actuation_Matrix is T/A at the "
                "workspace centre.\n")
        return head + yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)


def parse_field_calibration(data: object, source: str = "field calibration") -> FieldCalibration:
    """A calibration from the mapping a YAML file holds (ConfigError naming what is wrong)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: not a YAML mapping")
    data = dict(data)
    names = data.get("Coil_List")
    if not isinstance(names, list) or not names:
        raise ConfigError(f"{source}: Coil_List must list the coils")
    missing = [n for n in names if n not in data]
    if missing:
        raise ConfigError(f"{source}: Coil_List names {', '.join(map(str, missing))}, which the "
                          "file does not describe")
    data["coils"] = {n: data.pop(n) for n in names}
    try:
        calibration = FieldCalibration.model_validate({**data, "source": source})
    except ValidationError as err:
        problem = err.errors()[0]
        where = ".".join(str(p) for p in problem["loc"])
        raise ConfigError(f"{source}: {where}: {problem['msg']}") from None
    if calibration.model != FORMAT:
        raise ConfigError(f"{source}: Calibration_Model {calibration.model!r}; this rigctl reads "
                          f"{FORMAT!r}")
    return calibration


def load_field_calibration(path: str | Path) -> FieldCalibration:
    """Read a calibration file (ConfigError: missing, not YAML, or not a calibration)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"field calibration {path} does not exist") from None
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"field calibration {path}: cannot be read as YAML: "
                          f"{str(err).splitlines()[0]}") from None
    return parse_field_calibration(data, str(path))


def fitted_loops(calibration: FieldCalibration, names: list[str]
                 ) -> list[tuple[np.ndarray, np.ndarray, float, int, float]]:
    """(centre m, unit axis, radius m, turns, gain) of each coil in `names` order."""
    out = []
    for name in names:
        c = calibration.coil(name)
        axis = np.asarray(c.axis, dtype=float)
        out.append((np.asarray(c.centre_m, dtype=float), axis / np.linalg.norm(axis), c.radius_m,
                    c.turns, c.gain))
    return out


DEFAULT_GRID_HALF_MM = 100.0
"""The probe grid's half width: +-100 mm about the centre, the middle of the 400 mm floor the
rolling magnets use (the coils' windings are 150 mm beyond)."""


def probe_grid_mm(half_width_mm: float = DEFAULT_GRID_HALF_MM, per_axis: int = 3) -> np.ndarray:
    """The probe's grid: `per_axis`^3 points (x fastest) spanning +-half_width_mm, shape (n, 3);
    with an odd `per_axis` the centre is one of them."""
    ticks = np.linspace(-half_width_mm, half_width_mm, per_axis)
    z, y, x = np.meshgrid(ticks, ticks, ticks, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
