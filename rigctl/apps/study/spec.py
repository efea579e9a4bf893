"""A study spec (TOML): what every case runs, and the cases, as a product of parameters or a list.

    name = "rrt-solve"
    [run]                     # what each case runs
    command = "plan rrt"      # plan rrt|coverage|reachable|wall-contact|pair|depm, or execute
    args = { workspace = "ws.json", start = ["60,300", "60,250"], tuned = true, time = 5 }
    [parameters]              # the product of these (each a list of values) ...
    nn-eps = [0.0, 0.1]
    [[cases]]                 # ... or a list of cases (both: every listed case x the product)
    goal = ["330,300", "330,200"]
    [seeds]                   # the seeds, a product axis of their own: `count` (0..N-1), or `values`
    count = 20

A parameter or case key is the command's option without its dashes (`nn-eps` is `--nn-eps`); it
overrides `args`. A value `true` is a flag, a list gives the option once per item. Paths
(`workspace`, `tree`, `plan`, ...) are relative to the spec's folder. For `execute`, the keys
`slip`, `speed-spread`, `drift`, `noise`, `field-at-robots`, `world`, `firmware` set up the case's
own emulated bench, `speed` is its world's time factor, `backdoor` a list of backdoor requests
sent before the run (`{cmd = "place", ...}`), `rig.SECTION.KEY` overrides a value of its rig file,
and `fault = {device, kind, at_event = "energised", after_s = 0, n = 1}` injects a fault
through the bench's backdoor once the run record shows that event (`docs/studies.md`).

Each case has an id: a hash of what it runs (command, arguments, seed), so a study re-run with the
same spec finds the cases its results table already holds and does not run them again.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rigctl.core.errors import ConfigError

# options whose value is a file or folder: resolved against the spec's folder
PATH_OPTIONS = {"workspace", "tree", "rig", "rig-file", "sequence", "plan", "save-tree"}
# `execute` case keys that set up the case's emulated bench (`rigctl emulate` flags)
BENCH_OPTIONS = ("slip", "speed-spread", "drift", "noise", "field-at-robots", "world", "firmware",
                 "coil-error", "coil-seed")
EXECUTE_KEYS = set(BENCH_OPTIONS) | {"plan", "speed", "fault", "open-loop", "seed", "backdoor"}
# the commands a study runs, each with its default figures: (success, error) keys of its JSON
DEFAULT_FIGURES = {
    "plan rrt": ("solved", "distance"), "plan coverage": (None, "coverage"),
    "plan reachable": (None, "fraction"), "plan wall-contact": ("solved", "length"),
    "plan pair": ("solved", None), "plan depm": (None, None), "execute": ("reached", "error_mm"),
}
COMMANDS = tuple(DEFAULT_FIGURES)


@dataclass(frozen=True)
class Case:
    """One case: its parameters (for the table), the options it runs with, its seed."""

    id: str
    parameters: dict[str, Any]
    options: dict[str, Any]
    seed: int | None


@dataclass
class StudySpec:
    """A loaded study: the command, its cases (in spec order), where paths are relative to."""

    name: str
    command: str
    cases: list[Case]
    folder: Path
    success: str | None
    error: str | None
    parameter_names: list[str] = field(default_factory=list)
    error_label: str | None = None


def options_argv(options: dict[str, Any], folder: Path) -> list[str]:
    """Options as CLI arguments: `true` a flag, `false`/None left out, a list one option per item,
    paths (PATH_OPTIONS) against `folder`."""
    argv: list[str] = []
    for key, value in options.items():
        flag = f"--{key}"
        if value is True:
            argv.append(flag)
        elif value is False or value is None:
            continue
        else:
            for item in value if isinstance(value, list) else [value]:
                text = str(item)
                if key in PATH_OPTIONS:
                    text = str((folder / text).resolve())
                argv += [flag, text]
    return argv


def case_id(command: str, options: dict[str, Any]) -> str:
    """16 hex digits naming what a case runs (command and options, seed included)."""
    text = json.dumps([command, options], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _values(name: str, value: Any) -> list:
    if isinstance(value, dict) and set(value) <= {"start", "stop", "step"} and "stop" in value:
        start, stop, step = value.get("start", 0), value["stop"], value.get("step", 1)
        if not step or (stop - start) / step > 1_000_000:
            raise ConfigError(f"parameters.{name}: range start {start}, stop {stop}, step {step} is empty or too long")
        out, v = [], start
        while (v < stop) if step > 0 else (v > stop):
            out.append(round(v, 12))
            v += step
        return out
    if not isinstance(value, list) or not value:
        raise ConfigError(f"parameters.{name}: give a non-empty list of values (or {{start, stop, step}})")
    return value


def _seeds(data: Any) -> list[int | None]:
    if data is None:
        return [None]
    if isinstance(data, int) and not isinstance(data, bool):
        data = {"count": data}
    if not isinstance(data, dict) or not (set(data) <= {"count", "first", "values"}):
        raise ConfigError("seeds: give `count` (and `first`) or `values`, e.g. [seeds] count = 20")
    if "values" in data:
        values = data["values"]
        if not isinstance(values, list) or not all(isinstance(v, int) for v in values) or not values:
            raise ConfigError("seeds.values: a non-empty list of integers")
        return list(values)
    count, first = data.get("count"), data.get("first", 0)
    if not isinstance(count, int) or count < 1 or not isinstance(first, int):
        raise ConfigError(f"seeds.count: a positive integer, got {count!r}")
    return list(range(first, first + count))


def load_spec(path: str | Path) -> StudySpec:
    """Read a study spec; ConfigError naming the key when it is malformed."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not TOML: {err}") from None
    except OSError as err:
        raise ConfigError(f"{path}: {err.strerror}") from None
    return spec_from_dict(data, path.parent.resolve(), default_name=path.stem)


