"""The closed loop on the emulated bench (its own process, every device on its real transport, the
camera over MJPEG): with a rig that slips 15 %, spreads the robots' speeds and jitters them at
contacts, the example plan misses its goals by centimetres open-loop and reaches them within 1 mm
with the camera supervisor; a frozen camera suspends the run with the field held and it resumes
when frames come again.

The emulated bench runs in a subprocess so the tracker, the stream loop and the emulated physics do
not share one interpreter lock. Rolling runs at 4 turns/s (the coils' L/R = 20 ms keeps up) to keep
the file under a minute.
"""

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.config import load_rig
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.schema import load_plan
from rigctl.rigs.six_coil.global_moves import Run, execute_plan
from rigctl.rigs.six_coil.supervisor import SupervisorSettings

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
QUICK = EXAMPLES / "fig4-quick.json"
# The field that is not uniform (--field-at-robots) turns each robot's path by a few degrees and
# needs long wall manoeuvres to correct; bench/closed_loop.py measures it, the test leaves it out.
MISMATCH = ["--slip", "0.85", "--speed-spread", "0.01", "--noise", "0.05", "--drift", "0.005"]


def fast(rig):
    """The bench's rig at 4 turns/s, with a watchdog that tolerates a loaded CI machine."""
    return rig.model_copy(update={
        "field": rig.field.model_copy(update={"rolling_turns_per_s": 4.0,
                                              "steering_deg_per_s": 360.0}),
        "stream": rig.stream.model_copy(update={"reply_timeout_s": 1.0}),
    })


def truth_errors(summary):
    return np.array([a.truth_error_mm if a.truth_error_mm is not None else a.error_mm
                     for a in summary.agents])


SEEDS = (21, 22, 23)  # the emulated world's randomness: speed spread, drift direction, jitter


@pytest.fixture
def mismatched_bench(tmp_path):
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml",
                              extra_args=[*MISMATCH, "--seed", str(SEEDS[0])]) as rig_path:
        yield fast(load_rig(rig_path))


def test_closed_loop_reaches_the_goals_that_open_loop_misses(mismatched_bench, tmp_path):
    """The issue's goal over several randomised worlds, in a form a loaded machine cannot break:
    open loop misses by more than 5 mm in every world (slip alone leaves the free magnet 12 mm
    short), and the closed loop brings every robot within 1 mm by the emulator's ground truth in
    all worlds but at most one (the goal is 19 of 20; `bench/closed_loop.py` measures the rate)."""
    emulation = mismatched_bench.emulation  # the rig file records the mismatch
    assert emulation.slip == 0.85 and emulation.speed_spread == 0.01
    assert emulation.noise_mm == 0.05 and emulation.drift_mm_per_s == 0.005
    assert emulation.seed == SEEDS[0] and not emulation.field_at_robots
    plan = load_plan(QUICK)
    outcomes = {}
    with BackdoorClient(emulation.backdoor) as backdoor:
        for seed in SEEDS:
            # a new world for each seed (applied when the run places the robots)
            assert backdoor.request("mismatch", seed=seed)["mismatch"]["seed"] == seed
            open_loop = execute_plan(plan, mismatched_bench, runs_dir=tmp_path, progress_out=None,
                                     closed_loop=False)
            assert not open_loop.faults, open_loop.faults
            # slip alone: the 80 mm roll becomes 68 mm, so the free magnet stops 12 mm short
            assert truth_errors(open_loop).max() > 5.0, (seed, truth_errors(open_loop))
            assert not open_loop.reached
            closed = execute_plan(plan, mismatched_bench, runs_dir=tmp_path, progress_out=None,
                                  closed_loop=True, supervisor_settings=SupervisorSettings(seed=seed))
            outcomes[seed] = closed
    reached = [seed for seed, c in outcomes.items()
               if not c.faults and c.reached and truth_errors(c).max() < 1.0]
    assert len(reached) >= len(SEEDS) - 1, {
        seed: (c.faults, truth_errors(c).round(3).tolist()) for seed, c in outcomes.items()}

    closed = outcomes[reached[0]]  # what a successful closed-loop run leaves behind
    assert closed.replans >= 1
    assert closed.tracking["max_error_mm"] < 0.2 * 8.0  # the tracker against ground truth, at rest
    events = [json.loads(line) for line in (Path(closed.run) / "events.jsonl").read_text().splitlines()]
    replans = [e for e in events if e["event"] == "replan"]
    assert len(replans) == closed.replans
    assert replans[0]["reason"] == "off the plan" and max(replans[0]["error_mm"]) > 5.0
    summary = json.loads((Path(closed.run) / "summary.json").read_text())
    assert summary["replans"] == closed.replans and "lost_frames" in summary["tracking"]


