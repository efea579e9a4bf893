"""A global-moves plan on the six-coil rig (seed 000), as a program of the one run engine.

Order matters for safety. `prepare` does everything that can refuse a plan, with no I/O: the
plan's checks, its field program (`realize`: whole turns) and the coils' currents (`allocate`)
within their current and voltage limits; the engine's pre-flight certificate adds the coils'
heating (`checks`). `GlobalMovesProgram` then gives the stream each cycle's currents through its
`Sequencer` (the engine's pause, resume and abort requests taken at a move's end or at once, by
ramps) and, closed loop, through the camera `Supervisor` that judges every move and re-plans.
`Run` is the engine's run of it on the Kepco supplies (`CoilSupplies`): the engine opens,
energises and ramps them down, stops on a device fault naming it, records and summarises;
`execute_plan` runs one and returns its summary.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np

from rigctl.core.errors import PlanError
from rigctl.emulators.backdoor import BackdoorClient
from rigctl.plans.checks import check_plan, contact_for_rig, simulate
from rigctl.plans.schema import GlobalMovesPlan, Plan
from rigctl.rigs.six_coil.allocate import CurrentProgram, allocate
from rigctl.rigs.six_coil.realize import FieldProgram, realize_global_moves
from rigctl.rigs.six_coil.sequencer import Sequencer
from rigctl.rigs.six_coil.supervisor import Supervisor, SupervisorSettings
from rigctl.rigs.six_coil.supplies import CoilSupplies
from rigctl.run.agents import agent_results, place_agents, read_truth, truth_of
from rigctl.run.engine import Outcome, RunContext, Step
from rigctl.run.engine import Run as EngineRun
from rigctl.run.interruptions import RequestedControl
from rigctl.run.summary import RunSummary

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

log = logging.getLogger(__name__)


def prepare(plan: Plan, rig: SixCoilRig) -> tuple[GlobalMovesPlan, FieldProgram, CurrentProgram]:
    """Everything that can refuse a plan, with no I/O: returns the plan (expected filled), its
    field program and the allocated currents. Raises PlanError or LimitError naming what is wrong."""
    if not isinstance(plan, GlobalMovesPlan):
        raise PlanError(f"{plan.source}: a six-coil global-moves run takes a global-moves plan")
    if plan.rig != rig.rig.kind:
        raise PlanError(
            f"the plan is for a {plan.rig} rig but the rig file describes a {rig.rig.kind} rig"
        )
    if rig.rig.kind != "six-coil":
        raise PlanError(f"executing on a {rig.rig.kind} rig is not implemented yet")
    if plan.expected is None:
        plan = simulate(plan)
    check_plan(plan)
    program = realize_global_moves(np.asarray(plan.moves, dtype=float).reshape(-1, 2), rig)
    return plan, program, allocate(program, rig)


class GlobalMovesProgram(RequestedControl):
    """A global-moves plan's current program (`prepare`), sequenced with pause, resume and abort,
    and with `closed_loop` the camera supervisor that judges every move and re-plans. Construction
    refuses a bad plan (PlanError, LimitError) without I/O. Pause holds the field (the magnets lie
    still, aligned); pause now ramps it to zero and back up on resume; a late cycle slips."""

    late = "slip"

    def __init__(self, plan: Plan, rig: SixCoilRig, *, closed_loop: bool = False,
                 supervisor_settings: SupervisorSettings | None = None) -> None:
        self.plan, self.field_program, self.currents = prepare(plan, rig)
        self.rig = rig
        self.rate_hz = rig.stream.rate_hz
        self.n_moves = len(self.plan.moves)
        self.duration_s = float(self.field_program.duration_s)
        self.info = {"name": self.plan.name, "moves": self.n_moves,
                     "samples": len(self.currents.t_s),
                     "duration_s": round(self.duration_s, 3)}
        ramp = max(1, round(rig.stream.ramp_down_s * rig.stream.rate_hz))
        ends = [self.field_program.move_end_index(i) for i in range(self.field_program.n_moves)]
        self.sequencer = Sequencer(self.currents, ends, ramp)
        self._backdoor: BackdoorClient | None = None
        self.supervisor: Supervisor | None = None
        if closed_loop:
            self.supervisor = Supervisor(
                self.plan, rig, self.field_program, self.currents, ramp_samples=ramp,
                settings=supervisor_settings or SupervisorSettings(),
                truth=(lambda: truth_of(self._backdoor)) if rig.emulation else None)
            self.sequencer = self.supervisor.sequencer
        self.requests = self.sequencer.requests  # the stream thread's sequencer acts on them

    # -- control, from any thread (`RequestedControl`: pause, resume, abort) -------------------
    def pause_to_cool(self) -> None:
        """At the end of the move, the field ramped off (the magnets lie still); back on resume."""
        self.requests.pause(field_off=True)

    @property
    def aborted(self) -> bool:
        return self.sequencer.aborted

    @property
    def paused(self) -> bool:
        return self.sequencer.paused

    @property
    def suspended(self) -> str | None:
        return self.supervisor.suspension.reason if self.supervisor is not None else None

    def attach_wake(self, wake: Callable[[], None]) -> None:
        self.sequencer.wake = wake

    # -- the run's phases -----------------------------------------------------------------------
    def start(self, ctx: RunContext) -> None:
        plan = self.plan
        self._backdoor = ctx.backdoor
        place_agents(ctx, plan, [{"position": list(a.start), "radius": a.radius} for a in plan.agents],
                     contact=contact_for_rig(plan.rig), min_separation_mm=plan.min_separation_mm)
        if self.supervisor is not None:
            self.supervisor.tracking.tap(ctx.on_frame)  # the console's camera view, if any
            self.supervisor.start(ctx.record)  # the robots are found before anything is energised

    def checks(self) -> list:
        """The pre-flight of the whole current program (`rigctl.rigs.six_coil.certify`)."""
        from rigctl.rigs.six_coil.certify import current_program_checks

        program = self.field_program
        return current_program_checks(
            self.rig, self.currents.currents_A, self.rate_hz,
            # where `field.rest_s` rests: between moves, not after the last
            move_ends=[program.move_end_index(i) for i in range(program.n_moves - 1)],
            describe=program.describe_sample)

    def next(self, k: int, measured: np.ndarray | None) -> Step | None:
        step = self.sequencer.next()
        if step is None:
            return None
        setpoints, sample, move = step
        t_s = self.currents.t_s
        return Step(setpoints, sample, move, t_s=float(t_s[min(sample, len(t_s) - 1)]))

    def finish(self, ctx: RunContext) -> Outcome:
        plan, supervisor = self.plan, self.supervisor
        closed, camera = {}, None
        if supervisor is not None:
            supervisor.stop()
            closed, camera = supervisor.summary(), supervisor.final_positions
        agents, positions_from = agent_results(np.array([a.goal for a in plan.agents], dtype=float), camera,
                                               read_truth(ctx.backdoor))
        tolerance = plan.tolerance_mm
        reached = all(a.error_mm is not None and a.error_mm <= tolerance for a in agents)
        return Outcome(agents=agents, reached=reached, positions_from=positions_from,
                       tolerance_mm=tolerance, replans=closed.get("replans", 0),
                       tracking=closed.get("tracking"),
                       metrics={"identified": closed["identified"]} if closed else {},
                       gave_up=self.supervisor.fault if self.supervisor is not None else None)

    def close(self) -> None:
        if self.supervisor is not None:
            self.supervisor.stop()


def Run(plan: Plan, rig: SixCoilRig, *, closed_loop: bool = False,
        supervisor_settings: SupervisorSettings | None = None, **run_options) -> EngineRun:
    """The run of a global-moves plan on a six-coil rig (the one engine with this program);
    `run_options` are the engine's (`runs_dir`, `progress_out`, `on_cycle`, `on_state`)."""
    program = GlobalMovesProgram(plan, rig, closed_loop=closed_loop,
                                 supervisor_settings=supervisor_settings)
    return EngineRun(program, rig, CoilSupplies.connect, **run_options)


def execute_plan(
    plan: Plan,
    rig: SixCoilRig,
    *,
    runs_dir: str | Path = "runs",
    progress_out: TextIO | None = sys.stderr,
    closed_loop: bool | None = None,
    supervisor_settings: SupervisorSettings | None = None,
) -> RunSummary:
    """Run `plan` on `rig` and return the summary. Refusals (PlanError, LimitError) raise before
    anything is opened; device faults during the run are caught, reported and recorded.
    `closed_loop` (default: whenever the rig has a camera) runs the camera supervisor."""
    if closed_loop is None:
        closed_loop = rig.camera is not None
    return Run(plan, rig, runs_dir=runs_dir, progress_out=progress_out, closed_loop=closed_loop,
               supervisor_settings=supervisor_settings).execute()
