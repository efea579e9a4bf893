"""Identification from tracking (`rigctl.physics.identify`) and the global-input model's per-agent
response: estimates checked against the parameters that generated the data, the model against
hand-worked displacements and against the shared-input model it reduces to."""

import math

import numpy as np
import pytest

from rigctl.physics.identify import CommandedVelocity, LinearEstimate, RollingIdentifier
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.workspace import ShapeWorkspace

BOX = ShapeWorkspace(("rect", (0.0, 0.0, 400.0, 400.0)))


# -- the estimator --------------------------------------------------------------------------------

def test_linear_estimate_matches_the_closed_form_posterior():
    """Sequential updates equal the batch posterior (P0^-1 + H'H/s^2)^-1 computed by hand."""
    rng = np.random.default_rng(1)
    h = rng.normal(size=(12, 3))
    y = h @ np.array([0.7, -1.2, 2.0]) + rng.normal(0.0, 0.1, 12)
    estimate = LinearEstimate("abc", [0.0, 0.0, 0.0], [10.0, 10.0, 10.0])
    for row, value in zip(h, y):
        assert estimate.update(row[None], [value], 0.1, gate_sigma=None)
    information = np.eye(3) / 100.0 + h.T @ h / 0.01
    cov = np.linalg.inv(information)
    np.testing.assert_allclose(estimate.cov, cov, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(estimate.mean, cov @ (h.T @ y / 0.01), rtol=1e-9)
    batch = LinearEstimate("abc", [0.0, 0.0, 0.0], [10.0, 10.0, 10.0])
    batch.refit(h, y, 0.1)
    np.testing.assert_allclose(batch.mean, estimate.mean, rtol=1e-9)


def test_an_outlier_beyond_the_gate_is_left_out():
    estimate = LinearEstimate(["g"], [1.0], [0.01])
    assert not estimate.update([[10.0]], [20.0], 0.05)  # 10 mm off a 0.1 mm prediction spread
    assert estimate.mean[0] == 1.0 and estimate.rejected == 1
    assert estimate.update([[10.0]], [10.1], 0.05)


# -- rolling agents --------------------------------------------------------------------------------

def _rolled(gain: float, heading: float, u: np.ndarray, drift: np.ndarray, dt: float):
    c, s = math.cos(heading), math.sin(heading)
    return gain * np.array([c * u[0] - s * u[1], s * u[0] + c * u[1]]) + drift * dt


def test_rolling_identifier_recovers_each_agents_gain_heading_and_drift():
    truth_gain = np.array([0.85 * 1.1, 0.85 * 0.92, 0.85])
    truth_heading = np.radians([2.0, -3.0, 0.0])
    drift = np.array([0.004, -0.003])
    rng = np.random.default_rng(7)
    ident = RollingIdentifier(3)
    for k in range(12):
        angle = rng.uniform(0, 2 * math.pi)
        u = 10.0 * rng.integers(1, 6) * np.array([math.cos(angle), math.sin(angle)])
        dt = float(rng.uniform(2.0, 30.0))
        y = np.array([_rolled(g, h, u, drift, dt) for g, h in zip(truth_gain, truth_heading)])
        y += rng.normal(0.0, 0.05, y.shape)  # tracker noise, both ends
        free = np.array([True, True, k % 2 == 0])  # the third is against a wall every other move
        y[2] = y[2] if free[2] else np.array([0.0, 0.0])  # a wall stopped it: not used
        used = ident.observe(u, y, free, dt)
        assert used.tolist() == free.tolist()
    np.testing.assert_allclose(ident.gains, truth_gain, atol=0.004)
    np.testing.assert_allclose(ident.headings_rad, truth_heading, atol=math.radians(0.3))
    np.testing.assert_allclose(ident.drift_mm_s[:2], [drift, drift], atol=0.003)
    assert np.all(ident.gain_std < 0.004) and np.all(ident.gain_std > 0)
    assert ident.updates.tolist() == [12, 12, 6]


def test_an_agent_never_seen_free_plans_with_the_others_mean():
    ident = RollingIdentifier(2)
    u = np.array([30.0, 0.0])
    ident.observe(u, np.array([[25.5, 0.0], [0.0, 0.0]]), [True, False], 5.0)
    gains, headings = ident.response()
    assert gains[0] == pytest.approx(0.85, abs=0.01)
    assert gains[1] == gains[0] and headings[1] == headings[0]
    assert ident.gains[1] == 1.0  # its own estimate is still the prior


# -- the model with per-agent responses -------------------------------------------------------------

def test_default_response_is_the_shared_model_bit_for_bit():
    ws = ShapeWorkspace(("rect", (0.0, 0.0, 400.0, 400.0)), [("rect", (150, 150, 25, 100))])
    shared = GlobalInputModel(ws, [8.0, 8.0])
    neutral = shared.with_response([1.0, 1.0], [0.0, 0.0])
    rng = np.random.default_rng(0)
    p = np.array([[100.0, 200.0], [120.0, 230.0]])
    moves = rng.normal(0.0, 40.0, (50, 2))
    assert np.array_equal(shared.apply(p, moves), neutral.apply(p, moves))


def test_each_agent_moves_by_its_own_gain_and_heading_in_free_space():
    model = GlobalInputModel(BOX, [5.0, 5.0], gains=[0.9, 1.1],
                             headings_rad=[0.0, math.radians(90.0)])
    p = np.array([[100.0, 100.0], [300.0, 300.0]])
    out = model.apply(p, [20.0, 0.0])
    # by hand: 0.9 * (20, 0) and 1.1 * (20, 0) turned 90 degrees = (0, 22)
    np.testing.assert_allclose(out, [[118.0, 100.0], [300.0, 322.0]], atol=1e-9)


def test_a_wall_stops_the_faster_agent_first():
    """Both roll towards x = 400 from x = 350 (radius 5: contact at x = 395): the agent with gain
    1.2 reaches the wall on 37.5 mm of input, the one with 0.9 is at 350 + 0.9 * 40 = 386."""
    model = GlobalInputModel(BOX, [5.0, 5.0], gains=[1.2, 0.9])
    p = np.array([[350.0, 100.0], [350.0, 300.0]])
    out = model.apply(p, [40.0, 0.0])
    np.testing.assert_allclose(out, [[395.0, 100.0], [386.0, 300.0]], atol=1e-6)
    # the wall turns different gains into a relative move a shared translation cannot make
    back = model.apply(out, [-10.0, 0.0])
    np.testing.assert_allclose(back, [[383.0, 100.0], [377.0, 300.0]], atol=1e-6)


def test_agents_with_different_gains_do_not_pass_through_each_other():
    model = GlobalInputModel(BOX, [5.0, 5.0], gains=[1.5, 0.5])
    p = np.array([[100.0, 200.0], [115.0, 200.0]])  # 5 mm apart, the fast one behind
    out = model.apply(p, [20.0, 0.0])
    assert bool(model.is_free(out))
    assert np.hypot(*(out[1] - out[0])) >= 10.0 - 1e-6
    assert out[0, 0] <= out[1, 0]  # never overtook


def test_bad_per_agent_parameters_are_refused():
    from rigctl.core.errors import PlanError

    with pytest.raises(PlanError, match="gains"):
        GlobalInputModel(BOX, [5.0, 5.0], gains=[1.0])
    with pytest.raises(PlanError, match="gains must be > 0"):
        GlobalInputModel(BOX, [5.0, 5.0], gains=[1.0, -0.2])


# -- contact corrections ----------------------------------------------------------------------------

def test_a_contact_correction_fixes_a_relative_error_no_translation_can():
    """Two robots in a 400 mm box, the right one 1.2 mm too far right of the left one: no shared
    translation can fix that (the best, none, leaves 0.6 mm each). Pushing +x until the right
    robot rests on the wall at x = 392 and 1.2 mm further brings the left one 1.2 mm closer; the
    translation back then lands both. Checked by replaying the moves through the model."""
    from rigctl.plans.correction import correct_by_contact

    model = GlobalInputModel(BOX, [8.0, 8.0])
    goals = np.array([[300.0, 200.0], [200.0, 200.0]])
    start = goals + [[0.6, 0.0], [-0.6, 0.0]]
    best_translation = np.linalg.norm(start + (goals - start).mean(axis=0) - goals)
    assert best_translation == pytest.approx(0.6 * math.sqrt(2), abs=1e-9)
    correction = correct_by_contact(model, start, goals)
    assert correction.distance < 0.05
    replayed = model.rollout(start, correction.moves)[-1]
    np.testing.assert_allclose(replayed, correction.states[-1])
    assert np.linalg.norm(replayed - goals) < 0.05
    # it used a wall: some move pushed a robot into contact (x = 400 - 8 or x = 8)
    xs = np.concatenate([start[None], model.rollout(start, correction.moves)])[..., 0]
    assert np.isclose(xs, 392.0, atol=1e-6).any() or np.isclose(xs, 8.0, atol=1e-6).any()


def test_a_contact_correction_uses_the_identified_gains():
    """With gains 0.8 and 0.9, robots a commanded (25, -12) mm and a 0.5 mm relative error from
    their goals: the correction planned on the identified model lands (replayed through it);
    planned on the shared model it misses by about |0.05 (25, -12)| = 1.4 mm per robot."""
    from rigctl.plans.correction import correct_by_contact

    gains = np.array([0.8, 0.9])
    identified = GlobalInputModel(BOX, [8.0, 8.0], gains=gains)
    goals = np.array([[340.0, 150.0], [150.0, 260.0]])  # the right one 72 mm from a wall
    start = goals - gains[:, None] * [25.0, -12.0] + [[0.5, 0.0], [0.0, 0.0]]
    correction = correct_by_contact(identified, start, goals)
    assert np.linalg.norm(identified.rollout(start, correction.moves)[-1] - goals) < 0.05
    naive = correct_by_contact(GlobalInputModel(BOX, [8.0, 8.0]), start, goals)
    assert np.linalg.norm(identified.rollout(start, naive.moves)[-1] - goals) > 1.5


def test_commanded_velocity_integrates_piecewise_between_two_frames():
    log = CommandedVelocity()
    log.send(1.0, (2.0, 0.0))
    log.send(1.5, (0.0, -4.0))
    log.send(2.0, (1.0, 1.0))
    # [0.5, 1.0): nothing sent yet; [1.0, 1.5): 2 x 0.5 in x; [1.5, 2.0): -4 x 0.5 in y;
    # [2.0, 2.25]: 1 x 0.25 in both
    assert log.integral(0.5, 2.25) == pytest.approx([1.0 + 0.25, -2.0 + 0.25])
    assert log.integral(1.2, 1.4) == pytest.approx([0.4, 0.0])
    assert log.integral(3.0, 3.0) == pytest.approx([0.0, 0.0])


def test_commanded_velocity_keeps_only_recent_history():
    log = CommandedVelocity(keep_s=1.0)
    for k in range(100):
        log.send(0.1 * k, (1.0, 0.0))
    assert len(log._t) <= 12  # 1 s of 0.1 s entries, and the one that covers its start
    assert log.integral(9.0, 9.5) == pytest.approx([0.5, 0.0])


def test_named_agents_name_the_series_columns():
    columns = RollingIdentifier(1, names=["centroid"]).series_columns()
    assert "gain_centroid" in columns and "gain_centroid_std" in columns
    assert "moves_used_centroid" in columns
    with pytest.raises(ValueError):
        RollingIdentifier(2, names=["one"])


def test_an_agent_pressed_into_a_corner_is_not_known_by_it():
    """Seed 101's first move: robot 0 sits in the corner of a box and is pushed into it (it does
    not move, and the model says so for any gain: the derivatives are 0), robot 1 rolls freely,
    25.5 mm of 30 (gain 0.85). The move counts against robot 0 but tells nothing about it, so it
    plans with robot 1's 0.85, not with its untouched prior 1.0."""
    from rigctl.rigs.six_coil.supervisor import one_agent_move

    single = GlobalInputModel(BOX, [8.0])
    corner, u = np.array([8.0, 392.0]), np.array([-20.0, 20.0])
    predicted, jacobian = one_agent_move(single, corner, u, np.array([1.0, 0.0]))
    np.testing.assert_allclose(predicted, [0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(jacobian, 0.0, atol=1e-9)
    ident = RollingIdentifier(2)
    ident.observe(u, np.array([[0.0, 0.0], [-17.0, 17.0]]), [False, True], 5.0)
    assert ident.observe_linearised(0, u, predicted, jacobian, np.zeros(2), 5.0, 0.1)
    assert ident.updates.tolist() == [1, 1]
    assert ident.gains[0] == pytest.approx(1.0, abs=1e-6)  # its own estimate: the prior
    gains, _ = ident.response()
    assert gains[1] == pytest.approx(0.85, abs=0.01)
    assert gains[0] == gains[1]

def test_a_move_along_a_wall_is_linearised_by_hand():
    """A robot resting on the floor y = 0 (radius 8, centre y = 8) pushed by u = (20, -10) with
    a = 0.8, b = 0.05: freely it would go by (a u_x - b u_y, b u_x + a u_y) = (16.5, -7); the wall
    keeps its y, so it slides by (16.5, 0), and only the first row depends on (a, b):
    d/da = u_x = 20, d/db = -u_y = 10."""
    from rigctl.rigs.six_coil.supervisor import one_agent_move

    single = GlobalInputModel(BOX, [8.0])
    predicted, jacobian = one_agent_move(single, np.array([200.0, 8.0]), np.array([20.0, -10.0]),
                                         np.array([0.8, 0.05]))
    np.testing.assert_allclose(predicted, [16.5, 0.0], atol=1e-6)
    np.testing.assert_allclose(jacobian, [[20.0, 10.0], [0.0, 0.0]], atol=1e-4)


def test_a_robot_that_only_slides_along_walls_is_identified():
    """Every move pushes the robot along the floor or up the left wall (never free): the gain
    comes out of those moves alone, from the prior g = 1; the heading is left as it was."""
    from rigctl.rigs.six_coil.supervisor import one_agent_move

    g, theta = 0.75, 0.0
    a, b = g * math.cos(theta), g * math.sin(theta)
    single = GlobalInputModel(BOX, [8.0])
    identifier = RollingIdentifier(1)
    rng = np.random.default_rng(3)
    floor, wall = np.array([200.0, 8.0]), np.array([8.0, 200.0])
    for k in range(16):
        along_floor = k % 2 == 0
        start = floor if along_floor else wall
        commanded = np.array([30.0 * (-1) ** (k // 2), -15.0]) if along_floor else \
            np.array([-15.0, 30.0 * (-1) ** (k // 2)])
        truth = single.apply(start[None], [a * commanded[0] - b * commanded[1],
                                           b * commanded[0] + a * commanded[1]])[0]
        measured = truth - start + rng.normal(0.0, 0.05, 2)
        predicted, jacobian = one_agent_move(single, start, commanded,
                                             identifier.estimates[0].mean[:2])
        assert identifier.observe_linearised(0, commanded, predicted, jacobian, measured, 1.0,
                                             0.1)
    assert identifier.gains[0] == pytest.approx(g, abs=0.01)
    assert identifier.headings_rad[0] == pytest.approx(0.0, abs=1e-9)
    assert identifier.gain_std[0] < 0.01


def test_a_move_that_ends_on_the_ceiling_tells_the_gain_not_the_heading():
    """From (60, 300), radius 8, under a ceiling at y = 350, the input (30.6, 73.9) with g = 0.78
    rolls freely until y = 342 and then along the ceiling: x still grows by g u_x, so the robot
    ends at (60 + 0.78 * 30.6, 342) = (83.87, 342). That says g (one equation in a, b); the
    heading stays where it was instead of taking up the rest (the first run of seed 119 read
    2.5 degrees from this one move, on an emulator with none)."""
    from rigctl.rigs.six_coil.supervisor import one_agent_move

    single = GlobalInputModel(ShapeWorkspace(("rect", (0.0, 0.0, 400.0, 350.0))), [8.0])
    identifier = RollingIdentifier(1)
    start, commanded = np.array([60.0, 300.0]), np.array([30.6, 73.9])
    predicted, jacobian = one_agent_move(single, start, commanded, np.array([1.0, 0.0]))
    np.testing.assert_allclose(predicted, [30.6, 42.0], atol=1e-6)  # g = 1: (30.6, 42) by hand
    assert identifier.observe_linearised(0, commanded, predicted, jacobian,
                                         np.array([0.78 * 30.6, 42.0]), 1.0, 0.1)
    assert identifier.gains[0] == pytest.approx(0.78, abs=0.01)
    assert identifier.headings_rad[0] == pytest.approx(0.0, abs=1e-9)
