"""A local run's control endpoint (`rigctl execute`'s, `rigctl.apps.daemon.local`) answers in the
daemon's shapes (docs/daemon-protocol.md): `rigctl status --rig RIG` printed `state: running` and
then a traceback (`KeyError: 'sample'`), the local `status` having no `sample` in its `run`. Here a
real local run on the emulated six-coil bench, owning its rig through the lock as `rigctl
execute` does, is asked every verb a local run answers, by the `Rig` client and by the CLI."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from rigctl.apps.cli.main import main
from rigctl.apps.client import Rig
from rigctl.apps.daemon.local import LocalControl
from rigctl.apps.testing import wait_for
from rigctl.core.config import StreamSettings, dump_rig
from rigctl.emulators.bench import SixCoilBench
from rigctl.plans.schema import load_plan
from rigctl.rigs.owner import RigLock
from rigctl.rigs.six_coil.global_moves import Run

PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "fig4-two-magnets.json"

# what docs/daemon-protocol.md says the daemon's replies hold
STATUS_KEYS = {"state", "device", "reason", "rig", "run", "last_run", "plans", "devices",
               "last_fault", "hold", "manual_field_mT", "uptime_s"}
RUN_KEYS = {"kind", "id", "plan_id", "sample", "samples", "move", "moves", "duration_s"}
DEVICE_KEYS = {"name", "url", "health", "detail"}


@pytest.fixture
def local_run(tmp_path, monkeypatch):
    """(a `rigctl execute`-like local run on its bench, streaming; the rig file; a client)."""
    monkeypatch.setenv("RIGCTL_LOCK_DIR", str(tmp_path / "locks"))
    with SixCoilBench() as bench:
        rig = bench.rig.model_copy(update={"stream": StreamSettings(rate_hz=200.0)})
        rig_path = tmp_path / "bench.toml"
        rig_path.write_text(dump_rig(rig))
        run = Run(load_plan(PLAN), rig, runs_dir=tmp_path / "runs", progress_out=None,
                  closed_loop=False)
        with RigLock(rig, "rigctl execute") as lock, LocalControl(run) as control:
            lock.name_control(control.endpoint)
            thread = threading.Thread(target=run.execute)
            thread.start()
            try:
                with Rig(control.endpoint, timeout_s=2.0) as client:
                    wait_for(lambda: run.state.value == "running" and run.stream_loop
                             is not None and run.stream_loop.stats().cycles > 0, 60.0, "streaming")
                    yield run, rig_path, client
            finally:
                run.abort()
                thread.join(30.0)


def test_a_local_run_answers_every_verb_in_the_daemons_shape(local_run):
    run, _, client = local_run
    status: dict = {}

    def streamed() -> bool:  # the last cycle's sample, -1 before the first
        nonlocal status
        status = client.status()
        return status["run"]["sample"] >= 0

    wait_for(streamed, 10.0, "a cycle in status")
    assert STATUS_KEYS <= set(status)
    assert status["state"] == "running" and status["owner"] == "rigctl execute"
    assert RUN_KEYS <= set(status["run"]) and status["run"]["kind"] == "plan"
    assert status["run"]["moves"] == len(run.plan.moves)
    assert 0 <= status["run"]["sample"] < status["run"]["samples"]
    assert all(DEVICE_KEYS <= set(d) for d in status["devices"])
    assert {"protocol", "pid", "telemetry"} <= set(client.request("ping"))
    assert client.pause(immediate=True) == {"state": "running", "pending": "pause now"}
    wait_for(lambda: client.status()["state"] == "paused", 10.0, "paused")
    assert client.resume() == {"state": "paused", "pending": "resume"}
    wait_for(lambda: client.status()["state"] == "running", 10.0, "running again")
    assert client.abort()["pending"] == "ramp down and stop"


def test_rigctl_status_with_the_rig_file_prints_the_local_run(local_run, capsys):
    run, rig_path, _ = local_run
    assert main(["status", "--rig", str(rig_path)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0] == "state: running; owner: rigctl execute", out
    assert lines[2].startswith(f"run: {Path(run.record.path).name} sample "), out
    assert f"/{run.info['samples']} move " in lines[2] and lines[2].endswith(
        f"/{len(run.plan.moves)}"), out
    assert [line.split()[0] for line in lines[3:]] == ["x+", "x-", "y+", "y-", "z+", "z-",
                                                      "camera"], out
    assert main(["status", "--rig", str(rig_path), "--json"]) == 0
    assert '"sample": ' in capsys.readouterr().out



def test_rigctl_estop_at_the_local_endpoint_prints_what_it_did(local_run, capsys):
    run, _, client = local_run
    assert main(["estop", "--connect", client.endpoint]) == 0
    assert capsys.readouterr().out.startswith(
        "EMERGENCY STOP: state estopped; done: every device told to stop")
    wait_for(lambda: run.state.value == "estopped", 10.0, "the run e-stopped")