def spec_from_dict(data: dict, folder: Path, default_name: str = "study") -> StudySpec:
    """A study from its TOML table (paths relative to `folder`)."""
    unknown = set(data) - {"name", "run", "parameters", "cases", "seeds", "figures"}
    if unknown:
        raise ConfigError(f"unknown key(s) {', '.join(sorted(unknown))}; a study has name, run, "
                          "parameters, cases, seeds, figures")
    run = data.get("run")
    if not isinstance(run, dict) or "command" not in run:
        raise ConfigError(f"run.command: missing; one of {', '.join(COMMANDS)}")
    command = " ".join(str(run["command"]).split())
    if command not in COMMANDS:
        raise ConfigError(f"run.command: {command!r} is not one of {', '.join(COMMANDS)}")
    base = run.get("args", {})
    if not isinstance(base, dict) or set(run) - {"command", "args"}:
        raise ConfigError("run: has `command` and `args` (a table of the command's options) only")
    parameters = data.get("parameters", {})
    listed = data.get("cases", [{}])
    if not isinstance(parameters, dict) or not isinstance(listed, list) or not listed or \
            not all(isinstance(c, dict) for c in listed):
        raise ConfigError("parameters is a table of lists; cases a list of tables ([[cases]])")
    axes = {name: _values(name, value) for name, value in parameters.items()}
    seeds = _seeds(data.get("seeds"))
    figures = data.get("figures", {})
    if not isinstance(figures, dict) or set(figures) - {"success", "error", "error_label"}:
        raise ConfigError("figures: a table with `success`, `error` (names in the command's JSON) "
                          "and `error_label` (the error axis, with its unit)")
    default_success, default_error = DEFAULT_FIGURES[command]
    names = list(dict.fromkeys([*(k for c in listed for k in c), *axes]))
    cases, seen = [], set()
    for listed_case in listed:
        for combo in itertools.product(*axes.values()):
            for seed in seeds:
                params = {**listed_case, **dict(zip(axes, combo))}
                options = {**base, **params}
                if seed is not None:
                    options["seed"] = seed
                if command == "execute":
                    _check_execute(options)
                cid = case_id(command, options)
                if cid in seen:
                    raise ConfigError(f"case {params} seed {seed} is listed twice")
                seen.add(cid)
                cases.append(Case(cid, params, options, seed))
    return StudySpec(name=str(data.get("name", default_name)), command=command, cases=cases,
                     folder=folder, success=figures.get("success", default_success),
                     error=figures.get("error", default_error), parameter_names=names,
                     error_label=figures.get("error_label"))


def _check_execute(options: dict) -> None:
    if "plan" not in options:
        raise ConfigError("run.args.plan: an execute case needs the plan to run")
    for key in options:
        if key not in EXECUTE_KEYS and not key.startswith("rig."):
            raise ConfigError(f"{key}: not an option of an execute case; use "
                              f"{', '.join(sorted(EXECUTE_KEYS))} or rig.SECTION.KEY")
    requests = options.get("backdoor", [])
    if not isinstance(requests, list) or not all(isinstance(r, dict) and "cmd" in r for r in requests):
        raise ConfigError("backdoor: a list of requests, e.g. [{cmd = \"speed\", factor = 2}]")
    fault = options.get("fault")
    if fault is not None and (not isinstance(fault, dict) or not {"device", "kind"} <= set(fault)
                              or set(fault) - {"device", "kind", "at_event", "after_s", "n", "robot"}):
        raise ConfigError("fault: a table {device, kind, at_event, after_s, n, robot}, "
                          "e.g. {device = \"camera\", kind = \"freeze\", after_s = 1.0}")
