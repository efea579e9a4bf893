"""What a rig kind is to the rest of rigctl: one registry entry instead of a switch per place.

A `RigKind` names the plan kinds it runs (each a builder of the one engine `Run`), how an
operator's manual hold becomes setpoints (`hold`: every rig runs `hold` plans too), the channels
its actuators stream, its devices (for `status` and the direct make-safe), and how to make every
device safe with no run to ask (the e-stop with nothing active, a stream process that died). It
also carries everything else the applications ask of a rig: its rig file's model (`settings`), its
emulated bench, its `rigctl init` template, its `doctor` probes, its heating windings, how long
its devices may take to answer, what `calibrate` can do on it, its fault profile, its console
scene and its report's sections. A kind registers its `RigKind` under the entry-point group
`rigctl.rigs` (`rigctl.core.registry`); docs/rig-kinds.md says how to write one. The hooks import
their rig's modules when called, so `rigctl --help` does not load every rig.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rigctl.core.channels import Channel
from rigctl.core.config import RigConfig

if TYPE_CHECKING:
    from rigctl.physics.thermal import Windings
    from rigctl.rigs.faults import FaultProfile
    from rigctl.run.hold import HoldRequest

RunBuilder = Callable[..., Any]
"""build(plan, rig, *, runs_dir, progress_out=None, on_cycle=None, on_state=None, <options>)
-> rigctl.run.engine.Run, prepared: a plan the rig cannot run is refused here, with no I/O.
The options a builder names as keywords (closed_loop, agnostic, time_scale) are the only ones
`rigctl execute` passes it; any other flag is refused by name."""


def no_bench_args(plan: Any) -> list[str]:
    return []


@dataclass(frozen=True)
class Device:
    """One device of a rig as `status` lists it: its name, where it is, what it is."""

    name: str
    url: str
    kind: str  # "supply", "board", "arm", "hall board", "camera"


DeviceProbe = Callable[[RigConfig, "Device"], str]
"""`rigctl doctor`'s read-only probe of one device: a one-line detail of what it answered, or
RigError (or OSError) saying why it did not. One that also takes a `timed` keyword is asked by
`rigctl doctor` to time its device's round trip."""


def _default_settings() -> type[RigConfig]:
    return RigConfig


def no_windings(rig: RigConfig) -> Windings | None:
    return None


def no_patience(rig: RigConfig) -> float:
    return 0.0


@dataclass(frozen=True)
class ReportHooks:
    """What `rigctl report` shows of a kind beyond every rig's sections."""

    group_titles: Mapping[str, str] = field(default_factory=dict)
    """A channel group's title (`{"coil_current": "coil currents (six supplies)"}`)."""
    panels: Callable[[Any], list] | None = None
    """panels(RunData) -> [TimePanel]: the time panels only this kind has."""
    old_channels: Callable[[list[Channel], Path], list[Channel]] | None = None
    """old_channels(channels, run_dir): the channels of a record written before channels said
    their unit and group, as they were meant (the record's folder holds its rig file)."""


@dataclass(frozen=True)
class StudyHooks:
    """What `rigctl study` needs of a kind to run a case on its emulated bench beyond `bench` and
    `bench_args`: nothing yet (a field is added when a kind needs one)."""


