"""`rigctl calibrate field --rig RIG.toml [--model mpem|loops] [--order 1|2|3]`: measure a rig's
field with its Hall probe (its kind's `RigKind.field_fit`: the six-coil rig's is
`rigctl.rigs.six_coil.field_fit`) and fit a model of it, write the calibration file and name a
calibration in the rig file, so every later run allocates with it. A kind without "field" in its
`calibrations` is refused.

`--model mpem` (the default): mag_manip's multipole model of `--order` (default 3), fitted from the
drawn loops, judged on probe sensors the fit did not see, written in mag_manip's own format
(`rigctl.physics.fields.write_mpem`, Coil_List in the rig's coil order). `--model loops`: each
coil's loop with a gain, offset and tilt, in rigctl's "rigctl-loop-v1" file.

`--model mpem` names the MPEM file in the rig (`field_calibration`), which every later run's field
model then is (`rigctl.physics.coils.field_model`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from rigctl.core.errors import EXIT_OK, ConfigError

MODELS = ("mpem", "loops")


def add_field_flags(p: argparse.ArgumentParser) -> None:
    """The `calibrate field` options (the parser is `calibrate`'s, shared with the camera)."""
    g = p.add_argument_group("field (six-coil rig with a [field_probe])")
    g.add_argument("--grid-mm", type=float, default=None, metavar="MM",
                   help="emulated bench: put its probe array on a 3 x 3 x 3 grid of +-MM about the "
                   "centre (default 100); a real probe's board says where its sensors are")
    g.add_argument("--current", type=float, default=None, metavar="A",
                   help="the patterns' current (default: half the smallest coil limit); lower it "
                   "when a probe sensor saturates (iron-core stations)")
    g.add_argument("--patterns-seed", type=int, default=0, metavar="N",
                   help="seed of the mixed current patterns and of the probe sensors held out of "
                   "the MPEM fit (default 0)")
    g.add_argument("--model", choices=MODELS, default="mpem",
                   help="mpem (default): mag_manip's multipole model, written in mag_manip's "
                   "format; loops: each coil's loop with a fitted gain, offset and tilt (rigctl-loop-v1)")
    g.add_argument("--order", type=int, choices=(1, 2, 3), default=None,
                   help="the MPEM's order, 1 (dipoles) to 3 (default 3); --model mpem only")
    g.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def _say(args: argparse.Namespace, text: str) -> None:
    if not getattr(args, "quiet", False):
        print(text, file=sys.stderr, flush=True)


def cmd_calibrate_field(args: argparse.Namespace) -> int:
    from rigctl.core.config import dump_rig, load_rig
    from rigctl.core.registry import kind_names, rig_kind
    from rigctl.physics.field_calibration import DEFAULT_GRID_HALF_MM, probe_grid_mm
    from rigctl.rigs.doctor import preflight
    from rigctl.rigs.owner import RigLock

    for flag, value in (("--plan", args.plan), ("--markers", args.markers),
                        ("--marker-radius", args.marker_radius)):
        if value is not None:
            raise ConfigError(f"{flag} is for `rigctl calibrate camera`; the field is measured "
                              "with the rig's [field_probe]")
    rig_path = Path(args.rig)
    rig = load_rig(rig_path)
    kind = rig_kind(rig.rig.kind)
    if "field" not in kind.calibrations or kind.field_fit is None:
        able = [n for n in kind_names() if "field" in rig_kind(n).calibrations]
        raise ConfigError(f"{rig_path}: field calibration is for {' or '.join(able) or 'no'} rigs; "
                          f"this one is {rig.rig.kind!r}")
    fit = kind.field_fit()
    if rig.field_probe is None:
        raise ConfigError(f"{rig_path}: the rig has no [field_probe] table (url of the Hall probe "
                          "board) to measure the field with")
    if rig.actuation_matrix_T_per_A is not None:
        raise ConfigError(f"{rig_path}: actuation_matrix_T_per_A overrides the coils' geometry; "
                          "remove it to calibrate the coils")
    model = getattr(args, "model", "mpem")
    if model != "mpem" and getattr(args, "order", None) is not None:
        raise ConfigError("--order is the MPEM's; --model loops fits each coil's loop")
    order = getattr(args, "order", None) or 3
    if model == "mpem" and not hasattr(fit, "fit_mpem_calibration"):
        raise ConfigError(f"{rig_path}: a {rig.rig.kind} rig has no MPEM fit; use --model loops")
    if args.grid_mm is not None and not args.grid_mm > 0:
        raise ConfigError(f"--grid-mm must be > 0, got {args.grid_mm:g}")
    if args.grid_mm is not None and rig.emulation is None:
        raise ConfigError("--grid-mm places the emulated bench's probe; a real probe's board says "
                          "where its sensors are")
    out = Path(args.output) if args.output else rig_path.with_name(f"{rig_path.stem}-field.yaml")
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise ConfigError(f"-o {out}: the field calibration is a YAML file (.yaml)")
    drawn = rig.model_copy(update={"field_calibration": None})
    patterns = fit.drive_patterns(drawn, seed=args.patterns_seed, current_A=args.current)
    if rig.emulation is not None:
        from rigctl.emulators.backdoor import BackdoorClient

        half = DEFAULT_GRID_HALF_MM if args.grid_mm is None else args.grid_mm
        with BackdoorClient.of(rig.emulation) as backdoor:
            backdoor.request("probe", points_mm=probe_grid_mm(half).tolist())
        _say(args, f"emulated bench: probe array on a 3 x 3 x 3 grid of +-{half:g} mm")
    with RigLock(drawn, "rigctl calibrate field"):
        preflight(drawn)
        _say(args, f"driving {len(patterns)} current patterns through the coils, reading the probe")
        measured = fit.measure(drawn, patterns, progress=lambda line: _say(args, "  " + line))
    if model == "mpem":
        return _write_mpem(args, fit, rig, drawn, measured, rig_path, out, len(patterns), order)
    calibration = fit.fit_calibration(drawn, measured)
    relative = os.path.relpath(out.resolve(), rig_path.resolve().parent)
    calibration = calibration.model_copy(update={"source": relative})
    before = fit.prediction_error(drawn, measured)
    after = fit.prediction_error(drawn.model_copy(update={"field_calibration": calibration}), measured)
    out.write_text(calibration.to_yaml())
    rig_path.write_text(dump_rig(rig.model_copy(update={"field_calibration": calibration})))
    b0 = rig.field.b0_mT * 1e-3
    result = {
        "model": "loops", "calibration": str(out), "rig": str(rig_path), "patterns": len(patterns),
        "probe_points": len(measured.points_m), "duration_s": round(measured.duration_s, 2),
        "probe_rms_error_pct_of_b0": {"drawn_coils": round(100 * before / b0, 3),
                                      "calibrated": round(100 * after / b0, 3)},
        "coils": {name: {"gain": round(c.gain, 5),
                         "offset_mm": [round(v * 1e3, 2) for v in c.offset_m],
                         "misalignment_deg": round(c.tilt_rad * 57.29577951308232, 3)}
                  for name, c in calibration.coils.items()},
    }
    if args.json:
        print(json.dumps(result))
        return EXIT_OK
    print(f"field calibrated in {measured.duration_s:.1f} s ({len(patterns)} patterns, "
          f"{len(measured.points_m)} probe points); written to {out}, named in {rig_path}")
    print(f"model vs probe, RMS over every pattern and point: drawn coils "
          f"{100 * before / b0:.2f} % of {rig.field.b0_mT:g} mT, calibrated {100 * after / b0:.3f} %")
    print(f"{'coil':6}{'gain':>9}{'offset mm':>24}{'tilt deg':>10}")
    for name, c in result["coils"].items():
        offset = ", ".join(f"{v:.1f}" for v in c["offset_mm"])
        print(f"{name:6}{c['gain']:>9.4f}{offset:>24}{c['misalignment_deg']:>10.2f}")
    return EXIT_OK


def _write_mpem(args: argparse.Namespace, fit, rig, drawn, measured, rig_path: Path, out: Path,
                patterns: int, order: int) -> int:
    """`--model mpem`: fit, judge on the held-out sensors, write mag_manip's file, name a
    calibration in the rig file (see the module docstring), report."""
    from rigctl.core.config import dump_rig
    from rigctl.physics.fields import write_mpem

    held = len(fit.held_out_split(len(measured.points_m), seed=args.patterns_seed)[1])
    _say(args, f"fitting an order-{order} MPEM of {len(rig.coils)} coils to "
         f"{len(measured.points_m) - held} probe points x {patterns} patterns ({held} points "
         "held out), from the drawn loops")
    mpem = fit.fit_mpem_calibration(drawn, measured, order=order, seed=args.patterns_seed)
    _say(args, f"fitted in {mpem.fit.duration_s:.1f} s ({mpem.fit.cpu_s:.1f} s CPU, "
         f"{mpem.fit.evaluations} evaluations)")
    write_mpem(mpem.model, out, comment=(
        f"rigctl calibrate field --model mpem --order {order}: {rig.rig.name}, "
        f"{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}\n"
        f"{patterns} patterns, {len(measured.points_m) - held} probe points fitted, {held} held "
        f"out: {mpem.held_out_mT:.4f} mT RMS ({mpem.held_out_pct:.3f} % of the mean field) there"))
    from rigctl.physics.coils import MPEMCalibration

    named = out
    relative = os.path.relpath(out.resolve(), rig_path.resolve().parent)
    calibration = MPEMCalibration(text=out.read_text(), source=relative)
    rig_path.write_text(dump_rig(rig.model_copy(update={"field_calibration": calibration})))
    result = {
        "model": "mpem", "order": order, "calibration": str(out), "rig": str(rig_path),
        "named_in_rig": str(named), "coil_list": [c.name for c in rig.coils],
        "patterns": patterns, "probe_points": len(measured.points_m),
        "fitted_points": len(mpem.fitted_points), "held_out_points": len(mpem.held_points),
        "duration_s": round(measured.duration_s, 2),
        "fit_s": round(mpem.fit.duration_s, 3), "fit_cpu_s": round(mpem.fit.cpu_s, 3),
        "fit_evaluations": mpem.fit.evaluations,
        "fit_rms_mT": round(mpem.fit.rms_T * 1e3, 5),
        "held_out": {"mpem": {"rms_mT": round(mpem.held_out_mT, 5),
                              "pct_of_mean_field": round(mpem.held_out_pct, 4)},
                     "drawn_coils": {"rms_mT": round(mpem.drawn_mT, 5),
                                     "pct_of_mean_field": round(mpem.drawn_pct, 4)}},
    }
    if args.json:
        print(json.dumps(result))
        return EXIT_OK
    print(f"field measured in {measured.duration_s:.1f} s ({patterns} patterns, "
          f"{len(measured.points_m)} probe points); order-{order} MPEM fitted in "
          f"{mpem.fit.duration_s:.1f} s ({mpem.fit.cpu_s:.1f} s CPU); written to {out} "
          "(mag_manip's format)")
    print(f"on the {held} probe points the fit did not see, RMS over every pattern: MPEM "
          f"{mpem.held_out_mT:.4f} mT ({mpem.held_out_pct:.3f} % of the mean field), drawn coils "
          f"{mpem.drawn_mT:.4f} mT ({mpem.drawn_pct:.2f} %)")
    print(f"named in {rig_path}: every run allocates with it")
    return EXIT_OK


def add_coil_error_flags(p: argparse.ArgumentParser) -> None:
    """`rigctl emulate six-coil --coil-error F --coil-seed N` (`rigctl.emulators.coil_errors`)."""
    g = p.add_argument_group("the emulated six-coil bench's coils as built")
    g.add_argument("--coil-error", type=float, metavar="F",
                   help="each coil's gain off by up to F, centre by up to F x its radius, axis by "
                   "up to F rad (default 0.05; 0: the coils are exactly as the rig file says)")
    g.add_argument("--coil-seed", type=int, metavar="N", help="seed of the coil errors (default 0)")
    g.add_argument("--probe-noise", type=float, metavar="MT",
                   help="the Hall probe's noise, RMS per axis in mT (default 0.003, an MLX90395's)")
