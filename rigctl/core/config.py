"""The rig file: one TOML document that says what hardware (or emulator) a run talks to.

A rig file names the rig kind (`[rig] kind`), and the kind decides the rest of its schema: its
`RigKind.settings` is a subclass of `RigConfig` adding the kind's own tables (the six-coil rig's
coils and field settings, the coil board's `[board]`, the arms' `[depm]`: each kind's package
holds its model). `RigConfig` here has what every rig has: `[rig]`, `[stream]`, `[camera]`,
`[preflight]`, `[emulation]`, `[daemon]`. This module also keeps the building blocks a kind's
tables use (`RigTable`, `DeviceUrl`, `CoilThermal`) and the table models of the kinds rigctl ships
(`Coil`, `CoilBoardSettings`, `DepmSettings`, ...): their drivers, emulators and planners, below
the rig kinds, read them too. The emulated bench writes the same format with an `[emulation]` table,
so a run cannot tell a bench from a rig except by that table. This module is the one config loader:
everything reads rig files through `load_rig`, which asks the registry (`rigctl.core.registry`)
for the kind's model.

Units: lengths in mm, fields in mT, currents in A, voltages in V, times in s, unless a key's
name says otherwise.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, Protocol, Union, runtime_checkable

import tomli_w
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from rigctl.core.camera_model import Calibration
from rigctl.core.errors import ConfigError
from rigctl.core.transport import camera_source, parse_url

BOARD_FULL_SCALE = 127  # a coil-board drive is -127..127 (a SyRen's full scale; the wire's MAX_COMMAND)

Vector3 = tuple[float, float, float]


def _checked(check):
    """A pydantic validator from a `rigctl.core.transport` parser: its ConfigError as the field's error."""
    def validate(value):
        try:
            check(value)
        except ConfigError as err:
            raise ValueError(str(err)) from None
        return value if isinstance(value, str) else str(value)
    return validate


# Every device URL is parsed when the rig file is loaded, before anything connects.
DeviceUrl = Annotated[str, AfterValidator(_checked(parse_url))]
CameraSource = Annotated[str, BeforeValidator(_checked(camera_source))]  # `url = 0` is an index


class RigTable(BaseModel):
    """A table of a rig file: unknown keys are refused (a misspelt key is an error, not a default),
    and a loaded rig does not change."""

    model_config = ConfigDict(extra="forbid", frozen=True)


_Strict = RigTable


class RigInfo(_Strict):
    kind: str = Field(description="an installed rig kind (`rigctl init --help` lists them)")
    name: str = "unnamed rig"

    @field_validator("kind")
    @classmethod
    def _installed(cls, kind: str) -> str:
        from rigctl.core.registry import kind_names

        names = kind_names()
        if kind not in names:
            raise ValueError(f"{kind!r} is not an installed rig kind; the installed kinds are "
                             f"{', '.join(names) or 'none'}")
        return kind


class CoilThermal(_Strict):
    """How a coil's winding heats (`rigctl.physics.thermal`): one thermal resistance to the room and one
    heat capacity (a first-order model), the copper's resistance rising with its temperature.

    The defaults are a 400-turn, 200 mm air-core coil of about 26 kg of copper (2.7 mm wire,
    1.5 ohm): C = 385 J/(kg K) x 26 kg, and natural convection from about 0.3 m^2 of winding
    (h ~ 7 W/(m^2 K)) to the room. The limit keeps the winding's mean temperature well below
    insulation class B (130 C), as the mean is below the hot spot. Measure R_th and C_th from a
    heating curve (step current, winding resistance logged: docs/certificate.md).
    """

    thermal_resistance_K_per_W: Annotated[
        float, Field(gt=0, description="winding to room, in steady state")] = 0.5
    thermal_capacity_J_per_K: Annotated[float, Field(gt=0, description="of the winding")] = 10000.0
    ambient_C: Annotated[float, Field(ge=-40, le=60, description="room temperature")] = 25.0
    max_winding_C: Annotated[
        float, Field(gt=0, le=220, description="a plan that would pass this is refused; a run "
                     "that reaches it ramps down")] = 100.0
    warning_C: Annotated[
        float, Field(gt=0, le=220, description="a run that reaches this pauses at the end of the "
                     "move")] = 90.0
    reference_C: Annotated[
        float, Field(ge=-40, le=60, description="temperature at which resistance_ohm holds")] = 20.0
    alpha_per_K: Annotated[
        float, Field(ge=0, description="temperature coefficient of the winding's resistance "
                     "(copper: 0.00393 /K)")] = 0.00393

    @model_validator(mode="after")
    def _ordered(self) -> CoilThermal:
        if not self.ambient_C < self.warning_C <= self.max_winding_C:
            raise ValueError(f"need ambient_C < warning_C <= max_winding_C, got {self.ambient_C}, "
                             f"{self.warning_C}, {self.max_winding_C}")
        return self


