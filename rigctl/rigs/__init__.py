"""The rig kinds: what differs between the six-coil manipulator, the coil board and the arms.

`KINDS` is the one registry: `rigctl execute`, `rigctl emulate`, the daemon and its stream
process look a rig kind up here instead of switching on its name. `prepare_run` is what refuses a
plan on a rig: `rigctl validate`, `rigctl execute` and the daemon's `load` all call it, so each
refuses exactly what the others do."""

from __future__ import annotations

from typing import Any

from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, PlanError
from rigctl.rigs import coil_board, depm, six_coil
from rigctl.rigs.base import Device, RigKind

KINDS: dict[str, RigKind] = {k.name: k for k in (six_coil.KIND, coil_board.KIND, depm.KIND)}


def rig_kind(name: str) -> RigKind:
    try:
        return KINDS[name]
    except KeyError:
        raise ConfigError(f"rig kind {name!r} is not one of {', '.join(KINDS)}") from None


def prepare_run(plan: Any, rig: RigConfig, *, runs_dir: Any = "runs", **run: Any) -> Any:
    """The engine's run of `plan` on `rig`, prepared with no I/O: everything that refuses a plan
    on a rig, in one place. PlanError for a plan made for another rig kind or of a kind the rig
    does not run; then the builder's own (PlanError, ConfigError, LimitError, the pre-flight
    certificate's CertificateRefused): the schema-checked plan's geometry, the rig kind's rules
    (whole turns, two particles, the arms' constraints) and every limit. `run`: the builder's
    keywords (progress_out, on_cycle, closed_loop, ...)."""
    if plan.rig != rig.rig.kind:
        raise PlanError(f"plan: rig: the plan is for a {plan.rig} rig; {rig.rig.name!r} is a "
                        f"{rig.rig.kind} rig")
    return rig_kind(rig.rig.kind).builder(plan.kind)(plan, rig, runs_dir=runs_dir, **run)


__all__ = ["KINDS", "Device", "RigKind", "prepare_run", "rig_kind"]
