"""The plan format, version 1: what a plan file says, how it is checked, and how it is written back.

A plan is a JSON document ``{"schema": "rigctl.plan/1", "kind": ..., ...}``. `kind` selects the
document type (a discriminated union, so new kinds such as ``pair-formation`` or ``field-sequence``
slot in beside ``global-moves``). Lengths are in mm.

Shapes are one-key objects: ``{"rect": [x, y, w, h]}`` (lower-left corner, w, h > 0),
``{"polygon": [[x, y], ...]}`` (>= 3 vertices, simple, either orientation), ``{"disk": [cx, cy, r]}``.
A workspace is ``{"boundary": shape, "obstacles": [shape, ...]}`` or a picture
``{"image": "maze.png", "mm_per_px": 0.5, "origin": [x, y]}`` (path relative to the plan file, dark
pixels are obstacles, origin = workspace position of the image's lower-left corner).

Two levels of checking: `parse_plan` / `load_plan` validate the document (types, ranges, shapes)
and `check_plan` checks what only geometry can tell (agents in free space, apart, and `expected`
reproduced by the global-input model). Every error is a `PlanError` naming the file and the field
by its JSON path, e.g. ``plan.json: agents.1.radius: Input should be greater than or equal to
0.001``.
"""

from __future__ import annotations

import json
import logging
import math
import sys
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    PrivateAttr,
    Tag,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from rigctl.core.errors import PlanError

log = logging.getLogger(__name__)

SCHEMA_ID = "rigctl.plan/1"


def _kinds_running(plan_kind: str) -> list[str]:
    """The installed rig kinds whose `plans` include `plan_kind`, sorted (the registry's)."""
    from rigctl.core.registry import kinds

    return sorted(n for n, k in kinds().items() if plan_kind in k.plans)


def _runs(plan_kind: str):
    """A plan's `rig`: an installed rig kind that runs `plan_kind` plans (the registry says)."""

    def check(rig: str) -> str:
        able = _kinds_running(plan_kind)
        if rig not in able:
            raise PydanticCustomError("rig_kind", "a {plan_kind} plan runs on {able}, not {rig}",
                                      {"plan_kind": plan_kind, "able": " or ".join(able), "rig": repr(rig)})
        return rig

    return Annotated[str, AfterValidator(check),
                     Field(description=f"an installed rig kind that runs {plan_kind} plans")]


RigName = _runs("global-moves")  # rigs that run global-moves plans


def rig_running(plan_kind: str) -> str:
    """The installed rig kind that runs `plan_kind` plans (a planner writes its plans for it);
    PlanError when none or several do (then the planner must be told which)."""
    able = _kinds_running(plan_kind)
    if len(able) != 1:
        raise PlanError(f"no single installed rig kind runs {plan_kind} plans: "
                        f"{', '.join(able) or 'none'}")
    return able[0]
Contact = Literal["slide", "non-slip"]

# Bounds: what a plan may hold, checked before anything is allocated from it, so that no number
# in a document can make `validate` or the daemon's `load` take unbounded time or memory. Each is
# far beyond what a lab's plan holds, and each is stated in the published schema.
MAX_EXTENT_MM = 10_000.0
"""|x|, |y| of every position, size and move (mm): a 10 m workspace."""
MAX_MOVES = 5_000
"""Moves (global-moves) and segments (pair-formation) in a plan (one loads in about 6 s)."""
MAX_AGENTS = 64
MAX_PLAN_BYTES = 64 * 1024 * 1024
"""A plan file larger than this is not read (the daemon takes requests of at most 4 MiB)."""
MAX_SHAPES = 256
"""Obstacles in a workspace."""
MAX_VERTICES = 1024
"""Vertices of a polygon (checked for self-crossings in O(n^2): 0.17 s and 70 MB at the bound;
seed 004's intestine ring has 300)."""
MAX_IMAGE_PIXELS = 2048 * 2048
"""Pixels of a workspace image (width x height, read from the PNG header before decoding)."""
MAX_DURATION_S = 3600.0
"""Any time in a plan (holds, segments, knot times): one hour."""
MAX_SAMPLES = 100_000
"""Rows of a sampled series in a plan (knots, expected samples), and components of a sequence."""
# Lists that may be long (samples, moves, vertices) are `fail_fast`: validation stops at the first
# bad item of the list, so one list of 20,000 bad rows is one problem, not 119,226 of them whose
# listing took a fuzzed `load` past a second.
MAX_CHECK_SAMPLES = 50_000
"""Times at which a field-sequence plan's safety check samples both arms ((last knot - first) /
limits.check_step_s): about 4 kB each, so at most about 200 MB; 500 s at the default 10 ms."""
MAX_PROGRAM_SAMPLES = 1_000_000
"""Samples of the program a plan is realized into (17 min at 1 kHz, 2.8 h at 100 Hz; about 100 MB),
checked before the program is allocated; the program itself lasts at most MAX_DURATION_S."""


