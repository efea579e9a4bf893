"""The emulated rolling magnets against hand-worked kinematics: a cylinder of radius R rolling about
+u moves by R * angle * (u x z); steering turns the axis and moves nothing."""

import math

import numpy as np
import pytest

from rigctl.emulators.world.rolling import RollingMagnetWorld
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.schema import parse_workspace
from rigctl.plans.workspace import Workspace

R = 10.0 / (2 * math.pi)  # one turn rolls 10 mm
B0 = 3e-3


def make_world(positions, radius=5.0):
    spec = parse_workspace({"boundary": {"rect": [0, 0, 400, 400]}})
    model = GlobalInputModel(Workspace.from_spec(spec), np.full(len(positions), radius))
    return RollingMagnetWorld(model, np.array(positions, float), rolling_radius_mm=R,
                              min_field_T=0.5e-3)


def feel_rotation(world, start, axis, angle, steps=400):
    """Rotate the field vector `start` about `axis` by `angle` (Rodrigues), feeding every step."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    start = np.asarray(start, float)
    for a in np.linspace(0.0, angle, steps):
        rotated = (start * math.cos(a) + np.cross(axis, start) * math.sin(a)
                   + axis * (axis @ start) * (1 - math.cos(a)))
        world.feel(rotated)


def test_one_turn_about_x_rolls_one_circumference_along_minus_y():
    world = make_world([[200.0, 200.0]])
    # B starts along +y (horizontal, perpendicular to the axis x), then turns once about +x.
    feel_rotation(world, [0, B0, 0], [1, 0, 0], 2 * math.pi)
    # u = x, u x z = (0, -1, 0): the centre moves 2 pi R = 10 mm towards -y.
    np.testing.assert_allclose(world.positions_mm, [[200.0, 190.0]], atol=1e-9)


def test_rolling_backwards_and_about_y():
    world = make_world([[200.0, 200.0]])
    feel_rotation(world, [B0, 0, 0], [0, 1, 0], -3 * math.pi)  # 1.5 turns about -y
    # u = y (sign free), angle -3 pi: displacement R * (-3 pi) * (y x z) = -15 mm * x_hat
    np.testing.assert_allclose(world.positions_mm, [[185.0, 200.0]], atol=1e-9)


def test_steering_in_plane_moves_nothing_and_turns_the_axis():
    world = make_world([[100.0, 100.0], [150.0, 120.0]])
    feel_rotation(world, [0, B0, 0], [0, 0, 1], math.radians(60))
    np.testing.assert_allclose(world.positions_mm, [[100.0, 100.0], [150.0, 120.0]], atol=1e-12)
    # field now at 150 degrees in the plane; the axis is perpendicular to it
    assert abs(world.axis_xy @ [math.cos(math.radians(150)), math.sin(math.radians(150))]) < 1e-9


def test_weak_field_moves_nothing():
    world = make_world([[200.0, 200.0]])
    feel_rotation(world, [0, 0.2e-3, 0], [1, 0, 0], 2 * math.pi)
    np.testing.assert_allclose(world.positions_mm, [[200.0, 200.0]])


def test_all_magnets_share_the_displacement_until_a_wall_stops_one():
    # agent 0 is 6 mm from the top wall (clearance 1 mm beyond its 5 mm radius); a 10 mm roll
    # towards +y stops it after 1 mm while agent 1 goes the full 10 mm.
    world = make_world([[100.0, 394.0], [300.0, 200.0]])
    feel_rotation(world, [0, B0, 0], [1, 0, 0], -2 * math.pi)  # angle -2 pi about x: +10 mm in y
    np.testing.assert_allclose(world.positions_mm, [[100.0, 395.0], [300.0, 210.0]], atol=1e-6)


@pytest.mark.parametrize("slip", [0.85, 1.0])
def test_slip_scales_the_distance(slip):
    world = make_world([[200.0, 200.0]])
    world.slip = slip
    feel_rotation(world, [0, B0, 0], [1, 0, 0], 4 * math.pi)
    np.testing.assert_allclose(world.positions_mm, [[200.0, 200.0 - 20.0 * slip]], atol=1e-9)


def test_one_field_for_all_moves_the_robots_as_the_same_field_given_to_each():
    """`feel((3,))` has its own scalar path; `feel((n, 3))` with every row equal is the general
    one: over a random walk of the field (rolls, steering, vertical and weak fields, reversals)
    both leave every robot at the same place, axis and roll."""
    rng = np.random.default_rng(7)
    uniform = make_world([[100, 100], [140, 160], [250, 90]])
    each = make_world([[100, 100], [140, 160], [250, 90]])
    field = np.array([0.0, 0.0, B0])  # vertical first: no axis yet
    for step in range(3000):
        if step % 500 == 250:
            field = np.array([0.0, 0.0, 0.2e-3])  # below min_field_T: nothing follows
        else:
            turn = rng.normal(0.0, 0.05, 3) + [0.02, 0.0, 0.0]  # rolling, on the whole
            field = field + np.cross(turn, field) if np.linalg.norm(field) > 1e-3 else \
                np.array([B0, 0.0, 0.0])
            field *= B0 / np.linalg.norm(field)
        uniform.feel(field)
        each.feel(np.tile(field, (3, 1)))
    np.testing.assert_allclose(uniform.positions_mm, each.positions_mm, rtol=0, atol=1e-9)
    np.testing.assert_allclose(uniform.rolled_rad, each.rolled_rad, rtol=0, atol=1e-9)
    np.testing.assert_allclose(uniform._axes, each._axes, rtol=0, atol=1e-12)
    assert np.abs(uniform.rolled_rad).min() > 1.0  # they did roll, by over a radian each
