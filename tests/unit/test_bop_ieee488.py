"""The emulated BOP's IEEE 488.2 common commands, status registers and the BOP's SCPI tree.

Expected values come from the documents, not from the emulator: the status byte's and the event
register's bit values from IEEE 488.2 (ESB = 32, MSS = 64, MAV = 16, error queue = 4, questionable
= 8, operation = 128; *ESR? command error = 32, operation complete = 1), the operation register's
from the BOP manual par. 3.6.7.2 (constant current 1024, constant voltage 256, waiting for
trigger 32, list complete 4096, list running 16384), the protection maxima from its App. B.2 (1 %
above the rating), and the coil currents under a list from the closed form of L di/dt = v - R i
worked segment by segment by hand.
"""

from __future__ import annotations

import math

import pytest

from rigctl.emulators.kepco_bop.model import BopCoilModel
from rigctl.emulators.kepco_bop.protocol import BopScpi

R, L = 1.5, 0.03  # tau = 20 ms
TAU = L / R


@pytest.fixture
def scpi() -> BopScpi:
    return BopScpi(BopCoilModel(R, L))


def errors(scpi: BopScpi) -> list[str]:
    found = []
    for _ in range(20):
        reply = scpi.handle("SYST:ERR?")
        if reply.startswith("0,"):
            return found
        found.append(reply)
    raise AssertionError("the error queue did not empty")


# -- IEEE 488.2 common commands ------------------------------------------------------------------

def test_every_mandatory_common_command_is_answered_without_error(scpi) -> None:
    replies = scpi.handle("*CLS;*ESE 0;*ESE?;*ESR?;*IDN?;*OPC;*OPC?;*RST;*SRE 0;*SRE?;*STB?;*TST?;*WAI")
    ese, esr, idn, opc, sre, stb, tst = replies.split(";")  # the seven queries, in order
    assert (ese, esr, opc, sre, tst) == ("0", "0", "1", "0", "0")
    assert idn.startswith("KEPCO,")
    assert stb == "16"  # message available: the replies before it wait in the output queue
    assert scpi.handle("*ESR?") == "1"  # the *OPC in the message: operation complete
    assert errors(scpi) == []


def test_self_tests_answer_zero_for_pass(scpi) -> None:
    assert scpi.handle("*TST?") == "0"
    assert scpi.handle("DIAG:TST?") == "0"
    assert errors(scpi) == []


def test_event_status_enable_masks_the_summary_bit_of_the_status_byte(scpi) -> None:
    scpi.handle("BOGUS")  # -113: command error, *ESR? bit 5 (32)
    assert scpi.handle("*STB?") == "4"  # only the error queue (bit 2): *ESE is 0 after power on
    scpi.handle("*ESE 32")
    assert scpi.handle("*ESE?") == "32"
    assert scpi.handle("*STB?") == str(4 + 32)  # now the event summary bit (5) is set
    scpi.handle("*ESE 16")  # execution errors only: the command error no longer counts
    assert scpi.handle("*STB?") == "4"
    assert scpi.handle("*ESR?") == "32"  # the register itself was never masked
    assert scpi.handle("*ESR?") == "0"  # and reading it cleared it


def test_service_request_enable_sets_the_master_summary_bit(scpi) -> None:
    scpi.handle("*ESE 255;*SRE 32")
    scpi.handle("CURR 99")  # -222: execution error, *ESR? bit 4
    assert scpi.handle("*STB?") == str(4 + 32 + 64)
    scpi.handle("*SRE 4")  # the error-queue bit alone also requests service
    scpi.handle("*ESR?")
    assert scpi.handle("*STB?") == str(4 + 64)
    scpi.handle("*SRE 255")
    assert scpi.handle("*SRE?") == "191"  # bit 6 cannot be enabled (IEEE 488.2 11.3.2.3)


def test_common_enables_are_0_to_255(scpi) -> None:
    scpi.handle("*ESE 256")
    assert scpi.handle("*ESE?") == "0"
    assert errors(scpi) == ['-222,"Data out of range"']
    scpi.handle("*SRE")
    assert errors(scpi) == ['-109,"Missing parameter"']


