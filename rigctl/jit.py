"""numba's `njit`, with its on-disk cache where the install allows one.

Compiled kernels are cached in the first writable directory of: `$NUMBA_CACHE_DIR` (the user's
choice), `$CACHE_DIRECTORY` (systemd's, from the unit's `CacheDirectory=rigctl`),
`$XDG_CACHE_HOME/rigctl` or `~/.cache/rigctl`. With none of them writable (a read-only install and
home) the kernels are compiled in memory, in every process, instead of dying at import: numba's
`cache=True` raises when it finds no writable place. This is decided once, when this module is
imported, before numba is: numba reads `NUMBA_CACHE_DIR` when `numba.core.config` is imported
(and again, only when a `NUMBA_` variable changed, when the compiler calls `reload_config`), and
it picks a kernel's cache directory when the kernel is decorated. Child processes inherit the
setting through the environment.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping


def cache_dir(environ: Mapping[str, str] = os.environ) -> str | None:
    """The first writable cache directory (created if missing), or None."""
    home = environ.get("HOME") or os.path.expanduser("~")
    xdg = environ.get("XDG_CACHE_HOME") or os.path.join(home, ".cache")
    candidates = [environ.get("NUMBA_CACHE_DIR", ""),
                  *environ.get("CACHE_DIRECTORY", "").split(":"),
                  os.path.join(xdg, "rigctl")]
    for path in candidates:
        if path and _writable(path):
            return path
    return None


def _writable(path: str) -> bool:
    try:
        os.makedirs(path, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()  # numba's own test of a cache directory
    except OSError:
        return False
    return True


CACHE_DIR = cache_dir()
if CACHE_DIR is not None:
    os.environ["NUMBA_CACHE_DIR"] = CACHE_DIR

import numba  # after NUMBA_CACHE_DIR is set

numba.core.config.reload_config()  # in case numba was imported before this module


def njit(**options):
    """`numba.njit(**options)`, cached on disk when `CACHE_DIR` is set."""
    return numba.njit(cache=CACHE_DIR is not None, **options)
