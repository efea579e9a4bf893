"""Every Python package of the source tree is in pyproject's `packages` list (setuptools installs
only those): a package left out imports from a checkout and fails from an installed wheel, as
`rigctl.physics.fields` did once the rig's settings imported it (`test_readonly_install` found it,
in CI, at the end of a 15-minute suite; this finds it in milliseconds)."""

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_every_package_of_the_tree_is_listed_for_setuptools():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    setuptools = project["tool"]["setuptools"]
    listed, folders = set(setuptools["packages"]), setuptools["package-dir"]
    found = set()
    for package, folder in folders.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            inner = init.parent.relative_to(ROOT / folder).parts
            if "__pycache__" not in inner:
                found.add(".".join((package, *inner)))
    assert found - listed == set(), f"add to pyproject's packages: {sorted(found - listed)}"
