"""The plan format: spellings that must validate, messages that name the field, geometric checks."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from rigctl.core.errors import PlanError
from rigctl.plans.checks import check_plan, contact_for_rig, plan_workspace, simulate
from rigctl.plans.schema import (
    GlobalMovesPlan,
    ImageWorkspaceSpec,
    dump_plan,
    load_plan,
    load_workspace,
    parse_plan,
    plan_json_schema,
)

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"

ENV1 = {
    "boundary": {"rect": [0, 0, 400, 400]},
    "obstacles": [
        {"rect": [0, 0, 400, 50]},
        {"rect": [0, 350, 400, 50]},
        {"rect": [0, 0, 50, 400]},
        {"rect": [350, 0, 50, 400]},
        {"rect": [175, 150, 100, 25]},
        {"rect": [150, 150, 25, 100]},
    ],
}


def plan_data(**changes) -> dict:
    data = {
        "schema": "rigctl.plan/1",
        "kind": "global-moves",
        "rig": "six-coil",
        "workspace": copy.deepcopy(ENV1),
        "agents": [
            {"start": [100, 70], "goal": [130, 58], "radius": 8},
            {"start": [100, 300], "goal": [130, 270], "radius": 8},
        ],
        "moves": [[30, -30]],
    }
    data.update(changes)
    return data


def problem(data, source="plan.json") -> str:
    with pytest.raises(PlanError) as caught:
        parse_plan(data, source)
    return str(caught.value)


def test_all_three_shape_spellings_validate():
    workspace = {
        "boundary": {"polygon": [[0, 0], [400, 0], [400, 400], [0, 400]]},
        "obstacles": [{"rect": [10, 20, 30, 40]}, {"disk": [200, 200, 25]},
                      {"polygon": [[300, 300], [320, 300], [310, 330]]}],
    }
    plan = parse_plan(plan_data(workspace=workspace), "plan.json")
    assert isinstance(plan, GlobalMovesPlan)
    assert plan.workspace.boundary.polygon[2] == (400.0, 400.0)
    assert plan.workspace.obstacles[0].rect == (10.0, 20.0, 30.0, 40.0)
    assert plan.workspace.obstacles[1].disk == (200.0, 200.0, 25.0)
    assert plan.tolerance_mm == 1.0 and plan.expected is None and plan.name is None


def test_obstacles_are_optional_and_the_disk_can_be_the_boundary():
    plan = parse_plan(plan_data(workspace={"boundary": {"disk": [0, 0, 50]}},
                                agents=[{"start": [0, 0], "goal": [10, 0], "radius": 2}]))
    assert plan.workspace.obstacles == []


def test_kind_selects_the_document_type():
    assert problem(plan_data(kind="pair-wise")) == (
        'plan.json: kind: expected one of global-moves, field-sequence, pair-formation, '
        'got "pair-wise"'
    )
    # A known kind validates its own fields: a global-moves document is not a pair-formation one.
    assert "moves: Extra inputs are not permitted" in problem(plan_data(kind="pair-formation"))
    assert "kind" in problem({k: v for k, v in plan_data().items() if k != "kind"})


def test_messages_name_the_field_by_its_json_path():
    data = plan_data()
    data["agents"][1]["radius"] = -2
    assert problem(data) == "plan.json: agents.1.radius: Input should be greater than or equal to 0.001"
    data = plan_data()
    data["workspace"]["boundary"] = {"circle": [0, 0, 10]}
    assert problem(data) == 'plan.json: workspace.boundary: expected one of rect, polygon, disk, got {"circle": ...}'
    data = plan_data()
    data["workspace"]["obstacles"][4] = {"rect": [175, 150, 0, 25]}
    assert problem(data) == "plan.json: workspace.obstacles.4.rect.2: Input should be greater than or equal to 0.001"
    data = plan_data()
    data["workspace"]["obstacles"].append({"polygon": [[0, 0], [10, 10], [10, 0], [0, 10]]})
    assert problem(data) == "plan.json: workspace.obstacles.6.polygon: polygon is not simple: edges 0 and 2 cross"
    assert "workspace.obstacles.0.polygon: List should have at least 3 items" in problem(
        plan_data(workspace={"boundary": {"rect": [0, 0, 9, 9]}, "obstacles": [{"polygon": [[0, 0], [1, 1]]}]})
    )
    # the rig kinds that run a plan kind are the registry's (each kind's `plans`)
    assert problem(plan_data(rig="depm")) == ("plan.json: rig: a global-moves plan runs on coil-board or "
                                              "six-coil, not 'depm'")
    assert problem(plan_data(speed=3)) == "plan.json: speed: Extra inputs are not permitted"
    assert "schema" in problem({k: v for k, v in plan_data().items() if k != "schema"})
    assert "'rigctl.plan/9'" in problem(plan_data(schema="rigctl.plan/9"))


def test_a_plan_with_thousands_of_problems_lists_the_first_twenty_and_counts_the_rest():
    data = json.loads((EXAMPLES / "depm-plan.json").read_text())
    data["t_s"] = ["late"] * 5000  # a long list stops at its first bad row
    with pytest.raises(PlanError) as refused:
        parse_plan(data, "plan.json")
    assert str(refused.value) == ("plan.json: t_s.0: Input should be a valid number, unable to "
                                  "parse string as a number")
    data = json.loads((EXAMPLES / "depm-plan.json").read_text())
    data["sequence"] = [5] * 500  # 500 components, each not an object: one problem each
    with pytest.raises(PlanError) as refused:
        parse_plan(data, "plan.json")
    lines = str(refused.value).splitlines()
    assert len(lines) == 21
    assert lines[0].startswith("plan.json: sequence.0: Input should be")
    assert lines[19].startswith("plan.json: sequence.19: ")
    assert lines[20] == "plan.json: and 480 more problems like these"


def test_invalid_json_says_where(tmp_path):
    path = tmp_path / "plan.json"
    path.write_text('{\n  "schema": "rigctl.plan/1",\n  "kind": global\n}\n')
    with pytest.raises(PlanError, match=r"plan.json: line 3 column 11: not valid JSON"):
        load_plan(path)
    with pytest.raises(PlanError, match="no such file"):
        load_plan(tmp_path / "absent.json")


def test_dump_reads_back_the_same_plan():
    plan = simulate(parse_plan(plan_data(name="round trip", tolerance_mm=0.5)))
    text = dump_plan(plan)
    data = json.loads(text)
    assert list(data)[0] == "schema" and data["schema"] == "rigctl.plan/1"
    again = parse_plan(data, "again.json")
    assert again.model_dump() == plan.model_dump()


def test_published_schema_describes_the_format():
    schema = plan_json_schema()
    text = json.dumps(schema)
    for word in ('"schema"', '"global-moves"', '"rect"', '"polygon"', '"disk"', '"mm_per_px"', '"tolerance_mm"'):
        assert word in text
    assert schema["$id"] == "rigctl.plan/1"


def test_contact_for_rig():
    assert contact_for_rig("six-coil") == "slide"
    assert contact_for_rig("coil-board") == "non-slip"
    with pytest.raises(PlanError):
        contact_for_rig("depm")


def test_check_plan_catches_an_agent_starting_inside_the_l():
    plan = parse_plan(plan_data(agents=[{"start": [160, 200], "goal": [100, 100], "radius": 8}]), "plan.json")
    with pytest.raises(PlanError, match=r"plan.json: agents.0.start: \(160, 200\) is inside a wall"):
        check_plan(plan)
    # Free but closer to the L than the radius.
    plan = parse_plan(plan_data(agents=[{"start": [100, 100], "goal": [180, 200], "radius": 8}]), "plan.json")
    with pytest.raises(PlanError, match=r"agents.0.goal: \(180, 200\) is too close to a wall"):
        check_plan(plan)


def test_check_plan_catches_overlapping_agents():
    agents = [{"start": [100, 100], "goal": [100, 300], "radius": 8},
              {"start": [110, 100], "goal": [300, 300], "radius": 8}]
    with pytest.raises(PlanError, match="agents.1.start: overlaps agent 0"):
        check_plan(parse_plan(plan_data(agents=agents)))


def test_check_plan_compares_expected_with_the_model():
    # By hand: agent 0 meets the bottom wall (y = 58) after 12 mm and slides: (130, 58);
    # agent 1 is far from every wall: (130, 270).
    good = plan_data(expected=[[[130, 58], [130, 270]]])
    check_plan(parse_plan(good))
    wrong = plan_data(expected=[[[130, 58], [130, 270.5]]])
    with pytest.raises(PlanError, match=r"expected.0.1: .* after move 0, 0.5 mm from expected"):
        check_plan(parse_plan(wrong, "plan.json"))
    with pytest.raises(PlanError, match="expected: has 2 entries for 1 moves"):
        check_plan(parse_plan(plan_data(expected=[[[130, 58], [130, 270]]] * 2)))
    with pytest.raises(PlanError, match="expected.0: has 1 positions for 2 agents"):
        check_plan(parse_plan(plan_data(expected=[[[130, 58]]])))


def test_simulate_uses_the_rigs_contact():
    slid = simulate(parse_plan(plan_data(rig="six-coil")))
    stuck = simulate(parse_plan(plan_data(rig="coil-board")))
    np.testing.assert_allclose(slid.expected[0][0], [130, 58], atol=1e-9)
    np.testing.assert_allclose(stuck.expected[0][0], [112, 58], atol=1e-9)  # stops where it touches
    check_plan(stuck)


def test_image_workspace_resolves_next_to_the_plan(tmp_path):
    cv2 = pytest.importorskip("cv2")
    picture = np.full((100, 100), 255, dtype=np.uint8)
    picture[:, :20] = 0  # left fifth is wall
    (tmp_path / "maps").mkdir()
    cv2.imwrite(str(tmp_path / "maps" / "wall.png"), picture)
    data = plan_data(
        workspace={"image": "maps/wall.png", "mm_per_px": 0.5},
        agents=[{"start": [25, 25], "goal": [30, 25], "radius": 3}],
        moves=[[-20, 0]],
    )
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(data))
    plan = load_plan(path)
    assert isinstance(plan.workspace, ImageWorkspaceSpec) and plan.workspace.origin == (0.0, 0.0)
    # The wall ends at x = 20 * 0.5 = 10 mm; a 3 mm agent stops at 13 mm.
    np.testing.assert_allclose(simulate(plan).expected[0][0], [13.0, 25.0], atol=0.3)
    assert load_workspace(path) == plan.workspace
    with pytest.raises(PlanError, match="does not exist"):
        plan_workspace(parse_plan(data, str(tmp_path / "elsewhere" / "plan.json")))


@pytest.mark.parametrize("name", ["fig4-two-magnets.json", "fig4-quick.json"])
def test_example_plans_check_and_break_the_symmetry(name):
    plan = load_plan(EXAMPLES / name)
    check_plan(plan)
    assert plan.rig == "six-coil" and plan.expected is not None
    moves = np.array(plan.moves)
    assert np.all((moves == 0).sum(axis=1) == 1), "axis-aligned moves"
    lengths = np.abs(moves).sum(axis=1)
    np.testing.assert_array_equal(lengths % 10, 0)  # whole turns of the 10 mm magnet
    limit_moves, limit_mm = (12, 600) if name == "fig4-two-magnets.json" else (3, 120)
    assert len(moves) <= limit_moves and lengths.sum() <= limit_mm
    start = np.array([a.start for a in plan.agents])
    goal = np.array([a.goal for a in plan.agents])
    assert np.hypot(*((goal[1] - goal[0]) - (start[1] - start[0]))) > 10, "goal offset differs"
    np.testing.assert_allclose(plan.expected[-1], goal, atol=1e-9)


def test_broken_example_names_its_mistake():
    with pytest.raises(PlanError, match=r"broken-plan.json: agents.1.radius: Input should be "
                                        r"greater than or equal to 0.001"):
        load_plan(EXAMPLES / "broken-plan.json")
