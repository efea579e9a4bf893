"""numba's `njit`, with its on-disk cache where the install allows one.

Compiled kernels are cached in the first writable directory of: `$NUMBA_CACHE_DIR` (the user's
choice), `$CACHE_DIRECTORY` (systemd's, from the unit's `CacheDirectory=rigctl`),
`$XDG_CACHE_HOME/rigctl` or `~/.cache/rigctl`. With none of them writable (a read-only install and
home) the kernels are compiled in memory, in every process, instead of dying at import: numba's
`cache=True` raises when it finds no writable place. The place is decided once, when this module
is imported, and set as `NUMBA_CACHE_DIR` before numba is imported: numba reads it when
`numba.core.config` is imported (again, if a `NUMBA_` variable changed, at `reload_config`), and
picks a kernel's cache directory when the kernel is made. Child processes inherit the setting.
"""

from __future__ import annotations

import functools
import os
import tempfile
import threading
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
_lock = threading.Lock()


def njit(**options):
    """`numba.njit(**options)`, cached on disk when `CACHE_DIR` is set, made at the first call of
    a kernel of the module: a command that computes nothing does not import numba."""
    return lambda py_func: _Kernel(py_func, options)


class _Kernel:
    """A kernel until its module's first call: then every kernel of the module becomes numba's
    dispatcher in the module's globals, so that kernels calling kernels find dispatchers."""

    def __init__(self, py_func, options: dict) -> None:
        functools.update_wrapper(self, py_func)
        self.py_func, self.options, self.dispatcher = py_func, options, None

    def __call__(self, *args, **kwargs):
        if self.dispatcher is None:
            with _lock:
                _compile_module(self.py_func.__globals__)
        return self.dispatcher(*args, **kwargs)


def _compile_module(namespace: dict) -> None:
    import numba  # after NUMBA_CACHE_DIR is set

    numba.core.config.reload_config()  # in case numba was imported before CACHE_DIR was set
    for name, kernel in list(namespace.items()):
        if not isinstance(kernel, _Kernel):
            continue
        if kernel.dispatcher is None:
            kernel.dispatcher = numba.njit(cache=CACHE_DIR is not None, **kernel.options)(
                kernel.py_func)
        # a kernel imported from a module compiled before this one is its dispatcher here too
        namespace[name] = kernel.dispatcher
