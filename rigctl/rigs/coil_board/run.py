"""Run a two-particle plan on the coil board, the loop closed through the camera (seed 004 Alg. 1).

Alg. 1 is a feedback law: from wherever the particles are, it gives the next two-move step towards
the goal. A coil-board run uses it that way. It starts with the plan's moves; after every move it
looks at the particles (camera -> tracker), and if they are not where the move's expected state
put them (further than half the tolerance), it re-runs Alg. 1 from the measured positions and goes
on with the new moves. It stops when both particles are within the plan's tolerance of their goals
(reached), or after `max_moves` moves (not reached), or on a fault.

A move is driven, not timed: the coils pull along the move's direction (the +x/-x and +y/-y coils
in the ratio of its components, the larger at full drive), and every stream cycle looks at the
tracked particles: a move meant to bring a particle to a wall ends when it is there (or held); any
other when the particles that should end it in free space are, on average, where it puts them (a
particle meant to be pinned stays on its wall by itself). The drive is ramped down over the last
`slow_zone_mm` and the stop is anticipated by the tracking latency, so a particle that moves fast
near a coil does not overshoot much. What the field's non-uniformity does to the other particle is
measured after the move and corrected by re-planning.

On the one run engine (`rigctl.run.engine`) this is a `CoilBoardProgram`: the whole of Alg. 1's
loop is one generator that yields the four coil commands of each stream cycle (zeros while the
particles settle, while a frame is awaited, while paused or while tracking is lost; re-planning
inline, with the coils at zero), and `next()` advances it by one cycle. The engine owns the record,
the board (`BoardActuators`), the states, pause / abort / e-stop and the safe end. Particles in a
viscous fluid stop when the pull stops, so "hold still" is simply zero drive: a pause lets the
current move finish and holds zeros; a pause now ends the move at once, and on resume the run goes
on from the measured positions (re-planning if the move was left short). Lost tracking suspends
the run (zeros) until the particles are seen again; it is a fault of the camera only if it stays
lost for `lost_limit_s` (if set), and otherwise it ends as every rig's run does, once suspended
for the rig file's `[stream] suspended_limit_s`.

Safety as everywhere: the plan is checked before the board is opened; the board's watchdog zeroes
the coils if this process stops talking; every exit path stops the coils; a fault of the board,
the camera or the tracking ends the run with the device named (exit status 3).
"""

from __future__ import annotations

import functools
import logging
import math
import sys
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, TextIO

import numpy as np

from rigctl.core.errors import ConfigError, DeviceTimeout, PlanError
from rigctl.physics.identify import LinearEstimate
from rigctl.plans.checks import check_plan, plan_workspace
from rigctl.plans.schema import GlobalMovesPlan, ShapeWorkspaceSpec
from rigctl.plans.wall_contact import (
    DiskRegion,
    PolygonRegion,
    centre_region,
    plan_two_particles,
)
from rigctl.rigs.coil_board.actuators import BoardActuators
from rigctl.run.agents import agent_results, place_agents, read_truth
from rigctl.run.engine import Outcome, RunContext, Step
from rigctl.run.engine import Run as EngineRun
from rigctl.run.interruptions import RequestedControl, Requests, Suspension
from rigctl.run.summary import RunSummary

if TYPE_CHECKING:
    from rigctl.core.record import RunRecord
    from rigctl.rigs.coil_board.settings import CoilBoardRig
    from rigctl.vision.tracking import TrackingLoop

log = logging.getLogger(__name__)

ZERO = (0, 0, 0, 0)  # every coil off: the particles stop (viscous fluid)

# The commands of a run: one per stream cycle; returns when the run is over.
Commands = Generator[tuple[int, ...], None, None]