class StreamSettings(_Strict):
    rate_hz: Annotated[float, Field(gt=0, le=5000)] = 100.0
    reply_timeout_s: Annotated[
        float, Field(gt=0, description="watchdog: a device silent this long is a fault")
    ] = 0.25
    ramp_down_s: Annotated[float, Field(ge=0, description="safe stop ramp to zero")] = 0.1
    paused_limit_s: Annotated[float, Field(
        gt=0, allow_inf_nan=False,
        description="a run paused this long ramps down and ends (nothing holds current for ever)")
    ] = 600.0
    suspended_limit_s: Annotated[float, Field(
        gt=0, allow_inf_nan=False,
        description="a run suspended this long (tracking or a sensor lost) ramps down and ends")
    ] = 60.0
    unsafe_retry_s: Annotated[float, Field(
        ge=0, allow_inf_nan=False,
        description="a device without a watchdog of its own (a BOP supply) not confirmed safe "
                    "when the run stops is reached again every 0.5 s this long before the run ends")
    ] = 10.0


class CameraSettings(_Strict):
    """The overhead camera: where its frames come from and how pixels map to workspace mm."""

    url: CameraSource = Field(description="device index (0), /dev/video0, stream URL "
                              "(http://.../stream.mjpg) or video file")
    stamped: bool = Field(
        default=False, description="frames carry the emulated camera's capture-time stamp rows"
    )
    fps: Annotated[float, Field(gt=0)] = 60.0
    resolution: tuple[int, int] | None = None
    timeout_s: Annotated[float, Field(gt=0, description="no frame this long: tracking lost")] = 2.0
    reconnect_attempts: Annotated[int, Field(ge=0)] = 5
    threshold: float | None = Field(default=None, description="blob threshold; None = automatic")
    calibration: Calibration | None = Field(
        default=None, description="pixel -> mm homography (`rigctl calibrate camera`)"
    )
    record_video: bool = Field(
        default=True, description="write the frames the tracker reads into the run record "
        "(`video.avi`, MJPEG, each frame's time in `series/video.csv`; docs/video.md)"
    )
    video_fps: Annotated[float, Field(ge=15, le=120, description="the recorded video's rate: at "
                                      "most this many of the tracked frames a second (a slower "
                                      "camera's every frame)")] = 20.0


class FieldSettings(_Strict):
    """How a six-coil rig turns moves into a rotating field (seed 000 eq. 1-2)."""

    b0_mT: Annotated[float, Field(gt=0, description="magnitude of the rotating field")] = 3.0
    rolling_turns_per_s: Annotated[float, Field(gt=0, description="rolling speed omega")] = 2.0
    steering_deg_per_s: Annotated[float, Field(gt=0, description="steering speed Omega")] = 180.0
    ramp_s: Annotated[float, Field(ge=0, description="field ramp at start and end")] = 0.1
    hold_s: Annotated[
        float, Field(ge=0, description="dwell after each segment so the coils settle (>= 5 L/R)")
    ] = 0.1
    rest_s: Annotated[
        float, Field(ge=0, le=3600, description="after each move's hold the field ramps to zero "
                     "and stays off this long, so the coils cool (the pre-flight certificate says "
                     "how long a plan needs)")] = 0.0
    initial_heading_deg: Annotated[
        float, Field(description="direction of the first field in the xy plane (magnets align)")
    ] = 0.0
    whole_turns: bool = Field(
        default=True,
        description="moves must be whole turns of the magnets (false: fractional turns, B may end "
        "tilted out of the floor plane)",
    )


