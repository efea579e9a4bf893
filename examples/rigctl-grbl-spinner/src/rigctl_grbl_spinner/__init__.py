"""grbl-spinner: a rotating permanent magnet on a stepper motor behind a GRBL 1.1 controller, as a
rig kind rigctl finds through its `rigctl.rigs` entry point (this package's pyproject.toml).

Labs drive helical micro-swimmers with such a magnet: the swimmer turns with the field and swims
at a speed that goes with the rotation rate. The stepper is GRBL's X axis configured in degrees;
the rig streams short jogs at the plan's rates (`spin.py`, `actuators.py`, `driver.py`); its
emulated bench serves a GRBL 1.1h model on a pty (`bench.py`, `grbl_wire.py`, `grbl_model.py`).

Only `KIND` is imported with the entry point: every hook imports its module when called, so
`rigctl --help` loads none of this.
"""

from __future__ import annotations

from rigctl.core.channels import Channel
from rigctl.core.config import RigConfig
from rigctl.rigs.base import Device, RigKind

NAME = "grbl-spinner"
DEVICE_KIND = "grbl controller"


def _settings() -> type[RigConfig]:
    from rigctl_grbl_spinner.settings import SpinnerConfig

    return SpinnerConfig


def _spin_sequence(plan, rig, **run):
    from rigctl_grbl_spinner.spin import build_spin_run

    return build_spin_run(plan, rig, **run)


def _spin_plan_model() -> type:
    from rigctl_grbl_spinner.spin import SpinSequencePlan

    return SpinSequencePlan


def _channels(rig) -> list[Channel]:
    from rigctl_grbl_spinner.actuators import spinner_channels

    return spinner_channels(rig)


def _devices(rig) -> list[Device]:
    return [Device("grbl", str(rig.grbl.url), DEVICE_KIND)]


def _make_safe(rig) -> dict[str, str | None]:
    """The rotor at rest (jog cancel, feed hold, soft reset), opened anew; never raises."""
    from rigctl_grbl_spinner.actuators import SpinnerActuators

    try:
        return SpinnerActuators.make_safe_directly(rig)
    except Exception as err:  # make_safe never raises: the engine's contract
        return {"grbl": f"{type(err).__name__}: {err}"}


def _hold(rig, target: dict):
    """`{"rate_hz": r}`: turn at r turns/s (signed) until released, within `max_rate_hz`."""
    from rigctl.core.errors import LimitError
    from rigctl.run.hold import HoldRequest, target_values
    from rigctl_grbl_spinner.actuators import SpinnerActuators

    g = rig.grbl
    rate = target_values(target, "rate_hz", (1,), NAME, "turns/s, signed")
    if abs(rate[0]) > g.max_rate_hz:
        raise LimitError(f"{rate[0]:g} Hz is beyond the rig's max_rate_hz {g.max_rate_hz:g}; "
                         "ask for less")
    # any ramp is allowed: GRBL's planner holds every change of rate to $120 whatever it asks
    return HoldRequest({"rate_hz": rate.tolist()}, rate, SpinnerActuators.connect, g.rate_hz,
                       "slip", lambda start, ramp_s: None)


def _bench_rig() -> RigConfig:
    """The rig `rigctl emulate grbl-spinner` serves, before it starts (its pty is its own)."""
    from rigctl.core.config import Emulation, RigInfo
    from rigctl_grbl_spinner.settings import GrblSettings, SpinnerConfig

    return SpinnerConfig(rig=RigInfo(kind=NAME, name="emulated grbl-spinner bench"),
                         grbl=GrblSettings(url="/dev/null"),
                         emulation=Emulation(backdoor="tcp://127.0.0.1:1"))


def _template() -> str:
    from importlib.resources import files

    return files("rigctl_grbl_spinner").joinpath("grbl-spinner.toml").read_text()


def _probe(rig, device: Device) -> str:
    """Read-only: a `?` status exchange (repeated until the banner-and-boot of an Arduino that
    reset when its port opened is over), nothing written that moves or resets."""
    from rigctl_grbl_spinner.driver import probe

    return probe(rig.grbl)


def _patience_s(rig) -> float:
    """A healthy cycle may wait twice on the controller: for room in its RX buffer, for its
    status report (each within `[grbl] reply_timeout_s`)."""
    return 2.0 * rig.grbl.reply_timeout_s


def _faults():
    from rigctl_grbl_spinner.faults import fault_profile

    return fault_profile()


KIND = RigKind(
    name=NAME,
    description="a permanent magnet turned by a stepper motor behind a GRBL 1.1 controller",
    plans={"spin-sequence": _spin_sequence},
    channels=_channels, devices=_devices, make_safe=_make_safe, hold=_hold, bench_rig=_bench_rig,
    settings=_settings, bench="rigctl_grbl_spinner.bench:SpinnerBench", template=_template,
    probes={DEVICE_KIND: _probe}, faults=_faults, patience_s=_patience_s,
    plan_models={"spin-sequence": _spin_plan_model})
