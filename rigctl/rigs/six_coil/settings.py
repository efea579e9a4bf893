"""The six-coil rig's file: `[rig] kind = "six-coil"` adds its tables to every rig's (`SixCoilRig`,
the kind's `settings`).

`[field]` how moves become a rotating field (seed 000 eq. 1-2), `[magnets]` the rolling magnets,
`[[coils]]` the electromagnets (three or more: the six-coil cube is one instance, an OctoMag-like
station of eight or a Navion-like one of three others) and the supplies that feed them, an optional measured
`actuation_matrix_T_per_A` or a `rigctl calibrate field` file (`field_calibration`), and the Hall
probe that calibration reads (`[field_probe]`). The tables' models are `rigctl.core.config`'s (the
emulated bench and the planners, below the rig layer, build them too); the checks of the whole,
and the calibration file (read through `rigctl.physics.field_calibration`), are here.

Units: lengths in mm, fields in mT, currents in A, voltages in V, times in s, unless a key's
name says otherwise.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from pydantic import BeforeValidator, Field, ValidationInfo, model_validator

from rigctl.core.config import Coil, FieldProbe, FieldSettings, MagnetSettings, RigConfig
from rigctl.core.errors import ConfigError
from rigctl.physics.coils import MPEMCalibration, load_calibration
from rigctl.physics.field_calibration import FieldCalibration

MIN_COILS = 3
"""Fewer coils cannot make a field in every direction at the centre."""


def _calibration_file(value, info: ValidationInfo):
    """`field_calibration = "FILE.yaml"` is read, relative to the rig file (`load_rig` says where
    it is; with no rig file, to the working directory): a mag_manip MPEM file or a
    "rigctl-loop-v1" one (`rigctl.physics.coils.load_calibration`)."""
    if not isinstance(value, (str, Path)):
        return value
    rig_dir = (info.context or {}).get("rig_dir")
    return load_calibration(str(rig_dir / value) if rig_dir is not None else value)


class SixCoilRig(RigConfig):
    """An electromagnet rig file: every rig's tables and the coils', checked together (N >= 3
    coils with distinct names, the N of every per-coil thing: supplies, channels, currents; a
    measured matrix of 3 rows, one column per coil; an MPEM calibration naming these coils)."""

    field: FieldSettings = FieldSettings()
    magnets: MagnetSettings = MagnetSettings()
    coils: list[Coil] = []
    actuation_matrix_T_per_A: list[list[float]] | None = Field(
        default=None,
        description="measured 3 x n_coils matrix at the workspace centre; overrides the geometry",
    )
    field_calibration: Annotated[FieldCalibration | MPEMCalibration | None,
                                 BeforeValidator(_calibration_file)] = Field(
        default=None, description="a field calibration file (YAML): a mag_manip MPEM file or a "
        "`rigctl calibrate field` loop file; the allocator's field model")
    field_probe: FieldProbe | None = None

    @model_validator(mode="after")
    def _n_coils(self) -> SixCoilRig:
        if len(self.coils) < MIN_COILS:
            raise ValueError(f"an electromagnet rig needs at least {MIN_COILS} [[coils]] entries "
                             f"(three independent field directions), found {len(self.coils)}")
        names = [c.name for c in self.coils]
        if len(set(names)) != len(names):
            raise ValueError(f"coil names must be unique, got {names}")
        calibration = self.field_calibration
        if isinstance(calibration, MPEMCalibration) and sorted(calibration.coil_list) != sorted(names):
            raise ValueError(f"field_calibration {calibration.source}: its Coil_List "
                             f"({', '.join(calibration.coil_list)}) must name the rig's coils "
                             f"({', '.join(names)})")
        if self.actuation_matrix_T_per_A is not None:
            rows = self.actuation_matrix_T_per_A
            if len(rows) != 3 or any(len(r) != len(self.coils) for r in rows):
                raise ValueError(
                    f"actuation_matrix_T_per_A must be 3 rows of {len(self.coils)} columns"
                )
        return self

    def toml_data(self) -> dict[str, Any]:
        """The calibration named by its file, as the rig file named it (not its data inline)."""
        data = super().toml_data()
        data.pop("field_calibration", None)
        if self.field_calibration is not None and self.field_calibration.source is not None:
            data["field_calibration"] = self.field_calibration.source
        return data

    def for_record(self) -> tuple[RigConfig, dict[str, str]]:
        """The record keeps its own copy of the calibration file, and its rig.toml names that."""
        calibration = self.field_calibration
        if calibration is None:
            return self, {}
        copy = calibration.model_copy(update={"source": "field_calibration.yaml"})
        return (self.model_copy(update={"field_calibration": copy}),
                {"field_calibration.yaml": calibration.to_yaml()})


def six_coil_rig(rig: RigConfig) -> SixCoilRig:
    """`rig` as the electromagnet rig it is (the kind's hooks are handed a `RigConfig`; a rig file
    of kind six-coil is always a `SixCoilRig`), a ConfigError if it is of another kind."""
    if not isinstance(rig, SixCoilRig):
        raise ConfigError(f"rig '{rig.rig.name}' is a {rig.rig.kind} rig, not an electromagnet rig")
    return rig