@dataclass(frozen=True)
class CoilBoardRunSettings:
    """How a coil-board run drives and judges its moves.

    drive: |coil command| (1..127) of the stronger coil during a move; slow_zone_mm: the drive
    falls linearly over the last this-many mm of a move, down to min_drive_fraction; max_moves:
    bound on moves executed (then not reached); move_timeout_s: a move not done in this long is
    ended and the run re-plans; stall_s / stall_mm: no particle moved more than stall_mm in stall_s:
    the move is over (everything is held); settle_s: after the coils stop, the first frame taken
    this much later is the measurement; follow_fraction: measured within this fraction of the
    tolerance of the expected state, the current plan goes on (else re-plan); aim_fraction: Alg. 1
    aims at this fraction of the tolerance; done_fraction: the moves end once both particles are
    measured within this fraction of the tolerance, a margin for the camera's last look (another
    frame, which judges the run); a run that gets no closer than that is reached within the
    tolerance itself; rate_hz: command rate during a move (None: the rig file's `[board]
    rate_hz`, which the certificate holds to what the SyRen bus carries);
    skip_mm: moves shorter than this are not driven; chord_mm: a particle on a wall that a move
    carries at least this far to a wall is waited for (else it only grazes its wall);
    max_steer_deg: how far the pull may turn from the move's direction (steering to the target,
    and against the field's lean); lean_gain,
    lean_speed_mm_s, lean_lag_cycles: the lean estimate's filter gain, the speed below which it
    is not updated, and the age in commands of the command a frame's motion is compared with;
    free_margin_mm: a particle this far inside the planning region is off the walls (for learning
    the `RelativeDrift`); pin_margin_deg: a particle meant to stay on its wall is pushed into it at
    least this steeply (and one the move carries along is pulled off it as steeply);
    pin_slip_mm: if it moves this far anyway, the move ends (re-plan);
    push_mm: re-planned steps move the free particle at least this far into the pinning wall's
    normal direction (Alg. 1's `push`), so that the pinned one is pushed, not grazed;
    keep_apart_mm: re-planned relative moves keep this gap between the particles (the camera
    sees touching particles as one blob); learn_min_mm: only moves at least this long teach the
    `RelativeDrift`; syren_ready_timeout_s: the board's SyRens must report ready within this
    long; acquire_timeout_s: the camera must find both particles within this long; lost_limit_s:
    tracking lost (the run suspended, coils at zero) this long is a fault of the camera (None:
    no limit of its own; the rig file's `[stream] suspended_limit_s` ends the run).
    """

    drive: int = 127
    slow_zone_mm: float = 4.0
    min_drive_fraction: float = 0.06
    max_moves: int = 60
    move_timeout_s: float = 30.0
    stall_s: float = 0.5
    stall_mm: float = 0.02
    settle_s: float = 0.08
    follow_fraction: float = 0.5
    aim_fraction: float = 0.4
    done_fraction: float = 0.9
    rate_hz: float | None = None
    skip_mm: float = 0.02
    chord_mm: float = 1.0
    max_steer_deg: float = 25.0
    free_margin_mm: float = 0.1
    pin_margin_deg: float = 10.0
    push_mm: float = 1.0
    keep_apart_mm: float = 1.0
    learn_min_mm: float = 3.0
    pin_slip_mm: float = 0.15
    lean_gain: float = 0.3
    lean_speed_mm_s: float = 0.3
    lean_lag_cycles: int = 3
    syren_ready_timeout_s: float = 5.0
    acquire_timeout_s: float = 10.0
    lost_limit_s: float | None = None


def planning_region(plan: GlobalMovesPlan, radius_mm: float) -> PolygonRegion | DiskRegion:
    """The convex region Alg. 1 plans in: the plan's boundary (disk, rect, convex polygon), or for
    a boundary that is not convex (the intestine phantom's protrusions) the largest disk about the
    boundary's centroid that stays clear of it, as the paper planned its ring on a disk."""
    if not isinstance(plan.workspace, ShapeWorkspaceSpec):
        raise PlanError(f"{plan.source}: workspace: the wall-contact planner plans in a drawn "
                        "boundary (disk, rect, polygon), not in a picture's")
    boundary = plan.workspace.boundary.model_dump()
    try:
        return centre_region(boundary, radius_mm)
    except PlanError:
        if "polygon" not in boundary:
            raise
    vertices = np.asarray(boundary["polygon"], dtype=float)
    centre = vertices.mean(axis=0)
    room = float(plan_workspace(plan).clearance(centre))
    if room <= radius_mm:
        raise PlanError(f"{plan.source}: workspace: not convex, and no disk about its centroid "
                        "holds a particle; the wall-contact planner cannot plan in it")
    return DiskRegion(centre, room - radius_mm)


