"""A camera link that drops for longer than its driver's quick reconnections (about 3 s) during a
six-coil closed-loop run: the run suspends with the field held, the tracking loop reopens the
camera once it is back, and the run goes on to its goals; one that never comes back ends the run
once it has been suspended for the rig file's `[stream] suspended_limit_s`, with every supply at
zero (the emulator's truth)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.config import load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import load_plan
from rigctl.rigs.six_coil.global_moves import Run

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "fig4-two-magnets.json"


def fast(rig, **stream):
    """The bench's rig at 4 turns/s, a watchdog for a loaded machine, `stream` changes."""
    return rig.model_copy(update={
        "field": rig.field.model_copy(update={"rolling_turns_per_s": 4.0,
                                              "steering_deg_per_s": 360.0}),
        "stream": rig.stream.model_copy(update={"reply_timeout_s": 1.0, **stream}),
        "camera": rig.camera.model_copy(update={"timeout_s": 1.0}),
    })


@pytest.fixture
def bench(tmp_path):
    # the ideal bench (`--coil-error 0`): what is under test is the outage, not the coils' errors
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml",
                              extra_args=["--coil-error", "0"]) as rig_path:
        yield load_rig(rig_path)


class Watched:
    def __init__(self, rig, runs: Path):
        self.runs = runs
        self.run = Run(load_plan(PLAN), rig, runs_dir=runs, progress_out=None, closed_loop=True)
        self.result: dict = {}
        self.thread = threading.Thread(target=lambda: self.result.setdefault(
            "summary", self.run.execute()))
        self.thread.start()

    def events(self) -> list[dict]:
        files = list(self.runs.glob("*/events.jsonl"))
        return [json.loads(line) for line in files[0].read_text().splitlines() if line] \
            if files else []

    def rolling(self, backdoor) -> None:
        wait_for(lambda: self.run.state.value == "running", 60.0, "the run to stream")
        start = backdoor.request("truth")["agents"][0]
        wait_for(lambda: backdoor.request("truth")["agents"][0] != start, 60.0,
                 "the magnets to roll")

    def join(self):
        self.thread.join(120)
        assert not self.thread.is_alive(), "the run did not end"
        return self.result["summary"]


def test_a_camera_back_after_seconds_is_reopened_and_the_run_goes_on(bench, tmp_path):
    watched = Watched(fast(bench), tmp_path)
    with BackdoorClient(bench.emulation.backdoor) as backdoor:
        try:
            watched.rolling(backdoor)
            backdoor.request("camera", kind="drop_link")
            wait_for(lambda: watched.run.state.value == "suspended", 10.0, "suspended")
            time.sleep(6.0)  # past the driver's own reconnections (0.1 + 0.2 + ... + 1.6 s)
            assert watched.run.state.value == "suspended"
            backdoor.request("camera", kind="restore")
            wait_for(lambda: any(e["event"] == "resume" for e in watched.events()), 15.0,
                     "the run to resume")
        except BaseException:
            backdoor.request("camera", kind="restore")
            watched.run.abort()
            watched.join()
            raise
    summary = watched.join()
    assert summary.reached and not summary.faults, summary.faults


def test_a_camera_that_stays_away_ends_the_run_at_the_suspension_limit(bench, tmp_path):
    watched = Watched(fast(bench, suspended_limit_s=2.0), tmp_path)
    with BackdoorClient(bench.emulation.backdoor) as backdoor:
        try:
            watched.rolling(backdoor)
            backdoor.request("camera", kind="drop_link")
            summary = watched.join()
        finally:
            backdoor.request("camera", kind="restore")
        currents = backdoor.request("truth")["currents_A"]
    assert summary.state == "aborted" and not summary.reached and summary.safe
    assert "suspended for more than 2 s" in summary.faults[-1]["reason"]
    assert "suspended_limit_s" in summary.faults[-1]["reason"]
    assert max(abs(c) for c in currents.values()) < 0.05
