"""The Kepco BOP driver against scripted exchanges: the exact bytes it sends and how it reads."""

from __future__ import annotations

import pytest

from rigctl.apps.testing import ScriptedTransport
from rigctl.core.errors import (
    ConfigError,
    DeviceError,
    DeviceTimeout,
    Disconnected,
    LimitError,
    ProtocolError,
)
from rigctl.drivers.kepco_bop import KepcoBop

NO_ERROR = b'0,"No error"\n'


def bop(steps, **kwargs) -> tuple[KepcoBop, ScriptedTransport]:
    script = ScriptedTransport(steps)
    return KepcoBop(script, name="x+", **kwargs), script


def test_identify() -> None:
    driver, script = bop([(b"*IDN?\n", b"KEPCO,BOP 50-20GL,E1234,3.05\r\n")])
    assert driver.identify() == "KEPCO,BOP 50-20GL,E1234,3.05"
    script.assert_done()


def test_configure_sends_clear_mode_compliance_zero_and_checks_errors() -> None:
    driver, script = bop(
        [
            (b"*CLS\n", None),
            (b"FUNC:MODE CURR\n", None),
            (b"VOLT 60.00\n", None),
            (b"CURR 0.0000\n", None),
            (b"SYST:ERR?\n", NO_ERROR),
        ],
        compliance_V=60.0,
    )
    driver.configure()
    script.assert_done()


def test_configure_raises_the_device_errors_by_name() -> None:
    driver, script = bop(
        [
            (b"*CLS\n", None),
            (b"FUNC:MODE CURR\n", None),
            (b"VOLT 100.00\n", None),
            (b"CURR 0.0000\n", None),
            (b"SYST:ERR?\n", b'-222,"Data out of range"\n'),
            (b"SYST:ERR?\n", b'-113,"Undefined header"\n'),
            (b"SYST:ERR?\n", NO_ERROR),
        ]
    )
    with pytest.raises(DeviceError) as info:
        driver.configure()
    assert str(info.value).startswith('x+: device error -222 "Data out of range"')
    assert "-113" in str(info.value)
    assert info.value.device == "x+"
    script.assert_done()


def test_set_current_formats_four_decimals() -> None:
    driver, script = bop([(b"CURR -12.3457\n", None), (b"CURR 0.0000\n", None)])
    driver.set_current(-12.34567)
    driver.set_current(-0.00001)  # rounds to zero without a minus sign
    script.assert_done()
    assert driver.last_setpoint_A == pytest.approx(-0.00001)


@pytest.mark.parametrize("amps", [20.001, -25.0, float("nan"), float("inf")])
def test_limit_error_before_any_io(amps: float) -> None:
    driver, script = bop([])
    with pytest.raises(LimitError) as info:
        driver.set_current(amps)
    assert info.value.device == "x+"
    with pytest.raises(LimitError):
        driver.send_setpoint(amps)
    assert script.writes == []
    script.assert_done()


def test_lower_limit_is_enforced() -> None:
    driver, script = bop([(b"CURR 5.0000\n", None)], current_limit_A=5.0)
    driver.set_current(5.0)
    with pytest.raises(LimitError, match=r"\+-5 A"):
        driver.set_current(5.01)
    script.assert_done()


@pytest.mark.parametrize("kwargs", [{"current_limit_A": 21.0}, {"compliance_V": 150.0},
                                    {"current_limit_A": 0.0}, {"timeout_s": 0.0}])
def test_settings_beyond_the_pair_rating_are_refused(kwargs) -> None:
    with pytest.raises(ConfigError):
        KepcoBop(ScriptedTransport([]), name="x+", **kwargs)


def test_errors_drain_is_bounded() -> None:
    overflowing = [(b"SYST:ERR?\n", b'-222,"Data out of range"\n')] * 3
    driver, script = bop(overflowing)
    assert driver.errors(max_entries=3) == [(-222, "Data out of range")] * 3
    script.assert_done()  # exactly three queries although the queue was not empty


def test_errors_stop_at_no_error() -> None:
    driver, script = bop([(b"SYST:ERR?\n", b'20101,"OVER TEMPERATURE"\n'), (b"SYST:ERR?\n", NO_ERROR)])
    assert driver.errors() == [(20101, "OVER TEMPERATURE")]
    script.assert_done()


def test_check_errors_names_over_temperature() -> None:
    driver, script = bop([(b"SYST:ERR?\n", b'20101,"OVER TEMPERATURE"\n'), (b"SYST:ERR?\n", NO_ERROR)])
    with pytest.raises(DeviceError, match='x\\+: device error 20101 "OVER TEMPERATURE"'):
        driver.check_errors()
    script.assert_done()


def test_malformed_error_entry_is_a_protocol_error() -> None:
    driver, script = bop([(b"SYST:ERR?\n", b"oops\n")])
    with pytest.raises(ProtocolError, match="oops"):
        driver.errors()
    script.assert_done()


def test_send_setpoint_and_read_measured() -> None:
    driver, script = bop([(b"CURR 1.2345;:MEAS:CURR?\n", b"1.198700E+00\n")])
    driver.send_setpoint(1.2345)
    assert driver.read_measured() == pytest.approx(1.1987)
    script.assert_done()


