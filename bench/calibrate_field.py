"""Benchmark of the six-coil field calibration (issue 17 item 2): prints one JSON object.

An emulated six-coil bench whose coils are off the rig file by `--coil-error` (gain, centre,
axis; default 5 %, `rigctl.emulators.coil_errors`) is calibrated through the whole chain, as
`rigctl calibrate field` does it (the supplies over SCPI, the Hall probe array on its own TCP
port); then, for 3 mT fields in 14 directions (the six axes and the eight body diagonals), the
currents the allocator gives with the rig file's coils ("before") and with the calibration
("after") are put through the bench's *true* coils (its backdoor's ground truth), and the field
error |B_true - B_model| / 3 mT is taken at the workspace centre (there B_model is the field asked
for), at the 27 points of the probe's grid, and at 27 random points of the same cube that the
probe never visited ("held_out"); and what the error costs a magnet rolling at the centre: the
largest departure of its distance per turn from 2 pi R and of its heading from the roll's, over
eight headings (`rolling_*`: the emulator's own world fed the true field). Goals: after calibration
below 1 % of 3 mT at the centre and at
the 27 grid points; the calibration under 60 s of emulated time.

`mpem`: on the same measurements, `rigctl calibrate field --model mpem`'s fit
(`fit_mpem_calibration`) of each order 1-3: its wall and CPU seconds (the field kernel loaded
beforehand, `kernel_load_s`, as the first fit of a process pays it once), its error on the probe
sensors held out of it and the drawn loops' there (% of the mean field), and both models' error
per ampere at the 27 random points against the bench's true coils (RMS, % of the true field's RMS).

Usage: .venv/bin/python bench/calibrate_field.py [--coil-error 0.05] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.bench import SixCoilBench
from rigctl.emulators.coil_errors import CoilErrors
from rigctl.physics.coils import actuation_matrix
from rigctl.physics.field_calibration import DEFAULT_GRID_HALF_MM, probe_grid_mm
from rigctl.physics.fields import LoopModel
from rigctl.rigs.six_coil.allocate import currents_for_field
from rigctl.rigs.six_coil.field_fit import (
    drive_patterns,
    fit_calibration,
    fit_mpem_calibration,
    measure,
    model_field,
)

B0_T = 3e-3


def target_fields() -> np.ndarray:
    """(14, 3) T: 3 mT along the six axes and the eight body diagonals."""
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    diagonals = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) / np.sqrt(3)
    return B0_T * np.concatenate([axes, diagonals])


def field_errors(model, true_maps: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """|B_true - B_model| / B0 (targets, points) for the currents `model` allocates."""
    currents = currents_for_field(actuation_matrix(model), target_fields())  # (P, n)
    true = np.einsum("kin,pn->pki", true_maps, currents)
    predicted = model_field(model, points_mm * 1e-3, currents)
    return np.linalg.norm(true - predicted, axis=-1) / B0_T


def rolling_errors(model, true_centre: np.ndarray, headings: int = 8, turns: int = 2,
                   steps_per_turn: int = 720) -> tuple[float, float]:
    """What the field error costs a rolling magnet (the emulator's own world, seed 000's rule):
    the field the allocator makes for a roll of `turns` turns in each of `headings` directions,
    through the true coils at the centre (3, n T/A), felt by one magnet far from every wall.
    (largest |distance per turn / 2 pi R - 1| in %, largest heading error in degrees)."""
    from rigctl.emulators.world.rolling import RollingMagnetWorld
    from rigctl.plans.model import GlobalInputModel
    from rigctl.plans.schema import parse_workspace
    from rigctl.plans.workspace import Workspace

    A = actuation_matrix(model)
    radius = model.magnets.radius_mm
    floor = GlobalInputModel(Workspace.from_spec(parse_workspace(
        {"boundary": {"rect": [0, 0, 1000, 1000]}})), np.array([1.0]))
    worst_distance = worst_heading = 0.0
    for heading in np.arange(headings) * 2 * np.pi / headings:
        world = RollingMagnetWorld(floor,
                                   np.array([[500.0, 500.0]]), rolling_radius_mm=radius,
                                   min_field_T=model.magnets.min_field_mT * 1e-3)
        d = np.array([np.cos(heading), np.sin(heading), 0.0])
        w = np.cross(np.cross([0.0, 0.0, 1.0], d), d)  # +-z: the rolling plane is (d, z)
        alpha = np.linspace(0.0, 2 * np.pi * turns, turns * steps_per_turn + 1)
        wanted = B0_T * (np.cos(alpha)[:, None] * d + np.sin(alpha)[:, None] * w)
        felt = currents_for_field(A, wanted) @ true_centre.T  # (steps, 3)
        world.feel(felt[0])
        start = world.positions_mm[0].copy()
        for b in felt[1:]:
            world.feel(b)
        moved = world.positions_mm[0] - start
        worst_distance = max(worst_distance, abs(np.hypot(*moved) / (2 * np.pi * radius * turns) - 1))
        off = np.arctan2(moved[1], moved[0]) - heading
        worst_heading = max(worst_heading, abs(np.degrees((off + np.pi) % (2 * np.pi) - np.pi)))
    return 100 * worst_distance, worst_heading


def per_ampere_error_pct(model, true_maps: np.ndarray, points_m: np.ndarray) -> float:
    """RMS of the model's field per ampere minus the true coils' (K, 3, n) at points (K, 3) m, as %
    of the true field's RMS."""
    per_A = model.field_and_gradient_per_ampere(points_m)[:, :-1, 0:3].transpose(0, 2, 1)
    return float(100 * np.sqrt(np.mean((per_A - true_maps) ** 2) / np.mean(true_maps**2)))


