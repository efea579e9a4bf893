"""The coil board's four coils as the emulated bench builds them: windings that heat.

Each coil's winding follows `rigctl.physics.thermal` under the voltage its SyRen puts across it (the
output, -1..1, times the SyRens' supply: P = V^2 / R(T)), with thermal data of its own: the rig
file's R_th and C_th, each off by a seeded error uniform in +-`size` (`ThermalErrors`, default
5 %, as the six-coil bench's windings are 5 % off), so that the host's model meets windings that
differ from its data. Whoever drives the wire (the Python firmware or the AVR firmware in
simavr), the coils heat by what the bus carries, not by what the host asked for.

A thermal cut-out in series with each coil opens when its winding reaches `max_winding_C + 10`
(the cut-out behind rigctl's own limit, as on the six-coil bench's supplies) and closes again
`CUTOUT_HYSTERESIS_K` below: a coil whose cut-out is open carries no current and pulls nothing.
The board's protocol has no over-temperature flag, so the host learns of it only as a coil that
stops pulling; rigctl's own model reaches the limit 10 K before and stops the run (a guess at how
a lab would wire it, as the BOP's over-temperature report is).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigctl.core.config import CoilBoardSettings
from rigctl.physics.thermal import Windings, step_voltage_one

CUTOUT_ABOVE_LIMIT_K = 10.0
CUTOUT_HYSTERESIS_K = 10.0
THERMAL_STEP_S = 0.1  # a longer gap between two steps is taken in steps of this much


@dataclass(frozen=True)
class ThermalErrors:
    """How far the emulated windings are from the rig file's: R_th and C_th each (1 + e), e
    uniform in +-size, drawn per coil from `seed`."""

    size: float = 0.05
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.size < 0.5:
            raise ValueError(f"thermal error size must be in [0, 0.5), got {self.size}")


class BoardCoils:
    """The four windings of `board` (`CoilBoardSettings`) as built: `step` heats them by the
    SyRen outputs and says which outputs still reach their coils."""

    def __init__(self, board: CoilBoardSettings, errors: ThermalErrors = ThermalErrors()) -> None:
        self.board = board
        self.data = Windings.of_board(board)
        self.temperature_C = [float(t) for t in self.data.ambient_C]
        self.peak_C = list(self.temperature_C)
        self.open = [False] * len(self.temperature_C)
        self.trip_C = [float(t) + CUTOUT_ABOVE_LIMIT_K for t in self.data.limit_C]
        self.errors = errors
        self.rebuild(errors)

    def rebuild(self, errors: ThermalErrors) -> None:
        """The windings made anew with `errors` (their temperatures are kept)."""
        rng = np.random.default_rng(errors.seed)
        size = errors.size
        r_error, c_error = rng.uniform(-size, size, (2, len(self.temperature_C)))
        self.errors = errors
        self.windings = self.data.off_by(r_error, c_error)
        self._one = [self.windings.one(j) for j in range(len(self.temperature_C))]

    def step(self, dt_s: float, outputs: tuple[float, ...]) -> tuple[float, ...]:
        """Advance `dt_s` with the SyRen `outputs` (-1..1) held; the outputs that reach their
        coils (zero where a cut-out was open)."""
        driven = tuple(0.0 if cut else float(v) for v, cut in zip(outputs, self.open))
        for j, one in enumerate(self._one):
            volts, t, left = driven[j] * self.board.supply_V, self.temperature_C[j], dt_s
            while left > 0:
                h = min(left, THERMAL_STEP_S)
                t = step_voltage_one(t, volts, h, one)
                left -= h
            self.temperature_C[j] = t
            self.peak_C[j] = max(self.peak_C[j], t)
            if t >= self.trip_C[j]:
                self.open[j] = True
            elif self.open[j] and t < self.trip_C[j] - CUTOUT_HYSTERESIS_K:
                self.open[j] = False
        return driven

    def truth(self) -> dict:
        """Each coil's winding now and its peak (C) and whether its cut-out is open."""
        names = self.data.names
        return {"winding_C": dict(zip(names, self.temperature_C)),
                "winding_peak_C": dict(zip(names, self.peak_C)),
                "cutout_open": dict(zip(names, self.open))}

    def describe(self) -> dict:
        """The errors and each winding as built against the rig file's (the `windings` command)."""
        return {"size": self.errors.size, "seed": self.errors.seed,
                "coils": [{"name": name, "r_th_K_per_W": float(self.windings.r_th[j]),
                           "c_th_J_per_K": float(self.windings.c_th[j]),
                           "rig_r_th_K_per_W": float(self.data.r_th[j]),
                           "rig_c_th_J_per_K": float(self.data.c_th[j])}
                          for j, name in enumerate(self.data.names)]}
