"""Sec. IV-G of seed 004: two particles in right prisms and cylinders, checked by an independent
replay of eq. 1 (a second implementation of the point kinematics, written here)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.core.errors import PlanError
from rigctl.plans.wall_contact import centre_region
from rigctl.plans.wall_contact_3d import plan_two_particles_3d, prism_region

RADIUS = 0.5
HEIGHT = 10.0
EPSILON = 0.05
SECTIONS = {
    "cylinder": {"disk": [0.0, 0.0, 10.0]},
    "square prism": {"rect": [0.0, 0.0, 20.0, 20.0]},
    "acute triangle prism": {"polygon": [[0.0, 0.0], [20.0, 0.0], [10.0, 15.0]]},
    "obtuse triangle prism": {"polygon": [[0.0, 0.0], [24.0, 0.0], [4.0, 6.0]]},
    "hexagonal prism": {"polygon": [[10 * math.cos(a), 10 * math.sin(a)]
                                    for a in np.arange(6) * math.pi / 3]},
}


class Prism:
    """Where centres may be, from the shape alone: inside the section shrunk by RADIUS, and
    RADIUS <= z <= HEIGHT - RADIUS. Half-planes for polygons, a radius for the disk."""

    def __init__(self, shape: dict) -> None:
        if "disk" in shape:
            cx, cy, r = shape["disk"]
            self.disk = (np.array([cx, cy]), r - RADIUS)
            self.planes = None
        else:
            if "rect" in shape:
                x, y, w, h = shape["rect"]
                v = np.array([[x, y], [x + w, y], [x + w, y + h], [x, y + h]], dtype=float)
            else:
                v = np.array(shape["polygon"], dtype=float)
            a, b = v[1] - v[0], v[2] - v[1]
            if a[0] * b[1] - a[1] * b[0] < 0:
                v = v[::-1]
            edges = np.roll(v, -1, axis=0) - v
            normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
            normals /= np.hypot(*normals.T)[:, None]
            self.planes = (normals, np.sum(normals * v, axis=1) - RADIUS)

    def gap(self, p: np.ndarray) -> float:
        """Smallest distance from p (3,) to the boundary (negative outside)."""
        z_gap = min(p[2] - RADIUS, HEIGHT - RADIUS - p[2])
        if self.planes is None:
            centre, r = self.disk
            return min(z_gap, r - math.hypot(*(p[:2] - centre)))
        normals, offsets = self.planes
        return min(z_gap, float(np.min(offsets - normals @ p[:2])))

    def outward_normals(self, p: np.ndarray, tol: float = 1e-7) -> list[np.ndarray]:
        found = []
        if p[2] - RADIUS <= tol:
            found.append(np.array([0.0, 0.0, -1.0]))
        if HEIGHT - RADIUS - p[2] <= tol:
            found.append(np.array([0.0, 0.0, 1.0]))
        if self.planes is None:
            centre, r = self.disk
            w = p[:2] - centre
            if r - math.hypot(*w) <= tol:
                found.append(np.array([*(w / math.hypot(*w)), 0.0]))
        else:
            normals, offsets = self.planes
            for n, h in zip(normals, offsets):
                if h - n @ p[:2] <= tol:
                    found.append(np.array([n[0], n[1], 0.0]))
        return found


def replay(prism: Prism, start: np.ndarray, moves: np.ndarray, planned: np.ndarray) -> np.ndarray:
    """Eq. 1 for points: a particle on a wall the move pushes into stays; others travel along the
    move until the boundary (found by bisection on `gap`). A move along a wall is not into it (the
    convention of the 2D planner and the global-input model). Where a move grazes a wall a particle
    touches (|N . u| < 1e-6) the two implementations' rounding decides; there the planner's state
    (`planned`, (m, 2, 3)) is taken."""
    p = np.array(start, dtype=float)
    states = []
    for k, move in enumerate(moves):
        length = float(np.linalg.norm(move))
        u = move / length
        for i in range(2):
            along = [n @ u for n in prism.outward_normals(p[i])]
            if any(abs(a) < 1e-6 for a in along):
                p[i] = planned[k, i]
                continue
            if any(a > 0 for a in along):
                continue
            if prism.gap(p[i] + length * u) >= 0:
                p[i] = p[i] + length * u
                continue
            lo, hi = 0.0, length
            for _ in range(80):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if prism.gap(p[i] + mid * u) >= 0 else (lo, mid)
            p[i] = p[i] + lo * u
        states.append(p.copy())
    return np.array(states)


def random_point(rng: np.random.Generator, prism: Prism) -> np.ndarray:
    while True:
        p = np.array([*rng.uniform(-12, 26, 2), rng.uniform(RADIUS, HEIGHT - RADIUS)])
        if prism.gap(p) >= 0 and prism.gap(np.array([p[0], p[1], HEIGHT / 2])) >= 0.01:
            return p


@pytest.mark.parametrize("name", sorted(SECTIONS))
def test_random_pairs_end_within_epsilon_by_independent_replay(name: str) -> None:
    shape = SECTIONS[name]
    prism = Prism(shape)
    region = prism_region(centre_region(shape, RADIUS), HEIGHT, RADIUS)
    rng = np.random.default_rng(100 + sorted(SECTIONS).index(name))
    for _ in range(25):
        starts = np.array([random_point(rng, prism), random_point(rng, prism)])
        goals = np.array([random_point(rng, prism), random_point(rng, prism)])
        result = plan_two_particles_3d(region, starts, goals, EPSILON)
        assert result.solved
        states = replay(prism, starts, result.moves, result.states)
        assert np.abs(states - result.states).max() < 1e-6
        assert np.linalg.norm(states[-1] - goals, axis=1).max() <= EPSILON


@pytest.mark.parametrize("name", ["cylinder", "square prism"])
def test_z_moves_use_the_side_wall_never_the_caps(name: str) -> None:
    shape = SECTIONS[name]
    prism = Prism(shape)
    region = prism_region(centre_region(shape, RADIUS), HEIGHT, RADIUS)
    rng = np.random.default_rng(7)
    relative_z_changes = 0
    for _ in range(25):
        starts = np.array([random_point(rng, prism), random_point(rng, prism)])
        goals = np.array([random_point(rng, prism), random_point(rng, prism)])
        result = plan_two_particles_3d(region, starts, goals, EPSILON)
        before = np.concatenate([starts[None], result.states[:-1]])
        for move, p0, p1 in zip(result.moves, before, result.states):
            # Nobody rests on a cap before any move (Sec. IV-G uses no end-cap contact) ...
            for p in p0:
                assert min(p[2] - RADIUS, HEIGHT - RADIUS - p[2]) > 1e-9
            dz = p1[:, 2] - p0[:, 2]
            if abs(dz[1] - dz[0]) > 1e-9:
                # ... and the relative height changes only while one particle is held on the side
                # wall (its z does not change) and the move pushes into that wall.
                relative_z_changes += 1
                held = int(np.argmin(np.abs(dz)))
                assert abs(dz[held]) < 1e-12
                walls = [n for n in prism.outward_normals(p0[held]) if n[2] == 0]
                assert walls and walls[0] @ move > 0
        # The end states are inside the caps: the final z translation hits no cap early.
        assert np.all(result.states[:, :, 2] >= RADIUS - 1e-9)
        assert np.all(result.states[:, :, 2] <= HEIGHT - RADIUS + 1e-9)
    assert relative_z_changes >= 20  # nearly every random pair needs its relative height changed


def test_opposite_relative_heights_that_no_translation_fits_take_two_rounds() -> None:
    # Particle 2 starts 8 mm above particle 1 and must end 8 mm below it: |dz| + |dz'| = 16 mm is
    # more than the 9 mm of room between the caps, so the heights are first equalised.
    shape = SECTIONS["cylinder"]
    region = prism_region(centre_region(shape, RADIUS), HEIGHT, RADIUS)
    starts = np.array([[-3.0, 0.0, 1.0], [3.0, 1.0, 9.0]])
    goals = np.array([[2.0, -2.0, 9.0], [-4.0, 3.0, 1.0]])
    result = plan_two_particles_3d(region, starts, goals, EPSILON)
    assert result.solved
    states = replay(Prism(shape), starts, result.moves, result.states)
    assert np.linalg.norm(states[-1] - goals, axis=1).max() <= EPSILON


def test_particles_with_the_same_x_y_are_refused() -> None:
    region = prism_region(centre_region(SECTIONS["cylinder"], RADIUS), HEIGHT, RADIUS)
    with pytest.raises(PlanError, match="same x, y"):
        plan_two_particles_3d(region, [[1.0, 1.0, 2.0], [1.0, 1.0, 7.0]],
                              [[0.0, 0.0, 5.0], [3.0, 3.0, 5.0]], EPSILON)


def test_cli_height_writes_a_3d_document_that_replays_to_the_goals(tmp_path):
    import json

    from rigctl.apps.cli.main import main

    workspace = tmp_path / "ws.json"
    workspace.write_text(json.dumps({"boundary": SECTIONS["cylinder"]}))
    out = tmp_path / "plan3d.json"
    code = main(["plan", "wall-contact", "--workspace", str(workspace), "--height", str(HEIGHT),
                 "--start", "0,0,2", "--start", "3,3,8", "--goal=-4,2,5", "--goal", "5,-1,3",
                 "--epsilon", "0.05", "-o", str(out)])
    assert code == 0
    document = json.loads(out.read_text())
    assert document["kind"] == "global-moves-3d" and document["height_mm"] == HEIGHT
    starts = np.array([a["start"] for a in document["agents"]])
    goals = np.array([a["goal"] for a in document["agents"]])
    moves = np.array(document["moves"])
    states = replay(Prism(SECTIONS["cylinder"]), starts, moves, np.array(document["expected"]))
    assert np.linalg.norm(states[-1] - goals, axis=1).max() <= 0.05
    # X,Y without Z is refused when --height is given
    assert main(["plan", "wall-contact", "--workspace", str(workspace), "--height", "10",
                 "--start", "0,0", "--start", "3,3", "--goal", "1,1", "--goal", "2,2",
                 "-o", str(out)]) == 2
