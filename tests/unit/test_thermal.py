"""The winding model (`rigctl.physics.thermal`) against closed forms and an ODE solver, and the emulated
supply's winding that trips it on over-temperature (`emulators/kepco_bop/model.py`)."""

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from rigctl.core.config import CoilThermal
from rigctl.emulators.kepco_bop.model import (
    OVER_TEMPERATURE,
    QUES_OVERTEMPERATURE,
    BopCoilModel,
)
from rigctl.physics.thermal import (
    Windings,
    rest_to_pass,
    step_current,
    step_current_one,
    step_voltage,
    voltage_steady_C,
    winding_temperatures,
    with_rests,
)

R0 = 1.5  # ohm at 20 C


def windings(n=1, *, alpha=0.00393, r_th=0.5, c_th=200.0, limit=100.0, warning=90.0):
    thermal = CoilThermal(thermal_resistance_K_per_W=r_th, thermal_capacity_J_per_K=c_th,
                          ambient_C=25.0, max_winding_C=limit, warning_C=warning,
                          alpha_per_K=alpha)
    return Windings.of([f"c{j}" for j in range(n)], [R0] * n, [thermal] * n)


def ode(current_of_t, w, t_end, j=0, start_C=None):
    """C dT/dt = I(t)^2 R0 (1 + alpha (T - 20)) - (T - Ta)/R_th by a Runge-Kutta solver."""
    def rhs(t, temperature):
        current = current_of_t(t)
        power = current**2 * R0 * (1 + w.alpha[j] * (temperature - w.reference_C[j]))
        return (power - (temperature - w.ambient_C[j]) / w.r_th[j]) / w.c_th[j]
    start = w.ambient_C[j] if start_C is None else start_C
    return solve_ivp(rhs, (0, t_end), [start], rtol=1e-10, atol=1e-10, max_step=1.0)


def test_without_alpha_a_held_current_gives_the_first_order_step_response():
    w = windings(alpha=0.0)
    # T(t) = Ta + I^2 R0 R_th (1 - exp(-t / (R_th C))), by hand
    for t in (1.0, 100.0, 1e4):
        expected = 25.0 + 10.0**2 * R0 * 0.5 * (1 - math.exp(-t / 100.0))
        assert step_current([25.0], [10.0], t, w)[0] == pytest.approx(expected, rel=1e-12)


def test_with_alpha_the_exact_step_matches_an_ode_solver():
    w = windings()
    solved = ode(lambda t: 12.0, w, 300.0)
    assert step_current([25.0], [12.0], 300.0, w)[0] == pytest.approx(solved.y[0, -1], abs=1e-6)


def test_above_the_runaway_current_the_winding_has_no_steady_state():
    w = windings(c_th=50.0)
    runaway = math.sqrt(1 / (R0 * 0.00393 * 0.5))  # I^2 R0 alpha = 1 / R_th: 18.4 A
    solved = ode(lambda t: 20.0, w, 200.0)
    assert 20.0 > runaway
    assert step_current([25.0], [20.0], 200.0, w)[0] == pytest.approx(solved.y[0, -1], rel=1e-7)
    assert step_current([25.0], [20.0], 2000.0, w)[0] > 1e4  # no bound: it only grows


def test_the_scan_over_a_piecewise_program_equals_the_ode_and_the_step_by_step_loop():
    rng = np.random.default_rng(4)
    w = windings(3)
    currents = rng.uniform(-15, 15, (700, 3))
    dt = rng.uniform(0.0, 5.0, 700)
    dt[::50] = 5e4  # long rests: the decay factors floor, the chunks split
    scanned = winding_temperatures(currents, dt, w)
    temperature = w.ambient_C.copy()
    for k in range(len(dt)):
        temperature = step_current(temperature, currents[k], dt[k], w)
        assert scanned[k + 1] == pytest.approx(temperature, rel=1e-9)
    edges = np.concatenate([[0.0], np.cumsum(dt[1:50])])  # the samples between two long rests
    solved = ode(lambda t: currents[1 + min(np.searchsorted(edges, t, side="right") - 1, 48), 1],
                 w, edges[-1], j=1, start_C=scanned[1, 1])
    assert scanned[50, 1] == pytest.approx(solved.y[0, -1], abs=1e-3)


def test_the_emulators_scalar_step_is_the_same_physics():
    w = windings(2)
    for current, dt in ((0.0, 3.0), (7.5, 0.001), (19.0, 60.0)):
        assert step_current_one(40.0, current, dt, w.one(1)) == pytest.approx(
            step_current([40.0, 40.0], [current, current], dt, w)[1], rel=1e-13)


