"""`rigctl validate PLAN` refuses what the daemon's `load` and `rigctl execute` refuse: both run
`rigctl.rigs.prepare_run`, on the rig of `--rig`, and without it on the rig the plan's rig kind
runs without a rig file (its emulated bench's, `RigKind.bench_rig`). Before, validate without
`--rig` checked the plan alone and passed a six-coil move that is not a whole number of turns,
which `load` refused. One rule of each rig kind that only the rig's run knows, each checked by
validate (with and without `--rig`) and by the daemon's load path (its `PlanRuns`)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rigctl.apps.cli.main import main
from rigctl.apps.daemon.plan_runs import PlanRuns
from rigctl.core.config import dump_rig
from rigctl.core.errors import RigError
from rigctl.rigs import rig_kind

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"


def _example(name: str, **changes) -> dict:
    document = json.loads((EXAMPLES / name).read_text())
    document.pop("expected", None)  # the changes below change what the model expects
    document.update(changes)
    return document


def _third_particle() -> list:
    agents = _example("coilboard-disk.json")["agents"]
    return agents + [{"start": [0.0, -18.0], "goal": [0.0, -18.0], "radius": 0.5}]


def _renamed_arm() -> list:
    arms = _example("depm-plan.json")["arms"]
    return [{**arms[0], "name": "port"}, arms[1]]


CASES = {
    # a move of 31 mm is 3.1 turns of the bench's 1.59 mm magnets (10 mm a turn)
    "six-coil: whole turns": (_example("fig4-quick.json", moves=[[0.0, -80.0], [31.0, 0.0]]),
                              "rolling uses whole turns"),
    "six-coil: the rig's pull": (_example("pair-formation-change.json", max_pull_bl_s=1000.0),
                                 "this rig's coils"),
    "coil-board: two particles": (_example("coilboard-disk.json", agents=_third_particle()),
                                  "places exactly two particles"),
    "depm: the rig's arms": (_example("depm-plan.json", arms=_renamed_arm()),
                             "re-plan for this rig"),
}


def _load(document: dict, rig) -> str:
    """The daemon's `load` of `document` on `rig` (`Daemon._cmd_load`'s factory calls): why it
    is refused."""
    plans = PlanRuns()
    with pytest.raises(RigError) as refused:
        plans.prepare(plans.parse_plan(document), rig, runs_dir="runs", on_cycles=None,
                      on_state=None)
    return str(refused.value)


@pytest.mark.parametrize("case", list(CASES))
def test_validate_refuses_what_load_refuses_with_and_without_the_rig(case, tmp_path, capsys):
    document, says = CASES[case]
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps(document))
    rig = rig_kind(document["rig"]).bench_rig()
    assert says in _load(document, rig)
    assert main(["validate", str(plan)]) == 2  # on the plan's rig kind's bench
    without = capsys.readouterr().err
    assert without.startswith("error: ") and says in without and without.count("\n") == 1, without
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(dump_rig(rig))
    assert main(["validate", str(plan), "--rig", str(rig_file)]) == 2
    with_rig = capsys.readouterr().err
    assert says in with_rig and with_rig.splitlines()[-1] == without.rstrip("\n"), with_rig


@pytest.mark.parametrize("name", ["fig4-quick.json", "coilboard-disk.json", "depm-plan.json",
                                  "pair-formation-change.json"])
def test_validate_passes_the_examples_on_their_benches(name, capsys):
    assert main(["validate", str(EXAMPLES / name)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"OK: {EXAMPLES / name}: ") and "passed on the emulated" in out


def test_a_plan_for_another_rig_kind_is_refused_by_validate_as_by_load(tmp_path, capsys):
    plan = tmp_path / "plan.json"
    plan.write_text((EXAMPLES / "coilboard-disk.json").read_text())
    rig = rig_kind("six-coil").bench_rig()
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(dump_rig(rig))
    says = "the plan is for a coil-board rig; 'emulated six-coil bench' is a six-coil rig"
    assert says in _load(json.loads(plan.read_text()), rig)
    assert main(["validate", str(plan), "--rig", str(rig_file)]) == 2
    assert says in capsys.readouterr().err
