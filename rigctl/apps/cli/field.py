"""`rigctl field SOURCE --at X,Y,Z ...`: the field an electromagnet rig makes at a point, or the
currents for a field it should make.

SOURCE is a rig file (its coils and the field calibration it names) or a calibration file on its
own (mag_manip's MPEM YAML, or rigctl's older "rigctl-loop-v1"). Points are in mm in the rig's
frame, currents in A in the order of the model's coils (the rig file's [[coils]], the calibration
file's Coil_List), fields in mT, gradients in mT/m. A rig file's coils bring their current limits;
a calibration file alone has none unless `--max-current` gives one.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from rigctl.core.config import CoilRig
from rigctl.core.errors import EXIT_OK, ConfigError, PlanError


def _numbers(text: str, flag: str, count: int | None, unit: str) -> np.ndarray:
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v != ""]
    except ValueError:
        values = []
    if not values or (count is not None and len(values) != count):
        want = f"{count} numbers" if count else "numbers"
        raise PlanError(f"{flag}: expected {want} in {unit} separated by commas, got {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise PlanError(f"{flag}: every number must be finite, got {text!r}")
    return np.array(values)


def _model(source: str):
    """(FieldModel, per-coil current limits or None, what it is) of a rig file or a calibration
    file."""
    from rigctl.physics.coils import field_model
    from rigctl.physics.fields import load_field_model

    path = Path(source)
    if not path.is_file():
        raise ConfigError(f"field: {source} is not a file (a rig file .toml or a calibration file "
                          ".yaml)")
    if path.suffix.lower() == ".toml":
        from rigctl.core.config import load_rig

        rig = load_rig(path)
        if not isinstance(rig, CoilRig) or not rig.coils:
            raise ConfigError(f"field: {source} is a {rig.rig.kind} rig: it has no coils whose "
                              "field rigctl models")
        return (field_model(rig), np.array([c.current_limit_A for c in rig.coils]),
                f"rig {rig.rig.name!r}")
    return load_field_model(path), None, f"calibration {path.name}"


def _cmd_field(args: argparse.Namespace) -> int:
    from rigctl.physics.fields.allocate import allocate

    point_m = _numbers(args.at, "--at", 3, "mm") * 1e-3
    model, limits, what = _model(args.source)
    if args.max_current is not None:
        if not (math.isfinite(args.max_current) and args.max_current > 0):
            raise PlanError(f"--max-current: must be a positive number of A, got {args.max_current}")
        limits = np.full(model.n_coils, args.max_current)
    if (args.currents is None) == (args.want_field is None):
        raise PlanError("field: give --currents I1,...,IN (the field they make) or --want-field "
                        "BX,BY,BZ (the currents that make it), one of them")
    if args.want_gradient is not None and args.want_field is None:
        raise PlanError("--want-gradient needs --want-field (the field at the same point)")
    if args.currents is not None:
        currents = _numbers(args.currents, "--currents", model.n_coils, "A")
        if limits is not None and np.any(np.abs(currents) > limits * (1 + 1e-9)):
            k = int(np.argmax(np.abs(currents) / limits))
            raise PlanError(f"--currents: {currents[k]:g} A in coil {model.coil_names[k]} is beyond "
                            f"its limit of {limits[k]:g} A")
    else:
        field_T = _numbers(args.want_field, "--want-field", 3, "mT") * 1e-3
        gradient = (None if args.want_gradient is None
                    else _numbers(args.want_gradient, "--want-gradient", 5, "mT/m") * 1e-3)
        currents = allocate(model, point_m, field_T, gradient_T_per_m=gradient,
                            current_limits_A=limits).currents_A
    field_T, gradient_T = model.field_and_gradient(point_m, currents)
    from rigctl.physics.fields import GRADIENT_TERMS
    from rigctl.physics.magnetics import gradient_terms

    result = {"source": what, "point_mm": (point_m * 1e3).tolist(), "coils": list(model.coil_names),
              "currents_A": currents.tolist(), "field_mT": (field_T * 1e3).tolist(),
              "gradient_mT_per_m": (gradient_T * 1e3).tolist(),
              "gradient_terms": list(GRADIENT_TERMS),
              "gradient_terms_mT_per_m": (gradient_terms(gradient_T) * 1e3).tolist()}
    if args.json:
        print(json.dumps(result))
        return EXIT_OK
    x, y, z = result["point_mm"]
    print(f"{what}, at ({x:g}, {y:g}, {z:g}) mm")
    print("  currents (A):  " + ", ".join(f"{n} {i:.4g}" for n, i in zip(model.coil_names, currents)))
    b = result["field_mT"]
    print(f"  field (mT):    [{b[0]:.5g}, {b[1]:.5g}, {b[2]:.5g}]   |B| = {np.linalg.norm(b):.5g}")
    print("  gradient (mT/m), rows d/dx d/dy d/dz of Bx By Bz:")
    for row in result["gradient_mT_per_m"]:
        print("    [" + ", ".join(f"{v:10.5g}" for v in row) + "]")
    print("  independent terms (" + ", ".join(GRADIENT_TERMS) + "): ["
          + ", ".join(f"{v:.5g}" for v in result["gradient_terms_mT_per_m"]) + "] mT/m")
    sys.stdout.flush()
    return EXIT_OK


def register_field(sub) -> None:
    p = sub.add_parser(
        "field", help="the field (mT) and gradient an electromagnet rig makes at a point, or the "
        "currents for a wanted field",
        description="The field and gradient at a point for given currents, or the minimum-norm "
        "currents that make a wanted field (and gradient: 8 coils or more), within the coils' "
        "current limits. SOURCE: a rig file, or a calibration file alone (mag_manip's MPEM YAML "
        "or rigctl-loop-v1).",
        epilog="Example: rigctl field cal.yaml --at 0,0,0 --want-field 0,0,10 --max-current 8")
    p.add_argument("source", metavar="SOURCE", help="rig file (.toml) or calibration file (.yaml)")
    p.add_argument("--at", required=True, metavar="X,Y,Z", help="the point, mm, in the rig's frame")
    p.add_argument("--currents", metavar="I1,...,IN",
                   help="the coils' currents, A, in the model's coil order")
    p.add_argument("--want-field", metavar="BX,BY,BZ", help="the field wanted at the point, mT")
    p.add_argument("--want-gradient", metavar="G1,...,G5",
                   help="with --want-field: the five gradient terms dBx/dx, dBx/dy, dBx/dz, "
                   "dBy/dy, dBy/dz, mT/m")
    p.add_argument("--max-current", type=float, metavar="A",
                   help="every coil's current limit, A (a rig file's coils bring their own)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=_cmd_field)
