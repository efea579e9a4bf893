"""The actuator group of a rig, as the run engine drives it: six supplies, the coil board, two
arms. Each implements this; the engine never knows which it has."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from rigctl.core.channels import Channel
from rigctl.physics.thermal import Windings


class Actuators(Protocol):
    """One rig's actuator group. `cycle` writes every setpoint, then reads every device."""

    names: list[str]  # device names, as faults and the record name them
    channels: list[Channel]
    # the coils the run's winding model watches, in channel order: their channels are currents,
    # or a drive of `Windings.volts_per_unit` volts per unit
    windings: Windings | None

    def energise(self) -> None: ...

    def cycle(self, setpoints: np.ndarray) -> np.ndarray: ...

    def emergency_zero(self) -> list[str]:
        """Any thread, latched, never raises: the devices the e-stop could not be sent to."""

    def zero_now(self) -> None:
        """On the stream thread after an e-stop: zero again, best effort."""

    def stop(self, ramp_s: float) -> list[str]:
        """Ramp down, make safe, close; never raises: the devices whose safe state is not
        confirmed."""

    # A group whose devices hold their output when nobody talks to them (a Kepco BOP has no link
    # watchdog) also has `make_safe_directly(rig) -> {name: None | why not}`, a static method: the
    # engine reaches the devices `stop` could not confirm again with it before the run ends.
