"""The optional parts of rigctl and the extra that installs each.

The core install runs `execute`, `emulate`, `daemon`, `plan`, `validate` and `report` on every
rig. What only some operators use comes with an extra: the console (`[console]`: aiohttp),
studies (`[studies]`: Dask; `[dashboard]` adds Bokeh for Dask's dashboard), `[all]` for
everything. A command whose extra is missing says which one to install, in one line (exit 2).
"""

from __future__ import annotations

from importlib.util import find_spec

from rigctl.core.errors import ConfigError

EXTRAS = {"aiohttp": "console", "distributed": "studies", "dask": "studies", "bokeh": "dashboard"}


class MissingExtra(ConfigError):
    """What asked for a part that is not installed, and the pip line that installs it."""

    def __init__(self, what: str, module: str) -> None:
        extra = EXTRAS[module]
        super().__init__(f"{what} needs rigctl's [{extra}] extra ({module} is not installed): "
                         f"pip install 'rigctl[{extra}]'")


def need(module: str, what: str) -> None:
    """Raise MissingExtra if `module` (a key of EXTRAS) is not installed."""
    if find_spec(module) is None:
        raise MissingExtra(what, module)
