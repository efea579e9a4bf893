"""The example rig kind's GRBL 1.1h model and wire (examples/rigctl-grbl-spinner), stepped by hand.

The figures are closed forms of a trapezoidal move on one axis (a = $120, v = F / 60): a jog of
D degrees takes D / v + v / a seconds and ends at rest; a hold from v stops in v / a seconds over
v^2 / 2a degrees. The replies are GRBL 1.1's documented ones (gnea/grbl doc/markdown)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples" / "rigctl-grbl-spinner" / "src"))

from rigctl_grbl_spinner.grbl_model import GrblMachine  # noqa: E402
from rigctl_grbl_spinner.grbl_wire import GrblWire  # noqa: E402

A = 7200.0  # $120, degrees/s^2
V = 360.0  # F21600: one turn per second


def lines(out: bytes) -> list[str]:
    return [line for line in out.decode().split("\r\n") if line]


def test_a_jog_is_a_trapezoid_that_ends_at_rest_at_its_target():
    wire = GrblWire()
    assert lines(wire.receive(b"$J=G91X720F21600\n")) == ["ok"]
    m = wire.machine
    m.step(V / A)  # the acceleration
    assert m.speed_deg_s == pytest.approx(V, rel=0.02)
    assert m.position_deg == pytest.approx(V ** 2 / (2 * A), abs=0.5)
    m.step(720 / V + V / A - V / A - 0.01)  # just before the end of the closed form's time
    assert m.state == "Jog" and m.moving
    m.step(0.02)
    assert m.state == "Idle" and not m.moving
    assert m.machine_position_deg() == pytest.approx(720.0, abs=1 / m.steps_per_deg)


def test_a_feed_hold_in_a_jog_decelerates_at_the_acceleration_then_flushes_the_jogs():
    wire = GrblWire()
    wire.receive(b"$J=G91X3600F21600\n$J=G91X3600F21600\n")
    m = wire.machine
    m.step(0.5)
    at, where = m.speed_deg_s, m.position_deg
    assert at == pytest.approx(V)
    wire.receive(b"!")
    assert lines(wire.receive(b"?"))[0].startswith("<Jog|")  # a jog cancel still reports Jog
    m.step(V / A + 0.005)
    assert not m.moving and m.state == "Idle" and not m.queue  # flushed, not held
    assert m.position_deg - where == pytest.approx(V ** 2 / (2 * A), abs=0.5)


def test_a_hold_outside_a_jog_is_resumed_by_cycle_start():
    wire = GrblWire()
    wire.receive(b"!")
    assert lines(wire.receive(b"?"))[0].startswith("<Hold:0|")
    assert lines(wire.receive(b"$J=G91X10F600\n")) == ["error:8"]  # jogs only in Idle or Jog
    wire.receive(b"~")
    assert lines(wire.receive(b"?"))[0].startswith("<Idle|")


def test_jog_cancel_acts_only_in_a_jog():
    wire = GrblWire()
    wire.receive(b"\x85")
    assert wire.machine.state == "Idle"
    wire.receive(b"$J=G91X-3600F21600\n")
    wire.machine.step(0.3)
    wire.receive(b"\x85")
    wire.machine.step(V / A + 0.005)
    assert wire.machine.state == "Idle" and wire.machine.rate_hz == 0


def test_a_soft_reset_while_turning_raises_alarm_3_and_needs_an_unlock():
    wire = GrblWire()
    wire.receive(b"$J=G91X3600F21600\n")
    wire.machine.step(0.2)
    assert lines(wire.receive(b"\x18")) == ["ALARM:3", "Grbl 1.1h ['$' for help]",
                                            "[MSG:'$H'|'$X' to unlock]"]
    assert not wire.machine.moving  # stopped at once, not decelerated
    assert lines(wire.receive(b"$J=G91X10F600\n")) == ["error:8"]
    assert lines(wire.receive(b"G91\n")) == ["error:9"]  # G-code locked out in alarm
    assert lines(wire.receive(b"$X\n")) == ["[MSG:Caution: Unlocked]", "ok"]
    assert lines(wire.receive(b"?"))[0].startswith("<Idle|")


def test_a_soft_reset_at_rest_keeps_idle():
    wire = GrblWire()
    assert lines(wire.receive(b"\x18")) == ["Grbl 1.1h ['$' for help]"]
    assert wire.machine.state == "Idle"


def test_real_time_bytes_are_taken_out_of_a_line_and_two_queries_give_one_report():
    wire = GrblWire()
    out = lines(wire.receive(b"$J=G9?1X3?60F21600\n"))
    assert out[0] == "ok" and len([x for x in out if x.startswith("<")]) == 1
    assert wire.machine.queue[0].remaining_deg == pytest.approx(360.0)


def test_the_first_reports_after_a_reset_carry_the_work_offset_then_the_overrides():
    wire = GrblWire()
    first, second, third = (lines(wire.receive(b"?"))[0] for _ in range(3))
    assert first == "<Idle|MPos:0.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>"
    assert second == "<Idle|MPos:0.000,0.000,0.000|FS:0,0|Ov:100,100,100>"
    assert third == "<Idle|MPos:0.000,0.000,0.000|FS:0,0>"


@pytest.mark.parametrize(("line", "reply"), [
    (b"$J=X10\n", "error:22"),  # a jog needs its F
    (b"$J=G1X10F100\n", "error:16"),  # no other G-code in a jog
    (b"$J=F100\n", "error:26"),  # nor without an axis
    (b"$100=-1\n", "error:4"),
    (b"$999=1\n", "error:3"),
    (b"G0X10\n", "error:20"),  # motion G-code: the spinner is driven by jogs (see grbl_wire)
    (b"G91\n", "ok"),
    (b"\n", "ok"),  # an empty line is a line
    (b"X" * 90 + b"\n", "error:11"),
])
def test_error_codes(line, reply):
    assert lines(GrblWire().receive(line)) == [reply]


def test_settings_cannot_be_read_while_jogging():
    wire = GrblWire()
    wire.receive(b"$J=G91X3600F21600\n")
    wire.machine.step(0.05)
    assert lines(wire.receive(b"$$\n")) == ["error:8"]


def test_a_full_planner_holds_the_next_ok_until_a_block_is_done():
    wire = GrblWire()
    burst = b"".join(b"$J=G91X3.6F21600\n" for _ in range(6))  # 6 x 17 = 102 bytes: fits
    replies = lines(wire.receive(burst)) + lines(wire.receive(burst))
    assert replies.count("ok") == 12
    replies = lines(wire.receive(burst[:51]))  # 3 more: the planner holds 15
    assert replies.count("ok") == 3 and len(wire.machine.queue) == 15
    assert lines(wire.receive(b"$J=G91X3.6F21600\n")) == []  # the 16th waits
    wire.machine.step(0.1)  # the first blocks are run
    assert lines(wire.poll()) == ["ok"]


def test_bytes_beyond_the_rx_buffer_are_lost():
    wire = GrblWire()
    wire.receive(b"G" * 200)
    assert wire.lost_bytes == 200 - 127


def test_a_reversal_stops_at_the_junction():
    m = GrblMachine()
    m.jog(90.0, 21600.0)
    m.jog(-90.0, 21600.0)
    peak = 0.0
    for _ in range(400):
        m.step(0.001)
        peak = max(peak, m.position_deg)
    # up 90 and back: never past 90, back to where it started
    assert peak == pytest.approx(90.0, abs=0.5)
    m.step(0.5)
    assert m.position_deg == pytest.approx(0.0, abs=0.5) and not m.moving