class MagnetSettings(_Strict):
    """The rolling cylindrical magnets: one turn rolls them 2*pi*radius_mm."""

    radius_mm: Annotated[float, Field(gt=0)] = 10.0 / (2.0 * math.pi)
    min_field_mT: Annotated[
        float, Field(ge=0, description="below this the magnets do not follow the field")
    ] = 0.5



class Coil(_Strict):
    """One air-core coil (a circular loop of `turns` turns) and the supply pair that feeds it.

    `axis` is the direction of the coil's field at its centre for positive current;
    `centre_mm` is the loop's centre relative to the workspace centre.
    """

    name: str
    url: DeviceUrl = Field(description="the master supply: tcp://10.0.0.11:5025, "
                           "TCPIP::10.0.0.11::5025::SOCKET or serial:///dev/ttyUSB0?baud=9600")
    centre_mm: Vector3
    axis: Vector3
    loop_radius_mm: Annotated[float, Field(gt=0)]
    turns: Annotated[int, Field(gt=0)]
    resistance_ohm: Annotated[float, Field(gt=0)]
    inductance_H: Annotated[float, Field(gt=0)]
    current_limit_A: Annotated[float, Field(gt=0, le=20.0)] = 20.0
    compliance_V: Annotated[float, Field(gt=0, le=100.0)] = 100.0
    thermal: CoilThermal = CoilThermal()

    @field_validator("axis")
    @classmethod
    def _unit_axis(cls, axis: Vector3) -> Vector3:
        norm = math.sqrt(sum(a * a for a in axis))
        if norm == 0:
            raise ValueError("axis must not be the zero vector")
        return tuple(a / norm for a in axis)  # type: ignore[return-value]



class FieldProbe(_Strict):
    """A six-coil rig's Hall probe (array) for `rigctl calibrate field`: a Hall board stream
    (docs/hall-board.md) whose `hello` says where its sensors are, mm from the workspace centre."""

    url: DeviceUrl = Field(description="the probe board's sample stream, tcp://host:port")
    timeout_s: Annotated[float, Field(gt=0, description="no sample this long: a fault")] = 1.0


