"""The emulated spinner: a GRBL 1.1h controller on a pty, as its Arduino's USB serial port appears.

    with SpinnerBench() as bench:
        bench.rig        # SpinnerConfig: [grbl] url = the pty's stable path, [emulation] backdoor

The controller (`grbl_wire.GrblWire` in front of `grbl_model.GrblMachine`) is served by rigctl's
`EmulatorServer` on a pty in the server's loop thread; the machine steps from the bench's
`SimClock` every `TICK_S` and before every chunk the host writes or backdoor read, and a line
that waited for room in the planner is answered from the tick. The rig file's `[grbl]` carries
the controller's own `$100`, `$110` and `$120`.

Backdoor: the table of rigctl's `emulators/base.py` (`ping`, `help`, `speed`, `fault`), device
"grbl" with its link's faults (`drop_link`: unplugged, `stall`: no replies, `corrupt`: the next
`n` replies garbage, `restore`) and `reboot` (the board resets itself: banner, planner flushed),
plus `{"cmd": "truth"}`: the rotor's angle (degrees, unbounded) and rate (turns/s, signed), the
controller's state, the blocks queued, the bytes the host overran its RX buffer by, lines
executed, simulated time (and `agents`: none, as every bench's truth has them).
"""

from __future__ import annotations

import argparse

from rigctl.core.config import Emulation, RigInfo
from rigctl.emulators.base import EmulatedBench
from rigctl_grbl_spinner.grbl_model import GrblMachine
from rigctl_grbl_spinner.grbl_wire import GrblWire
from rigctl_grbl_spinner.settings import DEG_PER_MIN_PER_HZ, GrblSettings, SpinnerConfig

TICK_S = 0.005
KIND_NAME = "grbl-spinner"


class SpinnerBench(EmulatedBench):
    """The grbl-spinner bench (`EmulatedBench`); `settings`: the `$$` table to boot with."""

    title = "grbl-spinner bench"
    tick_s = TICK_S

    def __init__(self, *, host: str = "127.0.0.1", speed: float = 1.0,
                 settings: dict[int, float] | None = None) -> None:
        super().__init__(host=host, speed=speed)
        self.wire = GrblWire(GrblMachine(settings))
        self.endpoint = None
        self._stepped = 0.0
        self.commands["truth"] = self._truth

    @property
    def machine(self) -> GrblMachine:
        return self.wire.machine

    def _serve(self) -> SpinnerConfig:
        self.endpoint = endpoint = self.server.serve_bytes_pty(self._receive, name="grbl")
        self.server.call(endpoint._link.reply, self.wire.boot())  # power-on, through the link
        self.add_device("grbl", endpoint, reboot=lambda _: self._reboot())
        assert self.backdoor is not None
        m = self.machine
        grbl = GrblSettings(url=endpoint.url, steps_per_degree=m.steps_per_deg,
                            max_rate_hz=m.settings[110] / DEG_PER_MIN_PER_HZ,
                            max_acceleration_hz_per_s=m.accel_deg_s2 / 360.0)
        return SpinnerConfig(rig=RigInfo(kind=KIND_NAME, name=f"emulated {self.title}"),
                             grbl=grbl, emulation=Emulation(backdoor=self.backdoor.url))

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> SpinnerBench:
        return cls(host=args.host)

    def served(self, rig) -> list[tuple[str, str]]:
        return [("grbl", str(rig.grbl.url))]

    # -- the loop thread ------------------------------------------------------------------------
    def advance(self) -> None:
        """Step the machine to the clock's now; answer lines that waited for the planner."""
        now = self.clock.now()
        if now > self._stepped:
            self.machine.step(now - self._stepped)
            self._stepped = now
        if self.endpoint is not None:
            out = self.wire.poll()
            if out:
                self.endpoint._link.reply(out)  # loop thread, through the link's faults

    def _receive(self, data: bytes) -> bytes:
        self.advance()
        return self.wire.receive(data)

    def _reboot(self) -> None:
        """The board resets itself (a brown-out, the USB re-enumerating): as a soft reset."""
        self.advance()
        assert self.endpoint is not None
        self.endpoint._link.reply(self.wire.receive(b"\x18"))

    def _truth(self, request: dict) -> dict:
        self.advance()
        m = self.machine
        # "agents": none (the daemon samples every emulated bench's agents while a run lasts)
        return {"agents": [], "angle_deg": m.position_deg, "rate_hz": m.rate_hz, "state": m.status_state(),
                "queued_blocks": len(m.queue), "lost_bytes": self.wire.lost_bytes,
                "lines": self.wire.lines, "sim_time_s": m.time_s}
