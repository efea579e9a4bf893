"""An emulated KUKA LBR arm on a real TCP socket: the joint model behind the KST server protocol.

`EmulatedArm` puts one arm on a shared `EmulatorServer` loop: the Sunrise Toolbox server
(`protocol.KstServer`) on its own port (30001 on a real controller; any free port by default here,
`30001 + i` when the bench is asked for the real ports), one client at a time as on the robot.
Simulated time comes from the bench's `SimClock` (`emulators/base.py`) and the model is
stepped lazily in fixed 4 ms sub-steps: before every command and on the bench's periodic tick, so a PTP
completion or a servo watchdog stop happens at the right simulated instant even when nobody asks.
The servo watchdog's timeout is in real seconds (it guards the link, whatever the speed factor).

Backdoor (tests, `emulators/depm.py`): `endpoint.drop_link()` / `restore()` (connection loss),
`stall(joint)` / `unstall()`, `place(q)` (put the joints somewhere, what an operator does by hand
with the pendant), `set_flange_input(pin, high)` (what is wired to the media flange's X3 inputs),
and `truth()` (joints, mode, and the media flange's LED and pins). Call them through
`server.call` or from the loop thread.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from rigctl.emulators.base import SimClock
from rigctl.emulators.kuka.model import SERVO_TIMEOUT_S, ArmLimits, LbrArmModel
from rigctl.emulators.kuka.protocol import KstServer
from rigctl.emulators.server import EmulatorServer

log = logging.getLogger(__name__)

KST_PORT = 30001
STARVED_TICKS = 10  # a gap of this many tick periods between two advances: the loop was starved
PHYSICS_STEP_S = 4e-3  # 250 Hz: fine for 50 Hz streams, and cheap enough at 6x speed


class EmulatedArm:
    """One arm: model, KST server, TCP endpoint. All state is touched in the loop thread."""

    def __init__(self, server: EmulatorServer, *, name: str, clock: SimClock,
                 q0: np.ndarray | None = None, limits: ArmLimits | None = None,
                 host: str = "127.0.0.1", port: int = 0,
                 servo_timeout_s: float = SERVO_TIMEOUT_S,
                 tick_s: float | None = None) -> None:
        self.name = name
        self.server = server
        self.clock = clock
        # the stream watchdog is about link silence, so it counts real seconds whatever the speed
        self.servo_timeout_s = servo_timeout_s
        self.model = LbrArmModel(q0, limits=limits, servo_timeout_s=servo_timeout_s * clock.speed)
        self.kst = KstServer(self.model, name=name, before_command=self.advance)
        self._stepped = clock.now()
        # The period of the tick that advances this arm (None: no tick). A much longer gap between
        # two advances means the emulator's loop did not run (a loaded computer): servo targets
        # may be waiting unread in the socket, so that silence is not the client's and the
        # watchdog does not count it.
        self.tick_s = tick_s
        self._advanced_real = time.monotonic()
        self.endpoint = server.serve_sessions_tcp(self.kst, name=name, host=host, port=port,
                                                  max_clients=1)
        self.url = self.endpoint.url

    def advance(self) -> None:
        """Step the joints to the clock's now and send any PTP completion that is due."""
        target = self.clock.now()
        model = self.model
        model.servo_timeout_s = self.servo_timeout_s * self.clock.speed
        real = time.monotonic()
        if self.tick_s is not None:
            starved = real - self._advanced_real - STARVED_TICKS * self.tick_s
            if starved > 0 and model.mode == "servo":
                log.debug("%s: emulator loop starved for %.3f s; not counted as stream silence",
                          self.name, starved)
                model.discount_silence(starved * self.clock.speed)
        self._advanced_real = real
        while self._stepped < target:
            remaining = target - self._stepped
            dt = remaining if model.mode == "idle" else min(PHYSICS_STEP_S, remaining)
            model.step(dt)  # at rest only the model's clock moves: one step will do
            self._stepped += dt
        self.kst.deliver_completions()

    # -- backdoor -------------------------------------------------------------------------------
    def place(self, q: np.ndarray) -> None:
        self.advance()
        if self.model.mode != "idle":
            raise ValueError(f"{self.name}: cannot place the arm while it moves ({self.model.mode})")
        self.model.q = self.model.check_target(q).copy()
        self.model.qd[:] = 0.0

    def stall(self, joint: int) -> None:
        self.advance()
        self.model.stall(joint)

    def unstall(self) -> None:
        self.advance()
        self.model.unstall()

    def set_flange_input(self, pin: int, high: bool) -> None:
        inputs = self.kst.media_flange.inputs
        if pin not in inputs:
            raise ValueError(f"{self.name}: the media flange has no input pin {pin} "
                             f"(inputs: {sorted(inputs)})")
        inputs[pin] = bool(high)

    def truth(self) -> dict:
        self.advance()
        m = self.model
        return {"q": m.q.tolist(), "qd": m.qd.tolist(), "mode": m.mode,
                "watchdog_tripped": m.watchdog_tripped, "stalled": sorted(m.stalled),
                "connections": self.endpoint.connection_count,
                "media_flange": self.kst.media_flange.truth()}

    def close(self) -> None:
        self.endpoint.close()
