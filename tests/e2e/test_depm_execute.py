"""`rigctl execute` of field-sequence plans on the emulated dEPM bench, end to end.

The runs use a time scale (simulated seconds per real second) so the emulated arms and the Hall
board run four to six times faster than real time; nothing else changes. One bench process serves
the module (`bench`: each test starts from the arms parked and no fault in force); the baseline's
run starts its own, as `rigctl execute` does without `--rig`.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.emulators.process import EmulatedBenchProcess
from rigctl.plans.depm import EPM_MOMENT_AM2
from rigctl.plans.schema import parse_plan

from rigctl.cli.main import build_parser
from rigctl.config import load_rig
from rigctl.kinematics import DEFAULT_BASES, default_arms
from rigctl.magnetics import field_vector
from rigctl.testing import wait_for

MOMENT = EPM_MOMENT_AM2  # the planner's (and the bench's) default EPM
TIME_SCALE = 4.0


def _U_mT(arms, q: np.ndarray) -> list[float]:
    centres, moments = [], []
    for arm, joints in zip(arms, q):
        position, direction = arm.epm_pose(joints)
        centres.append(position)
        moments.append(MOMENT * np.asarray(direction))
    return [round(float(v), 9) for v in field_vector(np.zeros(3), np.array(centres),
                                                    np.array(moments)) * 1e3]


def hand_plan(*, into_keep_out: bool = False) -> dict:
    """Both EPMs 0.45 m from the centre; wrist joint A7 turns 60 deg and back (the EPM turns about
    its own centre), each pose held 3 s. `into_keep_out` moves the left EPM to 0.10 m instead."""
    arms = default_arms()
    seed = np.array([0, 0.5, 0, -1.2, 0, 0.8, 0.0])
    q0 = np.array([arm.solve(np.array([x, 0.0, 0.0]), np.array([0, 0, 1.0]), seed,
                             keep_out=(np.zeros(3), 0.15)).q for arm, x in zip(arms, (-0.45, 0.45))])
    assert all(arm.within_limits(q) for arm, q in zip(arms, q0))
    q1 = q0.copy()
    q1[:, 6] += np.radians(60)
    if into_keep_out:
        q1[0] = arms[0].solve(np.array([-0.10, 0.0, 0.0]), np.array([0, 0, 1.0]), q0[0]).q
    move, hold = 3.0, 3.0  # 60 deg at <= 1.5 x 60 / 3 = 30 deg/s peak (A7 limit: 40.5 deg/s)
    t = [0.0, 1.0, 1 + move, 1 + move + hold, 1 + 2 * move + hold, 1 + 2 * move + 2 * hold]
    knots = [q0, q0, q1, q1, q0, q0]
    segments = [
        {"name": "turn", "U": _U_mT(arms, q1), "start_s": t[1], "reached_s": t[2], "end_s": t[3],
         "residual": [0.0] * 8},
        {"name": "back", "U": _U_mT(arms, q0), "start_s": t[3], "reached_s": t[4], "end_s": t[5],
         "residual": [0.0] * 8},
    ]
    return {
        "schema": "rigctl.plan/1", "kind": "field-sequence", "rig": "depm", "name": "wrist-turn",
        "epm_moment_Am2": MOMENT, "tool_offset_mm": 85.0,
        "sequence": [{"name": s["name"], "U": s["U"], "hold_s": hold} for s in segments],
        "t_s": t, "segments": segments,
        "arms": [{"name": arm.name, "position_mm": list(arm.base[:3, 3] * 1e3),
                  "rpy_deg": list(DEFAULT_BASES[i][2]),
                  "joints_rad": [list(k[i]) for k in knots]} for i, arm in enumerate(arms)],
    }


def write_plan(tmp_path: Path, doc: dict, name: str = "plan.json") -> Path:
    parse_plan(doc, name)  # a valid plan document
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def execute(capsys, plan: Path, tmp_path: Path, *extra: str, time_scale: float = TIME_SCALE):
    args = build_parser().parse_args(["execute", str(plan), "--json", "-q", "--runs",
                                      str(tmp_path / "runs"), "--time-scale", str(time_scale),
                                      *extra])
    code = args.func(args)
    out = capsys.readouterr().out.strip().splitlines()
    return code, json.loads(out[-1]), "\n".join(out[:-1])


@pytest.fixture(scope="module")
def shared_bench(tmp_path_factory):
    """One emulated bench for the module: (rig file, backdoor client)."""
    folder = tmp_path_factory.mktemp("bench")
    with EmulatedBenchProcess("depm", folder / "bench.toml") as rig_path:
        with BackdoorClient(load_rig(rig_path).emulation.backdoor) as backdoor:
            yield rig_path, backdoor


@pytest.fixture
def bench(shared_bench):
    """The shared bench, arms parked at rest ("candle", all joints 0) and every fault cleared."""
    rig_path, backdoor = shared_bench
    for device in ("left", "right"):
        backdoor.request("fault", device=device, kind="unstall")
        backdoor.request("fault", device=device, kind="restore")
    backdoor.request("fault", device="hall", kind="restore")
    wait_for(lambda: all(a["mode"] == "idle" and a["connections"] == 0
                         for a in backdoor.request("truth")["arms"].values()),
             30.0, "both arms at rest, no client")
    for device in ("left", "right"):
        backdoor.request("place", arm=device, q=[0.0] * 7)
    return rig_path, backdoor


def test_hand_made_plan_reaches_both_poses(tmp_path, capsys, bench):
    plan = write_plan(tmp_path, hand_plan())
    code, summary, text = execute(capsys, plan, tmp_path, "--rig", str(bench[0]))
    assert code == 0, text
    assert summary["violations"] == 0 and not summary["faults"]
    table = summary["table1"]
    for label in ("Bz", "dBx/dx"):
        assert table[label]["steady_state_error_pct"] < 2.0, (label, table[label])
    # the small terms: within 2 % of the largest gradient asked for, or the sensors' noise
    for label in ("dBx/dy", "dBy/dy"):
        entry = table[label]
        margin = max(0.02 * table["dBx/dx"]["requested"], 3 * entry["steady_state_sem"])
        assert abs(entry["steady_state"] - entry["requested"]) < margin, (label, entry)
    assert summary["samples"] > 100 and summary["samples_lost"] == 0
    run = Path(summary["run"])
    assert (run / "summary.json").exists() and (run / "field.csv").exists()
    assert len((run / "joints.csv").read_text().splitlines()) > 100


def test_trajectory_into_the_keep_out_sphere_is_refused_before_anything_moves(tmp_path, capsys,
                                                                             bench):
    plan = write_plan(tmp_path, hand_plan(into_keep_out=True))
    rig_path, backdoor = bench
    code, summary, text = execute(capsys, plan, tmp_path, "--rig", str(rig_path), time_scale=1.0)
    arms = backdoor.request("truth")["arms"]
    assert code == 2
    assert summary["violations"] >= 1
    assert any("keep" in v and "left" in v for v in summary["violation_list"]), summary
    assert "refused" in text and "t = " in text
    assert all(not any(state["q"]) and state["connections"] == 0 for state in arms.values())


def test_unsafe_approach_to_the_first_pose_is_refused(tmp_path, capsys, bench):
    plan = write_plan(tmp_path, hand_plan())
    left = default_arms()[0]
    inside = left.solve(np.array([-0.10, 0.0, 0.0]), np.array([0, 0, 1.0]),
                        np.array([0, 0.5, 0, -1.2, 0, 0.8, 0.0])).q  # EPM inside the keep-out
    rig_path, backdoor = bench
    backdoor.request("place", arm="left", q=inside.tolist())
    code, summary, text = execute(capsys, plan, tmp_path, "--rig", str(rig_path))
    left_now = backdoor.request("truth")["arms"]["left"]["q"]
    assert code == 2
    assert "approach" in summary["refused"] and summary["violations"] >= 1
    assert np.allclose(left_now, inside)  # nothing moved


@pytest.mark.parametrize("fault, named", [
    ({"device": "left", "kind": "stall_joint", "joint": 6}, ("left", "A7")),
    ({"device": "hall", "kind": "drop_link"}, ("hall board", "link lost")),
], ids=["stalled-joint", "hall-board-lost"])
def test_device_fault_stops_the_run_naming_the_device(tmp_path, capsys, fault, named, bench):
    plan = write_plan(tmp_path, hand_plan())
    rig_path, backdoor = bench
    result: dict = {}
    runner = threading.Thread(target=lambda: result.update(
        zip(("code", "summary", "text"), execute(capsys, plan, tmp_path, "--rig", str(rig_path)))))
    runner.start()
    wait_for(lambda: backdoor.request("truth")["arms"]["left"]["mode"] == "servo", 60.0,
             "the arms servoing")
    backdoor.request("fault", **fault)
    runner.join(60.0)
    # both arms were stopped: they come to rest by themselves
    wait_for(lambda: all(a["mode"] == "idle" for a in backdoor.request("truth")["arms"].values()),
             10.0, "both arms at rest")
    assert result["code"] == 3
    assert any(all(word in f for word in named) for f in result["summary"]["faults"]), result["summary"]


# The eight-component sequence of seed 003 Sec. 4 (10 mT, 100 mT/m, 5 s holds), as shipped: planned
# (hybrid) by `rigctl plan depm --sequence plans/examples/depm-eight-components.json`.
EIGHT_PLAN = Path(__file__).resolve().parents[2] / "plans" / "examples" / "depm-plan.json"


def test_eight_component_sequence_planned_run(tmp_path, capsys, bench):
    rig_path, _ = bench
    code, summary, text = execute(capsys, EIGHT_PLAN, tmp_path, "--rig", str(rig_path),
                                  time_scale=6.0)
    log = rig_path.parent / "bench.log"
    if log.exists():
        text += "\nbench log:\n" + log.read_text()[-2000:]
    assert summary["violations"] == 0, text
    assert not summary["faults"], text
    table = summary["table1"]
    for label in ("Bx", "By", "Bz", "dBx/dx", "dBx/dy", "dBx/dz", "dBy/dy", "dBy/dz"):
        assert table[label]["steady_state_error_pct"] < 2.0, (label, table[label], text)
    assert code == 0


def test_agnostic_baseline_is_refused_with_its_violations(tmp_path, capsys):
    code, summary, text = execute(capsys, EIGHT_PLAN, tmp_path, "--agnostic")
    assert code == 2
    assert summary["planner"] == "agnostic"
    assert summary["violations"] > 0 and summary["table1"] is None
    assert "refused" in text and "nothing moved" in text