# Numbers: what every number in a plan may be, here and nowhere else (docs/plans.md lists them).
# Every number is finite (no NaN, no infinity: `allow_inf_nan=False`), normal (0, or at least
# MIN_NORMAL in size) and at most MAX_MAGNITUDE in size, and each field is held to the physical
# range of what it is: a length to a micrometre and ten metres, an angle to a hundred turns. A
# subnormal such as 1e-320 is no quantity anyone measures, and dividing by one overflows: an
# agent radius of 1e-320 passed `validate` and overflowed the model's wall step at the daemon's
# `load` (`internal`). Each range is stated in the published schema (`rigctl schema plan`); that
# a number is normal is checked here (`_normal`). The rig's own limits (currents, joints, field)
# are the pre-flight certificate's, narrower still.
MIN_NORMAL = sys.float_info.min
"""The smallest normal double, 2.2e-308: a non-zero number smaller than this is refused."""
MAX_MAGNITUDE = 1e9
"""No number in a plan is larger than this in size, whatever its field."""
MIN_LENGTH_MM = 1e-3
"""A length that must be positive (a radius, a size, a tolerance, a body's diameter) is at least
1 um: the pixel of the finest workspace image (`mm_per_px`)."""
MAX_ANGLE_DEG = 36_000.0
"""An angle in degrees (a heading, a field angle, a base's roll-pitch-yaw): a hundred turns
either way, for a heading unwrapped along a plan."""
MAX_JOINT_RAD = 2 * math.pi
"""A joint angle: a turn either way (an LBR iiwa's joints turn at most 175 deg; the safety check
holds each joint to its own range)."""
MAX_U = 1e6
"""Each component of a field/gradient 8-vector U: 1e6 mT (1 kT) or mT/m, far beyond any magnet; the
certificate holds it to the rig's."""
MIN_STEP_S = 1e-6
"""A time that must be positive (a segment's dt_s): 1 us, a thousandth of a 1 kHz stream period."""


def _normal(value: float) -> float:
    if value != 0.0 and abs(value) < MIN_NORMAL:
        raise PydanticCustomError(
            "subnormal", "{value} is subnormal: a number here is 0 or at least {least} in size",
            {"value": repr(value), "least": f"{MIN_NORMAL:.3g}"})
    return value


def _number(low: float, high: float, description: str | None = None) -> Any:
    """The type of a number field in [low, high], finite and normal."""
    assert -MAX_MAGNITUDE <= low < high <= MAX_MAGNITUDE
    return Annotated[float, Field(ge=low, le=high, description=description),
                     AfterValidator(_normal)]


Coordinate = _number(-MAX_EXTENT_MM, MAX_EXTENT_MM)
"""A position or a displacement (mm)."""
Point = tuple[Coordinate, Coordinate]
Length = _number(MIN_LENGTH_MM, MAX_EXTENT_MM)
"""A length that must be positive (mm): 1 um to 10 m."""
Gap = _number(0.0, MAX_EXTENT_MM)
"""A length that may be zero (mm)."""
Duration = _number(0.0, MAX_DURATION_S)
"""A time on a plan's clock or a hold (s): 0 to one hour."""
Step = _number(MIN_STEP_S, MAX_DURATION_S)
"""A time that must be positive (s): 1 us to one hour."""
AngleDeg = _number(-MAX_ANGLE_DEG, MAX_ANGLE_DEG)
JointRad = _number(-MAX_JOINT_RAD, MAX_JOINT_RAD)
UComponent = _number(-MAX_U, MAX_U)
BodyLengths = _number(1e-3, MAX_EXTENT_MM)
"""A distance in body lengths (pair formation): a thousandth of a body to 10,000 bodies."""
Fraction = _number(1e-3, 1.0)
"""A share of a maximum: 0.1 % to all of it."""
Pull = _number(-1e4, 1e4)
"""A pull as the centroid speed it gives (BL/s): ten thousand body lengths a second either way."""