def test_under_a_voltage_the_winding_settles_where_joule_heat_balances_the_loss():
    w = windings(c_th=40.0)
    steady = voltage_steady_C([12.0], w)[0]
    resistance = R0 * (1 + 0.00393 * (steady - 20.0))
    assert (steady - 25.0) / 0.5 == pytest.approx(12.0**2 / resistance, rel=1e-12)
    temperature = np.array([25.0])
    for _ in range(4000):  # 200 time constants of 20 s
        temperature = step_voltage(temperature, [12.0], 1.0, w)
    assert temperature[0] == pytest.approx(steady, abs=1e-6)


def test_the_rest_it_suggests_is_the_shortest_that_keeps_every_winding_below_its_limit():
    w = windings(2, c_th=20.0, limit=60.0, warning=55.0)
    moves = np.tile([[9.0, 3.0]], (400, 1))  # 4 s at 100 Hz per move ...
    program = np.vstack([moves] * 5)  # ... five of them
    ends = [400 * (i + 1) for i in range(5)]
    peak = winding_temperatures(program, 0.01, w).max()
    assert peak > 60.0  # back to back they overheat coil c0
    rest = rest_to_pass(program, 0.01, ends, w, tolerance_s=0.05)
    assert rest is not None and rest > 0

    def peak_with(r):
        currents, dt = with_rests(program, 0.01, ends, r)
        return winding_temperatures(currents, dt, w).max()

    assert peak_with(rest) < 55.0 <= peak_with(rest - 0.1)  # below the warning: no pause
    assert rest_to_pass(program * 0.3, 0.01, ends, w) == 0.0  # cool enough without
    one_long = np.tile([[12.0, 0.0]], (6000, 1))  # one 60 s move alone passes 55 C
    assert rest_to_pass(one_long, 0.01, [6000], w) is None


def test_the_emulated_supply_trips_on_its_winding_s_heat_and_recovers_when_cool():
    w = windings(alpha=0.0, c_th=100.0)  # tau = 50 s
    bop = BopCoilModel(R0, 0.03, winding=w, trip_C=110.0)
    bop.set_current(15.0)
    bop.set_output(True)
    # T(t) = 25 + 15^2 R0 R_th (1 - exp(-t / 50)) = 110 C at t = -50 ln(1 - 85 / 168.75), by hand
    trip_s = -50.0 * math.log(1 - 85.0 / (15.0**2 * R0 * 0.5))
    t = 0.0
    while not bop.overtemperature and t < 200:
        bop.step(0.01)
        t += 0.01
    assert t == pytest.approx(trip_s, abs=0.05)  # (the current's 20 ms rise only delays it)
    assert not bop.output_on and bop.questionable_condition() == QUES_OVERTEMPERATURE
    assert bop.pop_error() == OVER_TEMPERATURE
    assert not bop.set_output(True)  # refused while hot
    while bop.overtemperature and t < 1000:
        bop.step(0.5)
        t += 0.5
    assert bop.winding_C < 100.0  # cleared 10 K below the trip point
    assert bop.set_output(True)


def test_an_injected_over_temperature_stays_until_restored_however_cool_the_winding():
    bop = BopCoilModel(R0, 0.03, winding=windings(), trip_C=110.0)
    bop.inject_overtemperature()
    for _ in range(100):
        bop.step(1.0)
    assert bop.overtemperature and bop.winding_C == pytest.approx(25.0)
    bop.clear_overtemperature()
    assert not bop.overtemperature