class RelativeDrift:
    """How a translation changes the particles' relative position on this rig, learned in the run.

    On the paper's rig each coil pulls harder nearer itself and leans towards its centre. Per mm a
    particle travels under the +x or -x coil, the x gap between the particles grows by the
    fraction k_along (the pull's log-gradient along the coil's axis, n / d for a 1/d^n pull) and
    the y gap shrinks by k_across (the lean, 1 / d); the y coils likewise with x and y swapped.
    The board drives at most one coil per axis, so a translation (dx, dy) is |dx| under an x coil
    and |dy| under a y coil, and the gaps change multiplicatively:

        delta_x' = delta_x exp(k_along |dx| - k_across |dy|),
        delta_y' = delta_y exp(k_along |dy| - k_across |dx|),

    with both rates scaled by D / (D - s), s the travel's mean offset towards the active coil
    (D = 1 / k_across: a coil's pull converges on its centre). Two coils driven together (a
    diagonal move) thus spread both gaps by k_along - k_across, not as one coil along the
    diagonal.

    The particles' own mobilities differ too (one a little smaller, rougher, a clump): particle i
    travels m_i times what the pull gives a particle of the plan's radius, so with the mean
    mobility as the unit (the run ends moves on the camera, so only the ratio tells) particle 1
    goes 1 + mobility_diff / 2 and particle 0 1 - mobility_diff / 2 of the pair's mean travel T,
    and the gap also grows by mobility_diff x T (signed: a translation back shrinks it again,
    unlike the non-uniformity). mobility_diff = (m_1 - m_0) / mean(m).

    k_along, k_across and mobility_diff are identified (`rigctl.physics.identify.LinearEstimate`: the
    Gaussian posterior of the log-mean gaps' linear model, with the uniform field of equal
    particles as its prior, the k's of weight `prior_weight`, mobility_diff of spread
    `mobility_prior_std`; re-linearised from every sample, since the scales depend on k_across)
    from every move in which both particles moved freely, with their uncertainty (`std`), and
    used to aim Alg. 1's relative position so that the last translation lands on the goals.
    """

    SERIES_UNITS: ClassVar[dict[str, str]] = {
        "k_along": "1/mm", "k_along_std": "1/mm", "k_across": "1/mm", "k_across_std": "1/mm",
        "mobility_diff": "1", "mobility_diff_std": "1", "moves_used": "count"}

    def __init__(self, prior_weight: float = 0.05, k_max: float = 0.05,
                 mobility_prior_std: float = 0.2, mobility_max: float = 0.5) -> None:
        self.k_max = k_max
        self.prior_weight = prior_weight
        self.mobility_prior_std = mobility_prior_std
        self.mobility_max = mobility_max
        self.samples: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.k = np.zeros(2)  # (k_along, k_across) in 1/mm
        self.mobility_diff = 0.0  # (m_1 - m_0) / mean(m)
        # standard deviations of k_along, k_across (1/mm) and mobility_diff; unknown before a move
        self.std = np.full(3, np.nan)

    @property
    def mobilities(self) -> np.ndarray:
        """(2,) each particle's mobility over the pair's mean."""
        return np.array([1.0 - self.mobility_diff / 2.0, 1.0 + self.mobility_diff / 2.0])

    def _scales(self, middle: np.ndarray, travel: np.ndarray) -> np.ndarray:
        """(2,) factors D / (D - s) of the x and y coils that make `travel` from `middle`."""
        offset = np.sign(travel) * middle  # towards the coil pulling on each axis
        return 1.0 / np.clip(1.0 - self.k[1] * offset, 0.5, None)

    def _rates(self, middle: np.ndarray, travel: np.ndarray) -> np.ndarray:
        """(2, 2) coefficients of (k_along, k_across) in the log-growth of (delta_x, delta_y)."""
        ax, ay = np.abs(travel) * self._scales(middle, travel)
        return np.array([[ax, -ay], [ay, -ax]])

    def observe(self, start_mean: np.ndarray, travel: np.ndarray, delta_before: np.ndarray,
                delta_after: np.ndarray) -> None:
        """One free move: the particles' mean left `start_mean` (mm, from the coils' centre) and
        went `travel` (2,) mm; their relative position went from delta_before to delta_after."""
        self.samples.append((start_mean + travel / 2, travel, delta_before, delta_after))
        for _ in range(2):  # the scales depend on k_across
            rows, values = [], []
            for middle, moved, before, after in self.samples:
                rates = self._rates(middle, moved)
                for axis in range(2):
                    b, a = before[axis], after[axis]
                    if b * a > 0 and abs(b - a) > 1e-9:
                        mean = (a - b) / math.log(a / b)  # log-mean: exact for exponential growth
                    else:
                        mean = 0.5 * (a + b)
                    rows.append([*(mean * rates[axis]), moved[axis]])
                    values.append(a - b)
            a_mat, b_vec = np.array(rows), np.array(values)
            scale = self.prior_weight * max(1.0, float(np.abs(a_mat[:, :2]).max()))
            # the prior k ~ N(0, 1 / scale^2) for gaps measured to 1 mm: ridge least squares
            estimate = LinearEstimate(["k_along", "k_across", "mobility_diff"], [0.0, 0.0, 0.0],
                                      [1.0 / scale, 1.0 / scale, self.mobility_prior_std])
            estimate.refit(a_mat, b_vec, 1.0)
            residual = b_vec - a_mat @ estimate.mean
            spread = math.sqrt(float(residual @ residual) / max(len(b_vec) - 3, 1))
            # Both k are positive for coils that pull (1/d^n, towards their centres); a noisy fit
            # outside [0, k_max] would aim Alg. 1 far off.
            self.k = np.clip(estimate.mean[:2], 0.0, self.k_max)
            self.std = estimate.std * max(spread, 1e-3)  # scaled to the gaps' own scatter
            # Alike particles fit a difference of noise; aimed through, it only moves the goals
            # (a run of alike particles ended 0.502 mm off against 0.5): taken once it stands
            # out of its own spread by two standard deviations
            diff = float(estimate.mean[2])
            self.mobility_diff = (float(np.clip(diff, -self.mobility_max, self.mobility_max))
                                  if abs(diff) > 2.0 * self.std[2] else 0.0)

    def series_row(self, t_s: float) -> list[float]:
        """A row of the record's `identification` series (`SERIES_UNITS`) at run time t_s."""
        return [t_s, self.k[0], self.std[0], self.k[1], self.std[1], self.mobility_diff,
                self.std[2], len(self.samples)]

    def growth(self, start_mean: np.ndarray, travel: np.ndarray, steps: int = 8) -> np.ndarray:
        """(2,) factors by which translating `travel` from `start_mean` multiplies the gaps."""
        log_growth = np.zeros(2)
        for j in range(steps):
            middle = start_mean + (j + 0.5) / steps * travel
            log_growth += self._rates(middle, travel / steps) @ self.k
        return np.exp(log_growth)

    def predict(self, delta: np.ndarray, start_mean: np.ndarray,
                goal_mean: np.ndarray) -> np.ndarray:
        """The delta (2,) after translating the pair's mean from start_mean to goal_mean (mm,
        from the coils' centre) with `delta` before."""
        travel = goal_mean - start_mean
        return delta * self.growth(start_mean, travel) + self.mobility_diff * travel

    def aim(self, goal_delta: np.ndarray, start_mean: np.ndarray,
            goal_mean: np.ndarray) -> np.ndarray:
        """The delta (2,) to have before translating the mean from start_mean to goal_mean (mm,
        from the coils' centre) so that it ends at goal_delta (`predict` inverted)."""
        travel = goal_mean - start_mean
        return (goal_delta - self.mobility_diff * travel) / self.growth(start_mean, travel)




