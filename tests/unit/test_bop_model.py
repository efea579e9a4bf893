"""The emulated BOP: coil physics stepped by hand, and the SCPI command table on top of it.

Expected numbers come from the closed form i = I (1 - exp(-t R/L)) worked by hand, or from a
second method (a fine explicit-Euler integration of L di/dt = v - R i with the clamp).
"""

from __future__ import annotations

import math

import pytest

from rigctl.emulators.kepco_bop import ModelClock
from rigctl.emulators.kepco_bop.model import BopCoilModel
from rigctl.emulators.kepco_bop.protocol import BopScpi

R, L = 1.5, 0.03  # tau = 20 ms


def energised(setpoint: float, *, resistance: float = R, inductance: float = L,
              compliance: float = 100.0) -> BopCoilModel:
    model = BopCoilModel(resistance, inductance)
    assert model.set_voltage(compliance)
    assert model.set_current(setpoint)
    assert model.set_output(True)
    return model


def euler(setpoint: float, compliance: float, resistance: float, inductance: float,
          duration: float, n: int = 200_000) -> float:
    """Second method: many explicit-Euler steps of L di/dt = clamp(R I_set) - R i."""
    dt = duration / n
    v = max(-compliance, min(compliance, resistance * setpoint))
    i = 0.0
    for _ in range(n):
        i += dt * (v - resistance * i) / inductance
    return i


# -- dynamics ------------------------------------------------------------------------------------


def test_step_reaches_63_percent_after_one_time_constant() -> None:
    model = energised(10.0)
    model.step(0.020)
    assert model.current_A == pytest.approx(6.321205588, rel=1e-9)  # 10 (1 - 1/e)
    assert model.voltage_V == pytest.approx(15.0)  # R I_set: R i + L di/dt during the rise


def test_one_big_step_equals_many_small_ones() -> None:
    big, small = energised(-7.0), energised(-7.0)
    big.step(0.05)
    for _ in range(500):
        small.step(0.0001)
    assert big.current_A == pytest.approx(small.current_A, rel=1e-9)


def test_unclamped_rise_agrees_with_euler() -> None:
    model = energised(4.0)
    model.step(0.01)
    assert model.current_A == pytest.approx(euler(4.0, 100.0, R, L, 0.01), rel=1e-4)


def test_compliance_clamps_the_voltage_and_the_final_current() -> None:
    # 20 A into 10 ohm needs 200 V: the pair can give 100 V, so the current settles at 10 A.
    model = energised(20.0, resistance=10.0, inductance=0.1)
    model.step(0.004)
    assert model.voltage_V == pytest.approx(100.0)
    assert model.current_A == pytest.approx(euler(20.0, 100.0, 10.0, 0.1, 0.004), rel=1e-4)
    model.step(1.0)
    assert model.current_A == pytest.approx(10.0, rel=1e-9)


def test_a_lower_compliance_setting_slows_nothing_it_does_not_limit() -> None:
    # 2 A into 1.5 ohm needs 3 V < 5 V: the same curve as with 100 V.
    low, high = energised(2.0, compliance=5.0), energised(2.0)
    low.step(0.013)
    high.step(0.013)
    assert low.current_A == high.current_A
    # 10 A needs 15 V > 5 V: clamped, di/dt limited
    clamped = energised(10.0, compliance=5.0)
    clamped.step(1.0)
    assert clamped.current_A == pytest.approx(5.0 / 1.5)
    assert clamped.voltage_V == pytest.approx(5.0)


def test_output_off_decays_through_the_coil_resistance() -> None:
    model = energised(8.0)
    model.step(1.0)  # 50 tau: settled
    assert model.current_A == pytest.approx(8.0)
    model.set_output(False)
    model.step(0.040)
    assert model.current_A == pytest.approx(8.0 * math.exp(-2.0), rel=1e-9)
    assert model.voltage_V == 0.0


def test_negative_time_is_refused() -> None:
    with pytest.raises(ValueError):
        energised(1.0).step(-0.001)


# -- settings and errors ---------------------------------------------------------------------------


@pytest.mark.parametrize("amps", [20.5, -25.0, float("nan")])
def test_out_of_range_current_is_refused_with_222_and_unchanged(amps: float) -> None:
    model = energised(3.0)
    assert not model.set_current(amps)
    assert model.current_setpoint_A == 3.0
    assert model.pop_error() == (-222, "Data out of range")
    assert model.pop_error() == (0, "No error")


@pytest.mark.parametrize("volts", [100.5, 0.0, -10.0])
def test_out_of_range_compliance_is_refused(volts: float) -> None:
    model = energised(3.0, compliance=40.0)
    assert not model.set_voltage(volts)
    assert model.compliance_setting_V == 40.0
    assert model.pop_error()[0] == -222


def test_error_queue_is_fifo_bounded_with_overflow_marker() -> None:
    model = BopCoilModel(R, L)
    for k in range(1, 21):
        model.push_error(k, f"error {k}")
    drained = [model.pop_error() for _ in range(17)]
    assert drained[:15] == [(k, f"error {k}") for k in range(1, 16)]  # oldest kept
    assert drained[15] == (-350, "Too many errors")
    assert drained[16] == (0, "No error")


def test_over_temperature_trips_the_output_and_reports() -> None:
    model = energised(5.0)
    model.inject_overtemperature()
    assert not model.output_on
    assert model.questionable_condition() & 8
    assert model.read_event_status() & 8  # device-dependent error bit
    assert model.pop_error() == (20101, "OVER TEMPERATURE")
    assert not model.set_output(True)  # refused while hot
    assert model.pop_error() == (20101, "OVER TEMPERATURE")
    model.clear_overtemperature()
    assert model.set_output(True)
    assert model.questionable_condition() == 0


