"""Where numba's cache goes: the first writable of NUMBA_CACHE_DIR, CACHE_DIRECTORY (systemd),
XDG_CACHE_HOME/rigctl or ~/.cache/rigctl; none when none is
writable (the kernels compile in memory: tests/e2e/test_readonly_install.py)."""

from __future__ import annotations

from rigctl.core.jit import cache_dir


def test_the_first_writable_directory_in_order(tmp_path):
    blocked = tmp_path / "a-file"
    blocked.write_text("")  # nothing can be made below a file, whoever runs the test
    user, unit, xdg, home = (str(tmp_path / n) for n in ("user", "unit", "xdg", "home"))
    env = {"NUMBA_CACHE_DIR": user, "CACHE_DIRECTORY": unit, "XDG_CACHE_HOME": xdg, "HOME": home}
    assert cache_dir(env) == user
    env["NUMBA_CACHE_DIR"] = str(blocked / "numba")
    assert cache_dir(env) == unit
    env["CACHE_DIRECTORY"] = f"{blocked / 'unit'}:{unit}-2"  # systemd's list of several
    assert cache_dir(env) == f"{unit}-2"
    del env["CACHE_DIRECTORY"]
    assert cache_dir(env) == f"{xdg}/rigctl"
    del env["XDG_CACHE_HOME"]
    assert cache_dir(env) == f"{home}/.cache/rigctl"
    env["HOME"] = str(blocked)
    assert cache_dir(env) is None

