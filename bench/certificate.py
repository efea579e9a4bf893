"""Benchmark: the pre-flight certificate of the longest example plan of each rig (the issue's goal:
under 1 s), the winding model's speed, and how well it follows the emulated windings. Prints one
JSON object.

- `rigs`: for each rig kind, its longest example plan (six-coil: the longest program of its
  global-moves and pair plans), the time to build its run with no I/O (`build_ms`: plan checks,
  realize, allocate, and the certificate) and the certificate's own checks (`certificate_ms`),
  the least of `--repeat` tries; the number of checks and the verdict. The coil board's run
  needs a calibrated camera to be built, so its figure is the board's checks alone
  (`rigctl.rigs.coil_board.certify.board_checks`, what its program's `checks()` calls).
- `winding_model`: one hour of six currents at 100 Hz through the vectorised model
  (`winding_temperatures`) and through the step-by-step loop (`step_current`) in the same run:
  both times and their ratio, and the largest difference between the two.
- `model_vs_emulator`: the emulated BOP windings (R_th and C_th 5 % off) stepped by hand through
  `--minutes` of a current program changing every 15 s, against the model on the rig file's data:
  the largest difference (the issue: within 2 K over ten minutes).

    python bench/certificate.py                       # about a minute
    python bench/certificate.py --quick               # seconds
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from rigctl.core.config import (
    CoilBoardSettings,
    CoilThermal,
    Emulation,
    RigConfig,
    RigInfo,
    default_six_coil_coils,
)
from rigctl.emulators.bench import emulated_winding
from rigctl.emulators.depm import default_settings as depm_settings
from rigctl.emulators.kepco_bop.model import BopCoilModel
from rigctl.physics.thermal import Windings, step_current, winding_temperatures
from rigctl.plans.schema import load_plan
from rigctl.rigs import rig_kind
from rigctl.rigs.coil_board.settings import CoilBoardRig
from rigctl.rigs.depm.settings import DepmRig
from rigctl.rigs.six_coil.settings import SixCoilRig
from rigctl.run.certificate import certify

EXAMPLES = Path(__file__).resolve().parents[1] / "plans" / "examples"


def least(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return round(best * 1e3, 2), out


def six_coil_longest(rig: RigConfig) -> tuple[str, object]:
    """The six-coil example plan with the longest program on `rig`."""
    longest, name = -1.0, ""
    for path in sorted(EXAMPLES.glob("*.json")):
        document = json.loads(path.read_text())
        if not isinstance(document, dict) or document.get("rig") != "six-coil" \
                or "broken" in path.name:  # a workspace file; the deliberately broken example
            continue
        plan = load_plan(path)
        if plan.rig != "six-coil":
            continue
        run = rig_kind("six-coil").builder(plan.kind)(plan, rig, runs_dir="runs", closed_loop=False)
        if run.program.duration_s > longest:
            longest, name = run.program.duration_s, path.name
    return name, load_plan(EXAMPLES / name)


def bench_plan_run(kind: str, rig: RigConfig, plan, repeat: int, **options) -> dict:
    build = rig_kind(kind).builder(plan.kind)
    build_ms, run = least(lambda: build(plan, rig, runs_dir="runs", **options), repeat)
    certificate_ms, checks = least(run.program.checks, repeat)
    return {"plan_duration_s": round(run.program.duration_s, 2), "build_ms": build_ms,
            "certificate_ms": certificate_ms, "checks": len(checks),
            "passed": run.certificate.passed}


def bench_rigs(repeat: int) -> dict:
    from rigctl.rigs.coil_board.certify import board_checks
    from rigctl.rigs.coil_board.run import CoilBoardRunSettings

    out = {}
    six = SixCoilRig(rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils())
    name, plan = six_coil_longest(six)
    out["six-coil"] = {"plan": name, **bench_plan_run("six-coil", six, plan, repeat,
                                                      closed_loop=False)}
    # as `rigctl emulate depm` writes it: real arms are refused until the arm model is corrected
    depm = DepmRig(rig=RigInfo(kind="depm"), depm=depm_settings(),
                   emulation=Emulation(backdoor="tcp://127.0.0.1:1"))
    out["depm"] = {"plan": "depm-plan.json",
                   **bench_plan_run("depm", depm, load_plan(EXAMPLES / "depm-plan.json"), repeat)}
    board = CoilBoardRig(rig=RigInfo(kind="coil-board"), board=CoilBoardSettings(url="/dev/pts/0"))
    plan = load_plan(EXAMPLES / "coilboard-disk.json")
    ms, checks = least(lambda: board_checks(board, CoilBoardRunSettings(), len(plan.moves)), repeat)
    out["coil-board"] = {"plan": "coilboard-disk.json", "certificate_ms": ms,
                         "checks": len(checks), "passed": certify(board, plan.kind, "", checks).passed,
                         "note": "the board's checks alone (its run needs a calibrated camera)"}
    return out


def bench_winding_model(seconds: float) -> dict:
    rig = SixCoilRig(rig=RigInfo(kind="six-coil"), coils=default_six_coil_coils())
    w = Windings.of_coils(rig.coils)
    currents = np.random.default_rng(1).uniform(-20, 20, (int(seconds * 100), 6))
    t0 = time.perf_counter()
    scanned = winding_temperatures(currents, 0.01, w)
    vector_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    temperature, worst = w.ambient_C.copy(), 0.0
    for k in range(len(currents)):
        temperature = step_current(temperature, currents[k], 0.01, w)
        worst = max(worst, float(np.abs(temperature - scanned[k + 1]).max()))
    loop_s = time.perf_counter() - t0
    return {"samples": len(currents), "coils": 6, "vectorised_ms": round(vector_s * 1e3, 1),
            "step_loop_ms": round(loop_s * 1e3, 1), "loop_over_vectorised": round(loop_s / vector_s, 1),
            "max_difference_K": worst}


def bench_model_vs_emulator(minutes: float) -> dict:
    thermal = CoilThermal(thermal_resistance_K_per_W=0.5, thermal_capacity_J_per_K=1500.0,
                          ambient_C=22.0, max_winding_C=150.0, warning_C=140.0)
    coils = [c.model_copy(update={"thermal": thermal}) for c in default_six_coil_coils()]
    supplies = [BopCoilModel(c.resistance_ohm, c.inductance_H, **emulated_winding(c, 0.05))
                for c in coils]
    levels = np.random.default_rng(11).uniform(-14.0, 14.0, (int(minutes * 4) + 1, 6))
    dt, per_sample = 0.002, 5
    samples, truth = [], []
    for supply in supplies:
        supply.set_output(True)
    for k in range(int(minutes * 60 / (dt * per_sample))):
        for supply, amps in zip(supplies, levels[int(k * dt * per_sample // 15.0)]):
            supply.set_current(float(amps))
        samples.append([s.current_A for s in supplies])
        for _ in range(per_sample):
            for supply in supplies:
                supply.step(dt)
        truth.append([s.winding_C for s in supplies])
    model = winding_temperatures(np.array(samples), dt * per_sample, Windings.of_coils(coils))[1:]
    truth = np.array(truth)
    return {"emulated_minutes": minutes, "emulator_parameters_off": 0.05,
            "max_rise_K": round(float(truth.max() - 22.0), 2),
            "max_model_error_K": round(float(np.abs(model - truth).max()), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="tries per figure (the least counts)")
    parser.add_argument("--quick", action="store_true",
                        help="one try, 1 minute of model samples, 1 emulated minute")
    args = parser.parse_args()
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    repeat = 1 if args.quick else args.repeat
    load_before = round(os.getloadavg()[0], 2)
    out = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                       "load_average_1min_before": load_before},
           "goal_certificate_s": 1.0, "rigs": bench_rigs(repeat),
           "winding_model": bench_winding_model(60.0 if args.quick else 3600.0),
           "model_vs_emulator": bench_model_vs_emulator(1.0 if args.quick else 10.0)}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