def test_pipelined_across_supplies_order_is_kept() -> None:
    a, script_a = bop([(b"CURR 1.0000;:MEAS:CURR?\n", b"9.0E-1\n")])
    b, script_b = bop([(b"CURR -2.0000;:MEAS:CURR?\n", b"-1.5E0\n")])
    a.send_setpoint(1.0)
    b.send_setpoint(-2.0)
    assert (a.read_measured(), b.read_measured()) == (pytest.approx(0.9), pytest.approx(-1.5))
    script_a.assert_done()
    script_b.assert_done()


def test_read_measured_needs_a_setpoint_first() -> None:
    driver, _ = bop([(b"CURR 1.0000;:MEAS:CURR?\n", b"1.0\n")])
    with pytest.raises(RuntimeError):
        driver.read_measured()
    driver.send_setpoint(1.0)
    with pytest.raises(RuntimeError):
        driver.send_setpoint(1.0)


def test_measurements_parse_scientific_notation() -> None:
    driver, script = bop([(b"MEAS:CURR?\n", b"2.71E1\n"), (b"MEAS:VOLT?\n", b"-4.05E+01\n")])
    assert driver.measure_current() == pytest.approx(27.1)
    assert driver.measure_voltage() == pytest.approx(-40.5)
    script.assert_done()


@pytest.mark.parametrize(
    ("reply", "quoted"),
    [
        (b"\xfe\x81#%!\x00\xff\x9c\n", r"b'\xfe\x81#%!\x00\xff\x9c\n'"),
        (b"nan\n", "'nan'"),
        (b"1_0\n", "'1_0'"),
        (b"1.0 A\n", "'1.0 A'"),
    ],
)
def test_garbage_reply_is_a_protocol_error_quoting_it_then_input_is_discarded(
    reply: bytes, quoted: str
) -> None:
    driver, script = bop([(b"MEAS:CURR?\n", reply), (b"MEAS:CURR?\n", b"1.0\n")])
    with pytest.raises(ProtocolError) as info:
        driver.measure_current()
    assert info.value.device == "x+"
    assert quoted in str(info.value)
    discards = script.discards
    assert driver.measure_current() == 1.0
    assert script.discards == discards + 1
    script.assert_done()


def test_silence_is_a_watchdog_timeout_naming_the_device() -> None:
    driver, script = bop([(b"MEAS:CURR?\n", None)], timeout_s=0.25)
    with pytest.raises(DeviceTimeout) as info:
        driver.measure_current()
    assert str(info.value) == "x+: no reply within 0.25 s (watchdog)"
    script.assert_done()


def test_lost_link_is_disconnected_naming_the_device() -> None:
    lost = Disconnected("connection reset by tcp://127.0.0.1:5025")
    driver, script = bop([(b"CURR 1.0000;:MEAS:CURR?\n", lost)])
    driver.send_setpoint(1.0)
    with pytest.raises(Disconnected) as info:
        driver.read_measured()
    assert str(info.value) == "x+: link lost (connection reset by tcp://127.0.0.1:5025)"
    script.assert_done()


def test_output_on_is_confirmed() -> None:
    driver, script = bop([(b"OUTP ON;:OUTP?\n", b"1\n"), (b"OUTP OFF\n", None)])
    driver.output(True)
    driver.output(False)
    script.assert_done()


def test_output_refused_names_the_reason() -> None:
    driver, script = bop(
        [
            (b"OUTP ON;:OUTP?\n", b"0\n"),
            (b"SYST:ERR?\n", b'20101,"OVER TEMPERATURE"\n'),
            (b"SYST:ERR?\n", NO_ERROR),
        ]
    )
    with pytest.raises(DeviceError, match="output did not turn on.*OVER TEMPERATURE"):
        driver.output(True)
    script.assert_done()


def test_safe_stop_ramps_from_the_last_setpoint_then_turns_off() -> None:
    driver, script = bop(
        [
            (b"CURR 2.0000\n", None),
            (b"CURR 1.5000\n", None),
            (b"CURR 1.0000\n", None),
            (b"CURR 0.5000\n", None),
            (b"CURR 0.0000\n", None),
            (b"OUTP OFF;:OUTP?\n", b"0\n"),
        ]
    )
    driver.set_current(2.0)
    assert driver.safe_stop(ramp_s=0.0, steps=4) is True  # the supply confirmed output off
    script.assert_done()
    assert driver.last_setpoint_A == 0.0


def test_safe_stop_on_a_dead_link_logs_and_does_not_raise(caplog) -> None:
    driver, script = bop([(b"CURR -3.0000;:MEAS:CURR?\n", None)])
    driver.send_setpoint(-3.0)
    script.close()  # every further write raises Disconnected
    assert driver.safe_stop(ramp_s=0.0, steps=3) is False
    assert "x+: safe stop incomplete" in caplog.text


def test_emergency_zero_is_one_message_and_latches_every_later_setpoint_at_zero() -> None:
    driver, script = bop([(b"CURR 0.0000;:OUTP OFF\n", None), (b"CURR 0.0000;:MEAS:CURR?\n", None)])
    assert driver.emergency_zero() is True
    driver.send_setpoint(5.0)  # the stream thread, not yet stopped, still asks for 5 A
    script.assert_done()


def test_emergency_zero_on_a_dead_link_says_so_and_does_not_raise(caplog) -> None:
    driver, script = bop([])
    script.close()  # every write raises Disconnected
    assert driver.emergency_zero() is False
    assert "x+: e-stop could not be sent" in caplog.text


def test_close_closes_the_transport() -> None:
    driver, script = bop([])
    driver.close()
    assert script.closed
