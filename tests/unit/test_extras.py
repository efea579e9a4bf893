"""A command whose optional part is not installed names the extra to install, in one line, exit 2
(issue 38, item 2). The part is made missing the way pip leaves it: not importable (a finder
placed first on sys.meta_path refuses it, in a fresh interpreter), so the real import machinery
answers, not a stand-in of ours."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

WITHOUT = """
import importlib.abc, sys
class Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None
sys.meta_path.insert(0, Missing())
from rigctl.apps.cli.main import main
sys.exit(main({argv!r}))
"""


def _run_without(blocked: set[str], argv: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", WITHOUT.format(blocked=blocked, argv=argv)],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)


@pytest.mark.parametrize(("blocked", "argv", "extra"), [
    ({"distributed", "dask"}, ["study", str(ROOT / "studies" / "rrt-solve.toml"), "--serial"], "studies"),
    ({"aiohttp"}, ["daemon", "--bench", "six-coil", "--console"], "console"),
])
def test_a_missing_extra_is_named_in_one_line(tmp_path, blocked, argv, extra):
    done = _run_without(blocked, argv, tmp_path)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert f"pip install 'rigctl[{extra}]'" in lines[0]
    assert not list(tmp_path.iterdir())  # nothing started, nothing written


def test_the_core_commands_run_without_any_extra(tmp_path):
    plan = ROOT / "plans" / "examples" / "fig4-two-magnets.json"
    done = _run_without({"distributed", "dask", "aiohttp", "bokeh", "magpylib"}, ["validate", str(plan)],
                        tmp_path)
    assert done.returncode == 0, done.stderr