# -- the SCPI table ----------------------------------------------------------------------------------


@pytest.fixture
def scpi():
    return BopScpi(BopCoilModel(R, L))


@pytest.mark.parametrize(
    "command",
    ["CURR 1.5", "curr 1.5", "Current 1.5", "SOUR:CURR 1.5", "SOURce:CURRent:LEVel:IMMediate:AMPlitude 1.5",
     ":curr:lev 1.5", "CURR 1.5E0", "CURR +.15e1"],
)
def test_short_long_and_optional_forms_are_accepted(scpi, command: str) -> None:
    assert scpi.handle(command) is None
    assert float(scpi.handle("CURR?")) == 1.5
    assert scpi.handle("SYST:ERR?") == '0,"No error"'


def test_unknown_and_partial_keywords_are_undefined_headers(scpi) -> None:
    for command in ("CURRE 1", "FOO?", "MEAS:CURR", "SYST:ERR", "*XYZ"):
        scpi.handle(command)
        assert scpi.handle("SYST:ERR?") == '-113,"Undefined header"', command


def test_parameter_errors(scpi) -> None:
    expected = {
        "CURR": '-109,"Missing parameter"',
        "CURR abc": '-120,"Numeric data error"',
        "CURR 7000": '-120,"Numeric data error"',
        "CURR 25": '-222,"Data out of range"',
        "MEAS:CURR? 1": '-108,"Parameter not allowed"',
        "OUTP MAYBE": '-102,"Syntax error"',
        "CURR 1;;CURR 2": '-102,"Syntax error"',
    }
    for command, error in expected.items():
        scpi.handle(command)
        assert scpi.handle("SYST:ERR?") == error, command


def test_max_and_min_keywords(scpi) -> None:
    scpi.handle("CURR MAX")
    assert float(scpi.handle("CURR?")) == 20.0
    scpi.handle("CURR MIN")
    assert float(scpi.handle("CURR?")) == -20.0


def test_compound_message_with_root_reset_and_relative_path(scpi) -> None:
    reply = scpi.handle("OUTP ON;:CURR 2;:MEAS:CURR?;VOLT?")
    current, voltage = (float(x) for x in reply.split(";"))
    assert (current, voltage) == (0.0, 0.0)  # no time has passed
    scpi.model.step(0.020)
    # CURR? continues from MEAS: it is the measured current, not the 2 A setpoint
    voltage, current = (float(x) for x in scpi.handle("MEAS:VOLT?;CURR?").split(";"))
    assert voltage == pytest.approx(3.0)  # R I_set = 1.5 * 2 during the rise
    assert current == pytest.approx(2.0 * (1 - math.exp(-1)), rel=1e-6)


def test_command_error_discards_the_rest_of_the_message_execution_error_does_not(scpi) -> None:
    scpi.handle("CURR 1;BOGUS 2;:CURR 3")
    assert float(scpi.handle("CURR?")) == 1.0
    scpi.handle("CURR 30;:CURR 4")
    assert float(scpi.handle("CURR?")) == 4.0


def test_replies_are_in_scientific_notation(scpi) -> None:
    scpi.handle("CURR -1.25")
    assert scpi.handle("CURR?") == "-1.250000E+00"


def test_mode_output_and_common_commands(scpi) -> None:
    assert scpi.handle("*IDN?").startswith("KEPCO,BOP 50-20GL")
    assert scpi.handle("FUNC:MODE?") == "1"
    scpi.handle("FUNC:MODE VOLT")
    assert scpi.handle("FUNC:MODE?") == "0"
    assert scpi.handle("OUTP?") == "0"
    scpi.handle("OUTP ON")
    assert scpi.handle("OUTP?;*OPC?") == "1;1"
    scpi.handle("CURR 99")
    assert scpi.handle("*ESR?") == "16"  # execution error bit
    assert scpi.handle("*ESR?") == "0"  # cleared by reading
    scpi.handle("*RST")
    assert scpi.handle("OUTP?;FUNC:MODE?") == "0;1"
    assert scpi.handle("*STB?") == "4"  # the -222 is still queued
    scpi.handle("*CLS")
    assert scpi.handle("SYST:ERR?") == '0,"No error"'


def test_over_temperature_through_scpi(scpi) -> None:
    scpi.handle("OUTP ON")
    scpi.model.inject_overtemperature()
    assert scpi.handle("OUTP?") == "0"
    assert scpi.handle("STAT:QUES:COND?") == "8"
    assert scpi.handle("STAT:QUES?") == "8"
    assert scpi.handle("STAT:QUES?") == "0"  # the event register clears on read
    assert scpi.handle("SYST:ERR?") == '20101,"OVER TEMPERATURE"'


def test_before_command_runs_once_per_line() -> None:
    calls = []
    scpi = BopScpi(BopCoilModel(R, L), before_command=lambda: calls.append(1))
    scpi.handle("CURR 1;:MEAS:CURR?;VOLT?")
    scpi.handle("*IDN?")
    assert len(calls) == 2


def test_model_clock_steps_by_elapsed_time_times_speed() -> None:
    now = [100.0]
    steps = []
    clock = ModelClock(steps.append, speed=4.0, clock=lambda: now[0])
    clock.advance()  # starts the clock, no step
    now[0] = 100.25
    clock.advance()
    now[0] = 100.25  # no time passed: no step
    clock.advance()
    assert steps == [1.0]
