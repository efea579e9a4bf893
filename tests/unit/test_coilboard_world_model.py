"""The coil board's world: forces, velocities and contacts against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.emulators.world.coilboard import (
    CoilBoardPhysics,
    CoilBoardWorld,
    coil_forces,
    intestine_ring_spec,
)
from rigctl.plans.schema import parse_workspace
from rigctl.plans.workspace import Workspace

PHYSICS = CoilBoardPhysics(pole_distance_mm=100.0, exponent=4.0, force_at_centre_N=2e-4,
                           viscosity_Pa_s=10.0)
R = 0.5  # particle radius, mm
# Stokes: v = F / (6 pi eta r); in mm/s for F in N, eta in Pa s, r in m.
V0 = 2e-4 / (6 * math.pi * 10.0 * 0.5e-3) * 1e3  # 2.122 mm/s at the centre, one coil at full drive


def disk(radius: float = 20.0) -> Workspace:
    return Workspace.from_spec(parse_workspace({"boundary": {"disk": [0.0, 0.0, radius]}}))


def test_force_at_the_centre_is_f0_towards_the_active_coil() -> None:
    for coil, direction in enumerate([(1, 0), (-1, 0), (0, 1), (0, -1)]):
        outputs = np.zeros(4)
        outputs[coil] = 1.0
        force = coil_forces(PHYSICS, (0, 0), [[0.0, 0.0]], outputs)[0]
        assert force == pytest.approx(2e-4 * np.array(direction), abs=1e-15)


def test_force_grows_as_the_inverse_fourth_power_nearer_the_coil() -> None:
    # On the +x axis 20 mm from the centre the pole is 80 mm away: (100 / 80)^4 = 2.44140625.
    near = coil_forces(PHYSICS, (0, 0), [[20.0, 0.0]], [1, 0, 0, 0])[0]
    far = coil_forces(PHYSICS, (0, 0), [[-20.0, 0.0]], [1, 0, 0, 0])[0]
    assert near == pytest.approx([2e-4 * 2.44140625, 0.0], rel=1e-12)
    assert far == pytest.approx([2e-4 * (100 / 120) ** 4, 0.0], rel=1e-12)


def test_force_points_at_the_coils_centre_off_axis() -> None:
    # At (0, 30) the +x pole (100, 0) is at distance sqrt(100^2 + 30^2) = 104.403 in direction
    # (100, -30) / 104.403: the pull leans 16.70 degrees towards the axis.
    force = coil_forces(PHYSICS, (0, 0), [[0.0, 30.0]], [1, 0, 0, 0])[0]
    d = math.hypot(100, 30)
    expected = 2e-4 * (100 / d) ** 4 * np.array([100, -30]) / d
    assert force == pytest.approx(expected, rel=1e-12)
    assert math.degrees(math.atan2(-force[1], force[0])) == pytest.approx(16.699, abs=1e-3)


def test_reversed_drive_pulls_the_same_and_coils_add() -> None:
    p = [[3.0, -4.0]]
    assert coil_forces(PHYSICS, (0, 0), p, [-0.5, 0, 0, 0]) == pytest.approx(
        coil_forces(PHYSICS, (0, 0), p, [0.5, 0, 0, 0]))
    both = coil_forces(PHYSICS, (0, 0), p, [0.5, 0, 0.25, 0])
    apart = coil_forces(PHYSICS, (0, 0), p, [0.5, 0, 0, 0]) + coil_forces(
        PHYSICS, (0, 0), p, [0, 0, 0.25, 0])
    assert both == pytest.approx(apart, rel=1e-12)


def test_free_velocity_is_mobility_times_force() -> None:
    world = CoilBoardWorld(disk(), [[0.0, 0.0]], R, PHYSICS, centre_mm=(0, 0))
    assert world.free_velocities([0, 0, 1, 0])[0] == pytest.approx([0.0, V0], rel=1e-12)


def test_free_flight_along_the_axis_matches_the_closed_form() -> None:
    # dx/dt = V0 (D / (D - x))^4  =>  (D - x)^5 = (D - x0)^5 - 5 V0 D^4 t.
    world = CoilBoardWorld(disk(), [[-10.0, 0.0]], R, PHYSICS, centre_mm=(0, 0))
    world.step(4.0, [1, 0, 0, 0])
    expected = 100.0 - ((110.0) ** 5 - 5 * V0 * 100.0**4 * 4.0) ** 0.2
    assert world.positions_mm[0] == pytest.approx([expected, 0.0], abs=1e-4)


def test_a_particle_stops_on_the_wall_and_stays_while_pushed_into_it() -> None:
    world = CoilBoardWorld(disk(), [[10.0, 0.0]], R, PHYSICS, centre_mm=(0, 0))
    world.step(30.0, [1, 0, 0, 0])
    assert world.positions_mm[0] == pytest.approx([19.5, 0.0], abs=1e-6)  # wall at 20, radius 0.5
    # On the wall at 30 degrees the +x pull points into the wall with a tangential part; eq. 1
    # (friction = inf) holds the particle.
    on_wall = 19.5 * np.array([math.cos(math.pi / 6), math.sin(math.pi / 6)])
    world = CoilBoardWorld(disk(), [on_wall], R, PHYSICS, centre_mm=(0, 0))
    assert world.velocities([1, 0, 0, 0])[0] == pytest.approx([0.0, 0.0])
    world.step(5.0, [1, 0, 0, 0])
    assert world.positions_mm[0] == pytest.approx(on_wall, abs=1e-9)
    # Pulled away from the wall it leaves at the free velocity.
    free = CoilBoardWorld(disk(), [on_wall], R, PHYSICS, centre_mm=(0, 0)).free_velocities(
        [0, 1, 0, 0])
    assert world.velocities([0, 1, 0, 0]) == pytest.approx(free)


def test_a_finite_friction_cone_lets_a_steep_push_slide() -> None:
    # A particle on the flat wall y = -10 (a rect), pulled by the +x coil and a little by the -y
    # coil: into the wall with a larger part along it. Coulomb with mu = 0.5: it slides with the
    # tangential part less mu times the normal part; a steep push (mostly -y) holds it.
    ws = Workspace.from_spec(parse_workspace({"boundary": {"rect": [-10, -10, 20, 20]}}))
    physics = CoilBoardPhysics(pole_distance_mm=100.0, force_at_centre_N=2e-4,
                               viscosity_Pa_s=10.0, friction=0.5)
    world = CoilBoardWorld(ws, [[0.0, -9.5]], R, physics, centre_mm=(0, 0))
    v_free = world.free_velocities([1, 0, 0, 0.2])[0]
    normal, tangential = -v_free[1], v_free[0]  # into the wall (down), along it (+x)
    assert normal > 0 and tangential > 0.5 * normal
    v = world.velocities([1, 0, 0, 0.2])[0]
    assert v == pytest.approx([tangential - 0.5 * normal, 0.0], rel=1e-9)
    stuck = CoilBoardWorld(ws, [[0.0, -9.5]], R, physics, centre_mm=(0, 0))
    assert stuck.velocities([0.1, 0, 0, 1])[0] == pytest.approx([0.0, 0.0])  # inside the cone


def test_free_particles_in_contact_push_each_other_at_the_mean_speed() -> None:
    # Side by side across the +x coil's axis, touching: each is pulled towards the pole, so they
    # press together along y; free, they share the mean normal velocity (0 by symmetry) and keep
    # their own x speeds.
    world = CoilBoardWorld(disk(), [[0.0, 0.5], [0.0, -0.5]], R, PHYSICS, centre_mm=(0, 0))
    free = world.free_velocities([1, 0, 0, 0])
    assert free[0, 1] < 0 < free[1, 1]  # closing
    v = world.velocities([1, 0, 0, 0])
    assert v[:, 1] == pytest.approx([0.0, 0.0], abs=1e-15)
    assert v[:, 0] == pytest.approx(free[:, 0], rel=1e-12)
    # Ahead and faster (the one nearer the pole): they part, nothing changes.
    world = CoilBoardWorld(disk(), [[-1.0, 0.0], [0.0, 0.0]], R, PHYSICS, centre_mm=(0, 0))
    assert world.velocities([1, 0, 0, 0]) == pytest.approx(world.free_velocities([1, 0, 0, 0]))


def test_a_particle_held_by_the_wall_holds_the_one_pushed_into_it() -> None:
    world = CoilBoardWorld(disk(), [[19.5, 0.0], [18.5, 0.0]], R, PHYSICS, centre_mm=(0, 0))
    assert world.velocities([1, 0, 0, 0]) == pytest.approx(np.zeros((2, 2)))
    world.step(2.0, [1, 0, 0, 0])
    assert world.positions_mm.ravel() == pytest.approx([19.5, 0.0, 18.5, 0.0], abs=1e-9)


def test_particles_never_overlap_while_stepping() -> None:
    world = CoilBoardWorld(disk(), [[-5.0, 0.3], [5.0, -0.3]], R, PHYSICS, centre_mm=(0, 0))
    for outputs in ([1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.3]):
        world.step(8.0, outputs)
        gap = math.hypot(*(world.positions_mm[1] - world.positions_mm[0]))
        assert gap >= 2 * R - 1e-9
        assert np.all(world.workspace.clearance(world.positions_mm) >= R - 1e-9)


def test_intestine_ring_has_sixty_two_millimetre_protrusions() -> None:
    spec = intestine_ring_spec()
    vertices = np.array(spec["boundary"]["polygon"])
    radii = np.hypot(vertices[:, 0], vertices[:, 1])
    assert np.sum(np.isclose(radii, 21.0)) == 60  # tips: 23 mm - 2 mm
    assert np.all(np.isclose(radii, 21.0) | np.isclose(radii, 23.0))
    ws = Workspace.from_spec(parse_workspace(spec))
    assert ws.clearance(np.array([0.0, 0.0])) == pytest.approx(21.0)
    # Between two tips (3 degrees off a tip) a 1 mm particle reaches beyond r = 21.
    between = 21.7 * np.array([math.cos(math.radians(3)), math.sin(math.radians(3))])
    assert ws.clearance(between) > R
