"""Rig files against the emulated benches: VISA resource strings reach the same supplies as tcp://,
and `rigctl emulate KIND` writes only the tables its kind uses."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from urllib.parse import urlsplit

import pytest
import tomli_w

from rigctl.emulators.process import EmulatedBenchProcess


def test_a_six_coil_rig_file_with_visa_resources_passes_doctor(tmp_path) -> None:
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml") as bench:
        data = tomllib.loads(bench.read_text())
        for index, coil in enumerate(data["coils"]):
            where = urlsplit(coil["url"])
            coil["url"] = f"TCPIP{index or ''}::{where.hostname}::{where.port}::SOCKET"
        visa = tmp_path / "visa.toml"
        visa.write_text(tomli_w.dumps(data))
        done = subprocess.run([sys.executable, "-m", "rigctl", "doctor", "--rig", str(visa), "--json"],
                              capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    supplies = [d for d in report["devices"] if d["kind"] == "supply"]
    assert len(supplies) == 6 and all(d["ok"] for d in supplies), report
    assert all(d["url"].startswith("TCPIP") for d in supplies)


@pytest.mark.parametrize("kind, tables", [("coil-board", {"board", "camera"}), ("depm", {"depm"})])
def test_emulate_writes_only_the_tables_of_its_kind(tmp_path, kind, tables) -> None:
    with EmulatedBenchProcess(kind, tmp_path / "bench.toml") as bench:
        written = tomllib.loads(bench.read_text())
    assert written["rig"]["kind"] == kind
    assert tables <= set(written)
    assert not {"field", "magnets", "coils", "actuation_matrix_T_per_A"} & set(written), written
