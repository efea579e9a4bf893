"""The installed rig kinds: whatever registers a `rigctl.rigs.base.RigKind` under the entry-point
group `rigctl.rigs`.

The three rigs of the papers register there exactly as an outside package would (pyproject.toml:
`six-coil = "rigctl.rigs.six_coil:KIND"`), so the core, the CLI and the daemon find a rig kind by
asking this module, never by importing one by name. The group is loaded on first use and kept:
`rigctl --help` loads no rig kind. A broken entry point (a package that fails to import, an object
that is not a RigKind) is reported in one line naming it, on the log and in the error of a lookup
of that name, and does not hide the kinds that load.
"""

from __future__ import annotations

import logging
from importlib.metadata import entry_points
from typing import Any

from rigctl.core.errors import ConfigError

RigKind = Any  # a rigctl.rigs.base.RigKind: the rig layer's class, above the core, not imported

log = logging.getLogger(__name__)

GROUP = "rigctl.rigs"
DEFAULT_GROUP = "rigctl.default"  # one entry: the kind commands use when not told one

_loaded: tuple[dict[str, RigKind], dict[str, str]] | None = None  # (kinds, broken name -> why)


def _load() -> tuple[dict[str, RigKind], dict[str, str]]:
    """Every entry point of the group, loaded once: the kinds by name, and why each broken one is."""
    global _loaded
    if _loaded is None:
        found: dict[str, RigKind] = {}
        broken: dict[str, str] = {}
        for point in entry_points(group=GROUP):
            try:
                kind = point.load()
            except Exception as err:  # any import error of a lab's package: said, not raised
                broken[point.name] = f"{point.value} does not load: {type(err).__name__}: {err}"
            else:
                # a RigKind's class is the rig layer's (rigctl.rigs.base), above this one: what
                # the registry can check is that the object answers to its entry point's name
                if not isinstance(getattr(kind, "name", None), str):
                    broken[point.name] = f"{point.value} is a {type(kind).__name__}, not a RigKind"
                elif kind.name != point.name:
                    broken[point.name] = f"{point.value} is the rig kind {kind.name!r}"
                else:
                    found[point.name] = kind
                    continue
            log.warning("rig kind %s (entry point %s): %s", point.name, GROUP, broken[point.name])
        _loaded = dict(sorted(found.items())), broken
    return _loaded


def kinds() -> dict[str, RigKind]:
    """The installed rig kinds by name, sorted by name."""
    return dict(_load()[0])


def kind_names() -> list[str]:
    """The installed rig kinds' names, sorted: the CLI's choices."""
    return list(_load()[0])


def entry_point_names() -> list[str]:
    """The names registered in the group, sorted, without loading any rig kind's code: what
    `rigctl emulate --help` may list."""
    return sorted({point.name for point in entry_points(group=GROUP)})


def default_kind() -> str:
    """The kind a command uses when it is not told one (`rigctl daemon` without `--rig` or
    `--bench`, `rigctl plan rrt` without `--rig`): the one the entry-point group `rigctl.default`
    points at (rigctl's own: the seed papers' six-coil rig), found by its value among the rig
    kinds' entry points, so no kind's code is loaded."""
    rigs = {point.value: point.name for point in entry_points(group=GROUP)}
    for point in entry_points(group=DEFAULT_GROUP):
        if point.value in rigs:
            return rigs[point.value]
    names = entry_point_names()
    if not names:
        raise ConfigError("no rig kind is installed (entry points rigctl.rigs): reinstall rigctl")
    return names[0]


def rig_kind(name: str) -> RigKind:
    """The rig kind `name`; ConfigError naming the installed kinds (or why `name` is broken)."""
    found, broken = _load()
    try:
        return found[name]
    except KeyError:
        pass
    if name in broken:
        raise ConfigError(f"rig kind {name!r} is installed but broken: {broken[name]}")
    installed = ", ".join(found) or "none"
    raise ConfigError(f"rig kind {name!r} is not installed; the installed kinds are {installed}")
