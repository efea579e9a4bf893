"""`rigctl doctor --rig RIG.toml`: reach every device of a rig without energising anything and say
what each one answered, so that a wrong port or a dead link is found before a run.

One probe per device kind, each a read-only exchange on the device's own protocol: a supply's
`*IDN?` and its error queue (and, from `rigctl doctor`, its query round trip against the rig
file's `[preflight] scpi_round_trip_ms`); the coil board's handshake (firmware, channels, watchdog) and its
STATUS (outputs must read zero); each arm's joint positions; one Hall board sample (a board at
rest reads the earth's field, tens of microtesla); one camera frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, RigError
from rigctl.rigs import rig_kind
from rigctl.rigs.base import Device


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


ROUND_TRIPS = 20  # `MEAS:CURR?` queries timed per supply by `rigctl doctor`


def _supply(rig: RigConfig, device: Device, timed: bool = False) -> str:
    from rigctl.core.transport import open_transport
    from rigctl.drivers.kepco_bop import KepcoBop

    coil = next(c for c in rig.coils if c.name == device.name)
    timeout = rig.stream.reply_timeout_s
    bop = KepcoBop(open_transport(coil.url, timeout_s=timeout), name=coil.name,
                   current_limit_A=coil.current_limit_A, compliance_V=coil.compliance_V,
                   timeout_s=timeout)
    try:
        identity = bop.identify()
        queue = bop.errors()
        trips = []
        for _ in range(ROUND_TRIPS if timed else 0):  # a query: nothing is set
            started = time.perf_counter()
            bop.measure_current()
            trips.append(1e3 * (time.perf_counter() - started))
    finally:
        bop.close()
    if queue:
        raise RigError(f"{identity}; error queue: " + "; ".join(f"{c} {t}" for c, t in queue),
                       device=coil.name)
    return f"{identity}; error queue empty" + (_round_trip(rig, coil.url, trips) if trips else "")


def _round_trip(rig: RigConfig, url: str, trips_ms: list[float]) -> str:
    """The measured query round trip against what the pre-flight assumes of a LAN link
    (`[preflight] scpi_round_trip_ms`; a serial link's time comes from its baud rate)."""
    p50, worst = float(np.median(trips_ms)), max(trips_ms)
    text = f"; query round trip p50 {p50:.2f} ms, max {worst:.2f} ms over {len(trips_ms)}"
    if url.startswith("serial"):
        return text
    assumed = rig.preflight.scpi_round_trip_ms
    text += f" (rig file: scpi_round_trip_ms {assumed:g})"
    if p50 > assumed:
        text += (f": SLOWER than the pre-flight assumes; set [preflight] scpi_round_trip_ms to "
                 f"{worst:.2g} or more before streaming at the rate it certified")
    return text


def _board(rig: RigConfig, device: Device) -> str:
    from rigctl.drivers.coilboard import CoilBoard

    board = CoilBoard.from_settings(rig.board)
    try:
        hello, status = board.hello, board.status()
    finally:
        board.close()
    if any(status.outputs):
        raise RigError(f"outputs {list(status.outputs)} are not zero with nobody driving them",
                       device=device.name)
    return (f"firmware {hello.fw_major}.{hello.fw_minor}, {hello.channels} channels, watchdog "
            f"{hello.watchdog_ms} ms; outputs zero, {status.bad_frames} bad frames")


def _arm(rig: RigConfig, device: Device) -> str:
    from rigctl.drivers.kuka_sunrise import KukaArm

    arm = KukaArm.open(device.url, name=device.name, timeout_s=rig.depm.reply_timeout_s)
    try:
        q = arm.joint_positions()
    finally:
        arm.close()
    return "joints " + " ".join(f"{v:+.3f}" for v in np.asarray(q)) + " rad"


def _hall(rig: RigConfig, device: Device) -> str:
    from rigctl.drivers.hall import HallBoard

    board = HallBoard.open(device.url, name=device.name, timeout_s=rig.depm.reply_timeout_s)
    try:
        sample = board.read()
    finally:
        board.close()
    magnitude_uT = np.linalg.norm(sample.field_T, axis=1) * 1e6
    saturated = " SATURATED" if np.any(sample.saturated) else ""
    return (f"{len(magnitude_uT)} sensors, |B| " + ", ".join(f"{b:.0f}" for b in magnitude_uT)
            + f" uT{saturated}")


def _camera(rig: RigConfig, device: Device) -> str:
    from rigctl.drivers.camera import CameraDriver

    with CameraDriver(rig.camera.url, stamped=rig.camera.stamped, timeout_s=2.0,
                      reconnect_attempts=0) as camera:
        frame = camera.read()
    height, width = frame.image.shape[:2]
    return f"one frame, {width} x {height} px"


PROBES: dict[str, Callable[..., str]] = {
    "supply": _supply, "board": _board, "arm": _arm, "hall board": _hall, "camera": _camera}


def probe_rig(rig: RigConfig, timed: bool = False) -> list[Probe]:
    """Every device of the rig, probed in turn; never raises (a failure is that device's row).
    `timed`: each supply's query round trip is measured too (`rigctl doctor`)."""
    results = []
    for device in rig_kind(rig.rig.kind).devices(rig):
        started = time.monotonic()
        try:
            probe = PROBES[device.kind]
            detail = probe(rig, device, timed) if device.kind == "supply" else probe(rig, device)
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
