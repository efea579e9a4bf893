"""An independent client against the emulated BOP: pymeasure's own Kepco BOP driver over PyVISA.

Labs drive their supplies from their own scripts with the field's instrument libraries; the
emulator is only worth its name if such a client cannot tell it from the device (issue 38,
item 6). pymeasure's `KepcoBOP3612` (and the SCPI calls its `SCPIMixin` and `Instrument` bring)
opens the emulated supply through PyVISA's TCPIP SOCKET resource on the pure-Python pyvisa-py
backend, as a lab script would open a BOP's LAN port, and every call it offers is made here:
each property read, each property set, each method. What the supply then holds is read from the
emulator's model, and the measured values are checked against Ohm's law worked by hand: the coil's
L/R is 1 us, so by the next command the current has settled (exp(-1000) of the step is left).

pymeasure's driver is written for the BOP 36-12 (it truncates setpoints to +-12 A and +-36 V);
the emulated 50-20 pair accepts everything inside those ranges the same way.
"""

from __future__ import annotations

import pytest
from pymeasure.instruments.kepco import KepcoBOP3612

from rigctl.emulators.kepco_bop import serve_bop
from rigctl.emulators.server import EmulatorServer

# the emulator serves a real socket from a thread of this process; no process is started
pytestmark = pytest.mark.quick

R, L = 1.5, 1.5e-6  # tau = L/R = 1 us: settled by the time the next command arrives


@pytest.fixture(scope="module")
def served():
    with EmulatorServer() as server:
        bop = serve_bop(server, name="x+", resistance_ohm=R, inductance_H=L)
        port = bop.endpoint.url.rsplit(":", 1)[1]
        supply = KepcoBOP3612(f"TCPIP0::127.0.0.1::{port}::SOCKET", visa_library="@py",
                              timeout=2000)
        try:
            yield server, bop, supply
        finally:
            supply.adapter.close()


def held(served):
    """The model's state once every command sent so far has run: writes get no reply, so the
    client first waits on *OPC? as a lab script synchronises with a real supply."""
    server, bop, supply = served
    assert supply.complete == "1"
    return server.call(bop.model.status)


def test_identification_self_tests_and_common_queries(served) -> None:
    _, _, supply = served
    assert supply.id.startswith("KEPCO,BOP")
    assert supply.confidence_test == 0  # *TST?: 0 is a pass (BOP par. A.17)
    assert supply.bop_test == 0  # DIAG:TST?
    assert supply.options == "0"
    assert supply.complete == "1"  # *OPC?
    supply.clear()  # *CLS
    assert supply.status == "0"  # *STB? with nothing to report
    supply.wait_to_continue()  # *WAI
    supply.beep()  # SYST:BEEP
    assert supply.check_errors() == []  # none of the above was refused


def test_settings_reach_the_model_and_read_back(served) -> None:
    _, _, supply = served
    supply.reset()  # *RST: output off, current mode
    assert supply.operating_mode == "CURR"
    assert supply.output_enabled is False
    supply.voltage_setpoint = 30  # in current mode: the voltage limit
    supply.current_setpoint = 3.5
    supply.output_enabled = True
    status = held(served)
    assert (status.mode, status.output_on) == ("CURR", True)
    assert (status.current_setpoint_A, status.voltage_setpoint_V) == (3.5, 30.0)
    assert supply.current_setpoint == 3.5
    assert supply.voltage_setpoint == 30.0
    assert supply.output_enabled is True
    assert supply.current == pytest.approx(3.5)
    assert supply.voltage == pytest.approx(3.5 * R)  # 5.25 V across the coil
    assert supply.check_errors() == []


def test_voltage_mode_through_the_driver(served) -> None:
    _, _, supply = served
    supply.operating_mode = "VOLT"
    assert supply.operating_mode == "VOLT"
    supply.current_setpoint = 12  # in voltage mode: the current limit
    supply.voltage_setpoint = -6
    supply.output_enabled = True
    status = held(served)
    assert (status.mode, status.voltage_setpoint_V, status.current_setpoint_A) == ("VOLT", -6.0, 12.0)
    assert supply.voltage == pytest.approx(-6.0)
    assert supply.current == pytest.approx(-6.0 / R)  # -4 A, inside the 12 A limit
    supply.current_setpoint = 2.0  # now the limit holds the current at -2 A
    assert supply.current == pytest.approx(-2.0)
    supply.output_enabled = False
    assert held(served).output_on is False
    assert supply.check_get_errors() == [] and supply.check_set_errors() == []


def test_errors_reach_the_driver_and_the_status_byte(served) -> None:
    _, _, supply = served
    supply.clear()
    supply.write("BOGUS")
    assert supply.status == "4"  # error queue not empty: status byte bit 2
    assert supply.next_error == [-113, '"Undefined header"']
    assert supply.next_error == [0, '"No error"']
    supply.shutdown()
    assert supply.isShutdown