class CoilBoardSettings(_Strict):
    """The coil board's host link (docs/coilboard-protocol.md, docs/coilboard-driver.md)."""

    url: DeviceUrl = Field(description="pty path, serial:///dev/ttyACM0?baud=115200 or tcp://host:port")
    baud: Annotated[int, Field(gt=0, description="for a bare device path")] = 115200
    rate_hz: Annotated[
        float, Field(gt=0, le=500, description="SET rate while streaming (the SyRen bus updates ~60/s)")
    ] = 50.0
    reply_timeout_s: Annotated[float, Field(gt=0, le=1.0, description="per request attempt")] = 0.1
    retries: Annotated[int, Field(ge=0, le=10, description="re-sends after a lost reply")] = 2
    reconnect_s: Annotated[
        float, Field(ge=0, description="how long to try re-opening the board after an unplug")
    ] = 3.0
    max_command: Annotated[int, Field(ge=1, le=BOARD_FULL_SCALE,
                                      description="largest |coil command| allowed")] = BOARD_FULL_SCALE
    coil_names: tuple[str, str, str, str] = ("+x", "-x", "+y", "-y")
    coil_directions: tuple[int, int, int, int] = Field(
        default=(1, 1, 1, 1), description="+1, or -1 for a coil wired reversed"
    )
    supply_V: Annotated[
        float, Field(gt=0, le=30, description="the SyRens' supply: full drive puts this on a coil "
                     "(SyRen 10: 6-30 V)")] = 12.0
    coil_resistance_ohm: Annotated[float, Field(gt=0, description="each coil, at reference_C")] = 6.0
    coil_thermal: CoilThermal = Field(
        default=CoilThermal(thermal_resistance_K_per_W=2.5, thermal_capacity_J_per_K=400.0),
        description="each coil's winding (a small iron-core coil: about 1 kg of copper and iron)")

    @property
    def volts_per_unit(self) -> float:
        """A drive d puts d / BOARD_FULL_SCALE of the supply across its coil."""
        return self.supply_V / BOARD_FULL_SCALE

    @field_validator("coil_directions")
    @classmethod
    def _unit_directions(cls, directions: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        if any(d not in (1, -1) for d in directions):
            raise ValueError(f"each coil direction is +1 or -1, got {list(directions)}")
        return directions


class ExposurePoint(_Strict):
    """A place near a dual-EPM rig where a person may be (world frame, mm)."""

    name: str
    position_mm: Vector3


class DepmSettings(_Strict):
    """The dual-EPM rig (seed 003): two KUKA LBR arms carrying EPMs (KST servers) and the Hall board.

    Arms are listed in the same order in every `arm_*` key; base poses are in the world frame whose
    origin is the workspace centre (z up), as in `rigctl.physics.kinematics`. docs/depm.md, docs/hall-board.md.
    """

    arm_names: list[str] = ["left", "right"]
    arm_urls: list[DeviceUrl] = Field(description="KST servers, e.g. tcp://172.31.1.147:30001")
    arm_positions_mm: list[Vector3] = Field(description="arm bases in the world frame")
    arm_rpy_deg: list[Vector3] = Field(description="arm bases: fixed-axis roll, pitch, yaw")
    epm_moment_Am2: Annotated[float, Field(gt=0, description="each EPM's dipole moment")]
    tool_offset_mm: Annotated[float, Field(gt=0, description="EPM centre on the flange z axis")] = 85.0
    hall_url: DeviceUrl = Field(description="the Hall board's sample stream, tcp://host:port")
    sensor_offsets_mm: list[Vector3] = Field(
        default=[(0.0, 0.0, 0.0), (2.0, 0.0, 0.0), (0.0, 2.0, 0.0)],
        description="sensor positions from the workspace centre; the first is the reference")
    keep_out_radius_mm: Annotated[float, Field(gt=0)] = 150.0
    epm_radius_mm: Annotated[float, Field(gt=0)] = 72.0
    epm_min_distance_mm: Annotated[float, Field(gt=0)] = 300.0
    speed_fraction: Annotated[float, Field(gt=0, le=1, description="of each joint's max speed")] = 0.3
    servo_rate_hz: Annotated[float, Field(gt=0, le=1000, description="joint targets per second")] = 50.0
    reply_timeout_s: Annotated[float, Field(gt=0, description="watchdog on every arm/board reply")] = 0.5
    tracking_tolerance_deg: Annotated[
        float, Field(gt=0, description="measured joints this far from the commanded ones: fault")] = 5.0
    exposure_points: list[ExposurePoint] = Field(
        default_factory=lambda: [ExposurePoint(name="operator", position_mm=(0.0, -1200.0, 0.0)),
                                 ExposurePoint(name="patient table edge",
                                               position_mm=(0.0, 400.0, 0.0))],
        description="where people may be: the pre-flight checks the EPMs' field there along the "
                    "whole trajectory")
    exposure_limit_mT: Annotated[
        float, Field(gt=0, description="static field allowed at the exposure points (ICNIRP 2009: "
                     "400 mT for the general public, any part of the body)")] = 400.0

    @model_validator(mode="after")
    def _same_lengths(self) -> "DepmSettings":
        n = len(self.arm_names)
        if n != 2 or any(len(v) != n for v in (self.arm_urls, self.arm_positions_mm, self.arm_rpy_deg)):
            raise ValueError("a depm rig has two arms: arm_names, arm_urls, arm_positions_mm and "
                             "arm_rpy_deg need two entries each")
        if len(self.sensor_offsets_mm) < 3:
            raise ValueError("sensor_offsets_mm needs three sensors (eq. 24)")
        return self


class PreflightSettings(_Strict):
    """The pre-flight certificate (`rigctl.run.certificate`): the margins it allows for what a plan
    does not say."""

    heating_margin: Annotated[
        float, Field(ge=0, le=2, description="the heating check adds this fraction to the Joule "
                     "power of the plan's currents: the closed loop's corrections (re-plans, "
                     "extra moves) heat the coils too")] = 0.2
    max_field_mT: Annotated[
        float, Field(gt=0, description="largest |B| a plan may ask for at the workspace centre")] = 100.0
    max_gradient_mT_per_m: Annotated[
        float, Field(gt=0, description="largest gradient term a plan may ask for there")] = 2000.0
    scpi_round_trip_ms: Annotated[
        float, Field(gt=0, description="a supply's LAN answer to `CURR x;:MEAS:CURR?` (`rigctl "
                     "doctor --rig` measures it); a serial link's time is computed from its baud "
                     "rate")] = 2.0
    kst_round_trip_ms: Annotated[
        float, Field(gt=0, description="an arm's KST answer to a servo target (`jpJP_`, the "
                     "measured joints back) over the cabinet's LAN; a guess: measure yours "
                     "(time `KukaArm.servo`)")] = 5.0


class Emulation(_Strict):
    """Present only in rig files written by `rigctl emulate`: where the bench's backdoor is."""

    backdoor: DeviceUrl = Field(description="tcp://host:port of the bench's test backdoor")
    backdoor_token: str | None = Field(
        default=None, description="the backdoor's token, written by a bench serving beyond "
        "loopback (the rig file is then mode 0600); every backdoor request carries it")
    pid: int | None = None
    # How the emulated world departs from the planner's model (`rigctl emulate --slip ...`).
    slip: Annotated[float, Field(gt=0, description="distance per turn x slip (pair world: speed "
                                                   "under a force x slip)")] = 1.0
    speed_spread: Annotated[
        float, Field(ge=0, description="per-robot distance per turn x (1 + s_i), s_i ~ N(0, this)")
    ] = 0.0
    drift_mm_per_s: Annotated[float, Field(ge=0, description="steady drift, direction from seed")] = 0.0
    noise_mm: Annotated[float, Field(ge=0, description="jitter per turn while in contact")] = 0.0
    seed: int = 0
    field_at_robots: bool = Field(
        default=False, description="each robot feels the coils' field at its own position"
    )
    thermal_mismatch: Annotated[
        float, Field(gt=-0.5, lt=0.5, description="the emulated coils' R_th and C_th are this "
                     "fraction off the rig file's (the model must cope with a winding that "
                     "differs from its data)")] = 0.05


DEFAULT_COMMAND_ENDPOINT = "tcp://127.0.0.1:7810"
DEFAULT_TELEMETRY_ENDPOINT = "tcp://127.0.0.1:7811"
DEFAULT_EVENTS_ENDPOINT = "tcp://127.0.0.1:7812"


class DaemonSettings(BaseModel):
    """The `[daemon]` table of a rig file (all optional; the CLI flags override it)."""

    model_config = ConfigDict(extra="forbid")

    command: str = DEFAULT_COMMAND_ENDPOINT
    telemetry: str = DEFAULT_TELEMETRY_ENDPOINT
    events: str = DEFAULT_EVENTS_ENDPOINT
    runs_dir: str = "runs"
    server_key: str | None = Field(default=None, description="CURVE secret key file of the daemon")
    allowed_keys: str | None = Field(default=None, description="folder of operators' public keys")


class RigConfig(_Strict):
    """What every rig file has; a rig kind's `settings` subclasses it with the kind's own tables
    (and their checks). A rig of a kind is an instance of that kind's model (`parse_rig`)."""

    rig: RigInfo
    stream: StreamSettings = StreamSettings()
    camera: CameraSettings | None = None
    daemon: DaemonSettings | None = None
    emulation: Emulation | None = None
    preflight: PreflightSettings = PreflightSettings()

    @model_validator(mode="after")
    def _of_its_kind(self) -> RigConfig:
        model = settings_of(self.rig.kind)
        if not isinstance(self, model):
            raise ValueError(f"a {self.rig.kind} rig is a {model.__module__}.{model.__name__}, "
                             f"not a {type(self).__name__}")
        return self

    @property
    def emulated(self) -> bool:
        return self.emulation is not None

    def toml_data(self) -> dict[str, Any]:
        """The rig as a rig file's data (`dump_rig`): every table, None values left out."""
        return self.model_dump(mode="json", exclude_none=True)

    def for_record(self) -> tuple[RigConfig, dict[str, str]]:
        """The rig as a run record keeps it, and the files it names (file name -> text) that the
        record keeps beside it: none here; a kind whose rig file names other files copies them."""
        return self, {}


@runtime_checkable
class CoilRig(Protocol):
    """What the coils' field (`rigctl.physics.coils`) reads of a rig file: an electromagnet rig's
    (`rigctl.rigs.six_coil.settings.SixCoilRig`, which the layers below the rigs cannot import).
    Read-only here, so a pydantic model's fields match; `isinstance` asks for the three."""

    @property
    def rig(self) -> RigInfo: ...
    @property
    def coils(self) -> list[Coil]: ...
    @property
    def actuation_matrix_T_per_A(self) -> list[list[float]] | None: ...


def settings_of(kind: str) -> type[RigConfig]:
    """The rig file model of the installed rig kind `kind` (ConfigError naming the installed ones)."""
    from rigctl.core.registry import rig_kind

    model = rig_kind(kind).settings()
    if not (isinstance(model, type) and issubclass(model, RigConfig)):
        raise ConfigError(f"rig kind {kind!r}: its settings {model!r} are not a RigConfig")
    return model


def rig_json_schema() -> dict:
    """The JSON Schema of a rig file: one of the installed kinds' models."""
    from rigctl.core.registry import kind_names

    models = tuple(settings_of(name) for name in kind_names())
    # a Union built at run time from the installed kinds, which mypy cannot see as a type
    union = Union[models]  # type: ignore[valid-type]
    schema = TypeAdapter(union).json_schema() if len(models) > 1 else models[0].model_json_schema()
    return {"title": "rig file", **schema}


def default_six_coil_coils(urls: list[str] | None = None) -> list[Coil]:
    """The six-coil cube of the emulated bench: loops on the faces of a cube around a 400 mm
    workspace, opposite coils wound the same way so their fields add at the centre.

    The numbers are plausible for a 400 mm workspace (about 10 A for 3 mT with the min-norm
    solution), not measured from the seed's manipulator, whose coil data the paper does not give.
    """
    faces = [("x+", 0, +1), ("x-", 0, -1), ("y+", 1, +1), ("y-", 1, -1), ("z+", 2, +1), ("z-", 2, -1)]
    coils = []
    for index, (name, axis_index, side) in enumerate(faces):
        centre = [0.0, 0.0, 0.0]
        centre[axis_index] = side * 350.0
        axis = [0.0, 0.0, 0.0]
        axis[axis_index] = 1.0
        coils.append(
            Coil(
                name=name,
                url=urls[index] if urls else f"tcp://127.0.0.1:{5025 + index}",
                centre_mm=tuple(centre),  # type: ignore[arg-type]
                axis=tuple(axis),  # type: ignore[arg-type]
                loop_radius_mm=200.0,
                turns=400,
                resistance_ohm=1.5,
                inductance_H=0.03,
            )
        )
    return coils


def _format_validation_error(err: ValidationError, source: str) -> str:
    lines = []
    for problem in err.errors():
        where = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in problem["loc"])
        message = problem["msg"].removeprefix("Value error, ")
        lines.append(f"{source}: {where.lstrip('.') or '(top level)'}: {message}")
    return "\n".join(lines)


