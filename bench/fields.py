"""Field models: how fast an MPEM evaluates and allocates, how well it fits, and whether it agrees
with ETH's mag_manip 3.0.0. Prints one JSON object.

    python bench/fields.py [--smoke] [--mag-manip-python PATH] [--file CAL.yaml ...]

- eval: field + gradient of an 8-coil octopole (order 3) MPEM with an Offset at one point
  (`MPEM.field_and_gradient`), best and median of 300 batches of 20 calls, in us (goal <= 20 us;
  on a loaded machine the best batch is the figure, the median shows the load).
- allocate: currents for field + gradient (8 DOF) at one point (`fields.allocate.allocate`),
  in us (goal <= 50 us).
- fit: an order-3 fit (`fields.fit.fit_mpem`) of a perturbed OctoMag-like truth from a 4 x 4 x 4
  probe grid (60 mm cube) and 22 current patterns with 0.05 mT of probe noise, started from the
  drawing: seconds (wall and CPU), and the error on 40 held-out points x 5 held-out current vectors in mT and %
  of the mean field, against the noisy probe and against the truth, and the drawing's error.
- mag_manip: where a Python with mag_manip is found (`--mag-manip-python`, else
  $RIGCTL_MAG_MANIP_PYTHON, else .venv-mag-manip/bin/python), a file rigctl writes (the octopole
  station with an extra A source per coil, orders 1-3, and the Offset) and every `--file` are
  evaluated there (`tools/mag_manip_eval.py`, one file per process) and here: the largest
  difference relative to the largest value, field and gradient apart, and mag_manip's time per
  evaluation in the same run. Without mag_manip: why not.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rigctl.physics.fields import MPEM, Source, load_mpem, write_mpem  # noqa: E402
from rigctl.physics.fields.allocate import allocate  # noqa: E402
from rigctl.physics.fields.fit import fit_mpem, held_out_error  # noqa: E402
from rigctl.physics.fields.stations import octomag_like  # noqa: E402

NOISE_T = 0.05e-3
POINT = np.array([0.004, -0.003, 0.002])


def timed_us(call, batches: int, per_batch: int) -> dict:
    call()
    times = []
    for _ in range(batches):
        started = time.perf_counter()
        for _ in range(per_batch):
            call()
        times.append((time.perf_counter() - started) / per_batch * 1e6)
    return {"best_us": round(min(times), 2), "median_us": round(statistics.median(times), 2)}


def speed(batches: int, per_batch: int) -> dict:
    model = octomag_like(3, seed=1)
    currents = np.linspace(-3.0, 4.0, 8)
    field_b, gradient_g = np.array([5e-3, 0.0, 2e-3]), np.array([0.05, 0.0, 0.0, -0.02, 0.0])
    return {
        "eval": {"coils": 8, "order": 3, "offset": True,
                 **timed_us(lambda: model.field_and_gradient(POINT, currents), batches, per_batch)},
        "allocate_8dof": timed_us(lambda: allocate(model, POINT, field_b,
                                                   gradient_T_per_m=gradient_g,
                                                   current_limits_A=20.0), batches, per_batch),
    }


def probe(truth: MPEM, points: np.ndarray, currents: np.ndarray, rng) -> np.ndarray:
    fields = np.stack([truth.field(points, i) for i in currents])
    return fields if rng is None else fields + rng.normal(0.0, NOISE_T, fields.shape)


def fit_figures(order: int, per_axis: int) -> dict:
    truth, drawing = octomag_like(order, seed=7), octomag_like(order)
    rng = np.random.default_rng(0)
    ticks = np.linspace(-0.03, 0.03, per_axis)
    z, y, x = np.meshgrid(ticks, ticks, ticks, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    patterns = np.concatenate([5 * np.eye(8), -5 * np.eye(8), rng.uniform(-5, 5, (6, 8))])
    start = MPEM(drawing.coil_names, [[Source(s.position_m, s.direction, "B", (0.0,))]
                                      for (s,) in drawing.coil_sources])
    fit = fit_mpem(points, patterns, probe(truth, points, patterns, rng), start, order=order)
    held_points = rng.uniform(-0.03, 0.03, (40, 3))
    held_currents = rng.uniform(-5, 5, (5, 8))
    noisy = probe(truth, held_points, held_currents, rng)
    exact = probe(truth, held_points, held_currents, None)
    mT, pct = held_out_error(fit.model, held_points, held_currents, noisy)
    return {"order": order, "probe_points": len(points), "patterns": len(patterns),
            "seconds": round(fit.duration_s, 3), "cpu_seconds": round(fit.cpu_s, 3),
            "evaluations": fit.evaluations,
            "rms_fitted_mT": round(fit.rms_T * 1e3, 4),
            "held_out_mT": round(mT, 4), "held_out_pct": round(pct, 3),
            "held_out_vs_truth_pct": round(held_out_error(fit.model, held_points, held_currents,
                                                          exact)[1], 3),
            "drawing_held_out_pct": round(held_out_error(drawing, held_points, held_currents,
                                                         noisy)[1], 3)}


def mag_manip_python(arg: str | None) -> str | None:
    for candidate in (arg, os.environ.get("RIGCTL_MAG_MANIP_PYTHON"),
                      str(ROOT / ".venv-mag-manip" / "bin" / "python")):
        if candidate and Path(candidate).exists():
            return candidate
    return None


def rigctl_written_model() -> MPEM:
    """The octopole station with an A source (orders 1-3) added to every coil: both kinds and
    every order go through mag_manip."""
    base = octomag_like(3, seed=2)
    rng = np.random.default_rng(9)
    coils = [list(sources) + [Source(tuple(rng.uniform(-0.05, 0.05, 3)),
                                     tuple(rng.normal(size=3)), "A",
                                     tuple(rng.uniform(-1, 1) * 1e-4 * 10.0**k for k in range(3)))]
             for sources in base.coil_sources]
    return MPEM(base.coil_names, coils, base.offset_sources, name="rigctl-written",
                workspace_m=base.workspace_m)


def compare(python: str, path: Path, repeat: int) -> dict:
    """One file in mag_manip (its own process) against rigctl."""
    model = load_mpem(path)
    rng = np.random.default_rng(4)
    lo = np.array([pair[0] for pair in model.workspace_m])
    hi = np.array([pair[1] for pair in model.workspace_m])
    points = rng.uniform(lo, hi, (6, 3))
    currents = rng.uniform(-5, 5, (3, model.n_coils))
    request = {"points_m": points.tolist(), "currents_A": currents.tolist(), "repeat": repeat}
    done = subprocess.run([python, str(ROOT / "tools" / "mag_manip_eval.py"), str(path)],
                          input=json.dumps(request), capture_output=True, text=True, timeout=300)
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else
                f"exit {done.returncode}"}
    theirs = json.loads(done.stdout)
    mm_u = np.array(theirs["field_gradient5"])  # (points, currents, 8)
    ours_u = np.stack([[model.actuation(p) @ i + model.offset(p) for i in currents]
                       for p in points])
    mm_a = np.array(theirs["actuation"])
    ours_a = model.actuation(points)

    def rel(ours: np.ndarray, theirs: np.ndarray) -> dict:
        """Largest |difference| over the largest |value|, U's field and gradient rows apart
        (last axis)."""
        return {name: float(np.max(np.abs(ours[..., rows] - theirs[..., rows]))
                            / np.max(np.abs(theirs[..., rows])))
                for name, rows in (("field", slice(0, 3)), ("gradient", slice(3, 8)))}

    u_rel = rel(ours_u, mm_u)
    a_rel = rel(ours_a.transpose(0, 2, 1), mm_a.transpose(0, 2, 1))
    return {"coils": theirs["coils"], "offset": model.has_offset, "max_order": model.max_order,
            "max_rel_diff_field_gradient": u_rel, "max_rel_diff_actuation": a_rel,
            "agrees_1e-9": max(*u_rel.values(), *a_rel.values()) <= 1e-9,
            "mag_manip_eval_us": theirs["eval_us"]}


def mag_manip_figures(python: str | None, files: list[str], repeat: int) -> dict:
    if python is None:
        return {"available": False,
                "reason": "no Python with mag_manip: make one with `python3 -m venv "
                          ".venv-mag-manip && .venv-mag-manip/bin/pip install 'numpy<2' "
                          "mag-manip==3.0.0` (mag_manip 3.0.0 is built against numpy 1.x)"}
    out: dict = {"available": True, "python": python, "files": {}}
    with tempfile.TemporaryDirectory() as tmp:
        written = Path(tmp) / "rigctl_written.yaml"
        write_mpem(rigctl_written_model(), written, comment="written by rigctl bench/fields.py")
        out["files"]["rigctl_written"] = compare(python, written, repeat)
    for name in files:
        out["files"][name] = compare(python, Path(name), repeat)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true",
                        help="every stage once, tiny (an order-1 fit, few repeats)")
    parser.add_argument("--mag-manip-python", help="a Python that imports mag_manip 3.0.0")
    parser.add_argument("--file", action="append", default=[],
                        help="also compare this mag_manip calibration file (repeatable)")
    args = parser.parse_args()
    # many short batches: on a shared machine the best of them is the unloaded figure
    batches, per_batch = (3, 50) if args.smoke else (300, 20)
    figures = {"load_average": [round(v, 2) for v in os.getloadavg()]}
    figures.update(speed(batches, per_batch))
    figures["fit"] = fit_figures(1, 3) if args.smoke else fit_figures(3, 4)
    figures["mag_manip"] = mag_manip_figures(mag_manip_python(args.mag_manip_python), args.file,
                                             3 if args.smoke else 20)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
