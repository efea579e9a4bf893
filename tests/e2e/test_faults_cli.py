"""`rigctl faults --quick`, end to end: the quick campaign (tests/e2e's CI form of item 5 of issue
15) starts every rig's emulated bench and a daemon, injects its faults, and must end with every
cell in a named outcome, every device safe and every record intact (exit 0). Its claims are then
checked against the run records it kept, read here with nothing of the campaign's: a device fault
is in the record's events naming that device, a killed stream process left a fault event, and a
record the campaign calls complete has its summary."""

from __future__ import annotations

import json
from pathlib import Path

from rigctl.apps.faults import OUTCOMES, rig_profile
from rigctl.apps.testing import run_rigctl


def events(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "events.jsonl").read_text().splitlines()
            if line.strip()]


def test_the_quick_campaign_passes_and_its_records_say_what_it_reports(tmp_path):
    keep = tmp_path / "campaign"
    done = run_rigctl("faults", "--quick", "--json", "--keep", str(keep), "-o",
                      str(tmp_path / "out.json"), cwd=tmp_path, timeout_s=600)
    document = json.loads(done.stdout)  # --json: stdout is the one JSON document
    failed = [c for c in document["cells"] if not c["ok"]]
    assert done.returncode == 0 and document["ok"], (failed, done.stderr[-3000:])
    assert json.loads((tmp_path / "out.json").read_text()) == document
    assert "[six-coil 1/" in done.stderr  # progress on stderr

    cells = document["cells"]
    assert {(c["path"], c["fault"], c["phase"]) for c in cells if c["rig"] == "six-coil"} == \
        set(rig_profile("six-coil").quick)
    assert {c["rig"] for c in cells} == {"six-coil", "coil-board", "depm"}
    for cell in cells:
        assert cell["outcome"] in OUTCOMES and cell["safe"], cell
        runs = keep / cell["rig"] / ("runs" if cell["path"] == "daemon" else "runs-execute")
        if cell["run"] is None:
            continue
        run_dir = runs / cell["run"]
        log = events(run_dir)
        if cell["record"] == "complete":
            summary = json.loads((run_dir / "summary.json").read_text())
            assert (run_dir / "plan.json").is_file()
        else:
            summary = None
        device = cell["fault"].split(":")[0]
        if cell["outcome"] == "faulted" and device != "stream process" and cell["device"]:
            # the device the campaign reports is the one the record's fault event names
            assert any(e["event"] == "fault" and e.get("device") == cell["device"] for e in log)
        if cell["fault"] == "stream process:sigkill":
            assert cell["outcome"] == "faulted"
            assert any(e["event"] == "fault" and "stream process" in e.get("reason", "")
                       for e in log), log[-5:]
        if summary is not None and cell["outcome"] == "completed":
            assert summary["state"] == "done"

    # the one cell each of the coil board and the arms runs stops its run: a hung board link
    # and a stalled arm joint are persistent faults, named with the device
    by = {(c["rig"], c["fault"]): c for c in cells}
    assert by[("coil-board", "board:stall")]["outcome"] == "faulted"
    assert by[("depm", "left:stall_joint")]["device"] == "left"
    assert by[("six-coil", "x+:stall")]["device"] == "x+"  # a hung supply, named
