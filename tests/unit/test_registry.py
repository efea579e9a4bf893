"""The rig kinds are what the entry-point group `rigctl.rigs` says: rigctl's three are found
there, a lab's package installed beside them is found the same way, and a broken one is named in
one line without hiding the others."""

import sys
import textwrap

import pytest

from rigctl.core import registry
from rigctl.core.errors import ConfigError
from rigctl.rigs.base import RigKind


@pytest.fixture
def fresh_registry(monkeypatch):
    """The registry loaded anew (and again after the test), so a package the test puts on the
    path is seen and then forgotten."""
    monkeypatch.setattr(registry, "_loaded", None)
    yield registry
    registry._loaded = None


def _install(tmp_path, monkeypatch, name: str, entry_points: str, module: str) -> None:
    """A package `name` on the path with its dist-info, as pip leaves one installed."""
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(module))
    info = tmp_path / f"{name}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[rigctl.rigs]\n" + textwrap.dedent(entry_points))
    monkeypatch.syspath_prepend(str(tmp_path))


def test_the_three_kinds_register_through_entry_points(fresh_registry):
    kinds = fresh_registry.kinds()
    assert list(kinds) == ["coil-board", "depm", "six-coil"]
    assert all(isinstance(k, RigKind) and k.name == name for name, k in kinds.items())
    import rigctl.rigs

    assert rigctl.rigs.KINDS == kinds and rigctl.rigs.rig_kind("depm") is kinds["depm"]


def test_an_unknown_kind_names_the_installed_ones(fresh_registry):
    with pytest.raises(ConfigError, match="rig kind 'maglev' is not installed; the installed "
                       "kinds are coil-board, depm, six-coil"):
        fresh_registry.rig_kind("maglev")


def test_a_lab_package_registers_a_kind_and_a_broken_one_hides_no_other(
        fresh_registry, tmp_path, monkeypatch, caplog):
    _install(tmp_path, monkeypatch, "lab_rigs", """\
        spinner = lab_rigs:SPINNER
        broken = lab_rigs_missing:KIND
        notakind = lab_rigs:NOT_A_KIND
        """, """\
        from rigctl.rigs.base import RigKind

        SPINNER = RigKind(name="spinner", description="a magnet on a stepper", plans={},
                          channels=lambda rig: [], devices=lambda rig: [],
                          make_safe=lambda rig: {}, hold=lambda rig, target: None)
        NOT_A_KIND = 42
        """)
    kinds = fresh_registry.kinds()
    assert list(kinds) == ["coil-board", "depm", "six-coil", "spinner"]
    assert kinds["spinner"].settings().__name__ == "RigConfig"  # the defaults of a small kind
    assert kinds["spinner"].bench is None and kinds["spinner"].probes == {}
    with pytest.raises(ConfigError, match="rig kind 'broken' is installed but broken: "
                       "lab_rigs_missing:KIND does not load: ModuleNotFoundError"):
        fresh_registry.rig_kind("broken")
    with pytest.raises(ConfigError, match="lab_rigs:NOT_A_KIND is a int, not a RigKind"):
        fresh_registry.rig_kind("notakind")
    said = [r.getMessage() for r in caplog.records if r.name == "rigctl.core.registry"]
    assert len(said) == 2 and all("\n" not in line for line in said)
    assert "broken" in said[0] and "notakind" in said[1]
    sys.modules.pop("lab_rigs", None)


def test_rigctl_rigs_loads_no_kind_until_asked():
    import subprocess

    code = ("import sys, rigctl.rigs; "
            "print(sorted(m for m in sys.modules if m.startswith('rigctl.rigs.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "['rigctl.rigs.base']"


def test_the_cli_s_kind_choices_load_no_kind():
    """`rigctl --help` (every subcommand's parser, choices included) imports no rig kind's code:
    the choices are the entry points' names."""
    import subprocess

    code = ("import sys; from rigctl.apps.cli.main import build_parser; p = build_parser(); "
            "print(sorted(m for m in sys.modules if m.startswith('rigctl.rigs.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"


def test_the_default_kind_is_the_one_pyproject_names_and_loads_no_kind():
    """`rigctl daemon` and `rigctl plan rrt` untold use the kind the `rigctl.default` entry point
    names (pyproject.toml, read here on its own), found without importing any kind's code."""
    import subprocess
    import sys
    import tomllib
    from pathlib import Path

    project = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    points = project["project"]["entry-points"]
    (value,) = points["rigctl.default"].values()
    expected = next(name for name, target in points["rigctl.rigs"].items() if target == value)
    code = ("import sys; from rigctl.core.registry import default_kind; print(default_kind()); "
            "print(any(m.startswith('rigctl.rigs.') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == [expected, "False"]