def test_a_frozen_camera_suspends_the_run_with_the_field_held_and_it_resumes(tmp_path):
    # fig4-quick: two long rolls whose end the closed loop corrects every time (bench/closed_loop.py
    # at its defaults); fig4-two-magnets ends 1-3 mm off at times in a state its re-plans cannot
    # correct in time, which is the planner's problem, not the suspension's
    plan = load_plan(EXAMPLES / "fig4-quick.json")
    with EmulatedBenchProcess("six-coil", tmp_path / "bench.toml") as rig_path:
        rig = fast(load_rig(rig_path))
        rig = rig.model_copy(update={"camera": rig.camera.model_copy(update={"timeout_s": 1.0})})
        run = Run(plan, rig, runs_dir=tmp_path, progress_out=None, closed_loop=True)
        result = {}
        runner = threading.Thread(target=lambda: result.setdefault("summary", run.execute()))
        runner.start()

        def events():
            files = list(tmp_path.glob("*/events.jsonl"))
            if not files:
                return []
            return [json.loads(line) for line in files[0].read_text().splitlines() if line]

        with BackdoorClient(rig.emulation.backdoor) as backdoor:
            # freeze in the middle of a roll
            start = list(plan.agents[0].start)
            wait_for(lambda: run.program.sequencer.index > 150 and backdoor.request("truth")["agents"][0]
                     != start, what="the magnets to roll")
            backdoor.request("camera", kind="freeze")
            wait_for(lambda: any(e["event"] == "suspend" for e in events()), timeout_s=5,
                     what="the supervisor to suspend")
            suspend = next(e for e in events() if e["event"] == "suspend")
            assert "no fresh frame" in suspend["reason"]
            # the field holds: once the coils settled (L/R = 20 ms) the magnets stay where they
            # are and the currents stay on; watching nothing move for a while is the point here
            time.sleep(0.3)
            held = np.array(backdoor.request("truth")["agents"])
            currents = backdoor.request("truth")["currents_A"]
            time.sleep(0.5)
            truth = backdoor.request("truth")
            # 1 um in 0.5 s (a roll moves 10 mm a turn): held. The emulated world's last steps of
            # the settling may land in this window when its thread waits for a core (30 nm seen)
            np.testing.assert_allclose(truth["agents"], held, atol=1e-3)
            assert max(abs(c) for c in currents.values()) > 1.0
            assert run.state.value == "suspended"  # held until tracking returns
            backdoor.request("camera", kind="restore")
            wait_for(lambda: any(e["event"] == "resume" for e in events()), timeout_s=5,
                     what="the supervisor to resume")
        runner.join(timeout=60)
        assert not runner.is_alive()
        summary = result["summary"]
        assert not summary.faults, summary.faults
        assert summary.reached
        assert summary.tracking["lost_frames"] > 0


def test_calibrate_camera_from_markers_agrees_with_the_emulated_camera(tmp_path):
    from rigctl.apps.cli.main import main
    from rigctl.core.config import dump_rig
    from rigctl.emulators.bench import SixCoilBench

    markers = [[80.0, 90.0], [310.0, 70.0], [290.0, 320.0], [100.0, 300.0], [200.0, 180.0]]
    with SixCoilBench() as bench:
        truth = bench.rig.camera.calibration  # the emulated camera's own projection
        uncalibrated = bench.rig.model_copy(update={
            "camera": bench.rig.camera.model_copy(update={"calibration": None})})
        rig_file = tmp_path / "rig.toml"
        rig_file.write_text(dump_rig(uncalibrated))
        with BackdoorClient(bench.rig.emulation.backdoor) as backdoor:  # the operator's markers
            backdoor.request("place", workspace={"boundary": {"rect": [0, 0, 400, 400]}},
                             agents=[{"position": m, "radius": 8.0} for m in markers])
        code = main(["calibrate", "camera", "--rig", str(rig_file), "--markers",
                     ";".join(f"{x},{y}" for x, y in markers), "--marker-radius", "8"])
        assert code == 0
        calibrated = load_rig(rig_file).camera.calibration
    grid = np.stack(np.meshgrid(np.linspace(60, 340, 5), np.linspace(60, 340, 5)), -1).reshape(-1, 2)
    pixels = truth.to_px(grid)
    np.testing.assert_allclose(calibrated.to_mm(pixels), grid, atol=1.0)
