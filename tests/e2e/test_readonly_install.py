"""The wheel installed read-only, as the service runs it (`ProtectSystem=strict`, `ProtectHome=yes`).

The wheel goes into a fresh venv whose dependencies are the test venv's (a .pth file, nothing
downloaded); the venv and HOME are then mounted read-only in a private mount namespace for every
command (root ignores file modes, not a read-only mount). numba finds no writable cache there, so
the kernels compile in memory, or, given systemd's `CACHE_DIRECTORY`, are cached in it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "plans" / "examples"
# the repository's parts that make the wheel (pyproject's package-dir)
SOURCES = ["pyproject.toml", "README.md", "LICENSE", "MANIFEST.in", "rigctl", "drivers", "emulators", "plans",
           "firmware"]
# runs as root (CI) or maps the user to root in a user namespace
UNSHARE = ["unshare", "--mount", *([] if os.geteuid() == 0 else ["--map-root-user"])]


def _wrap(read_only: Path, *command) -> list[str]:
    """`command` in a private mount namespace where `read_only` is a read-only bind mount."""
    script = 'mount --bind -o ro "$0" "$0" && exec "$@"'
    return [*UNSHARE, "sh", "-c", script, str(read_only), *map(str, command)]


def _tree(path: Path) -> dict[str, tuple[int, int]]:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in path.rglob("*")}


@pytest.fixture(scope="module")
def install(tmp_path_factory):
    """(the read-only folder, the installed venv's rigctl, an environment with HOME inside it)."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare(1): cannot make a read-only mount")
    base = tmp_path_factory.mktemp("readonly")
    read_only = base / "ro"
    (read_only / "home").mkdir(parents=True)
    probe = subprocess.run(_wrap(read_only, "sh", "-c", 'test ! -w "$0"', read_only),
                           check=False, capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"no read-only bind mount in a private mount namespace: {probe.stderr.strip()}")

    src = base / "src"  # a copy, so that setuptools' build/ does not land in the checkout
    src.mkdir()
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(ROOT / name, src / name)
    # built in isolation with the build backend pyproject.toml asks for (setuptools >= 77 for the
    # SPDX licence), from the registry
    pip = [sys.executable, "-m", "pip", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "-w", base / "wheel", src], check=True, capture_output=True)
    venv = read_only / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", venv], check=True)
    subprocess.run([*pip, "--python", venv / "bin" / "python", "install", "--no-deps",
                    *(base / "wheel").glob("rigctl-*.whl")], check=True, capture_output=True)
    paths = sysconfig.get_paths()
    where = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
    site = Path(subprocess.run([venv / "bin" / "python", "-c", where], check=True,
                               capture_output=True, text=True).stdout.strip())
    (site / "test-venv-deps.pth").write_text(f"{paths['purelib']}\n{paths['platlib']}\n")

    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_CACHE_DIR", "CACHE_DIRECTORY", "XDG_CACHE_HOME", "PYTHONPATH")}
    env["HOME"] = str(read_only / "home")
    return read_only, venv / "bin" / "rigctl", env


def _run(install, cwd: Path, *args, **env):
    read_only, rigctl, base_env = install
    return subprocess.run(_wrap(read_only, rigctl, *args), check=False, cwd=cwd,
                          env={**base_env, **env}, capture_output=True, text=True, timeout=120)


def test_the_installed_cli_runs_from_a_read_only_install_and_home(install, tmp_path):
    read_only = install[0]
    before = _tree(read_only)
    result = _run(install, tmp_path, "--help")
    assert result.returncode == 0, result.stderr
    assert "execute" in result.stdout
    # the installed copy ran, not the checkout
    where = _run(install, tmp_path, "--version")
    assert where.returncode == 0 and "rigctl 0.1" in where.stdout, where.stdout + where.stderr

    # with no writable place at all the kernels compile in memory (validate runs the model) ...
    result = _run(install, tmp_path, "validate", EXAMPLES / "fig4-two-magnets.json")
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("OK: ")

    # ... and with systemd's CacheDirectory= they are cached there: a whole emulated run (without
    # a cache the emulated bench's own process compiles them mid-run, and its supplies answer late)
    cache = tmp_path / "cache"
    cache.mkdir()
    # (open loop on the ideal bench, `--coil-error 0`: the default bench's coils are off the rig
    # file's, and only the closed loop makes up for that)
    result = _run(install, tmp_path, "execute", EXAMPLES / "fig4-quick.json", "--open-loop",
                  "--coil-error", "0", "--json", "--runs", tmp_path / "runs", CACHE_DIRECTORY=str(cache))
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads(result.stdout)
    assert summary["reached"] is True
    assert Path(summary["run"]).is_dir()
    assert list(cache.rglob("*.nbi")), "no numba cache index written to CACHE_DIRECTORY"

    assert _tree(read_only) == before, "something was written under the install or HOME"
