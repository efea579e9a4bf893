"""mag_manip's MPEM calibration files: read exactly as mag_manip 3.0 reads them, written so that
it loads them.

The layout (mag_manip `ElectromagnetCalibration::loadCalibration`; SI units):

    System_Name: OctoMag                      # a string
    Workspace_Dimensions: [[xmin, xmax], [ymin, ymax], [zmin, zmax]]    # m
    Coil_List: [Coil_0, ..., Coil_7, Offset]  # the currents' order; any name containing
                                              # "Offset" is the current-independent field
    Coil_0:
      Source_List: [Src_0, Src_1]
      Src_0:
        A_Coeff: ~                            # both keys present, exactly one null (~): mag_manip
                                              # refuses a missing key as "both defined"
        B_Coeff: [b1, b2, b3]                 # orders 1, 2, 3 (`rigctl.physics.fields.mpem`)
        Source_Direction: [x, y, z]           # normalised on reading; must not be zero
        Source_Position: [x, y, z]            # m

Other keys are ignored, as mag_manip ignores them. Where mag_manip would accept a file and then
misbehave, this reader refuses it instead, with one line naming the key (ConfigError): a zero or
non-finite source direction (mag_manip aborts the whole process), two coils named *Offset*
(mag_manip keeps the last one silently), an empty coefficient list, a workspace whose min
exceeds its max. Files in rigctl's older loop layout (`Calibration_Model: rigctl-loop-v1`,
`rigctl.physics.field_calibration`) are read as a `LoopModel` by `load_field_model`.
"""

from __future__ import annotations

import math
from pathlib import Path

import yaml

from rigctl.core.errors import ConfigError
from rigctl.physics.fields.model import FieldModel
from rigctl.physics.fields.mpem import MPEM, Source

OFFSET_MARK = "Offset"
"""mag_manip takes every Coil_List entry whose name contains this as the offset pseudo-coil."""

_TOP_KEYS = ("System_Name", "Workspace_Dimensions", "Coil_List")


def _numbers(value: object, count: int | None, where: str) -> list[float]:
    if not isinstance(value, list) or (count is not None and len(value) != count) or not value:
        size = f"{count} numbers" if count else "a non-empty list of numbers"
        raise ConfigError(f"{where}: must be {size}, got {value!r}")
    out = []
    for item in value:
        if isinstance(item, str):  # PyYAML (YAML 1.1) reads 1e-07 as a string; yaml-cpp a number
            try:
                item = float(item)
            except ValueError:
                pass
        if isinstance(item, bool) or not isinstance(item, (int, float)) or not math.isfinite(item):
            raise ConfigError(f"{where}: {item!r} is not a finite number")
        out.append(float(item))
    return out


def _source(node: object, where: str) -> Source:
    if not isinstance(node, dict):
        raise ConfigError(f"{where}: must be a mapping with A_Coeff, B_Coeff, Source_Direction "
                          "and Source_Position")
    for key in ("A_Coeff", "B_Coeff"):
        if key not in node:  # mag_manip takes a missing key for a given one: "both defined"
            raise ConfigError(f"{where}.{key}: missing (write ~ for the one not used)")
    a, b = node["A_Coeff"], node["B_Coeff"]
    if a is not None and b is not None:
        raise ConfigError(f"{where}: both A_Coeff and B_Coeff are given; exactly one must be null")
    if a is None and b is None:
        raise ConfigError(f"{where}: A_Coeff and B_Coeff are both null or missing; one must list "
                          "the coefficients")
    kind, key = ("A", "A_Coeff") if a is not None else ("B", "B_Coeff")
    coefficients = _numbers(node[key], None, f"{where}.{key}")
    if "Source_Direction" not in node:
        raise ConfigError(f"{where}.Source_Direction: missing")
    if "Source_Position" not in node:
        raise ConfigError(f"{where}.Source_Position: missing")
    direction = _numbers(node["Source_Direction"], 3, f"{where}.Source_Direction")
    if math.hypot(*direction) == 0.0:
        raise ConfigError(f"{where}.Source_Direction: the zero vector has no direction")
    position = _numbers(node["Source_Position"], 3, f"{where}.Source_Position")
    return Source((position[0], position[1], position[2]), (direction[0], direction[1], direction[2]),
                  kind, tuple(coefficients))


def _workspace(data: dict, source: str) -> list[list[float]]:
    """Workspace_Dimensions: [[xmin, xmax], [ymin, ymax], [zmin, zmax]] in m."""
    workspace = data["Workspace_Dimensions"]
    if not isinstance(workspace, list) or len(workspace) != 3:
        raise ConfigError(f"{source}: Workspace_Dimensions: must be [[xmin, xmax], [ymin, ymax], "
                          f"[zmin, zmax]] in m, got {workspace!r}")
    bounds = [_numbers(pair, 2, f"{source}: Workspace_Dimensions[{i}]")
              for i, pair in enumerate(workspace)]
    for axis, (lo, hi) in zip("xyz", bounds):
        if lo > hi:
            raise ConfigError(f"{source}: Workspace_Dimensions: {axis}min {lo} > {axis}max {hi}")
    return bounds