def mpem_figures(rig, measured, true_maps: np.ndarray, points_m: np.ndarray) -> dict:
    """`rigctl calibrate field --model mpem`'s fit of each order on these measurements."""
    from rigctl.physics.fields.stations import octomag_like

    started = time.perf_counter()
    octomag_like(1).field(np.zeros(3), np.zeros(8))  # loads (or compiles) the MPEM kernel
    out: dict = {"kernel_load_s": round(time.perf_counter() - started, 2),
                 "drawn_true_error_pct": round(per_ampere_error_pct(LoopModel.from_rig(rig),
                                                                    true_maps, points_m), 4)}
    for order in (1, 2, 3):
        c = fit_mpem_calibration(rig, measured, order=order)
        out[f"order_{order}"] = {
            "fit_s": round(c.fit.duration_s, 3), "fit_cpu_s": round(c.fit.cpu_s, 3),
            "evaluations": c.fit.evaluations, "held_out_pct": round(c.held_out_pct, 4),
            "drawn_held_out_pct": round(c.drawn_pct, 4),
            "true_error_pct": round(per_ampere_error_pct(c.model, true_maps, points_m), 4)}
    return out


def one_bench(size: float, seed: int) -> dict:
    grid = probe_grid_mm(DEFAULT_GRID_HALF_MM)
    held_out = np.random.default_rng(100 + seed).uniform(-DEFAULT_GRID_HALF_MM, DEFAULT_GRID_HALF_MM,
                                                         size=(27, 3))
    with SixCoilBench(coil_errors=CoilErrors(size=size, seed=seed)) as bench:
        rig = bench.rig
        with BackdoorClient(rig.emulation.backdoor) as backdoor:
            backdoor.request("probe", points_mm=grid.tolist())
            t0 = backdoor.request("truth")["sim_time_s"]
            measured = measure(rig, drive_patterns(rig))
            emulated_s = backdoor.request("truth")["sim_time_s"] - t0
            points = np.concatenate([np.zeros((1, 3)), grid, held_out])
            maps = np.array(backdoor.request("coil_fields", points_mm=points.tolist())["T_per_A"])
        calibration = fit_calibration(rig, measured)
    calibrated = rig.model_copy(update={"field_calibration": calibration})
    out = {"seed": seed, "calibration_emulated_s": round(emulated_s, 2),
           "calibration_wall_s": round(measured.duration_s, 2),
           "mpem": mpem_figures(rig, measured, maps[28:], held_out * 1e-3)}
    for label, model in (("before", rig), ("after", calibrated)):
        e = 100 * field_errors(model, maps, points)  # (targets, 1 + 27 + 27) %
        out[label] = {"centre_max_pct": round(float(e[:, 0].max()), 4),
                      "grid27_max_pct": round(float(e[:, 1:28].max()), 4),
                      "grid27_median_pct": round(float(np.median(e[:, 1:28])), 4),
                      "held_out27_max_pct": round(float(e[:, 28:].max()), 4)}
        distance, heading = rolling_errors(model, maps[0])
        out[label]["rolling_distance_per_turn_off_max_pct"] = round(distance, 3)
        out[label]["rolling_heading_off_max_deg"] = round(heading, 3)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--coil-error", type=float, default=0.05,
                        help="the bench's coil error size (default 0.05)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2],
                        help="coil-error seeds, one bench each (default 0 1 2)")
    args = parser.parse_args(argv)
    runs = []
    for seed in args.seeds:
        print(f"bench with {args.coil_error:.0%} coil errors, seed {seed}: calibrating",
              file=sys.stderr, flush=True)
        runs.append(one_bench(args.coil_error, seed))
    worst = {label: {key: max(r[label][key] for r in runs) for key in runs[0][label]}
             for label in ("before", "after")}
    print(json.dumps({
        "coil_error": args.coil_error, "b0_mT": B0_T * 1e3, "grid_half_mm": DEFAULT_GRID_HALF_MM,
        "worst": worst,
        "calibration_emulated_s_max": max(r["calibration_emulated_s"] for r in runs),
        "goals": {"after_centre_and_grid27_below_pct": 1.0, "calibration_emulated_s_below": 60.0},
        "met": bool(worst["after"]["centre_max_pct"] < 1.0 and worst["after"]["grid27_max_pct"] < 1.0
                    and max(r["calibration_emulated_s"] for r in runs) < 60.0),
        "runs": runs,
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
