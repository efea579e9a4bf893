"""Benchmark: how long the `rigctl` command takes to answer what needs none of its commands'
modules, against the floor of starting Python at all, measured in the same run. Prints one JSON
object.

- `floor`: `python -c pass` (the interpreter's own start, site-packages included);
- `version`: `rigctl --version`; `help`: `rigctl --help` (issue 38's goal: at most 0.3 s);
- `command_help`: `rigctl execute --help`, which builds the whole parser (every command's module
  imported): what `--help` cost before the top level was answered on its own.

Each is the median wall time of `--runs` starts (s), and `over_floor` the median less the floor's.
The command is the installed console script beside this interpreter (`rigctl`), else `python -m
rigctl` (`how` says which). Wall times on a shared machine: `load` is the load average at the end.

    python bench/cli.py               # 15 starts of each, about 15 s
    python bench/cli.py --smoke       # one of each
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

HELP_GOAL_S = 0.3  # issue 38: `rigctl --help` within 0.3 s


def rigctl_command() -> tuple[list[str], str]:
    """The console script beside this interpreter, else `python -m rigctl`."""
    script = Path(sys.executable).parent / "rigctl"
    if script.exists():
        return [str(script)], "console script"
    return [sys.executable, "-m", "rigctl"], "python -m rigctl"


def wall_s(argv: list[str], runs: int) -> list[float]:
    """Wall seconds of `runs` starts of argv, each run to its end (output discarded; exit 0)."""
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True,
                       env={**os.environ, "COLUMNS": "100"})
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=15, help="starts of each command (median)")
    parser.add_argument("--smoke", action="store_true", help="one start of each")
    args = parser.parse_args()
    runs = 1 if args.smoke else args.runs
    if runs < 1:
        parser.error("--runs must be at least 1")
    rigctl, how = rigctl_command()
    floor = statistics.median(wall_s([sys.executable, "-c", "pass"], runs))
    figures: dict = {"runs": runs, "how": how, "floor": {"median_s": round(floor, 4)}}
    for name, argv in (("version", ["--version"]), ("help", ["--help"]),
                       ("command_help", ["execute", "--help"])):
        median = statistics.median(wall_s([*rigctl, *argv], runs))
        figures[name] = {"argv": ["rigctl", *argv], "median_s": round(median, 4),
                         "over_floor_s": round(median - floor, 4)}
    figures["help"]["goal_s"] = HELP_GOAL_S
    figures["help"]["within_goal"] = figures["help"]["median_s"] <= HELP_GOAL_S
    figures["load"] = [round(v, 2) for v in os.getloadavg()]
    figures["python"] = platform.python_version()
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