def test_message_available_bit_while_a_response_waits(scpi) -> None:
    assert scpi.handle("*IDN?;*STB?").split(";")[1] == "16"


def test_opc_sets_operation_complete_and_wai_returns(scpi) -> None:
    assert scpi.handle("*OPC;*ESR?") == "1"
    assert scpi.handle("*WAI;*OPC?") == "1"


def test_cls_clears_events_but_not_enables(scpi) -> None:
    scpi.handle("*ESE 60;*SRE 48;STAT:OPER:ENAB 1024;:STAT:QUES:ENAB 8;:BOGUS")
    scpi.handle("*CLS")
    assert scpi.handle("*STB?") == "0"
    assert scpi.handle("*ESR?;STAT:OPER?;QUES?") == "0;0;0"
    assert scpi.handle("*ESE?;*SRE?;STAT:OPER:ENAB?;:STAT:QUES:ENAB?") == "60;48;1024;8"


def test_rst_does_not_touch_the_status_registers(scpi) -> None:
    scpi.handle("*ESE 32;BOGUS")
    scpi.handle("*RST")
    assert scpi.handle("*ESE?;*ESR?") == "32;32"


def test_unknown_commands_still_go_to_the_error_queue(scpi) -> None:
    scpi.handle("*FOO")
    scpi.handle("SYST:FROB?")
    assert errors(scpi) == ['-113,"Undefined header"'] * 2


def test_saved_setup_is_recalled(scpi) -> None:
    scpi.handle("CURR 1.5;:VOLT 40;*SAV 7;CURR -2;:VOLT 90;:FUNC:MODE VOLT")
    scpi.handle("*RCL 7")
    assert scpi.handle("FUNC:MODE?;:CURR?;:VOLT?") == "1;1.500000E+00;4.000000E+01"
    scpi.handle("*RCL 8")  # never saved
    assert errors(scpi) == ['-222,"Data out of range"']


def test_trigger_applies_the_triggered_level_only_when_armed(scpi) -> None:
    scpi.handle("CURR 1;:CURR:TRIG 2.5")
    scpi.handle("*TRG")
    assert float(scpi.handle("CURR?")) == 1.0  # not armed: ignored (BOP par. 3.6.3.3)
    scpi.handle("INIT")
    assert int(scpi.handle("STAT:OPER:COND?")) & 32  # waiting for trigger
    scpi.handle("*TRG")
    assert float(scpi.handle("CURR?")) == 2.5
    assert not int(scpi.handle("STAT:OPER:COND?")) & 32


# -- status subsystem ----------------------------------------------------------------------------

def test_operation_register_follows_the_mode(scpi) -> None:
    assert scpi.handle("STAT:OPER:COND?") == "1024"  # constant current after *RST
    assert scpi.handle("STAT:OPER?") == "1024"  # the 0 -> 1 at power on, latched
    assert scpi.handle("STAT:OPER?") == "0"  # cleared by reading
    scpi.handle("FUNC:MODE VOLT")
    assert scpi.handle("STAT:OPER:COND?;EVEN?") == "256;256"


def test_operation_and_questionable_enables_reach_the_status_byte(scpi) -> None:
    scpi.handle("STAT:OPER?")
    scpi.handle("STAT:OPER:ENAB 256")
    scpi.handle("FUNC:MODE VOLT")
    assert scpi.handle("*STB?") == "128"
    scpi.handle("STAT:OPER?;:STAT:QUES:ENAB 8")
    scpi.model.inject_overtemperature()
    assert int(scpi.handle("*STB?")) & 8  # questionable summary
    scpi.handle("STAT:PRES")  # enables to 0: nothing reaches the status byte any more
    scpi.handle("*CLS")
    scpi.model.inject_overtemperature()
    assert int(scpi.handle("*STB?")) & (8 | 128) == 0
    assert scpi.handle("STAT:OPER:ENAB?;:STAT:QUES:ENAB?") == "0;0"