@dataclass(frozen=True)
class MoveRoles:
    """What one move asks of each particle (each a (2,) bool): `watched`, the particles whose
    mean ends the move; `pinned`, those it leaves on their wall (the pull must push into the wall
    by `pin_margin_deg`); `grazing`, those on a wall it carries along (the pull must leave that
    wall by as much, or the wall holds them where the plan moves them, and the next re-plan asks
    for the same graze again)."""

    watched: np.ndarray
    pinned: np.ndarray
    grazing: np.ndarray


def move_roles(region: PolygonRegion | DiskRegion, s: CoilBoardRunSettings, u: np.ndarray, start: np.ndarray,
               end: np.ndarray, before: np.ndarray) -> MoveRoles:
    """The roles of the particles in a move along unit `u` (2,) that Alg. 1 planned from state
    `before` to `end` (2, 2), the particles measured at `start` (2, 2). What the move does to a
    particle is the difference of the two planned states, not of a planned and a measured one: the
    camera's few hundredths of a mm made a particle the plan leaves on its wall look like one it
    carries along (`skip_mm`), and the pull then took it off its wall (47 % of pinned particles
    slipped in bench/coilboard.py's 20 runs, 20 % since)."""
    step = end - before  # (2, 2) what Alg. 1 has each particle do in this move
    planned = step @ u  # (2,) planned advance along u
    on_wall = ~region.contains(start, slack=0.05)
    free_end = region.contains(end, slack=0.01)  # ends the move off every wall
    # A move that brings a particle to a wall (Alg. 1's move 1) is over when that particle is
    # there, also when it leaves one wall for another across a chord (stopping on the free
    # particle instead would leave it short, and the next steps would close in on the wall
    # only geometrically); otherwise when the particles meant to end in free space are where
    # they should be. A particle that only grazes its wall is not waited for (it is held).
    leaves = ~on_wall | (planned > s.chord_mm)
    contact = ~free_end & leaves & (planned > s.skip_mm)
    watched = contact if contact.any() else free_end & (planned > s.skip_mm)
    if not watched.any():
        watched = planned > s.skip_mm
    pinned = (np.hypot(*step.T) < s.skip_mm) & on_wall
    return MoveRoles(watched, pinned, ~pinned & on_wall & (planned > s.skip_mm))


