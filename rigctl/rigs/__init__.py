"""The rig kinds: what differs between the six-coil manipulator, the coil board and the arms.

Each kind is a package that registers its `RigKind` under the entry-point group `rigctl.rigs`
(`rigctl.core.registry`, which loads them on first use); the three here register themselves in
rigctl's own pyproject.toml exactly as a lab's package would in its. `KINDS` and `rig_kind` read
that registry: `rigctl execute`, `rigctl emulate`, the daemon and its stream process look a rig kind
up there instead of switching on its name. `prepare_run` is what refuses a plan on a rig: `rigctl
validate`, `rigctl execute` and the daemon's `load` all call it, so each refuses exactly what the
others do."""

from __future__ import annotations

from typing import Any

from rigctl.core.config import RigConfig
from rigctl.core.errors import PlanError
from rigctl.core.registry import kinds, rig_kind
from rigctl.rigs.base import Device, RigKind


def __getattr__(name: str) -> Any:
    """`KINDS`: the installed rig kinds by name, read from the registry when first asked for (so
    that importing `rigctl.rigs` loads no kind)."""
    if name == "KINDS":
        return kinds()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
