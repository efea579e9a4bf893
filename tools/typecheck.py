"""mypy over rigctl as it is installed: `drivers/`, `emulators/` and `plans/` are the subpackages
`rigctl.drivers`, `rigctl.emulators` and `rigctl.plans` (pyproject's package-dir), which mypy
cannot see through an editable install's import hook nor from the folders as they lie. So the
package is laid out as installed in a tree of symlinks (build/typecheck/rigctl), mypy checks it
with pyproject.toml's [tool.mypy], and the paths it prints are turned back into the repository's.

    python tools/typecheck.py                 # every module; exit status mypy's
    python tools/typecheck.py --rooms         # and the errors counted per room (one JSON line)

mypy is in the [test] extra (one major version) and `.ci/run` runs this before the tests.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAPPED = ("drivers", "emulators", "plans")  # top-level folders that install under rigctl/


def installed_tree() -> Path:
    """build/typecheck/rigctl: rigctl/'s entries and the mapped folders, as symlinks."""
    tree = ROOT / "build" / "typecheck"
    package = tree / "rigctl"
    package.mkdir(parents=True, exist_ok=True)
    wanted = {entry.name: entry for entry in (ROOT / "rigctl").iterdir()}
    wanted.update({name: ROOT / name for name in MAPPED})
    for link in package.iterdir():
        if link.name not in wanted:
            link.unlink()
    for name, target in wanted.items():
        link = package / name
        if not link.is_symlink() or link.resolve() != target:
            link.unlink(missing_ok=True)
            link.symlink_to(target)
    return tree


def repository_path(line: str) -> str:
    """rigctl/drivers/x.py:3: ... -> drivers/x.py:3: ..."""
    return re.sub(rf"^rigctl/({'|'.join(MAPPED)})/", r"\1/", line)


def main(argv: list[str]) -> int:
    rooms = "--rooms" in argv
    args = [a for a in argv if a != "--rooms"]
    tree = installed_tree()
    done = subprocess.run([sys.executable, "-m", "mypy", "--config-file",
                           str(ROOT / "pyproject.toml"), "--cache-dir",
                           str(ROOT / "build" / "mypy-cache"), *args, "-p", "rigctl"],
                          cwd=tree, capture_output=True, text=True)
    lines = [repository_path(line) for line in done.stdout.splitlines()]
    print("\n".join(lines))
    print(done.stderr, end="", file=sys.stderr)
    if rooms:
        errors = [line.split(":", 1)[0] for line in lines if ": error: " in line]
        per_room = Counter("/".join(Path(path).parts[:2 if path.startswith("rigctl/") else 1])
                           for path in errors)
        print(json.dumps({"errors": len(errors), "rooms": dict(per_room.most_common())}))
    return done.returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
