"""The spinner's rig file: rigctl's common tables plus `[grbl]`, the controller and its axis.

    [rig]
    kind = "grbl-spinner"
    [grbl]
    url = "serial:///dev/ttyACM0?baud=115200"
    steps_per_degree = 8.889        # GRBL $100 (X in degrees: 3200 microsteps per turn / 360)
    max_rate_hz = 5.0               # turns/s; GRBL $110 = max_rate_hz * 21600 degrees/min
    max_acceleration_hz_per_s = 20  # turns/s^2; GRBL $120 = 360 x this, degrees/s^2

The controller's `$100`, `$110` and `$120` must say what this table says: the driver reads them
on connect and refuses a controller configured otherwise (it never writes them: they are EEPROM
settings a lab sets once, and the limits a plan is checked against come from here).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from rigctl.core.config import DeviceUrl, RigConfig

DEG_PER_MIN_PER_HZ = 360.0 * 60.0  # a GRBL feed in degrees/min per turn/s


class GrblSettings(BaseModel):
    """The GRBL controller of the spinner and the stepper's axis (X, configured in degrees)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    url: DeviceUrl = Field(description="serial:///dev/ttyACM0?baud=115200, a pty path or tcp://host:port")
    baud: Annotated[int, Field(gt=0, description="for a bare device path")] = 115200
    steps_per_degree: Annotated[float, Field(gt=0, description="GRBL $100")] = 3200 / 360
    max_rate_hz: Annotated[float, Field(gt=0, le=50, description="turns/s; GRBL $110 / 21600")] = 5.0
    max_acceleration_hz_per_s: Annotated[float, Field(
        gt=0, description="turns/s^2; GRBL $120 / 360")] = 20.0
    rate_hz: Annotated[float, Field(gt=0, le=100, description="jogs streamed per second")] = 50.0
    reply_timeout_s: Annotated[float, Field(
        gt=0, le=5, description="every exchange: an ok, a status report (the status-poll watchdog)")] = 0.25
    boot_timeout_s: Annotated[float, Field(
        gt=0, le=10, description="the welcome banner after a reset (an Arduino's bootloader: ~2 s)")] = 3.0
    magnet: str = Field("magnet", description="the channel's name: what turns")

    @property
    def max_rate_deg_min(self) -> float:
        return self.max_rate_hz * DEG_PER_MIN_PER_HZ

    @property
    def acceleration_deg_s2(self) -> float:
        return self.max_acceleration_hz_per_s * 360.0


class SpinnerConfig(RigConfig):
    """A grbl-spinner rig file: the common tables and `[grbl]`."""

    grbl: GrblSettings
