"""The rooms of ARCHITECTURE.md hold: no module cycle and no import up a layer (core, physics,
run, rigs, apps), checked by tools/import_graph.py over every import, those in functions too."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_no_import_cycle_and_no_import_upwards():
    out = subprocess.run([sys.executable, str(ROOT / "tools" / "import_graph.py"), str(ROOT)],
                         capture_output=True, text=True, check=True).stdout
    assert "module cycles: 0\n" in out, out
    assert "upward imports: 0\n" in out, out
