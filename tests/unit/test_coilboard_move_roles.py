"""What a coil-board move asks of each particle (`move_roles`), in the 46 mm disk of the paper's
rig with 0.5 mm particles: the centres' region is the disk of radius 22.5 mm, so a centre more
than 22.45 mm out (`slack` 0.05) is on the wall. The states are those of a recorded run in which
the camera measured a particle that Alg. 1 leaves on its wall 0.04 mm from where the plan had it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from rigctl.core.errors import PlanError
from rigctl.plans.schema import parse_plan
from rigctl.plans.wall_contact import centre_region
from rigctl.rigs.coil_board.run import CoilBoardRunSettings, move_roles, planning_region

REGION = centre_region({"disk": [0.0, 0.0, 23.0]}, 0.5)
SETTINGS = CoilBoardRunSettings()
ON_WALL = np.array([-20.07, 10.18])  # 22.504 mm out: Alg. 1's state, on the wall
MEASURED_THERE = np.array([-20.06, 10.14])  # 22.477 mm out, 0.041 mm from ON_WALL


def test_the_states_are_where_the_test_says():
    assert math.hypot(*ON_WALL) > 22.45 and math.hypot(*MEASURED_THERE) > 22.45
    assert math.hypot(*(MEASURED_THERE - ON_WALL)) > SETTINGS.skip_mm


def test_a_particle_the_plan_leaves_on_its_wall_is_pinned_wherever_the_camera_puts_it():
    move = np.array([0.84, 1.66])
    before = np.array([ON_WALL, [0.0, 0.0]])
    end = np.array([ON_WALL, move])  # particle 1, free, goes with the move; particle 0 stays
    start = np.array([MEASURED_THERE, [0.01, -0.02]])
    roles = move_roles(REGION, SETTINGS, move / math.hypot(*move), start, end, before)
    assert roles.pinned.tolist() == [True, False]
    assert roles.grazing.tolist() == [False, False]  # not pulled off its wall
    assert roles.watched.tolist() == [False, True]


def test_a_particle_the_plan_carries_along_its_wall_is_grazing():
    # 0.3 mm along the wall (clockwise), ending on it; particle 1, free, goes as far
    angle = math.atan2(ON_WALL[1], ON_WALL[0]) - 0.3 / 22.5
    along = 22.5 * np.array([math.cos(angle), math.sin(angle)])
    move = along - ON_WALL
    before = np.array([ON_WALL, [0.0, 0.0]])
    end = np.array([along, move])
    start = np.array([MEASURED_THERE, [0.0, 0.0]])
    roles = move_roles(REGION, SETTINGS, move / math.hypot(*move), start, end, before)
    assert roles.pinned.tolist() == [False, False]
    assert roles.grazing.tolist() == [True, False]
    assert roles.watched.tolist() == [False, True]  # the wall may hold it: not waited for


def test_a_move_that_brings_a_particle_to_a_wall_ends_on_that_particle():
    before = np.array([[-12.0, 0.0], [5.0, 0.0]])
    end = np.array([[-22.5, 0.0], [-5.5, 0.0]])  # particle 0 stops on the wall
    roles = move_roles(REGION, SETTINGS, np.array([-1.0, 0.0]), before, end, before)
    assert roles.watched.tolist() == [True, False]
    assert not roles.pinned.any() and not roles.grazing.any()


def test_a_plan_on_a_picture_workspace_is_refused_in_one_line_not_a_traceback():
    # a coil-board plan whose workspace is a PNG (a drawn maze): Alg. 1 plans in a boundary it
    # can draw (disk, rect, polygon), so the run refuses it by name (an AttributeError before)
    examples = Path(__file__).resolve().parents[2] / "plans" / "examples"
    data = json.loads((examples / "coilboard-disk.json").read_text())
    data["workspace"] = {"image": str(examples / "vessel-maze.png"), "mm_per_px": 0.1}
    data["moves"], data["expected"] = [], None
    plan = parse_plan(data)
    with pytest.raises(PlanError, match="drawn boundary"):
        planning_region(plan, 0.5)