class CoilBoardProgram(RequestedControl):
    """Alg. 1 closed through the camera, as the engine's program (see the module docstring).

    Construction refuses what cannot run (PlanError, ConfigError) without I/O. `start` places the
    particles (emulated bench), starts tracking and takes the first measurement; `next` gives each
    stream cycle's four coil commands; `finish` takes the camera's last look."""

    late = "slip"  # a late cycle only holds the pull a little longer; a move ends on the camera

    def __init__(self, plan: GlobalMovesPlan, rig: CoilBoardRig, *,
                 settings: CoilBoardRunSettings = CoilBoardRunSettings()) -> None:
        if plan.kind != "global-moves" or plan.rig != "coil-board":
            raise PlanError(f"{plan.source}: a coil-board run takes a coil-board global-moves plan")
        if len(plan.agents) != 2:
            raise PlanError(f"{plan.source}: agents: the coil board's planner places exactly two "
                            f"particles, the plan has {len(plan.agents)}")
        if rig.rig.kind != "coil-board" or rig.board is None:
            raise ConfigError("the rig is not a coil board (kind coil-board with a [board] table)")
        if rig.camera is None or rig.camera.calibration is None:
            raise ConfigError("a coil-board run closes the loop through the camera: the rig needs a "
                              "[camera] table with a calibration (`rigctl calibrate camera`)")
        if not 1 <= settings.drive <= rig.board.max_command:
            raise ConfigError(f"drive {settings.drive} must be 1..{rig.board.max_command} (the "
                              "board's max_command)")
        check_plan(plan)
        if settings.rate_hz is None:  # the rig file's rate, as every rig's run streams at
            settings = replace(settings, rate_hz=rig.board.rate_hz)
        assert settings.rate_hz is not None
        self.plan = plan
        self.rig = rig
        self.camera = rig.camera  # there is one (checked above)
        self.settings = settings
        self.rate_hz = settings.rate_hz
        self.planned_moves = np.array(plan.moves, dtype=float).reshape(-1, 2)
        self.n_moves = len(self.planned_moves)
        self.duration_s = 0.0  # unknown: a move lasts until the camera sees it done
        self.info = {"name": plan.name, "moves": self.n_moves, "duration_s": None}
        self.radii = np.array([a.radius for a in plan.agents], dtype=float)
        self.starts = np.array([a.start for a in plan.agents], dtype=float)
        self.goals = np.array([a.goal for a in plan.agents], dtype=float)
        self.tolerance = float(plan.tolerance_mm)
        self.region = planning_region(plan, float(self.radii.max()))
        self.workspace = plan_workspace(plan)
        # Rig coordinates have their origin at the coils' centre (docs/coilboard-rig.md).
        self.coils_centre = np.zeros(2)
        # Particles that touch make one blob on the camera: re-planned moves keep them apart.
        self.reach = float(self.radii.sum() + max(plan.min_separation_mm, settings.keep_apart_mm))
        self.suspension = Suspension(settings.lost_limit_s)
        self.replans = 0
        self.moves_done = 0
        self.drift = RelativeDrift()
        self.tracking: TrackingLoop | None = None  # from `start`
        self.record: RunRecord | None = None
        self.reached = False
        self._say: Callable[[str], None] = lambda text: None
        self._commands: Commands | None = None
        self._position: np.ndarray | None = None
        self._move = -1  # the move being driven (0-based, as the record's `move`), -1 between
        self._stage = "starting"
        self.requests = Requests()
        self._holding = False
        self._aborted = False

    @property
    def aborted(self) -> bool:
        return self._aborted

    @property
    def paused(self) -> bool:
        """Holding still at a pause (the coils at zero), or ending the move for a pause now."""
        return self._holding or (self.requests.pause_wanted and self.requests.immediate)

    @property
    def suspended(self) -> str | None:
        return self.suspension.reason

    def attach_wake(self, wake: Callable[[], None]) -> None:
        self.requests.wake = wake  # a hold of zeros: the next command may as well leave now

    # -- the run's phases -----------------------------------------------------------------------
    def checks(self) -> list:
        """The pre-flight of the run's bounds (`rigctl.rigs.coil_board.certify`)."""
        from rigctl.rigs.coil_board.certify import board_checks

        return board_checks(self.rig, self.settings, self.n_moves)

    def start(self, ctx: RunContext) -> None:
        """Place the particles (emulated bench), start tracking them and take the first
        measurement; nothing is energised yet."""
        from rigctl.vision.tracking import TrackingLoop

        self.record, self._say = ctx.record, ctx.say
        self._series = ctx.record.open_series(
            "identification", ["t_s", *RelativeDrift.SERIES_UNITS],
            {"t_s": "s", **RelativeDrift.SERIES_UNITS})
        self._series.row(self.drift.series_row(time.monotonic() - ctx.record.t0))  # the prior
        self.suspension.record, self.suspension.say = ctx.record, ctx.say
        place_agents(ctx, self.plan, [{"position": a.start, "radius": a.radius}
                                      for a in self.plan.agents])
        xmin, ymin, xmax, ymax = self.workspace.bounds
        self.tracking = tracking = TrackingLoop(self.camera, self.radii, self.starts,
                                                roi_mm=(xmin, ymin, xmax, ymax),
                                                on_floor=self.workspace.contains)
        tracking.record_to(ctx.record)  # the camera's positions, in the run record
        tracking.tap(ctx.on_frame)  # the console's camera view, if any
        tracking.start(self.settings.acquire_timeout_s)
        self._position = self._measure_now()
        ctx.record.event("found", positions=self._position.tolist(),
                         tolerance_mm=self.tolerance)
        self._commands = self._run_moves()

    def next(self, k: int, measured: np.ndarray | None) -> Step | None:
        if self.requests.abort_wanted:
            if self._aborted:
                return None
            self._aborted = True  # one cycle of zeros, then the end (the engine stops the coils)
            self._holding, self.suspension.reason, self._move = False, None, -1
            return Step(np.zeros(4), k, -1, stage="aborting")
        if self._commands is None:
            return None
        try:
            values = next(self._commands)
        except StopIteration:
            return None
        return Step(np.array(values, dtype=float), k, self._move, stage=self._stage)

    def finish(self, ctx: RunContext) -> Outcome:
        """The camera's last look (the coils are off) against the goals, with ground truth's
        error beside it on an emulated bench."""
        measured = self._final_measurement()
        if self.tracking is not None:
            self.tracking.stop()
        agents, source = agent_results(self.goals, measured, read_truth(ctx.backdoor))
        # Reached: the camera's last look, after the coils were stopped, has both within tolerance.
        reached = measured is not None and all(a.error_mm is not None and a.error_mm <= self.tolerance
                                               for a in agents)
        tracking = None
        if self.tracking is not None:
            tracking = {"frames": self.tracking.frames, "lost_frames": self.tracking.lost_frames,
                        "holds": self.suspension.count}
        ctx.record.event("closed_loop", reached=reached, moves=self.moves_done,
                         replans=self.replans, drift_k=self.drift.k.tolist(),
                         mobility_diff=self.drift.mobility_diff)
        return Outcome(
            agents=agents, reached=reached, positions_from=source, tolerance_mm=self.tolerance,
            metrics={"moves": self.moves_done, "drift_k": [round(float(v), 6) for v in self.drift.k],
                     "drift_k_std": [round(float(v), 6) if np.isfinite(v) else None
                                     for v in self.drift.std[:2]],
                     "mobility": [round(float(v), 4) for v in self.drift.mobilities],
                     "mobility_diff": round(self.drift.mobility_diff, 4),
                     "mobility_diff_std": round(float(self.drift.std[2]), 4)
                     if np.isfinite(self.drift.std[2]) else None},
            replans=self.replans, tracking=tracking,
            details=[f"moves: {self.moves_done} driven, {self.replans} re-plans from the camera"])

    def close(self) -> None:
        if self._commands is not None:
            self._commands.close()
        if self.tracking is not None:
            self.tracking.stop()

    # -- Alg. 1's loop, one command per stream cycle --------------------------------------------
    def _run_moves(self) -> Commands:
        """Moves until both particles are within the tolerance (`reached`), or Alg. 1 finds
        nothing better, or `max_moves` moves were driven."""
        s = self.settings
        moves = self.planned_moves
        expected = np.array(self.plan.expected, dtype=float).reshape(-1, 2, 2) \
            if self.plan.expected is not None else None
        index = 0
        position = self._position
        assert position is not None
        # Where the particles should be now: the end of the last move driven, or where they were
        # measured when the moves were (re-)planned. A skipped move leaves it (nothing moved), so
        # a measured position Alg. 1 had to pull into its region is not "off the plan" again and
        # again (a re-plan every cycle that never drove and never yielded to the stream).
        reference: np.ndarray | None = None
        # Alg. 1's state before the present move (what the move does to each: `move_roles`)
        planned_from = self._into_region(position)
        while True:
            if self.requests.pause_wanted:
                yield from self._hold()
                position = yield from self._measure(time.monotonic(), "a frame after the pause")
            error = float(np.max(np.hypot(*(position - self.goals).T)))
            if error <= s.done_fraction * self.tolerance:
                self._reached(error)
                return
            if self.moves_done >= s.max_moves:
                self._say(f"stopping after {self.moves_done} moves: worst error {error:.3f} mm")
                self._reached(error)
                return
            follow = (expected is not None and index < len(moves) and (reference is None or float(
                np.max(np.hypot(*(position - reference).T))) <= s.follow_fraction * self.tolerance))
            if not follow:
                # inline, on the stream thread: the coils are at zero and the particles still
                moves, expected = self._replan(position)
                index, reference = 0, position
                planned_from = self._into_region(position)  # where Alg. 1 started
                if not len(moves) or np.hypot(*moves.T).max() < s.skip_mm:
                    self._say(f"Alg. 1 finds no move the rig can make that improves on "
                              f"{error:.3f} mm")
                    self._reached(error)
                    return
            assert expected is not None  # followed only with one; a re-plan gives one
            move, end = moves[index], expected[index]
            before = expected[index - 1] if index > 0 else planned_from
            index += 1
            if math.hypot(*move) < s.skip_mm:
                continue
            self.moves_done += 1
            self._say(f"move {self.moves_done}: ({move[0]:+.2f}, {move[1]:+.2f}) mm"
                      + ("" if follow else " (re-planned)"))
            position = yield from self._drive(move, position, end, before)
            reference = end

    def _reached(self, error: float) -> None:
        """The moves are over with both particles `error` mm (worst) from their goals."""
        self.reached = error <= self.tolerance
        if self.reached:
            self._say(f"both particles within {self.tolerance:g} mm (worst {error:.3f} mm)")

    def _hold(self) -> Commands:
        """A pause: zeros until resumed (or aborted: `next` ends the run)."""
        self._holding, self._move, self._stage = True, -1, "paused"
        self._say("paused: every coil at zero")
        try:
            while self.requests.pause_wanted:
                yield ZERO
        finally:
            self._holding = False
        self._stage = "measuring"  # where the particles stand now: the run goes on from there
        self._say("resumed")

    def _replan(self, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Alg. 1 from the measured positions (2, 2): moves (m, 2) and the states it expects.

        The relative position is aimed so that the last move (the translation to the goals) ends
        on them under the learned `RelativeDrift` (two fixed-point rounds)."""
        self.replans += 1
        aim = self.settings.aim_fraction * self.tolerance
        inside = self._into_region(position)
        centre = self.goals.mean(axis=0)
        goal_delta = self.goals[1] - self.goals[0]
        goals = self.goals
        push, reach = self.settings.push_mm, self.reach
        result = plan_two_particles(self.region, inside, goals, aim, reach=reach, push=push)
        if not result.solved:
            # The margins (pushing, keeping apart) leave no way there: the paper's set may.
            plain = plan_two_particles(self.region, inside, goals, aim, reach=float(self.radii.sum()))
            if plain.error < result.error:
                push, reach, result = 0.0, float(self.radii.sum()), plain
        for _ in range(2):
            if not len(result.moves) or not (self.drift.k.any() or self.drift.mobility_diff):
                break
            before = result.states[-2] if len(result.states) > 1 else inside
            delta = self.drift.aim(goal_delta, before.mean(axis=0) - self.coils_centre,
                                   centre - self.coils_centre)
            aimed = np.stack([centre - delta / 2, centre + delta / 2])
            if not self.region.contains(aimed).all():
                break
            goals = aimed
            result = plan_two_particles(self.region, inside, goals, aim, reach=reach, push=push)
        # Alg. 1 ends with the translation to the aimed goals; the real goals' midpoint is the same.
        assert self.record is not None  # from `start`
        self.record.event("replan", measured=position.tolist(), moves=result.moves.tolist(),
                          aimed_goals=goals.tolist(), drift_k=self.drift.k.tolist(),
                          mobility_diff=self.drift.mobility_diff, push_mm=push,
                          seconds=result.seconds)
        return result.moves, result.states

    def _into_region(self, position: np.ndarray) -> np.ndarray:
        """Measured positions pulled into the planning region (the tracker's noise, a particle in
        a phantom's villus) so Alg. 1's point kinematics start from a valid state."""
        inside = position.copy()
        for i in range(len(inside)):
            if self.region.contains(inside[i])[0]:
                continue
            if isinstance(self.region, DiskRegion):
                w = inside[i] - self.region.centre
                inside[i] = self.region.centre + w * (self.region.radius / math.hypot(*w))
            else:
                centroid = self.region.vertices.mean(axis=0)
                u = inside[i] - centroid
                length = math.hypot(*u)
                inside[i] = centroid + self.region.exit_distance(centroid, u / length) * u / length
        return inside

    # -- one move -------------------------------------------------------------------------------
    def _drive(self, move: np.ndarray, start: np.ndarray, end: np.ndarray,
               before: np.ndarray) -> Generator[tuple[int, ...], None, np.ndarray]:
        """Pull along `move` until the particles that should end it in free space are, on average,
        where the move puts them; then stop the coils and measure. Returns positions (2, 2).
        `start`: measured now; `end` and `before`: Alg. 1's states after and before the move
        (which particles it moves, which it leaves on their wall).

        The pull is steered (within `max_steer_deg` of the move's direction) towards the watched
        particles' mean target, and turned against the measured difference between the direction
        the coils were asked to pull in and the direction the particles went (the field leans
        towards the active coils' centres). A pause now ends the move at once."""
        s = self.settings
        u = move / math.hypot(*move)
        roles = move_roles(self.region, s, u, start, end, before)
        watched, pinned, grazing = roles.watched, roles.pinned, roles.grazing
        target = np.mean(end[watched], axis=0)
        outward = -self.workspace.normal(start)  # (2, 2)
        pin_angles = [math.atan2(outward[i, 1], outward[i, 0]) for i in np.flatnonzero(pinned)]
        pin_limit = math.pi / 2 - math.radians(s.pin_margin_deg)
        graze_angles = [math.atan2(outward[i, 1], outward[i, 0]) for i in np.flatnonzero(grazing)]
        history: list[tuple[float, np.ndarray]] = []
        sent: list[float] = []  # angle of each command sent, radians
        lean = 0.0  # measured motion angle minus commanded angle
        began = time.monotonic()
        tracking = self.tracking
        assert tracking is not None
        number = self.moves_done
        self._move, self._stage = number - 1, f"move {number}"
        max_steer = math.radians(s.max_steer_deg)
        base = math.atan2(u[1], u[0])
        interrupted = False

        while True:
            if self.requests.pause_wanted and self.requests.immediate:
                interrupted = True  # pause now: the coils go to zero in this very cycle
                break
            now = time.monotonic()
            state = tracking.latest()
            if state is None or not tracking.ok(now):
                # Suspended (coils off) while the tracker looks for them.
                self.suspension.lost(now, f"tracking lost during a move "
                                     f"({tracking.why_lost(now, 'particle')}); the coils were "
                                     "stopped", tracking.failure)
                history.clear()
                yield ZERO
                continue
            began += self.suspension.regained(now)  # the hold is not the move's time
            if not history or history[-1][0] != state.t_source:
                history.append((state.t_source, state.positions_mm))
                # Keep one frame older than the stall window (all `_stalled` needs) and the last
                # three (the velocity): each cycle then costs the same however long the move runs.
                while len(history) > 3 and history[1][0] <= history[-1][0] - s.stall_s:
                    del history[0]
            velocity = np.zeros(2)
            if len(history) >= 3 and history[-1][0] > history[-3][0]:
                (t0, p0), (t1, p1) = history[-3], history[-1]
                velocity = np.mean((p1 - p0)[watched], axis=0) / (t1 - t0)
            # Where the watched particles will be when a command sent now takes effect.
            lead = (now - state.t_source) + 1.0 / self.rate_hz
            offset = target - np.mean(state.positions_mm[watched], axis=0) - velocity * lead
            if offset @ u <= 0 or now - began > s.move_timeout_s or self._stalled(
                    history, now, began, watched):
                break
            speed = math.hypot(*velocity)
            if speed > s.lean_speed_mm_s and len(sent) > s.lean_lag_cycles:
                seen = math.atan2(velocity[1], velocity[0]) - sent[-1 - s.lean_lag_cycles]
                seen = (seen + math.pi) % (2 * math.pi) - math.pi
                lean += s.lean_gain * (max(-max_steer, min(max_steer, seen)) - lean)
            wanted = math.atan2(offset[1], offset[0]) - base
            wanted = (wanted + math.pi) % (2 * math.pi) - math.pi
            angle = base + max(-max_steer, min(max_steer, wanted)) - lean
            for wall in graze_angles:
                off = (angle - wall + math.pi) % (2 * math.pi) - math.pi
                if abs(off) < math.pi - pin_limit:
                    angle = wall + math.copysign(math.pi - pin_limit, off)
            for wall in pin_angles:
                off = (angle - wall + math.pi) % (2 * math.pi) - math.pi
                angle = wall + max(-pin_limit, min(pin_limit, off))
            if pinned.any() and float(np.max(np.hypot(*(state.positions_mm - start)[pinned].T))) \
                    > s.pin_slip_mm:
                break  # a pinned particle slipped: stop and re-plan from here
            sent.append(angle)
            direction = np.array([math.cos(angle), math.sin(angle)])
            direction /= max(abs(direction[0]), abs(direction[1]))
            pulls = (max(direction[0], 0), max(-direction[0], 0), max(direction[1], 0),
                     max(-direction[1], 0))
            fraction = min(1.0, max(s.min_drive_fraction, (offset @ u) / s.slow_zone_mm))
            yield tuple(int(round(s.drive * fraction * p)) for p in pulls)

        # The coils go to zero from this cycle on; the first frame taken `settle_s` later is the
        # measurement.
        measured = yield from self._measure(time.monotonic() + s.settle_s,
                                            "no frame with both particles after the move")
        # A move both particles made freely (neither held, neither stopped by a wall) shows how
        # a translation changes their relative position here.
        advances = (measured - start) @ u
        advance = float(np.mean(advances))
        if self.region.contains(measured, slack=s.free_margin_mm).all() and \
                advance > s.learn_min_mm and advances.min() > 0.5 * advance:
            self.drift.observe(start.mean(axis=0) - self.coils_centre,
                               measured.mean(axis=0) - start.mean(axis=0),
                               start[1] - start[0], measured[1] - measured[0])
            assert self.record is not None  # from `start`
            self._series.row(self.drift.series_row(time.monotonic() - self.record.t0))
        assert self.record is not None  # from `start`
        self.record.event("move", number=number, move=move.tolist(), expected=end.tolist(),
                          measured=measured.tolist(), lean_deg=math.degrees(lean),
                          seconds=time.monotonic() - began, interrupted=interrupted)
        self._move = -1
        return measured

    def _stalled(self, history: list, now: float, began: float, watched: np.ndarray) -> bool:
        """The watched particles moved less than `stall_mm` in the last `stall_s` (held)."""
        s = self.settings
        if now - began < s.stall_s or len(history) < 2:
            return False
        recent = [p for t, p in history if t >= history[-1][0] - s.stall_s]
        if history[0][0] > history[-1][0] - s.stall_s:
            return False
        return float(np.max(np.hypot(*(recent[-1] - recent[0])[watched].T))) < s.stall_mm

    # -- measuring --------------------------------------------------------------------------------
    def _measure(self, after: float, what: str) -> Generator[tuple[int, ...], None, np.ndarray]:
        """Zeros until a frame taken after monotonic `after` shows both particles; returns their
        positions (2, 2) mm. No such frame within the camera's timeout (or the tracker lost
        them): suspended until there is one."""
        assert self.tracking is not None
        tracking = self.tracking
        while True:
            now = time.monotonic()
            state = tracking.latest()
            if state is not None and state.t_source > after and not state.lost.any():
                self.suspension.regained(now)
                return state.positions_mm.copy()
            if not tracking.ok(now) or now > after + tracking.timeout_s:
                self.suspension.lost(now, f"tracking lost: {what}", tracking.failure)
            yield ZERO

    def _measure_now(self) -> np.ndarray:
        """Positions (2, 2) mm from the first frame taken from now on (blocking: nothing is
        being streamed); DeviceTimeout naming the camera if none comes in its timeout."""
        assert self.tracking is not None
        state = self.tracking.captured_after(time.monotonic(), self.camera.timeout_s)
        if state is None:
            raise DeviceTimeout("no frame with both particles", device="camera")
        return state.positions_mm.copy()

    def _final_measurement(self) -> np.ndarray | None:
        """The first frame from now on, else the last one seen (None: none ever was)."""
        if self.tracking is None or self.tracking.latest() is None:
            return None
        state = self.tracking.captured_after(time.monotonic(), self.camera.timeout_s)
        state = state or self.tracking.latest()
        return state.positions_mm.copy() if state is not None else None


def CoilBoardRun(plan: GlobalMovesPlan, rig: CoilBoardRig, *,
                 settings: CoilBoardRunSettings = CoilBoardRunSettings(), **run_options) -> EngineRun:
    """The run of a two-particle plan on a coil board (the one engine with `CoilBoardProgram`);
    `run_options` are the engine's (`runs_dir`, `progress_out`, `on_cycle`, `on_state`). Refusals
    (PlanError, ConfigError) raise here, before anything is opened."""
    program = CoilBoardProgram(plan, rig, settings=settings)
    connect = functools.partial(BoardActuators.connect,
                                syren_ready_timeout_s=settings.syren_ready_timeout_s)
    return EngineRun(program, rig, connect, **run_options)


def execute_coilboard(plan: GlobalMovesPlan, rig: CoilBoardRig, *, runs_dir: str | Path = "runs",
                      progress_out: TextIO | None = sys.stderr,
                      settings: CoilBoardRunSettings = CoilBoardRunSettings()) -> RunSummary:
    """Run `plan` on the coil board `rig` and return the summary; refusals raise before anything
    is opened, device faults are reported in the summary."""
    return CoilBoardRun(plan, rig, runs_dir=runs_dir, progress_out=progress_out,
                        settings=settings).execute()