# `replay` agreement demanded by check_plan (mm).
REPLAY_TOLERANCE_MM = 1e-6


class _Document(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# Shapes


class RectShape(_Document):
    rect: tuple[Coordinate, Coordinate, Length, Length] = Field(
        description="[x, y, w, h]: lower-left corner, width and height (mm)"
    )


class PolygonShape(_Document):
    polygon: list[Point] = Field(fail_fast=True,
        min_length=3, max_length=MAX_VERTICES,
        description=f"vertices [[x, y], ...] (mm), simple, either orientation, at most {MAX_VERTICES}"
    )

    @field_validator("polygon")
    @classmethod
    def _simple(cls, vertices: list[Point]) -> list[Point]:
        problem = _polygon_problem(np.asarray(vertices, dtype=float))
        if problem:
            raise ValueError(problem)
        return vertices


class DiskShape(_Document):
    disk: tuple[Coordinate, Coordinate, Length] = Field(description="[cx, cy, r] (mm)")


_SHAPE_KEYS = ("rect", "polygon", "disk")


def _shape_tag(value: Any) -> str | None:
    if isinstance(value, dict):
        found = [k for k in _SHAPE_KEYS if k in value]
    else:
        found = [k for k in _SHAPE_KEYS if getattr(value, k, None) is not None]
    return f"shape:{found[0]}" if len(found) == 1 else None


Shape = Annotated[
    Union[
        Annotated[RectShape, Tag("shape:rect")],
        Annotated[PolygonShape, Tag("shape:polygon")],
        Annotated[DiskShape, Tag("shape:disk")],
    ],
    Discriminator(
        _shape_tag,
        custom_error_type="shape_kind",
        custom_error_message="expected one of rect, polygon, disk",
    ),
]


# Workspaces


class ShapeWorkspaceSpec(_Document):
    boundary: Shape
    obstacles: list[Shape] = Field(default=[], max_length=MAX_SHAPES,
                                   description=f"at most {MAX_SHAPES}")


class ImageWorkspaceSpec(_Document):
    image: str = Field(max_length=4096, description="PNG path, relative to the plan file; dark "
                       f"(< 128) = obstacle; at most {MAX_IMAGE_PIXELS} pixels")
    mm_per_px: _number(MIN_LENGTH_MM, 100.0, "1 um to 100 mm")
    origin: Point = Field(
        default=(0.0, 0.0), description="workspace position (mm) of the image's lower-left corner"
    )


def _workspace_tag(value: Any) -> str | None:
    if isinstance(value, dict):
        if "image" in value:
            return "workspace:image"
        if "boundary" in value:
            return "workspace:shapes"
        return None
    return "workspace:image" if hasattr(value, "image") else "workspace:shapes"


WorkspaceSpec = Annotated[
    Union[
        Annotated[ShapeWorkspaceSpec, Tag("workspace:shapes")],
        Annotated[ImageWorkspaceSpec, Tag("workspace:image")],
    ],
    Discriminator(
        _workspace_tag,
        custom_error_type="workspace_kind",
        custom_error_message="expected {boundary, obstacles} or {image, mm_per_px, origin}",
    ),
]


# Plans


class Agent(_Document):
    start: Point
    goal: Point
    radius: Length


class _PlanDocument(_Document):
    """What every plan kind shares: the format id, a name, and where the document came from."""

    schema_: Literal["rigctl.plan/1"] = Field(alias="schema")
    name: str | None = None

    model_config = ConfigDict(populate_by_name=True)

    # Where the plan came from: names it in messages and resolves a relative image path.
    _source: str = PrivateAttr(default="plan")
    _base_dir: Path | None = PrivateAttr(default=None)

    @property
    def source(self) -> str:
        return self._source

    @property
    def base_dir(self) -> Path | None:
        return self._base_dir

    @property
    def size(self) -> str:
        """How big the plan is, as `validate` and `load` say it."""
        raise NotImplementedError


class GlobalMovesPlan(_PlanDocument):
    """Every agent receives the same displacements `moves` in turn (seed 000, seed 004)."""

    kind: Literal["global-moves"]
    rig: RigName
    name: str | None = None
    workspace: WorkspaceSpec
    agents: list[Agent] = Field(min_length=1, max_length=MAX_AGENTS,
                                description=f"at most {MAX_AGENTS}")
    moves: list[Point] = Field(fail_fast=True, max_length=MAX_MOVES,
                               description="shared displacements [dx, dy] (mm), applied in order; "
                               f"at most {MAX_MOVES}")
    expected: Annotated[list[Annotated[list[Point], Field(max_length=MAX_AGENTS)]],
                        Field(fail_fast=True)] | None = Field(
        default=None, max_length=MAX_MOVES,
        description="expected[i][j]: agent j's position after move i (mm)"
    )
    tolerance_mm: Length = Field(
        default=1.0, description="how far a measured agent may be from expected before correcting"
    )
    min_separation_mm: Gap = Field(
        default=0.0, description="agents keep centre distance >= r_i + r_j + this (planner option)"
    )

    @property
    def size(self) -> str:
        return f"{len(self.agents)} agents, {len(self.moves)} moves"


# Kind: field-sequence (seed 003, rig depm). Its fields and their checks belong to the DEPM planner
# (rigctl.plans.depm); `check_plan` calls that module's `check(plan)`.


Vector8 = tuple[UComponent, UComponent, UComponent, UComponent, UComponent, UComponent, UComponent,
                UComponent]
Joints7 = tuple[JointRad, JointRad, JointRad, JointRad, JointRad, JointRad, JointRad]


class SequenceComponent(_Document):
    """One requested actuation: U in mT (Bx, By, Bz) and mT/m (dBx/dx, dBx/dy, dBx/dz, dBy/dy,
    dBy/dz), held for `hold_s` once the arms arrive."""

    name: str
    U: Vector8 = Field(description="[Bx, By, Bz] mT, [dBx/dx, dBx/dy, dBx/dz, dBy/dy, dBy/dz] mT/m")
    hold_s: Duration = Field(default=5.0, description="hold after the arms arrive (s), at most 1 h")


class ArmPlan(_Document):
    """One arm: where its base stands and its joint knots (one row of 7 angles per `t_s`)."""

    name: str
    position_mm: tuple[Coordinate, Coordinate, Coordinate] = Field(
        description="base position, world frame (mm)")
    rpy_deg: tuple[AngleDeg, AngleDeg, AngleDeg] = Field(
        default=(0.0, 0.0, 0.0), description="base orientation, fixed-axis roll, pitch, yaw (deg)"
    )
    joints_rad: list[Joints7] = Field(fail_fast=True, max_length=MAX_SAMPLES,
                                      description="joint knots (rad), one row per entry of t_s")


class Segment(_Document):
    """When a requested component is approached and held (times on the plan's clock, s)."""

    name: str
    U: Vector8 = Field(description="requested U (mT, mT/m)")
    start_s: Duration = Field(description="the transition toward this component starts")
    reached_s: Duration = Field(description="the arms arrive: the hold starts")
    end_s: Duration = Field(description="the hold ends (the next transition starts)")
    residual: Vector8 = Field(
        description="U the planned end poses make minus U requested (mT, mT/m), dipole model"
    )


class ExpectedField(_Document):
    """U at the workspace centre the planned poses make (dipole model), sampled at `rate_hz`."""

    rate_hz: _number(1e-3, 10_000.0)
    t_s: list[Duration] = Field(fail_fast=True, max_length=MAX_SAMPLES)
    U: list[Vector8] = Field(fail_fast=True, max_length=MAX_SAMPLES,
                             description="one row per t_s (mT, mT/m)")


class DepmLimits(_Document):
    """The safety constraints every trajectory is checked against (rigctl.plans.depm_safety)."""

    keep_out_radius_mm: Length = 150.0
    epm_radius_mm: Length = 72.0
    epm_min_distance_mm: Length = 300.0
    speed_fraction: Fraction = 0.3
    accel_fraction: Fraction = 0.5
    check_step_s: _number(1e-4, 1.0, f"the safety check's time step (s); at most "
                          f"{MAX_CHECK_SAMPLES} steps over the plan") = 0.01


class FieldSequencePlan(_PlanDocument):
    """A sequence of requested field/gradient 8-vectors U and the arm trajectories that make them
    (seed 003). Joint trajectories are PCHIP curves through the knots (`t_s`, `arms[i].joints_rad`):
    `rigctl.plans.depm.joint_trajectory(plan)` evaluates them; both arms share the knot times."""

    kind: Literal["field-sequence"]
    rig: _runs("field-sequence")
    planner: Literal["hybrid", "agnostic"] = "hybrid"
    arm_model: Literal["lbr-iiwa-14-r820"] = "lbr-iiwa-14-r820"
    epm_moment_Am2: _number(1e-3, 1e5) = Field(
        description="|m| of each EPM (A m^2), 1e-3 (a 1 mm NdFeB cube) to 1e5; the moment points "
        "along the flange x axis"
    )
    tool_offset_mm: Length = Field(
        default=85.0, description="EPM centre along the flange z axis (mm)"
    )
    waypoints: Annotated[int, Field(ge=2, le=1000)] = 20
    k: Annotated[int, Field(ge=1, le=100)] = 4
    limits: DepmLimits = DepmLimits()
    sequence: list[SequenceComponent] = Field(min_length=1, max_length=1000)
    interpolation: Literal["pchip"] = "pchip"
    t_s: list[Duration] = Field(fail_fast=True, min_length=2, max_length=MAX_SAMPLES,
                                description="knot times (s), strictly increasing, at most 1 h")
    arms: list[ArmPlan] = Field(min_length=2, max_length=2)
    segments: list[Segment] = Field(max_length=1000,
                                    description="one per sequence component, in order")
    expected: ExpectedField | None = None

    @model_validator(mode="after")
    def _consistent(self) -> "FieldSequencePlan":
        times = np.asarray(self.t_s, dtype=float)
        if np.any(np.diff(times) <= 0):
            raise ValueError("t_s: knot times must be strictly increasing")
        for index, arm in enumerate(self.arms):
            if len(arm.joints_rad) != len(self.t_s):
                raise ValueError(
                    f"arms.{index}.joints_rad: has {len(arm.joints_rad)} rows for "
                    f"{len(self.t_s)} knot times (one per t_s)"
                )
        if len(self.segments) != len(self.sequence):
            raise ValueError(
                f"segments: has {len(self.segments)} entries for {len(self.sequence)} sequence "
                "components (one per component)"
            )
        if self.expected is not None and len(self.expected.U) != len(self.expected.t_s):
            raise ValueError("expected: U needs one row per t_s")
        checks = (times[-1] - times[0]) / self.limits.check_step_s
        if checks > MAX_CHECK_SAMPLES:
            raise ValueError(
                f"t_s: {times[-1] - times[0]:.6g} s checked every limits.check_step_s = "
                f"{self.limits.check_step_s:g} s is {checks:.3g} samples; at most "
                f"{MAX_CHECK_SAMPLES} (a larger check_step_s, or a shorter plan)")
        return self

    @property
    def size(self) -> str:
        return f"{len(self.sequence)} components, {self.t_s[-1]:.1f} s"


# Kind: pair-formation (seed 002, rig six-coil). Its fields and their checks belong to the pair
# planner (rigctl.plans.pair); `check_plan` calls that module's `check(plan)`.


class PairAgents(_Document):
    """The two agents (spheres, moments along the field) and the liquid they move in."""

    body_diameter_mm: Length = Field(default=1.0, description="D, the body length BL")
    moment_Am2: _number(1e-15, 1.0) = Field(
        default=5.6e-7, description="|m| of each agent, 1e-15 (a micrometre magnet) to 1 A m^2")
    viscosity_Pa_s: _number(1e-6, MAX_MAGNITUDE) = Field(
        default=2.0e-3, description="liquid eta, 1e-6 (below any liquid's) to 1e9 Pa s")


class PairState(_Document):
    """A formation: centroid (mm), separation r (body diameters), heading of agent 1 -> 2 (deg)."""

    x_mm: Coordinate
    y_mm: Coordinate
    r_bl: BodyLengths
    phi_deg: AngleDeg


class PairSegment(_Document):
    """One control held for dt_s: global field angle psi (deg from +x) and the pull as the
    centroid speed it gives, f = F / (sigma D) in body lengths per second."""

    psi_deg: AngleDeg
    f_x: Pull = Field(description="pull along x, BL/s")
    f_y: Pull = Field(description="pull along y, BL/s")
    dt_s: Step


class PairFormationPlan(_PlanDocument):
    """Two interacting agents steered by the field angle psi and a pulling gradient (seed 002)."""

    kind: Literal["pair-formation"]
    rig: _runs("pair-formation")
    workspace: WorkspaceSpec
    agents: PairAgents = PairAgents()
    field_mT: _number(1e-3, 1e4) = Field(
        default=2.0, description="uniform field magnitude, 1 uT to 10 T")
    max_pull_bl_s: _number(1e-6, 1e4) = Field(
        description="the planner's pull bound p: |f_x| <= p |cos psi|, |f_y| <= p |sin psi|")
    r_min_bl: BodyLengths = 1.5
    r_max_bl: BodyLengths = 3.5
    start: PairState
    goal: PairState
    segments: list[PairSegment] = Field(fail_fast=True, max_length=MAX_MOVES,
                                        description=f"at most {MAX_MOVES}")
    expected: Annotated[list[PairState], Field(fail_fast=True)] | None = Field(
        default=None, max_length=MAX_MOVES, description="expected[k]: the formation after segment k")
    tolerance_bl: BodyLengths = Field(
        default=0.2, description="each agent within this of its goal position counts as reached")
    hold_s: Duration = Field(
        default=3.0, description="how long execution holds the goal formation (at most 1 h)")

    @model_validator(mode="after")
    def _bounded(self) -> PairFormationPlan:
        total = sum(segment.dt_s for segment in self.segments) + self.hold_s
        if total > MAX_DURATION_S:
            raise ValueError(f"segments: {total:.6g} s in all with hold_s; at most "
                             f"{MAX_DURATION_S:g} s")
        return self

    @property
    def size(self) -> str:
        return f"2 agents, {len(self.segments)} segments"


def _plan_tag(value: Any) -> str | None:
    kind = value.get("kind") if isinstance(value, dict) else getattr(value, "kind", None)
    return f"plan:{kind}" if isinstance(kind, str) else None


PLAN_KINDS = ("global-moves", "field-sequence", "pair-formation")

Plan = Annotated[
    Union[
        Annotated[GlobalMovesPlan, Tag("plan:global-moves")],
        Annotated[FieldSequencePlan, Tag("plan:field-sequence")],
        Annotated[PairFormationPlan, Tag("plan:pair-formation")],
    ],
    Discriminator(
        _plan_tag,
        custom_error_type="plan_kind",
        custom_error_message="expected one of " + ", ".join(PLAN_KINDS),
    ),
]

_PLAN_ADAPTER: TypeAdapter = TypeAdapter(Plan)
_WORKSPACE_ADAPTER: TypeAdapter = TypeAdapter(WorkspaceSpec)
_TAGS = {"shape:rect", "shape:polygon", "shape:disk", "workspace:shapes", "workspace:image"}
_TAGS |= {f"plan:{kind}" for kind in PLAN_KINDS}


# Reading and writing


def parse_plan(
    data: Any, source: str = "plan", base_dir: str | Path | None = None
) -> GlobalMovesPlan:
    """Validate a decoded plan document; `source` names it in messages (usually the file name).

    `base_dir` resolves a relative workspace image (default: the folder of `source`).
    """
    if not isinstance(data, dict):
        raise PlanError(f"{source}: a plan is a JSON object, got {type(data).__name__}")
    if "schema" not in data:
        raise PlanError(f'{source}: schema: missing; a plan starts with "schema": "{SCHEMA_ID}"')
    if data["schema"] != SCHEMA_ID:
        raise PlanError(
            f"{source}: schema: {data['schema']!r} is not a plan format this version reads "
            f"(expected {SCHEMA_ID!r})"
        )
    model = _installed_plan_model(data.get("kind"))
    try:
        plan = (_PLAN_ADAPTER if model is None else model).validate_python(data)
    except ValidationError as err:
        raise PlanError(_describe(err, source)) from None
    if model is not None:
        return plan  # a lab's plan kind: its model is its own
    plan._source = source
    plan._base_dir = Path(base_dir) if base_dir is not None else Path(source).parent
    return plan


def _installed_plan_model(kind: Any) -> TypeAdapter | None:
    """The model an installed rig kind registers (`RigKind.plan_models`) for a plan kind this
    schema does not know; None for the schema's own kinds and for kinds nobody registers (the
    union then names what it expected)."""
    if not isinstance(kind, str) or kind in PLAN_KINDS:
        return None
    from rigctl.core.registry import kinds

    for rig_kind in kinds().values():
        model = rig_kind.plan_models.get(kind)
        if model is not None:
            return TypeAdapter(model())
    return None


def load_plan(path: str | Path) -> GlobalMovesPlan:
    """Read and validate a plan file (schema level; `check_plan` does the geometry)."""
    path = Path(path)
    data = _read_json(path)
    return parse_plan(data, str(path), base_dir=path.parent)


def parse_workspace(
    data: Any, source: str = "workspace"
) -> ShapeWorkspaceSpec | ImageWorkspaceSpec:
    """Validate a workspace document on its own (the `workspace` object of a plan)."""
    try:
        return _WORKSPACE_ADAPTER.validate_python(data)
    except ValidationError as err:
        raise PlanError(_describe(err, source)) from None


def load_workspace(path: str | Path) -> ShapeWorkspaceSpec | ImageWorkspaceSpec:
    """Read a workspace file: a bare workspace object, or a plan whose workspace is taken."""
    path = Path(path)
    data = _read_json(path)
    if isinstance(data, dict) and "workspace" in data and "boundary" not in data:
        data = data["workspace"]
        source = f"{path}: workspace"
    else:
        source = str(path)
    return parse_workspace(data, source)


def dump_plan(plan: GlobalMovesPlan) -> str:
    """The plan as JSON text (indent 2, key `schema` first) that `parse_plan` reads back."""
    data = plan.model_dump(mode="json", by_alias=True, exclude_none=True)
    return _format_json(data) + "\n"


def _format_json(value: Any, depth: int = 0) -> str:
    """JSON with indent 2, except that a point list or a list of points stays on one line."""
    pad, inner = "  " * depth, "  " * (depth + 1)
    if isinstance(value, dict) and len(value) == 1:
        ((key, item),) = value.items()
        if not isinstance(item, (dict, list)) or (isinstance(item, list) and _is_flat(item)):
            return "{" + json.dumps(key) + ": " + _format_json(item, depth + 1) + "}"  # a shape
    if isinstance(value, dict) and value:
        items = [f"{inner}{json.dumps(k)}: {_format_json(v, depth + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(value, list) and value and not _is_flat(value):
        items = [inner + _format_json(v, depth + 1) for v in value]
        return "[\n" + ",\n".join(items) + "\n" + pad + "]"
    return json.dumps(value)


def _is_flat(value: list) -> bool:
    """Numbers, or lists of numbers: short enough to read on one line."""
    def scalar(v: Any) -> bool:
        return not isinstance(v, (dict, list))

    return all(scalar(v) or (isinstance(v, list) and all(scalar(w) for w in v)) for v in value)


def plan_json_schema() -> dict:
    """The published JSON Schema of plan documents (what `rigctl schema plan` prints)."""
    schema = _PLAN_ADAPTER.json_schema(by_alias=True)
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["$id"] = SCHEMA_ID
    schema["title"] = "rigctl plan"
    schema["description"] = (  # what JSON Schema cannot say of the numbers (docs/plans.md)
        f"Every number is finite and normal: 0, or at least {MIN_NORMAL:.4g} in size (a "
        "subnormal is refused), and within its field's minimum and maximum.")
    return schema


def _read_json(path: Path) -> Any:
    try:
        if path.stat().st_size > MAX_PLAN_BYTES:
            raise PlanError(f"{path}: {path.stat().st_size} bytes; a plan has at most "
                            f"{MAX_PLAN_BYTES}")
        text = path.read_text()
    except FileNotFoundError:
        raise PlanError(f"{path}: no such file") from None
    except OSError as err:
        raise PlanError(f"{path}: cannot read: {err.strerror}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        where = f"line {err.lineno} column {err.colno}"
        raise PlanError(f"{path}: {where}: not valid JSON: {err.msg}") from None
    except RecursionError:
        raise PlanError(f"{path}: not a plan: nested too deeply") from None
    except ValueError as err:  # an integer over Python's int-str limit
        raise PlanError(f"{path}: not a plan: {err}") from None


MAX_PROBLEMS_SHOWN = 20
"""Problems a refusal lists; the rest are counted. A plan with one list of 20,000 bad rows had
119,226 problems, and formatting them all took most of its 1.2 s `load` (fuzzed)."""


def _describe(err: ValidationError, source: str) -> str:
    """One line per problem: `source: json.path: reason`, union tags left out of the path; the
    first MAX_PROBLEMS_SHOWN of them, then how many more."""
    lines = []
    problems = err.errors(include_url=False)
    more = len(problems) - MAX_PROBLEMS_SHOWN
    for problem in problems[:MAX_PROBLEMS_SHOWN]:
        path = ".".join(str(part) for part in problem["loc"] if part not in _TAGS)
        where = path or "(top level)"
        if problem["type"] == "shape_kind":
            message = f"{problem['msg']}, got {_brief(problem['input'])}"
        elif problem["type"] == "plan_kind":
            kind = problem["input"].get("kind") if isinstance(problem["input"], dict) else None
            where = f"{path}.kind" if path else "kind"
            message = f"{problem['msg']}, got {_brief(kind)}"
        elif problem["type"] == "workspace_kind":
            message = f"{problem['msg']}, got {_brief(problem['input'])}"
        else:
            message = problem["msg"].removeprefix("Value error, ")
        lines.append(f"{source}: {where}: {message}")
    if more > 0:
        lines.append(f"{source}: and {more} more problems like these")
    return "\n".join(lines)


def _brief(value: Any, limit: int = 60) -> str:
    """A value as short JSON: `{"circle": ...}` rather than the whole thing."""
    if isinstance(value, dict):
        inner = ", ".join(f"{json.dumps(str(k))}: ..." for k in value)
        return "{" + inner + "}"
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _polygon_problem(vertices: np.ndarray) -> str | None:
    """Why these vertices (V, 2) are not a simple polygon, or None (every pair of edges at once:
    MAX_VERTICES^2 pairs)."""
    count = len(vertices)
    ends = np.roll(vertices, -1, axis=0)
    repeated = np.flatnonzero(np.all(vertices == ends, axis=1))
    if len(repeated):
        return f"polygon repeats vertex {repeated[0]}"
    i, j = np.triu_indices(count, 1)
    keep = (j != i + 1) & ((j + 1) % count != i)  # neighbouring edges share a vertex
    i, j = i[keep], j[keep]
    a, b, c, d = vertices[i], ends[i], vertices[j], ends[j]
    crossed = _segments_cross(a, b, c, d)
    if crossed.any():
        first = np.flatnonzero(crossed)[0]
        return f"polygon is not simple: edges {i[first]} and {j[first]} cross"
    x, y = vertices[:, 0], vertices[:, 1]
    if 0.5 * abs(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) == 0.0:
        return "polygon has zero area"
    return None


def _segments_cross(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Whether segment a-b meets segment c-d (touching counts), for rows of (n, 2) arrays."""
    def orient(p, q, r) -> np.ndarray:
        return (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])

    def on_segment(p, q, r) -> np.ndarray:
        inside = (np.minimum(p, q) <= r) & (r <= np.maximum(p, q))
        return inside[:, 0] & inside[:, 1]

    o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
    return (((o1 * o2 < 0) & (o3 * o4 < 0))
            | ((o1 == 0) & on_segment(a, b, c)) | ((o2 == 0) & on_segment(a, b, d))
            | ((o3 == 0) & on_segment(c, d, a)) | ((o4 == 0) & on_segment(c, d, b)))


# Semantics beyond the schema