def parse_rig(data: dict, source: str = "rig file", *, rig_dir: Path | None = None) -> RigConfig:
    """A rig file's data validated with its kind's model (`[rig] kind`, asked of the registry).
    `rig_dir`: where the rig file is (a file it names is relative to it). ConfigError, one line
    per problem, each naming `source` and the key."""
    info = data.get("rig") if isinstance(data, dict) else None
    kind = info.get("kind") if isinstance(info, dict) else None
    model = RigConfig  # no kind or not a string: RigInfo's check says so
    if isinstance(kind, str):
        try:
            model = settings_of(kind)
        except ConfigError as err:
            raise ConfigError(f"{source}: rig.kind: {err}") from None
    try:
        return model.model_validate(data, context={"rig_dir": rig_dir})
    except ValidationError as err:
        raise ConfigError(_format_validation_error(err, source)) from None


def load_rig(path: str | Path) -> RigConfig:
    """Read and validate a rig file; a ConfigError names the file and the offending key."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"rig file {path} does not exist") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML: {err}") from None
    return parse_rig(data, str(path), rig_dir=path.parent)


def dump_rig(rig: RigConfig) -> str:
    """The rig as TOML text, loadable by `load_rig`: the tables its kind's model has."""
    return tomli_w.dumps(rig.toml_data())
