"""The example rig kind's GRBL driver against its GRBL 1.1h emulator on a real pty, in this process.

What is asserted comes from GRBL's documented behaviour and closed forms, not from the driver: the
rate GRBL's own status report gives is the rate streamed, the rotor's angle (the model's truth)
is the integral of it, a jog cancel stops a rotor at `$120` without an alarm, an e-stop's soft
reset while turning raises alarm 3, and a silent or garbled link is a fault naming the
controller within its reply deadline."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples" / "rigctl-grbl-spinner" / "src"))

from rigctl_grbl_spinner.driver import GrblController, stop_rotor  # noqa: E402
from rigctl_grbl_spinner.grbl_wire import GrblWire  # noqa: E402
from rigctl_grbl_spinner.settings import GrblSettings  # noqa: E402

from rigctl.core.errors import ConfigError, DeviceTimeout, ProtocolError  # noqa: E402
from rigctl.emulators.server import EmulatorServer  # noqa: E402

pytestmark = pytest.mark.quick  # the emulator runs in this process's threads


class Controller:
    """A GRBL 1.1h emulator on a pty, its machine stepped from the monotonic clock."""

    def __init__(self, server: EmulatorServer) -> None:
        self.wire = GrblWire()
        self.server = server
        self._t = time.monotonic()
        self.endpoint = server.serve_bytes_pty(self._receive, name="grbl")
        server.every(0.005, self._tick)

    def _step(self) -> None:
        now = time.monotonic()
        self.wire.machine.step(now - self._t)
        self._t = now

    def _receive(self, data: bytes) -> bytes:
        self._step()
        return self.wire.receive(data)

    def _tick(self) -> None:
        self._step()
        out = self.wire.poll()
        if out:
            self.endpoint._link.reply(out)

    def truth(self) -> tuple[float, float, str]:
        def read():
            self._step()
            m = self.wire.machine
            return m.position_deg, m.rate_hz, m.state
        return self.server.call(read)


@pytest.fixture
def grbl():
    with EmulatorServer() as server:
        yield Controller(server)


def connect(grbl: Controller, **settings) -> tuple[GrblController, GrblSettings]:
    s = GrblSettings(url=grbl.endpoint.url, reply_timeout_s=0.3, **settings)
    controller = GrblController.open(s)
    controller.connect()
    return controller, s


def spin(controller: GrblController, rate_hz: float, seconds: float, period_s: float = 0.02,
         lead_s: float = 0.2):
    """Stream jogs of `rate_hz` for `seconds`, the first `lead_s` ahead (GRBL runs only as fast
    as it can stop within its queue: a queue of exactly that slows at every late cycle); the
    last status."""
    last = t0 = time.monotonic()
    status = None
    controller.jog(rate_hz * 360.0 * lead_s, rate_hz)
    while time.monotonic() - t0 < seconds:
        time.sleep(period_s)
        now = time.monotonic()
        controller.jog(rate_hz * 360.0 * (now - last), rate_hz)
        last = now
        status = controller.query_status()
    return status


def test_connect_reads_the_banner_and_refuses_settings_the_rig_file_does_not_have(grbl):
    controller, _ = connect(grbl)
    assert controller.version == "1.1h"
    controller.close()
    with pytest.raises(ConfigError, match=r"\$100=8.889 on the controller.*steps_per_degree"):
        connect(grbl, steps_per_degree=10.0)


def test_connect_unlocks_an_alarm(grbl):
    grbl.server.call(grbl.wire.receive, b"$J=G91X3600F21600\n")
    time.sleep(0.1)
    grbl.server.call(grbl.wire.receive, b"\x18")  # reset while turning: alarm 3
    assert grbl.truth()[2] == "Alarm"
    controller, _ = connect(grbl)
    assert grbl.truth()[2] == "Idle"
    controller.close()


def test_the_rate_streamed_is_the_rate_grbl_reports_and_the_rotor_turns(grbl):
    controller, settings = connect(grbl)
    angle0 = grbl.truth()[0]
    t0 = time.monotonic()
    status = spin(controller, 2.0, 1.0)
    elapsed = time.monotonic() - t0
    assert status.state == "Jog"
    assert status.feed_deg_min / 21600.0 == pytest.approx(2.0, abs=0.05)
    angle, rate, _ = grbl.truth()
    assert rate == pytest.approx(2.0, abs=0.05)
    # turned at 2 Hz from the start, less what the acceleration held back (v^2 / 2a)
    lag_deg = 720.0 ** 2 / (2 * 7200.0)
    assert angle - angle0 == pytest.approx(720.0 * elapsed - lag_deg, abs=30.0)
    assert grbl.wire.lost_bytes == 0
    stop_rotor(controller, settings)
    controller.close()


def test_character_counting_never_overruns_the_rx_buffer(grbl):
    controller, _ = connect(grbl)
    for _ in range(40):  # far more than the planner takes: oks come only as blocks are run
        controller.jog(36.0, 5.0)
    assert sum(n for _, n in controller._in_flight) <= 127
    controller.drain()
    assert grbl.wire.lost_bytes == 0 and grbl.wire.machine.state == "Jog"
    controller.close()


def test_stop_rotor_decelerates_without_an_alarm(grbl):
    controller, settings = connect(grbl)
    spin(controller, 3.0, 0.5)
    status = stop_rotor(controller, settings)
    assert status.state == "Idle" and not status.moving
    assert grbl.truth()[1:] == (0.0, "Idle")  # decelerated to rest first: no alarm 3
    controller.close()


def test_the_e_stop_is_a_soft_reset_that_stops_the_rotor_at_once(grbl):
    controller, _ = connect(grbl)
    spin(controller, 3.0, 0.5)
    assert controller.emergency_stop()
    time.sleep(0.05)
    angle, rate, state = grbl.truth()
    assert rate == 0.0 and state == "Alarm"  # GRBL: reset while in motion
    with pytest.raises(Exception, match="e-stopped"):
        controller.jog(10.0, 1.0)
    controller.close()


def test_a_stalled_link_is_a_timeout_naming_the_controller(grbl):
    controller, _ = connect(grbl)
    grbl.endpoint.stall()
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="^grbl: no reply within 0.3 s waiting for a status report"):
        controller.query_status()
    assert time.monotonic() - t0 < 1.0
    controller.close()


def test_a_garbled_reply_is_a_fault_naming_the_controller(grbl):
    controller, _ = connect(grbl)
    grbl.endpoint.corrupt(1)  # the next reply's bytes replaced by garbage with no line end
    with pytest.raises(DeviceTimeout, match="^grbl: "):
        controller.query_status()
    with pytest.raises(ProtocolError, match="^grbl: unreadable line from GRBL"):
        controller.query_status()  # the garbage, then this report, as one line
    controller.close()
