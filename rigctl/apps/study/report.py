"""`rigctl study report`: success and error against each parameter, small multiples, to PNG.

One column of panels per parameter (x), one row per figure (success share, error). In a panel,
one line per combination of the other parameters (up to MAX_LINES; beyond that they are pooled).
Each point's interval is 95 %: for a success share, the Wilson score interval over the point's
cases (one per seed when the other parameters are fixed); for an error, the Student-t interval of
the mean over seeds (each seed's mean over its cases at the point is one sample; without seeds,
each case is one).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.errors import ConfigError

LABELS = {  # axis labels with units, for the parameters and figures the shipped studies use
    "d12": "d12 (workspace diameters)", "moves": "moves M", "slip": "slip (x distance per turn)",
    "noise": "contact noise (mm)", "drift": "drift (mm/s)", "speed-spread": "speed spread (s.d.)",
    "nn-eps": "nn-eps (approximate nearest node)", "time": "time budget (s)", "seed": "seed",
    "distance": "distance to the goal (mm)", "length": "path length (mm)",
    "fraction": "reachable fraction", "error_mm": "final error, ground truth (mm)",
    "coverage": "C-space coverage", "epsilon": "epsilon (mm)", "radius": "radius (mm)",
    "speed": "world speed (x real time)", "goal-bias": "goal bias", "k": "directions k",
}
Z95 = 1.959963984540054


def wilson(successes: int, n: int) -> tuple[float, float]:
    """95 % Wilson score interval of a share."""
    if n == 0:
        return (math.nan, math.nan)
    p = successes / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / (1 + Z95**2 / n)
    return (centre - half, centre + half)


def t_interval(samples: list[float]) -> tuple[float, float, float]:
    """(mean, low, high): the 95 % Student-t interval of the mean (low = high = mean for n = 1)."""
    from scipy.stats import t

    values = np.asarray(samples, dtype=float)
    mean = float(values.mean())
    if len(values) < 2:
        return (mean, mean, mean)
    half = float(t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / math.sqrt(len(values)))
    return (mean, mean - half, mean + half)


def _label(value: Any, width: int = 18) -> str:
    """A parameter's value as a short label: a table's values (a fault: "x+ drop_link 0.5")."""
    if isinstance(value, str) and value.startswith("{"):
        try:
            value = " ".join(str(v) for v in json.loads(value).values())
        except ValueError:
            pass
    text = "none" if value is None else str(value)
    return text if len(text) <= width else text[:width - 1] + "~"


def _key(value: Any) -> Any:
    return value if isinstance(value, (int, float, str)) or value is None else json.dumps(value)


MAX_LINES = 8


def summarise(rows: list[dict], parameter: str, figure: str, *, share: bool,
              by: Sequence[str] = ()) -> list[dict]:
    """Per value of `parameter` (and per combination of the parameters `by`, the line): n cases,
    the mean of `figure` and its 95 % interval (the module docstring); cases without it left out."""
    cells: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        if r.get(figure) is not None:
            line = tuple(_key(r.get(b)) for b in by)
            cells[(line, _key(r.get(parameter)))].append(r)
    out = []
    for line, value in sorted(cells, key=lambda k: (tuple(map(str, k[0])), isinstance(k[1], str), k[1])):
        cell = cells[(line, value)]
        values = [float(r[figure]) for r in cell]
        if share:
            mean = float(np.mean(values))
            low, high = wilson(round(sum(values)), len(values))
        else:
            per_seed: dict[Any, list[float]] = defaultdict(list)
            for i, r in enumerate(cell):
                per_seed[r.get("seed") if r.get("seed") is not None else f"case {i}"].append(float(r[figure]))
            mean, low, high = t_interval([float(np.mean(v)) for v in per_seed.values()])
        out.append({"line": dict(zip(by, line)), "value": value, "n": len(cell), "mean": mean,
                    "low": low, "high": high})
    return out


def report(folder: str | Path, output: str | Path) -> dict:
    """Draw the study in `folder` to PNG `output`; the numbers drawn, per figure and parameter."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rigctl.apps.study.execution import STUDY_FILE
    from rigctl.apps.study.table import read_results

    folder = Path(folder)
    try:
        meta = json.loads((folder / STUDY_FILE).read_text())
        rows = [r for r in read_results(folder).to_pylist() if r["status"] == "ok"]
    except (OSError, ValueError) as err:
        raise ConfigError(f"{folder}: not a study's results folder ({err})") from None
    if not rows:
        raise ConfigError(f"{folder}: no case has finished ok yet; nothing to draw")
    parameters = [p for p in meta["parameters"] if len({_key(r.get(p)) for r in rows}) > 1]
    if not parameters:
        parameters = ["seed"]
    figures = [(name, label, share) for name, label, share in [
        ("success", f"success ({meta['success']})", True),
        ("error", meta.get("error_label") or LABELS.get(meta["error"] or "", meta["error"]), False),
    ] if meta.get(name) and any(r.get(name) is not None for r in rows)]
    if not figures:
        raise ConfigError(f"{folder}: the study names no success or error figure to draw")
    drawn: dict[str, dict] = {}
    fig, axes = plt.subplots(len(figures), len(parameters), squeeze=False,
                             figsize=(3.6 * len(parameters) + 0.8, 3.0 * len(figures) + 0.8))
    for i, (name, label, share) in enumerate(figures):
        drawn[name] = {}
        for j, parameter in enumerate(parameters):
            ax = axes[i][j]
            others = [p for p in parameters if p != parameter]
            lines = {tuple(_key(r.get(p)) for p in others) for r in rows}
            by = others if len(lines) <= MAX_LINES else []
            stats = summarise(rows, parameter, name, share=share, by=by)
            drawn[name][parameter] = stats
            values = sorted({s["value"] for s in stats}, key=lambda v: (isinstance(v, str), v))
            numeric = all(isinstance(v, (int, float)) for v in values)
            position = {v: (v if numeric else i) for i, v in enumerate(values)}
            for line in dict.fromkeys(json.dumps(s["line"], sort_keys=True) for s in stats):
                points = [s for s in stats if json.dumps(s["line"], sort_keys=True) == line]
                xs = [position[s["value"]] for s in points]
                means = np.array([s["mean"] for s in points])
                lows = np.array([s["low"] for s in points])
                highs = np.array([s["high"] for s in points])
                tag = ", ".join(f"{k} {_label(v)}" for k, v in json.loads(line).items()) or None
                ax.errorbar(xs, means, yerr=[means - lows, highs - means], fmt="o-", capsize=3,
                            markersize=3, label=tag)
            if by and len(stats) > len(values):
                ax.legend(fontsize=7)
            elif others and not by:
                ax.set_title(f"pooled over {', '.join(others)}", fontsize=8)
            if not numeric:
                ax.set_xticks(range(len(values)), [_label(v) for v in values], rotation=20,
                              ha="right")
            if share:
                ax.set_ylim(-0.05, 1.05)
            ax.set_xlabel(LABELS.get(parameter, parameter))
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
    seeds = len({r.get("seed") for r in rows} - {None})
    fig.suptitle(f"study {meta['name']}: {meta['command']}, {len(rows)} cases ok, {seeds} seeds; "
                 "95 % intervals (success: Wilson; error: t over seeds)", fontsize=10)
    fig.tight_layout()
    fig.savefig(output, dpi=110)
    plt.close(fig)
    return {"study": meta["name"], "cases_ok": len(rows), "png": str(output), "figures": drawn}
