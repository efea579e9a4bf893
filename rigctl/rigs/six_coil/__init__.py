"""The six-coil manipulator (seeds 000 and 002): realize, allocate, the Kepco supplies, global
moves with their camera supervisor, and pair formation with pure pursuit."""

from __future__ import annotations

from rigctl.channels import Channel
from rigctl.config import RigConfig
from rigctl.rigs.base import Device, RigKind, camera_devices


def _global_moves(plan, rig: RigConfig, *, closed_loop: bool | None = None, **run):
    from rigctl.rigs.six_coil.global_moves import Run

    return Run(plan, rig, closed_loop=rig.camera is not None if closed_loop is None else closed_loop,
               **run)


def _pair_formation(plan, rig: RigConfig, *, closed_loop: bool | None = None, **run):
    from rigctl.rigs.six_coil.pair import PairRun, PairRunSettings, loopback_rig

    closed = rig.camera is not None if closed_loop is None else closed_loop
    if rig.emulation is not None:
        rig = loopback_rig(rig)
    return PairRun(plan, rig, settings=PairRunSettings(closed_loop=closed), **run)


def _bench_rig() -> RigConfig:
    from rigctl.plans.pair import default_rig

    return default_rig()


def _bench_args(plan) -> list[str]:
    return ["--world", "pair"] if plan.kind == "pair-formation" else []


def _channels(rig: RigConfig) -> list[Channel]:
    from rigctl.rigs.six_coil.supplies import supply_channels

    return supply_channels(rig)


def _devices(rig: RigConfig) -> list[Device]:
    return [Device(c.name, c.url, "supply") for c in rig.coils] + camera_devices(rig)


def _make_safe(rig: RigConfig) -> dict[str, str | None]:
    from rigctl.rigs.six_coil.supplies import zero_supplies_directly

    return zero_supplies_directly(rig)


KIND = RigKind(
    name="six-coil",
    description="six air-core coils fed by Kepco BOP supplies, overhead camera",
    plans={"global-moves": _global_moves, "pair-formation": _pair_formation},
    channels=_channels, devices=_devices, make_safe=_make_safe, bench_args=_bench_args,
    bench_rig=_bench_rig)