@dataclass(frozen=True)
class RigKind:
    name: str
    description: str
    plans: dict[str, RunBuilder]  # plan kind -> builder
    channels: Callable[[RigConfig], list[Channel]]
    devices: Callable[[RigConfig], list[Device]]
    make_safe: Callable[[RigConfig], dict[str, str | None]]
    """Open every actuator anew and make it safe; never raises: device name -> None when done,
    else why it could not be reached."""
    hold: Callable[[RigConfig, dict], HoldRequest]
    """An operator's hold request (`{"field_mT": ...}`, `{"drive": ...}`, `{"joints_rad": ...}`)
    as setpoints, its limits checked with no I/O: ConfigError for a request of the wrong shape,
    LimitError for one beyond a limit, each saying what to ask instead."""
    bench_args: Callable[[Any], list[str]] = no_bench_args
    """The `rigctl emulate` flags a plan needs of the emulated bench (a pair plan: its world)."""
    bench_rig: Callable[[], RigConfig] | None = None
    """The rig its emulated bench serves, known without starting it: `rigctl execute` refuses a
    plan against it before a bench is started."""
    settings: Callable[[], type[RigConfig]] = _default_settings
    """The rig file's model for this kind: `RigConfig` (the common tables) or a subclass adding
    the kind's own tables. `load_rig` validates a rig file whose `[rig] kind` names this kind
    with it."""
    bench: str | None = None
    """"module:Class" of its emulated bench (a `rigctl.emulators.base.EmulatedBench`), which
    `rigctl emulate KIND` starts; None: the kind has no emulator."""
    template: Callable[[], str] | None = None
    """The commented rig file `rigctl init KIND` writes."""
    probes: Mapping[str, DeviceProbe] = field(default_factory=dict)
    """`rigctl doctor`'s probe per `Device.kind` its `devices()` lists (the core probes a
    "camera" itself)."""
    windings: Callable[[RigConfig], Windings | None] = no_windings
    """The windings the heating model watches (`rigctl.physics.thermal.Windings`), in the order
    of its channels; None where nothing heats."""
    patience_s: Callable[[RigConfig], float] = no_patience
    """How long the kind's devices may take to answer (s): the daemon's stream host waits the
    larger of this and `[stream] reply_timeout_s` before it calls a stream process hung (the
    coil board: its retries and a reconnect; the arms: their own reply timeout)."""
    calibrations: frozenset[str] = frozenset()
    """What `rigctl calibrate` can do on it ("field"; "camera" needs only a `[camera]`)."""
    field_fit: Callable[[], Any] | None = None
    """`rigctl calibrate field`'s measurement and fit, imported when called: an object with
    `drive_patterns`, `measure`, `fit_calibration` and `prediction_error` (the six-coil rig's:
    the module `rigctl.rigs.six_coil.field_fit`)."""
    faults: Callable[[], FaultProfile] | None = None
    """Its profile for `rigctl faults` (None: the campaign does not run on it)."""
    scene: str = "camera"
    """The console's view: "camera" (the overhead image, tracked and planned paths) or "arms"."""
    scene_of: Callable[[RigConfig], dict] | None = None
    """What an "arms" scene draws (bases, link lengths), as JSON-ready data."""
    report: ReportHooks = field(default_factory=ReportHooks)
    """What `rigctl report` adds for this kind."""
    study: StudyHooks | None = None
    """What `rigctl study` needs beyond `bench` and `bench_args` (None: nothing)."""
    plan_models: Mapping[str, Callable[[], type]] = field(default_factory=dict)
    """The document model (a pydantic class, schema `rigctl.plan/1`) of each plan kind this kind
    brings that `rigctl.plans.schema` does not know, by plan kind: `parse_plan` validates such a
    plan with it (a lab's plan kinds; the papers' kinds are in the schema's union)."""
    turn_mm: Callable[[RigConfig | None], float] | None = None
    """The length (mm) of one whole roll of the kind's agents, for a kind whose global moves must
    be whole rolls (rolling magnets), from its rig file (None: the kind's defaults); the planners
    quantise moves to it. None: moves of any length."""
    wall_contact: str | None = None
    """How agents meet walls in the kind's global-moves plans, for the global-input model and its
    planners: "slide" (rolling magnets) or "non-slip" (particles stick); None: it runs none."""

    teleop: Callable[[RigConfig, str | None], Any] | None = None
    """teleop(rig, mode) -> a `rigctl.run.teleop.TeleopDrive`: how an operator's live input
    (steering by hand) becomes setpoints on this kind, in the mode named (None: its first);
    ConfigError for a mode it has not. None: the kind has no teleoperation."""
    plan_goals: Callable[[RigConfig, Any], Any] | None = None
    """plan_goals(rig, problem) -> GoalPlan: a plan from where the agents are to goals an
    operator clicked (`rigctl.plans.goals`: a `GoalProblem` in, a `GoalPlan` out, a plan document
    or one line saying why not), with the kind's own planner, within the problem's time budget;
    the daemon's `plan_goals` runs it in a process of its own. None: the kind cannot plan to a
    clicked goal."""

    def builder(self, plan_kind: str) -> RunBuilder:
        from rigctl.core.errors import PlanError

        if plan_kind == "hold":
            return self._hold_run
        if plan_kind == "teleop":
            return self._teleop_run
        try:
            return self.plans[plan_kind]
        except KeyError:
            runs = ", ".join(sorted(self.plans))
            raise PlanError(f"plan: a {self.name} rig runs {runs} plans, not {plan_kind}") from None

    def _hold_run(self, plan, rig: RigConfig, **options):
        """The engine's run of a `HoldPlan` on this rig (refused here, with no I/O, if the
        request breaks a limit)."""
        from rigctl.run.engine import Run
        from rigctl.run.hold import HoldProgram

        request = self.hold(rig, plan.target)
        return Run(HoldProgram(plan, rig, request), rig, request.connect, **options)

    def _teleop_run(self, plan, rig: RigConfig, **options):
        """The engine's run of a teleoperation session (`rigctl.run.teleop.TeleopPlan`) on this
        rig: PlanError for a kind without teleoperation, the certificate of any input here."""
        from rigctl.core.errors import PlanError
        from rigctl.run.engine import Run
        from rigctl.run.teleop import NO_TELEOP, TeleopProgram

        if self.teleop is None:
            raise PlanError(f"teleop: {NO_TELEOP} ({self.name})")
        drive = self.teleop(rig, plan.mode)
        return Run(TeleopProgram(plan, rig, drive), rig, drive.connect, **options)


def camera_devices(rig: RigConfig) -> list[Device]:
    if rig.camera is None:
        return []
    return [Device("camera", str(rig.camera.url), "camera")]