def test_system_queries(scpi) -> None:
    assert scpi.handle("SYST:VERS?") == "1997.0"
    scpi.handle("SYST:REM OFF")
    assert scpi.handle("SYST:REM?") == "0"
    scpi.handle("SYST:BEEP;:BOGUS;*BAR")
    assert scpi.handle("SYST:ERR:CODE:ALL?") == "-113"  # the command error ended the message
    assert scpi.handle("SYST:ERR:CODE?") == "0"


# -- protection limits ---------------------------------------------------------------------------

def test_protection_limits_start_one_percent_above_the_rating(scpi) -> None:
    assert scpi.handle("VOLT:PROT?") == "1.010000E+02,-1.010000E+02"  # 1.01 x 100 V
    assert scpi.handle("CURR:PROT?") == "2.020000E+01,-2.020000E+01"  # 1.01 x 20 A
    assert scpi.handle("CURR:PROT:LIM?") == "2.020000E+01,-2.020000E+01"


def test_protection_settings_and_their_maxima(scpi) -> None:
    scpi.handle("VOLT:PROT:POS 30;NEG 12")
    assert scpi.handle("VOLT:PROT?;PROT:POS?;NEG?") == \
        "3.000000E+01,-1.200000E+01;3.000000E+01;-1.200000E+01"
    scpi.handle("VOLT:PROT:LIM 20")  # a lower maximum pulls the positive limit down with it
    assert scpi.handle("VOLT:PROT?") == "2.000000E+01,-1.200000E+01"
    scpi.handle("VOLT:PROT 25")  # above its maximum
    scpi.handle("CURR:PROT:LIM 21")  # above 1 % over the rating
    assert errors(scpi) == ['-222,"Data out of range"'] * 2
    assert scpi.handle("VOLT:PROT?;:CURR:PROT:MODE?") == "2.000000E+01,-1.200000E+01;FIX"


def test_voltage_protection_bounds_the_coil_current_in_current_mode(scpi) -> None:
    # 20 A through 1.5 ohm needs 30 V; a 15 V protection limit holds the current at 15 / 1.5 A
    scpi.handle("CURR 20;:VOLT:PROT:POS 15;:OUTP ON")
    scpi.model.step(20 * TAU)
    assert float(scpi.handle("MEAS:CURR?")) == pytest.approx(10.0, rel=1e-6)
    scpi.handle("CURR -20")  # the negative side keeps its own limit (101 V): the full -20 A
    scpi.model.step(40 * TAU)
    assert float(scpi.handle("MEAS:CURR?")) == pytest.approx(-20.0, rel=1e-6)


def test_current_protection_bounds_the_current_in_voltage_mode(scpi) -> None:
    scpi.handle("FUNC:MODE VOLT;:CURR 20;:CURR:PROT 4;:VOLT 30;:OUTP ON")
    scpi.model.step(20 * TAU)
    assert float(scpi.handle("MEAS:CURR?")) == pytest.approx(4.0)


# -- the list ------------------------------------------------------------------------------------

def test_list_points_dwell_and_queries(scpi) -> None:
    scpi.handle("LIST:CLE;CURR 1,2,3;CURR 4;DWEL 0.01")
    assert scpi.handle("LIST:CURR:POIN?;:LIST:DWEL:POIN?;:LIST:VOLT:POIN?") == "4;1;0"
    scpi.handle("LIST:QUER 2")
    assert scpi.handle("LIST:QUER?;CURR?") == "2;3.000000E+00,4.000000E+00"
    scpi.handle("LIST:VOLT 1")  # one list holds one channel's points
    scpi.handle("LIST:CURR 25")  # beyond the 20 A rating
    assert errors(scpi) == ['-221,"Settings conflict"', '-222,"Data out of range"']


