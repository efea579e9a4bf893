"""Benchmark of the coil-board rig, PLANNER PART ONLY (plans/wall_contact.py); prints ONE JSON object.

Issue 6 asks this script also for the protocol round trip and command rate over the pty for both
emulators, and the command rate of a 115200-baud link; those parts are not built yet and appear
here as null.

Planner: random start/goal pairs (1 mm particles, radius 0.5 mm, epsilon 0.01 mm) in five
workspaces sized like the paper's rig (a 50 mm square, a 46 mm disk, an acute and an obtuse
triangle, a hexagon of 25 mm circumradius). Per workspace:
- planner_ms: Alg. 1 time per solve (median, p95, max), the 50 ms goal of issue 6;
- total_ms: the same plus the replay through the non-slip model that fills `expected`
  (and any re-planning from the model's state);
- delivered: share of pairs whose model replay ends within epsilon for both particles;
- moves and path length (mm): median and max.

Usage: python bench/coilboard.py [--pairs N] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time

import numpy as np

from rigctl.plans.model import GlobalInputModel
from rigctl.plans.wall_contact import centre_region, plan_with_model
from rigctl.plans.workspace import ShapeWorkspace

RADIUS_MM = 0.5
EPSILON_MM = 0.01

_HEXAGON = tuple((25.0 * math.cos(a), 25.0 * math.sin(a)) for a in np.arange(6) * math.pi / 3)
WORKSPACES = {
    "square": {"rect": [0.0, 0.0, 50.0, 50.0]},
    "disk": {"disk": [0.0, 0.0, 23.0]},
    "acute_triangle": {"polygon": [[0.0, 0.0], [50.0, 0.0], [20.0, 40.0]]},
    "obtuse_triangle": {"polygon": [[0.0, 0.0], [60.0, 0.0], [5.0, 15.0]]},
    "hexagon": {"polygon": [list(v) for v in _HEXAGON]},
}


def _shape(boundary: dict) -> tuple:
    (kind, value), = boundary.items()
    return (kind, tuple(map(tuple, value)) if kind == "polygon" else tuple(value))


def _pair(ws: ShapeWorkspace, rng: np.random.Generator) -> np.ndarray:
    while True:
        points = ws.sample_free(rng, 2, RADIUS_MM + 0.05)
        if np.hypot(*(points[1] - points[0])) > 2 * RADIUS_MM + 0.05:
            return points


def _summary(values: list[float], digits: int = 3) -> dict:
    ordered = sorted(values)
    p95 = ordered[min(len(ordered) - 1, int(math.ceil(0.95 * len(ordered))) - 1)]
    return {"median": round(statistics.median(ordered), digits), "p95": round(p95, digits),
            "max": round(ordered[-1], digits)}


def bench_workspace(boundary: dict, pairs: int, rng: np.random.Generator) -> dict:
    ws = ShapeWorkspace(_shape(boundary))
    region = centre_region(boundary, RADIUS_MM)
    model = GlobalInputModel(ws, [RADIUS_MM, RADIUS_MM], "non-slip")
    planner_ms, total_ms, moves, lengths, delivered = [], [], [], [], 0
    for _ in range(pairs):
        starts, goals = _pair(ws, rng), _pair(ws, rng)
        started = time.perf_counter()
        result, chosen, planner_s = plan_with_model(model, region, starts, goals, EPSILON_MM)
        total_ms.append(1e3 * (time.perf_counter() - started))
        planner_ms.append(1e3 * float(planner_s))
        end = model.rollout(starts, result.moves)[-1] if len(result.moves) else starts
        delivered += bool(np.all(np.hypot(*(end - chosen).T) <= EPSILON_MM))
        moves.append(len(result.moves))
        lengths.append(result.length)
    return {
        "pairs": pairs,
        "delivered": delivered / pairs,
        "planner_ms": _summary(planner_ms),
        "total_ms": _summary(total_ms),
        "moves": {"median": statistics.median(moves), "max": max(moves)},
        "length_mm": _summary(lengths, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=100, help="start/goal pairs per workspace")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    planner = {name: bench_workspace(b, args.pairs, rng) for name, b in WORKSPACES.items()}
    print(json.dumps({
        "benchmark": "coilboard",
        "python": platform.python_version(),
        "radius_mm": RADIUS_MM,
        "epsilon_mm": EPSILON_MM,
        "planner": planner,
        "protocol_round_trip_ms": None,  # emulators not built yet (issue 6 items 4-6)
        "command_rate_hz": None,
        "link_115200_rate_hz": None,
    }))


if __name__ == "__main__":
    main()
