"""`rigctl doctor --rig RIG.toml`: reach every device of a rig without energising anything and say
what each one answered, so that a wrong port or a dead link is found before a run.

One probe per device kind, each a read-only exchange on the device's own protocol. The rig kind
brings the probes of its devices (`RigKind.probes`: a supply's `*IDN?` and error queue, the coil
board's handshake and STATUS, each arm's joints, a Hall board sample); the camera's, one frame,
is every rig's and lives here. `timed` (`rigctl doctor`) is passed to a probe that takes a
`timed` keyword: it times its device's round trip too (a supply's against `[preflight]
scpi_round_trip_ms`).
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, RigError
from rigctl.rigs import rig_kind
from rigctl.rigs.base import Device, DeviceProbe


@dataclass
class Probe:
    device: str
    kind: str
    url: str
    ok: bool
    detail: str
    ms: float

    def as_dict(self) -> dict:
        return asdict(self)


def _camera(rig: RigConfig, device: Device) -> str:
    from rigctl.drivers.camera import CameraDriver

    camera_settings = rig.camera
    if camera_settings is None:  # a camera device is listed only for a rig with a [camera]
        raise ConfigError("the rig has no [camera]")
    with CameraDriver(camera_settings.url, stamped=camera_settings.stamped, timeout_s=2.0,
                      reconnect_attempts=0) as camera:
        frame = camera.read()
    height, width = frame.image.shape[:2]
    return f"one frame, {width} x {height} px"


GENERIC_PROBES: dict[str, DeviceProbe] = {"camera": _camera}
"""The probes of devices any rig kind may have; a kind's own come from its `RigKind.probes`."""


def _probe_for(kind, device: Device) -> DeviceProbe:
    probe = kind.probes.get(device.kind) or GENERIC_PROBES.get(device.kind)
    if probe is None:
        raise RigError(f"rig kind {kind.name} has no doctor probe for a {device.kind!r}",
                       device=device.name)
    return probe


def probe_rig(rig: RigConfig, timed: bool = False) -> list[Probe]:
    """Every device of the rig, probed in turn; never raises (a failure is that device's row).
    `timed`: each supply's query round trip is measured too (`rigctl doctor`)."""
    results = []
    kind = rig_kind(rig.rig.kind)
    for device in kind.devices(rig):
        started = time.monotonic()
        try:
            probe = _probe_for(kind, device)
            if timed and "timed" in inspect.signature(probe).parameters:
                timed_probe: Callable[..., str] = probe  # one that takes `timed` (just checked)
                detail = timed_probe(rig, device, timed=True)
            else:
                detail = probe(rig, device)
            ok = True
        except (RigError, OSError) as err:
            detail, ok = str(err), False
        results.append(Probe(device.name, device.kind, device.url, ok, detail,
                             round(1e3 * (time.monotonic() - started), 1)))
    return results


class DeviceUnreachable(ConfigError):
    """A device of the rig did not pass its probe, or could not be made safe, before anything was
    energised (exit 2: fix the rig file or the wiring; `rigctl doctor` shows every device)."""


def preflight(rig: RigConfig) -> None:
    """What the daemon and `rigctl execute` do first, once they own the rig and before a run record
    exists: every device answers its doctor probe, then every device is made safe, so that what a
    process killed before it left energised (a Kepco BOP has no link watchdog) is zeroed before
    anything else happens. Refuses with `DeviceUnreachable`, naming each device that failed."""
    failed = [f"{p.device} ({p.url}): {p.detail}" for p in probe_rig(rig) if not p.ok]
    if not failed:
        failed = [f"{name}: not made safe: {err}"
                  for name, err in rig_kind(rig.rig.kind).make_safe(rig).items() if err]
    if failed:
        raise DeviceUnreachable("; ".join(failed) + ". Nothing was energised; `rigctl doctor "
                                "--rig RIG.toml` probes every device")
