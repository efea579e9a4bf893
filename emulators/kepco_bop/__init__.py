"""Emulated Kepco BOP bipolar supply pair driving one coil.

`model.py` is the coil and supply physics (pure, stepped by hand), `protocol.py` the SCPI dialect,
and `serve_bop` puts both on a TCP port of a shared `EmulatorServer`, stepping the model to the
present (`ModelClock`, on the benches' `SimClock`) before every command:

    with EmulatorServer() as server:
        bop = serve_bop(server, name="x+", resistance_ohm=1.5, inductance_H=0.03)
        transport = open_transport(bop.endpoint.url)          # tcp://127.0.0.1:<port>
        server.call(bop.model.inject_overtemperature)         # backdoor, in the loop thread
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from rigctl.emulators.base import SimClock
from rigctl.emulators.kepco_bop.model import BopCoilModel
from rigctl.emulators.kepco_bop.protocol import BopScpi
from rigctl.emulators.server import EmulatorServer, Endpoint

__all__ = ["BopCoilModel", "BopScpi", "EmulatedBop", "ModelClock", "serve_bop"]


class ModelClock:
    """Steps a model to "now" on the benches' one clock (`SimClock`: elapsed monotonic time x speed)."""

    def __init__(self, step: Callable[[float], None], speed: float = 1.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.step, self.sim = step, SimClock(speed, monotonic=clock)
        self._last: float | None = None

    def advance(self) -> None:
        now = self.sim.now()
        if self._last is not None and now > self._last:
            self.step(now - self._last)
        self._last = now


@dataclass
class EmulatedBop:
    """One served BOP: its model (touch only through `server.call`), protocol and endpoint."""

    model: BopCoilModel
    protocol: BopScpi
    endpoint: Endpoint
    clock: ModelClock


def serve_bop(
    server: EmulatorServer,
    *,
    name: str,
    resistance_ohm: float = 1.5,
    inductance_H: float = 0.03,
    current_limit_A: float = 20.0,
    compliance_V: float = 100.0,
    host: str = "127.0.0.1",
    port: int = 0,
    speed: float = 1.0,
) -> EmulatedBop:
    """Serve one emulated BOP pair on TCP (LF-terminated SCPI, as on the BOP's LAN port)."""
    model = BopCoilModel(resistance_ohm, inductance_H, current_limit_A, compliance_V)
    clock = ModelClock(model.step, speed=speed)
    clock.advance()  # start the clock now
    protocol = BopScpi(model, before_command=clock.advance)
    endpoint = server.serve_lines_tcp(protocol.handle, name=name, host=host, port=port)
    return EmulatedBop(model=model, protocol=protocol, endpoint=endpoint, clock=clock)