def _coil_sources(data: dict, tag: str, source: str) -> list[Source]:
    """The sources of one Coil_List entry, in its Source_List order."""
    coil = data.get(tag)
    if not isinstance(coil, dict):
        raise ConfigError(f"{source}: {tag}: Coil_List names it, but the file has no mapping "
                          "for it")
    tags = coil.get("Source_List")
    if not isinstance(tags, list) or not tags:
        raise ConfigError(f"{source}: {tag}.Source_List: must list the coil's sources")
    sources = []
    for src in tags:
        if str(src) not in coil:
            raise ConfigError(f"{source}: {tag}.{src}: Source_List names it, but {tag} does "
                              "not describe it")
        sources.append(_source(coil[str(src)], f"{source}: {tag}.{src}"))
    return sources


def parse_mpem(data: object, source: str = "MPEM calibration") -> MPEM:
    """An MPEM from the mapping a mag_manip calibration file holds (ConfigError naming the key)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: not a YAML mapping")
    for key in _TOP_KEYS:
        if key not in data:
            raise ConfigError(f"{source}: {key}: missing")
    name = data["System_Name"]
    if not isinstance(name, (str, int, float)) or isinstance(name, bool):
        raise ConfigError(f"{source}: System_Name: must be a string, got {name!r}")
    bounds = _workspace(data, source)
    names = data["Coil_List"]
    if not isinstance(names, list) or not names:
        raise ConfigError(f"{source}: Coil_List: must list the coils")
    coils, offset, seen = [], None, set()
    for entry in names:
        tag = str(entry)
        if tag in seen:
            raise ConfigError(f"{source}: Coil_List: {tag} is listed twice")
        seen.add(tag)
        sources = _coil_sources(data, tag, source)
        if OFFSET_MARK in tag:
            if offset is not None:
                raise ConfigError(f"{source}: {tag}: a second Offset coil (after {offset[0]}); "
                                  "mag_manip would silently keep only the last")
            offset = (tag, sources)
        else:
            coils.append((tag, sources))
    if not coils:
        raise ConfigError(f"{source}: Coil_List: lists only the Offset, no coil")
    return MPEM([t for t, _ in coils], [s for _, s in coils], offset[1] if offset else (),
                name=str(name), workspace_m=bounds)


def _read_yaml(path: Path, what: str) -> object:
    try:
        return yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist") from None
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{what} {path}: cannot be read as YAML: "
                          f"{str(err).splitlines()[0]}") from None


def load_mpem(path: str | Path) -> MPEM:
    """Read a mag_manip MPEM calibration file (ConfigError: missing, not YAML, malformed)."""
    path = Path(path)
    return parse_mpem(_read_yaml(path, "MPEM calibration"), str(path))


def load_field_model(path: str | Path) -> FieldModel:
    """A field model from a calibration file: MPEM (mag_manip's layout), or a `LoopModel` from
    a "rigctl-loop-v1" file (its coils in its Coil_List order)."""
    from rigctl.physics.field_calibration import FORMAT, parse_field_calibration
    from rigctl.physics.fields.loops import LoopModel

    path = Path(path)
    data = _read_yaml(path, "field calibration")
    if isinstance(data, dict) and data.get("Calibration_Model") == FORMAT:
        return LoopModel.from_calibration(parse_field_calibration(data, str(path)))
    return parse_mpem(data, str(path))


def _source_node(s: Source) -> dict:
    coefficients = [float(c) for c in s.coefficients]
    return {"A_Coeff": coefficients if s.kind == "A" else None,
            "B_Coeff": coefficients if s.kind == "B" else None,
            "Source_Direction": [float(v) for v in s.direction],
            "Source_Position": [float(v) for v in s.position_m]}


def mpem_to_yaml(model: MPEM, comment: str = "") -> str:
    """The model as a mag_manip calibration file (floats written to round-trip exactly)."""
    clash = [n for n in model.coil_names if OFFSET_MARK in n or n in _TOP_KEYS]
    if clash:
        raise ConfigError(f"coil name {clash[0]!r} cannot be written: mag_manip would read it as "
                          "the Offset or a top-level key")
    data: dict = {"System_Name": model.name,
                  "Workspace_Dimensions": [list(pair) for pair in model.workspace_m],
                  "Coil_List": list(model.coil_names) + ([OFFSET_MARK] if model.has_offset else [])}
    entries = list(zip(model.coil_names, model.coil_sources))
    if model.has_offset:
        entries.append((OFFSET_MARK, model.offset_sources))
    for tag, sources in entries:
        node: dict = {"Source_List": [f"Src_{k}" for k in range(len(sources))]}
        for k, s in enumerate(sources):
            node[f"Src_{k}"] = _source_node(s)
        data[tag] = node
    head = "".join(f"# {line}\n" for line in comment.splitlines())
    return head + yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)


def write_mpem(model: MPEM, path: str | Path, comment: str = "") -> None:
    Path(path).write_text(mpem_to_yaml(model, comment))
