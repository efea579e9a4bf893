"""The operator console serves the run viewer for its own run records (`/viewer?run=ID` and the
`/records` routes), with its own access rules: a loopback console reads them to a loopback host
name, and refuses a request naming another host (DNS rebinding). The console runs in this
process with no daemon behind it (its telemetry and status poll wait for one meanwhile)."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request

import pytest

from rigctl.apps.cli.init import template
from rigctl.apps.console.server import Console
from rigctl.core.channels import symmetric
from rigctl.core.config import load_rig
from rigctl.core.record import RunRecord

pytestmark = pytest.mark.quick  # no process: the console's thread in this one


def get(url: str, headers: dict | None = None) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}),
                                    timeout=10) as reply:
            return reply.status, reply.read()
    except urllib.error.HTTPError as err:
        return err.code, err.read()


def test_the_console_serves_the_viewer_of_its_runs(tmp_path):
    (tmp_path / "rig.toml").write_text(template("six-coil"))
    rig = load_rig(tmp_path / "rig.toml")
    record = RunRecord(tmp_path / "runs", "a short run")
    record.write_file("plan.json", json.dumps({"name": "a short run"}))
    record.open_stream(symmetric(["x+", "x-"], "A", [20.0, 20.0], "supplies"), 100.0)
    for k in range(50):
        record.stream_row(k, 0, [0.1 * k, -0.1 * k], [0.1 * k, -0.1 * k])
    record.finish({"reached": True, "faults": []})
    console = Console(rig, command_endpoint="tcp://127.0.0.1:9", runs_dir=tmp_path / "runs",
                      clock_origin=time.monotonic(), address="127.0.0.1:0")
    url = console.start()
    try:
        status, page = get(f"{url}viewer?run={record.path.name}")
        assert status == 200 and b"/static/viewer.js" in page
        status, listing = get(f"{url}records")
        assert status == 200 and [r["id"] for r in json.loads(listing)] == [record.path.name]
        status, body = get(f"{url}records/{record.path.name}/data.json")
        document = json.loads(body)
        assert status == 200 and document["plan"] == "a short run"
        channels = document["plots"][0]["channels"]
        assert [c["name"] for c in channels] == ["x+", "x-"]
        assert channels[0]["measured"]["y"][-1] == pytest.approx(4.9, abs=1e-4)
        assert get(f"{url}records/{record.path.name}/data.json",
                   {"Host": "rebind.example:80"})[0] == 403
    finally:
        console.stop()
