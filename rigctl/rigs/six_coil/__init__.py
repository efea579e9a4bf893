"""The six-coil manipulator (seeds 000 and 002): realize, allocate, the Kepco supplies, global
moves with their camera supervisor, and pair formation with pure pursuit."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rigctl.core.channels import Channel
from rigctl.core.config import RigConfig
from rigctl.rigs.base import Device, RigKind, camera_devices
from rigctl.rigs.six_coil.faults import fault_profile
from rigctl.rigs.six_coil.report import REPORT

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig



def _own(rig: RigConfig) -> SixCoilRig:
    """`rig` as this kind's rig file model (imported when a hook runs, not when the kind loads)."""
    from rigctl.rigs.six_coil.settings import six_coil_rig

    return six_coil_rig(rig)

def _global_moves(plan, rig: RigConfig, *, closed_loop: bool | None = None, **run):
    from rigctl.rigs.six_coil.global_moves import Run

    rig = _own(rig)
    return Run(plan, rig, closed_loop=rig.camera is not None if closed_loop is None else closed_loop,
               **run)


def _pair_formation(plan, rig: RigConfig, *, closed_loop: bool | None = None, **run):
    from rigctl.rigs.six_coil.pair import PairRun, PairRunSettings, loopback_rig

    rig = _own(rig)
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

    rig = _own(rig)
    return supply_channels(rig)


def _devices(rig: RigConfig) -> list[Device]:
    rig = _own(rig)
    return [Device(c.name, c.url, "supply") for c in rig.coils] + camera_devices(rig)


def _make_safe(rig: RigConfig) -> dict[str, str | None]:
    from rigctl.rigs.six_coil.supplies import zero_supplies_directly

    rig = _own(rig)
    return zero_supplies_directly(rig)


def _hold(rig: RigConfig, target: dict):
    """`{"field_mT": [bx, by, bz]}` at the workspace centre: the minimum-norm currents, each
    within its coil's limit, and the supplies' compliance R I + L dI/dt over the ramp to them."""
    import numpy as np

    from rigctl.physics.coils import actuation_matrix, field_offset
    from rigctl.rigs.six_coil.allocate import check_current_limits, currents_for_field
    from rigctl.rigs.six_coil.supplies import CoilSupplies
    from rigctl.run.hold import HoldRequest, ramp, target_values

    rig = _own(rig)
    field_mT = target_values(target, "field_mT", (3,), KIND.name, "mT")
    currents = currents_for_field(actuation_matrix(rig), field_mT * 1e-3 - field_offset(rig)[0:3])
    rate = rig.stream.rate_hz
    asked = f"{field_mT.tolist()} mT"

    def check_ramp(start: np.ndarray, ramp_s: float) -> None:
        samples = ramp(start, currents, ramp_s, rate)
        check_current_limits(
            np.vstack([samples, currents]), rig, rate,
            lambda k: f"{asked} ({'held' if k == len(samples) else 'ramping'})",
            current_advice="ask for a weaker field", start_A=start,
            voltage_advice="ramp more slowly (a longer ramp_s) or ask for a weaker field")

    check_current_limits(currents[None], rig, None, lambda _: asked,
                         current_advice="ask for a weaker field")
    return HoldRequest({"field_mT": field_mT.tolist()}, currents, CoilSupplies.connect, rate,
                       "slip", check_ramp)


def _teleop(rig: RigConfig, mode: str | None):
    from rigctl.rigs.six_coil.teleop import teleop_drive

    rig = _own(rig)
    return teleop_drive(rig, mode)


def _settings() -> type[RigConfig]:
    from rigctl.rigs.six_coil.settings import SixCoilRig

    return SixCoilRig



def _probe_supply(rig: RigConfig, device: Device, timed: bool = False) -> str:
    from rigctl.rigs.six_coil.probes import supply

    rig = _own(rig)
    return supply(rig, device, timed)


def _windings(rig: RigConfig):
    """The rig's coils (six on the cube, any N >= 3), each fed a current by its supply."""
    from rigctl.physics.thermal import Windings

    rig = _own(rig)
    return Windings.of_coils(rig.coils)


def _field_fit():
    """`rigctl calibrate field`'s measurement and fit (drive_patterns, measure, fit_calibration,
    prediction_error)."""
    from rigctl.rigs.six_coil import field_fit

    return field_fit


def _template() -> str:
    """The commented rig file of `rigctl init six-coil` (package data)."""
    from importlib.resources import files

    return (files("rigctl.rigs.six_coil") / "template.toml").read_text()

def _turn_mm(rig: RigConfig | None) -> float:
    """One whole roll of a rolling magnet: 2 pi r, r from the rig file's [magnets] (or the
    default magnets for none, or for a rig file of another kind)."""
    import math

    from rigctl.core.config import MagnetSettings

    return 2.0 * math.pi * (getattr(rig, "magnets", None) or MagnetSettings()).radius_mm


def _plan_goals(rig: RigConfig, problem):
    """Clicked goals for rolling magnets: the global-input RRT (seed 000), moves of whole turns;
    for two agents last run as a pair formation, the pair planner (seed 002)."""
    from dataclasses import replace

    from rigctl.plans.goals import plan_pair_goals, plan_rrt_goals

    if problem.plan_kind == "pair-formation":
        return plan_pair_goals(problem)
    return plan_rrt_goals(replace(problem, turn_mm=_turn_mm(rig)), "slide")


KIND = RigKind(
    teleop=_teleop,
    plan_goals=_plan_goals,
    wall_contact="slide",
    turn_mm=_turn_mm,
    name="six-coil",
    description="N >= 3 electromagnets (six air-core coils on a cube by default) fed by Kepco "
    "BOP supplies, overhead camera",
    faults=fault_profile,
    report=REPORT,
    plans={"global-moves": _global_moves, "pair-formation": _pair_formation},
    channels=_channels, devices=_devices, make_safe=_make_safe, hold=_hold,
    bench_args=_bench_args, bench_rig=_bench_rig, settings=_settings,
    template=_template, bench="rigctl.emulators.bench:SixCoilBench",
    probes={"supply": _probe_supply}, windings=_windings,
    calibrations=frozenset({"field"}), field_fit=_field_fit)