def test_a_current_list_runs_its_points_for_their_dwell_then_returns_to_fixed(scpi) -> None:
    scpi.handle("LIST:CLE;CURR 1,2,3;DWEL 0.01;COUN 2;:OUTP ON;:STAT:OPER?")
    scpi.handle("CURR:MODE LIST")
    assert scpi.handle("CURR:MODE?;:STAT:OPER:COND?") == f"LIST;{16384 + 1024}"
    model = scpi.model
    model.step(0.005)
    assert model.current_setpoint_A == 1.0
    model.step(0.025)  # three dwells of 10 ms, in one step the model must split
    # closed form per segment, i(t+dt) = I + (i - I) exp(-dt/tau), with I = 1, 2, 3 A in turn
    decay = math.exp(-0.01 / TAU)
    i = 0.0
    for setpoint in (1.0, 2.0, 3.0):
        i = setpoint + (i - setpoint) * decay
    assert model.current_A == pytest.approx(i, rel=1e-9)
    model.step(0.005)  # second pass, first point
    assert model.current_setpoint_A == 1.0
    model.step(0.05)  # past the end of the second pass
    assert scpi.handle("CURR:MODE?;:CURR?") == "FIX;3.000000E+00"  # the last point stays
    event = int(scpi.handle("STAT:OPER?"))
    assert event & 4096 and event & 16384  # list complete, and it had been running
    assert scpi.handle("STAT:OPER:COND?") == "1024"


def test_list_skip_and_direction(scpi) -> None:
    scpi.handle("LIST:CLE;CURR 1,2,3;DWEL 0.01;COUN 2;COUN:SKIP 1")
    scpi.handle("CURR:MODE LIST")
    scpi.model.step(0.035)  # second pass leaves out the first point: 2 A
    assert scpi.model.current_setpoint_A == 2.0
    scpi.handle("CURR:MODE FIX;:LIST:DIR DOWN;DIR?")
    scpi.handle("CURR:MODE LIST")
    assert scpi.model.current_setpoint_A == 3.0


def test_list_needs_matching_lengths_and_the_present_mode(scpi) -> None:
    scpi.handle("LIST:CLE;CURR 1,2,3;DWEL 0.01,0.02")
    scpi.handle("CURR:MODE LIST")
    scpi.handle("VOLT:MODE LIST")  # the supply is in current mode
    assert errors(scpi) == ['-226,"Lists not same length"', '-221,"Settings conflict"']
    assert scpi.handle("CURR:MODE?") == "FIX"


def test_a_voltage_list_runs_in_voltage_mode(scpi) -> None:
    scpi.handle("FUNC:MODE VOLT;:LIST:CLE;VOLT 5,-5;DWEL 0.02,0.04;COUN 0")
    scpi.handle("VOLT:MODE LIST")
    scpi.model.step(0.03)
    assert scpi.model.voltage_setpoint_V == -5.0
    scpi.model.step(0.06)  # count 0 repeats until stopped: 0.09 s is in the second pass's -5 V
    assert scpi.model.voltage_setpoint_V == -5.0
    assert scpi.handle("VOLT:MODE?") == "LIST"


# -- software limits and the output mode ---------------------------------------------------------

def test_software_limits_bound_settings_and_give_max_and_min_their_meaning(scpi) -> None:
    assert scpi.handle("CURR:LIM?") == "2.000000E+01,-2.000000E+01"  # the rating
    scpi.handle("CURR:LIM:POS 6;:CURR:LIM:NEG 4")
    scpi.handle("CURR MAX")
    assert scpi.handle("CURR?;CURR? MAX;CURR? MIN") == \
        "6.000000E+00;6.000000E+00;-4.000000E+00"  # "VOLT MAX ... set to the limit" (App. B.2)
    scpi.handle("CURR -5")  # beyond the negative limit
    scpi.handle("CURR:LIM 21")  # beyond the rating
    assert errors(scpi) == ['-222,"Data out of range"'] * 2
    assert float(scpi.handle("CURR?")) == 6.0


def test_output_mode_is_remembered(scpi) -> None:
    assert scpi.handle("OUTP:MODE?") == "ACTIVE"
    scpi.handle("OUTP:MODE RES")
    assert scpi.handle("OUTP:MODE?") == "RESISTIVE"
    scpi.handle("OUTP:MODE LOUD")
    assert errors(scpi) == ['-102,"Syntax error"']