def test_model_and_emulated_windings_agree_within_2_K_over_ten_emulated_minutes():
    """The six-coil bench's emulated supplies (their windings made by the bench's own
    `emulated_winding`, R_th and C_th 5 % off the rig file's) stepped by hand through ten
    minutes of a current program that changes every 15 s; the model is given the supplies'
    currents every 10 ms and the rig file's data."""
    from rigctl.core.config import default_six_coil_coils
    from rigctl.emulators.bench import emulated_winding

    thermal = CoilThermal(thermal_resistance_K_per_W=0.5, thermal_capacity_J_per_K=1500.0,
                          ambient_C=22.0, max_winding_C=150.0, warning_C=140.0)
    coils = [c.model_copy(update={"thermal": thermal}) for c in default_six_coil_coils()]
    supplies = [BopCoilModel(c.resistance_ohm, c.inductance_H, **emulated_winding(c, 0.05))
                for c in coils]
    levels = np.random.default_rng(11).uniform(-14.0, 14.0, (40, 6))
    dt, per_sample = 0.002, 5  # the bench's millisecond-scale steps; one model sample per 10 ms
    samples, truth = [], []
    for supply in supplies:
        supply.set_output(True)
    for k in range(int(600.0 / (dt * per_sample))):
        level = levels[int(k * dt * per_sample // 15.0)]
        for supply, amps in zip(supplies, level):
            supply.set_current(float(amps))
        samples.append([s.current_A for s in supplies])  # what a read-back would measure now
        for _ in range(per_sample):
            for supply in supplies:
                supply.step(dt)
        truth.append([s.winding_C for s in supplies])
    model = winding_temperatures(np.array(samples), dt * per_sample, Windings.of_coils(coils))[1:]
    truth = np.array(truth)
    assert truth.max() > 22.0 + 25  # they did heat, by tens of kelvin
    assert np.abs(model - truth).max() < 2.0


def test_the_live_monitor_follows_the_model_and_says_warning_then_limit():
    from rigctl.physics.thermal import WindingMonitor

    w = windings(2, c_th=20.0, limit=60.0, warning=55.0)
    monitor = WindingMonitor(w)
    states, temperature = [], w.ambient_C.copy()
    for _ in range(3000):  # 30 s at 10 A in coil c0 (steady 25 + 75 / (1 - 0.29) C), c1 off
        states.append(monitor.update(np.array([10.0, 0.0]), 0.01))
        temperature = step_current(temperature, [10.0, 0.0], 0.01, w)
    assert monitor.temperature_C == pytest.approx(temperature, rel=1e-12)
    first_warning, first_limit = states.index("warning"), states.index("limit")
    assert 0 < first_warning < first_limit and set(states[:first_warning]) == {"ok"}
    assert monitor.hottest()[0] == "c0" and monitor.peak_C[1] == pytest.approx(25.0)


# -- windings driven by a voltage (the coil board's SyRens) ---------------------------------------

def board_windings(*, alpha=0.00393, r_th=2.5, c_th=4.0, warning=60.0, limit=70.0):
    """Four coil-board windings of 6 ohm on a 12 V supply, driven in SyRen units (12/127 V each)."""
    from rigctl.core.config import CoilBoardSettings

    thermal = CoilThermal(thermal_resistance_K_per_W=r_th, thermal_capacity_J_per_K=c_th,
                          ambient_C=25.0, warning_C=warning, max_winding_C=limit, alpha_per_K=alpha)
    return Windings.of_board(CoilBoardSettings(url="/dev/null", coil_thermal=thermal))


def test_without_alpha_a_held_voltage_gives_the_first_order_step_response():
    from rigctl.physics.thermal import step_voltage_one

    w = board_windings(alpha=0.0)
    # T(t) = Ta + R_th V^2 / R0 (1 - exp(-t / (R_th C))): 8 V on 6 ohm, tau = 10 s, by hand
    t, temperature = 0.0, 25.0
    for dt in (0.02,) * 500 + (1.0,) * 20:
        temperature = step_voltage_one(temperature, 8.0, dt, w.one(2))
        t += dt
        expected = 25.0 + 2.5 * 8.0**2 / 6.0 * (1 - math.exp(-t / 10.0))
        assert temperature == pytest.approx(expected, rel=1e-12)


def test_with_alpha_the_voltage_step_follows_an_ode_solver():
    from rigctl.physics.thermal import step_voltage_one

    w = board_windings()

    def rhs(t, temperature):  # C dT/dt = V^2 / (R0 (1 + alpha (T - 20))) - (T - Ta) / R_th
        volts = 12.0 if t < 30.0 else 4.0
        return (volts**2 / (6.0 * (1 + 0.00393 * (temperature - 20.0)))
                - (temperature - 25.0) / 2.5) / 4.0

    solved = solve_ivp(rhs, (0, 60.0), [25.0], rtol=1e-10, atol=1e-10, max_step=0.01,
                       dense_output=True)
    temperature = 25.0
    for k in range(3000):  # the stream's 50 Hz
        temperature = step_voltage_one(temperature, 12.0 if k < 1500 else 4.0, 0.02, w.one(0))
        if k % 250 == 249:
            assert temperature == pytest.approx(solved.sol((k + 1) * 0.02)[0], abs=0.01)


def test_the_live_monitor_takes_the_boards_drive_as_volts_and_says_warning_then_limit():
    from rigctl.physics.thermal import WindingMonitor

    w = board_windings(alpha=0.0, warning=50.0, limit=60.0)
    assert w.volts_per_unit == pytest.approx(12.0 / 127)
    monitor = WindingMonitor(w)
    states = [monitor.update(np.array([127, -127, 0, 0]), 0.02) for _ in range(2500)]  # 50 s
    # full drive, either sense: 12 V, 24 W, steady 25 + 60 C, tau 10 s; the others stay cold
    expected = 25.0 + 60.0 * (1 - math.exp(-50.0 / 10.0))
    assert monitor.temperature_C == pytest.approx([expected, expected, 25.0, 25.0], rel=1e-9)
    # it reaches 50 C at t = -tau ln(1 - 25/60) and 60 C at -tau ln(1 - 35/60), by hand
    warning_s, limit_s = -10.0 * math.log(1 - 25.0 / 60.0), -10.0 * math.log(1 - 35.0 / 60.0)
    assert states.index("warning") == math.ceil(warning_s / 0.02) - 1
    assert states.index("limit") == math.ceil(limit_s / 0.02) - 1
    assert monitor.hottest()[0] in ("+x", "-x")


def test_the_emulated_board_coils_heat_by_the_syren_output_with_their_own_seeded_data():
    from rigctl.core.config import CoilBoardSettings
    from rigctl.emulators.coilboard.coils import BoardCoils, ThermalErrors

    thermal = CoilThermal(thermal_resistance_K_per_W=2.5, thermal_capacity_J_per_K=4.0,
                          ambient_C=25.0, warning_C=90.0, max_winding_C=100.0, alpha_per_K=0.0)
    board = CoilBoardSettings(url="/dev/null", coil_thermal=thermal)
    coils = BoardCoils(board, ThermalErrors(size=0.05, seed=3))
    built = coils.describe()["coils"]
    r_th = np.array([c["r_th_K_per_W"] for c in built])
    c_th = np.array([c["c_th_J_per_K"] for c in built])
    assert np.all(np.abs(r_th / 2.5 - 1) <= 0.05) and np.all(np.abs(c_th / 4.0 - 1) <= 0.05)
    assert np.all(r_th != 2.5) and len(set(r_th)) == 4  # each coil its own
    assert BoardCoils(board, ThermalErrors(size=0.05, seed=3)).describe()["coils"] == built
    for _ in range(300):  # 30 s: +x at full output, -x at half reversed, the y coils off
        assert coils.step(0.1, (1.0, -0.5, 0.0, 0.0)) == (1.0, -0.5, 0.0, 0.0)
    # T = Ta + R_th V^2 / R0 (1 - exp(-t / (R_th C_th))) with the coil's own R_th, C_th, by hand
    for j, volts in enumerate((12.0, 6.0, 0.0, 0.0)):
        expected = 25.0 + r_th[j] * volts**2 / 6.0 * (1 - math.exp(-30.0 / (r_th[j] * c_th[j])))
        assert coils.temperature_C[j] == pytest.approx(expected, rel=1e-9)


def test_an_emulated_board_coil_past_its_cut_out_pulls_nothing_until_it_has_cooled():
    from rigctl.core.config import CoilBoardSettings
    from rigctl.emulators.coilboard.coils import BoardCoils, ThermalErrors

    thermal = CoilThermal(thermal_resistance_K_per_W=4.0, thermal_capacity_J_per_K=1.0,
                          ambient_C=25.0, warning_C=60.0, max_winding_C=70.0, alpha_per_K=0.0)
    coils = BoardCoils(CoilBoardSettings(url="/dev/null", coil_thermal=thermal), ThermalErrors(0.0))
    pulls = [coils.step(0.05, (1.0, 0.0, 0.0, 0.0))[0] for _ in range(200)]  # 10 s
    # full output: T = 25 + 96 (1 - exp(-t / 4)) reaches the cut-out's 80 C at t = -4 ln(1 - 55/96),
    # and off, T = 25 + 55 exp(-t / 4) is down to 70 C (10 K below) after 4 ln(55/45), by hand
    opened = pulls.index(0.0)
    assert opened == math.ceil(-4.0 * math.log(1 - 55.0 / 96.0) / 0.05)
    assert pulls[opened:].index(1.0) == math.ceil(4.0 * math.log(55.0 / 45.0) / 0.05)
    assert coils.peak_C[0] == pytest.approx(80.0, abs=0.7) and max(coils.peak_C[1:]) == 25.0
    assert pulls.count(0.0) > 50  # it cycles on its cut-out; the other coils never heat
