"""The daemon's wire protocol: requests, replies, telemetry messages, named constants, error codes.

Commands are JSON objects over a ZeroMQ request socket (a plain REQ socket works):
`{"id": ..., "cmd": NAME, "args": {...}}` is answered by `{"id": ..., "ok": true, "result": ...}`
or `{"id": ..., "ok": false, "error": {"code": CODE, "message": TEXT}}`. Every command's arguments
are a pydantic model here, so a request with wrong types is refused with `bad_args` naming the field.

Telemetry goes out on two PUB sockets as two-frame messages `[topic, JSON]`: the *data* socket
carries the high-rate topics (`currents`, `field`, `agents`, `stream`), which a slow subscriber may
lose (its queue is bounded), and the *events* socket carries `state`, `fault` and `log`, which are
rare and have a queue of their own, so a flood of currents can never push a state change out. Every
telemetry message carries a per-topic sequence number: a subscriber sees any gap.

The document for people is `docs/daemon-protocol.md`; this module is the one the code uses.
"""

from __future__ import annotations

import gc
import ipaddress
import json
import re
from enum import Enum
from typing import Annotated, Any, Literal, cast
from urllib.parse import urlsplit

import numpy as np
import orjson
from pydantic import BaseModel, ConfigDict, Field, PlainValidator, model_validator
from pydantic_core import PydanticCustomError

# the rig file's [daemon] table and its defaults, re-exported ("X as X": mypy's explicit form)
from rigctl.core.config import DEFAULT_COMMAND_ENDPOINT as DEFAULT_COMMAND_ENDPOINT
from rigctl.core.config import DEFAULT_EVENTS_ENDPOINT as DEFAULT_EVENTS_ENDPOINT
from rigctl.core.config import DEFAULT_TELEMETRY_ENDPOINT as DEFAULT_TELEMETRY_ENDPOINT
from rigctl.core.config import DaemonSettings as DaemonSettings
from rigctl.core.errors import ConfigError

PROTOCOL = "rigctl.apps.daemon/1"


MAX_REQUEST_BYTES = 4 * 1024 * 1024
"""A request larger than this is answered with `too_large` (and not parsed)."""

HARD_MAX_MESSAGE_BYTES = 64 * 1024 * 1024
"""ZMQ_MAXMSGSIZE on the command socket: a peer sending more is disconnected by ZeroMQ itself."""

MAX_JSON_DEPTH = 64
"""Deeper nesting in a request is refused as `bad_json` (a plan needs 6 levels)."""

MAX_INT_DIGITS = 30
"""An integer literal longer than this is refused as `bad_json` (Python's int-str limit is 4300)."""

DATA_SEND_HWM = 1000
"""Per-subscriber queue (messages) on the data socket: about 10 s of telemetry, then drops."""

TELEMETRY_BATCH_S = 0.02
"""The publisher sends the cycles it collected every this often (currents: all of them)."""

EVENTS_SEND_HWM = 100_000
"""Per-subscriber queue on the events socket: hours of state changes; it bounds memory, not loss."""

STATE_HEARTBEAT_S = 1.0
"""The current state is re-published this often, so a subscriber that joins late learns it."""


class Command(str, Enum):
    PING = "ping"
    STATUS = "status"
    LOAD = "load"
    EXECUTE = "execute"
    PAUSE = "pause"
    RESUME = "resume"
    ABORT = "abort"
    ESTOP = "estop"
    RESET = "reset"
    HOLD = "hold"
    SET_FIELD = "set_field"
    RUNS = "runs"
    RUN = "run"
    TELEOP = "teleop"
    STEER = "steer"
    PLAN_GOALS = "plan_goals"


class ErrorCode(str, Enum):
    """Why a request was refused. Stable strings: scripts may branch on them."""

    BAD_JSON = "bad_json"  # not UTF-8 JSON (or nested too deeply, a huge integer, a lone surrogate)
    BAD_REQUEST = "bad_request"  # JSON, but not {"id", "cmd", "args"} with the right types
    TOO_LARGE = "too_large"  # over MAX_REQUEST_BYTES
    UNKNOWN_COMMAND = "unknown_command"
    BAD_ARGS = "bad_args"  # the command's arguments have the wrong names or types
    PLAN_INVALID = "plan_invalid"  # the plan does not validate (schema, workspace, whole turns)
    LIMIT = "limit"  # a current, voltage or field limit would be exceeded; nothing moved
    UNKNOWN_PLAN = "unknown_plan"
    UNKNOWN_RUN = "unknown_run"
    WRONG_STATE = "wrong_state"  # the command makes no sense in the daemon's current state
    BUSY = "busy"  # a run is still stopping; retry shortly
    DEVICE = "device"  # a device failed while carrying the command out
    DEADLINE = "deadline"  # `load` took longer than LOAD_DEADLINE_S: the plan is not loaded
    INTERNAL = "internal"  # a bug: logged with its traceback on the daemon's side
    FORBIDDEN = "forbidden"  # the connection's CURVE key was removed from the allow-list
    UNREACHABLE = "unreachable"  # plan_goals: no plan to those goals (the message says why)


class DaemonState(str, Enum):
    IDLE = "idle"
    RUNNING = "running"
    PAUSED = "paused"
    SUSPENDED = "suspended"  # waiting on a condition (lost tracking); resumes by itself
    FAULTED = "faulted"  # a device fault stopped the run; `reset` to leave
    ESTOPPED = "estopped"  # emergency stop; `reset` to leave


class Topic(str, Enum):
    STATE = "state"
    AGENTS = "agents"
    ACTUATORS = "actuators"
    FIELD = "field"
    STREAM = "stream"
    FAULT = "fault"
    LOG = "log"
    FRAME = "frame"  # camera frames (a daemon with a console only), decimated
    WINDING = "winding"  # the live winding model's estimate (rigs whose coils heat)


EVENT_TOPICS = frozenset({Topic.STATE, Topic.FAULT, Topic.LOG})
DATA_TOPICS = frozenset(set(Topic) - EVENT_TOPICS)


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _Args(_Message):
    """A request's arguments: no NaN or infinity anywhere (telemetry may carry NaN, requests not)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# -- requests and replies ------------------------------------------------------------------------

def _request_id(value: Any) -> str | int | None:
    """A request's `id` as given, if it is a string, an integer or absent (null); anything else
    is refused (`bad_request`) rather than converted: pydantic's lax union made `1.0` and `true`
    the integer 1 and `false` 0, so a reply carried another id than the request's."""
    if value is None or type(value) in (str, int):  # not bool, a subclass of int
        return cast("str | int | None", value)
    kind = {bool: "a boolean", float: "a number with a fraction or an exponent", list: "a list",
            dict: "an object"}.get(type(value), type(value).__name__)
    raise PydanticCustomError("request_id", "an id is a string or an integer, not {kind}",
                              {"kind": kind})


RequestId = Annotated[str | int | None,
                      PlainValidator(_request_id, json_schema_input_type=str | int | None)]
"""A request's id: a string, an integer, or null (left out). The reply echoes it as given."""


class BadJson(ValueError):
    """A request frame that `decode_request` refuses (answered with `bad_json`)."""


def decode_request(payload: bytes) -> Any:
    """The JSON value of a request frame, or BadJson saying why not: not UTF-8, not JSON, an
    integer over MAX_INT_DIGITS digits, nesting deeper than MAX_JSON_DEPTH, or a string with an
    unpaired surrogate (no reply could carry it). NaN and Infinity are read as JSON's Python
    dialect has them, for the models to refuse by field. Every check runs at C speed, and an
    ordinary request skips them (fewer than 64 brackets, no \\uD8xx, no 31 digits in a row).
    `read_json` reads it: 11 us against the standard library's 42 at p50 with the caches cold,
    as a `status` after an idle 5 ms finds them (`bench/daemon.py`'s round trip)."""
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as err:
        raise BadJson(f"not JSON: {err}") from None
    if _depth(text) > MAX_JSON_DEPTH:
        raise BadJson(f"nested more than {MAX_JSON_DEPTH} levels deep")
    if _LONG_DIGITS.search(text):  # in a string, a float or an integer?
        found = _LONG_INTEGER.search(_STRING.sub("", text))
        if found:
            raise BadJson(f"an integer of {len(found.group().lstrip('-'))} digits (at most "
                          f"{MAX_INT_DIGITS})")
    paused = gc.isenabled() and len(text) > 65536  # a big tree: no collections meanwhile
    if paused:  # (3x faster: 4 MiB of small lists in 0.15 s, not 0.45 s)
        gc.disable()
    try:
        data = _loads(text)
    finally:
        if paused:
            gc.enable()
    if _SURROGATE.search(text):  # an escape of one: is any unpaired?
        try:
            json.dumps(data, ensure_ascii=False, allow_nan=True).encode("utf-8")
        except UnicodeEncodeError:
            raise BadJson("a string with an unpaired surrogate (\\ud800-\\udfff)") from None
    return data


def read_json(text: str | bytes) -> Any:
    """`json.loads(text)` at orjson's speed: orjson reads it unless a number has 19 digits or
    more (orjson makes a float of an integer beyond 64 bits), the standard library reads what
    orjson refuses (NaN, an unpaired surrogate, invalid JSON: its ValueError says why)."""
    if not (_DIGITS_19.search(text) if isinstance(text, str) else _DIGITS_19_BYTES.search(text)):
        try:
            return orjson.loads(text)
        except orjson.JSONDecodeError:
            pass
    return json.loads(text)


def _loads(text: str) -> Any:
    try:
        return read_json(text)
    except RecursionError:  # cannot happen within MAX_JSON_DEPTH; kept as the last guard
        raise BadJson(f"nested more than {MAX_JSON_DEPTH} levels deep") from None
    except ValueError as err:  # JSONDecodeError is a ValueError
        raise BadJson(f"not JSON: {err}") from None


_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"')
_SURROGATE = re.compile(r"\\u[dD][89a-fA-F]")
_DIGITS_19, _DIGITS_19_BYTES = re.compile("[0-9]{19}"), re.compile(b"[0-9]{19}")
_LONG_DIGITS = re.compile(f"[0-9]{{{MAX_INT_DIGITS + 1}}}")
_LONG_INTEGER = re.compile(rf"(?<![0-9.eE+-])-?[0-9]{{{MAX_INT_DIGITS + 1},}}(?![0-9.eE])")
_NESTING = np.zeros(128, dtype=np.int8)
_NESTING[[ord("["), ord("{")]], _NESTING[[ord("]"), ord("}")]] = 1, -1


def _depth(text: str) -> int:
    """How deep the brackets of a JSON text nest (strings left out); 0 below MAX_JSON_DEPTH
    brackets in all."""
    if text.count("[") + text.count("{") <= MAX_JSON_DEPTH:
        return 0
    bare = np.frombuffer(_STRING.sub("", text).encode("ascii", "replace"), dtype=np.uint8)
    return int(np.cumsum(_NESTING[np.minimum(bare, 127)], dtype=np.int64).max(initial=0))


class Request(_Message):
    id: RequestId = None
    cmd: str
    args: dict[str, Any] = {}


class NoArgs(_Args):
    pass


class LoadArgs(_Args):
    plan: dict[str, Any]


class ExecuteArgs(_Args):
    plan_id: str = Field(max_length=64)


class PauseArgs(_Args):
    immediate: bool = Field(
        default=False,
        description="false: pause at the end of the current move; true: ramp the field down now",
    )


class HoldArgs(_Args):
    target: dict[str, Any] | None = Field(
        default=None, description='the rig\'s request: {"field_mT": [bx, by, bz]} (six-coil), '
        '{"drive": [v per coil]} (coil board), {"joints_rad": [[7], [7]]} (depm)')
    release: bool = Field(default=False, description="ramp to the rig's rest and end the hold")
    ramp_s: Annotated[float, Field(ge=0, le=60)] = 0.1

    @model_validator(mode="after")
    def _one_of(self) -> HoldArgs:
        if (self.target is None) == (not self.release):
            raise ValueError('give either "target" or "release": true')
        return self


class SetFieldArgs(_Args):
    field_mT: Annotated[
        list[float], Field(min_length=3, max_length=3, description="B at the workspace centre")
    ]
    ramp_s: Annotated[float, Field(ge=0, le=10)] = 0.1


class RunsArgs(_Args):
    limit: Annotated[int, Field(ge=1, le=1000)] = 20


class RunArgs(_Args):
    run: str = Field(max_length=255, description="a run id from `runs` (the record directory's name)")


class TeleopArgs(_Args):
    mode: str | None = Field(default=None, max_length=40, description="the kind of input: "
                             "rolling (six-coil), drive (coil board); none: the rig's first")
    end: bool = Field(default=False, description="let go, bring the rig to rest, end the session")


class SteerArgs(_Args):
    input: dict[str, float] | None = Field(
        default=None, description='the operator\'s input now ({"heading_deg": .., "speed": ..} '
        'rolling, {"heading_deg": .., "drive": ..} drive); none: let go. Counts for 200 ms')
class GoalArg(_Args):
    """One agent's goal: in the workspace's mm, or in the camera's pixels (the rig's calibration
    maps them to the floor)."""

    agent: Annotated[int, Field(ge=0, le=63)]
    mm: Annotated[list[float], Field(min_length=2, max_length=2)] | None = None
    px: Annotated[list[float], Field(min_length=2, max_length=2)] | None = None

    @model_validator(mode="after")
    def _one_of(self) -> GoalArg:
        if (self.mm is None) == (self.px is None):
            raise ValueError('give the goal as either "mm" or "px"')
        return self


class PlanGoalsArgs(_Args):
    """`plan_goals` (docs/click-a-goal.md): the agents from where the daemon last tracked them to
    these goals (an agent left out keeps its place), planned by the rig kind's planner; the plan
    is loaded, for `execute`."""

    goals: Annotated[list[GoalArg], Field(min_length=1, max_length=64)]
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] = 0
    budget_s: Annotated[float, Field(gt=0, le=60, description="the planner's time budget")] = 5.0
    tolerance_mm: Annotated[float, Field(gt=0, le=100)] | None = None


COMMAND_ARGS: dict[Command, type[_Message]] = {
    Command.PING: NoArgs,
    Command.STATUS: NoArgs,
    Command.LOAD: LoadArgs,
    Command.EXECUTE: ExecuteArgs,
    Command.PAUSE: PauseArgs,
    Command.RESUME: NoArgs,
    Command.ABORT: NoArgs,
    Command.ESTOP: NoArgs,
    Command.RESET: NoArgs,
    Command.HOLD: HoldArgs,
    Command.SET_FIELD: SetFieldArgs,
    Command.RUNS: RunsArgs,
    Command.RUN: RunArgs,
    Command.TELEOP: TeleopArgs,
    Command.STEER: SteerArgs,
    Command.PLAN_GOALS: PlanGoalsArgs,
}


class ErrorBody(_Message):
    code: ErrorCode
    message: str


class Reply(_Message):
    id: RequestId = None
    ok: bool
    result: Any = None
    error: ErrorBody | None = None


def ok_reply(request_id: RequestId, result: Any) -> Reply:
    return Reply(id=request_id, ok=True, result=result)


def error_reply(request_id: RequestId, code: ErrorCode, message: str) -> Reply:
    return Reply(id=request_id, ok=False, error=ErrorBody(code=code, message=message))


# -- telemetry -----------------------------------------------------------------------------------


class _Telemetry(_Message):
    seq: int = Field(description="per-topic sequence number from 0; a gap means lost messages")
    t: float = Field(description="seconds since the daemon started (monotonic clock)")


class StateMsg(_Telemetry):
    topic: Literal["state"] = "state"
    state: DaemonState
    run: str | None = None
    plan_id: str | None = None
    device: str | None = None
    reason: str | None = None


class ActuatorsMsg(_Telemetry):
    """Every stream cycle since the previous message (k cycles, at the stream rate): each of the
    rig's actuator channels commanded and measured in its own unit (A for the supplies, SyRen
    drive units for the coil board, rad for the arms' joints)."""

    topic: Literal["actuators"] = "actuators"
    channels: list[str] = Field(description="channel names, in column order")
    units: list[str] = Field(description="each channel's unit")
    times: list[float] = Field(description="(k,) s since the daemon started, per cycle")
    samples: list[int] = Field(description="(k,) program sample index per cycle")
    moves: list[int] = Field(description="(k,) plan move per cycle, -1 during ramps and holds")
    commanded: list[list[float]] = Field(description="(k, n_channels) setpoints")
    measured: list[list[float | None]] = Field(
        description="(k, n_channels) what the devices reported; null where one gave no reading")


class FieldMsg(_Telemetry):
    topic: Literal["field"] = "field"
    commanded_mT: list[float] = Field(description="(3,) B at the workspace centre from setpoints")
    measured_mT: list[float] = Field(description="(3,) B from the measured currents")


class AgentsMsg(_Telemetry):
    topic: Literal["agents"] = "agents"
    move: int
    tracked_mm: list[list[float]] | None = Field(description="(n, 2), None without a tracker")
    expected_mm: list[list[float]] | None = Field(description="(n, 2) after the current move")
    source: str


class StreamMsg(_Telemetry):
    topic: Literal["stream"] = "stream"
    rate_hz: float
    cycles: int
    late_cycles: int
    period_error_p50_us: float
    period_error_p99_us: float
    period_error_max_us: float
    dropped_samples: int = Field(description="telemetry samples the publisher had to drop")


class FrameMsg(_Telemetry):
    """A camera frame the tracker read during a closed-loop run, decimated (at most the stream
    process's FRAME_HZ) and JPEG-encoded off the tracking thread, with what the tracker saw in it.
    Published only by a daemon started with `--console`."""

    topic: Literal["frame"] = "frame"
    jpeg_b64: str = Field(description="the frame as JPEG, base64 (possibly scaled down)")
    width: int = Field(description="the camera's frame width, px (the calibration's pixels)")
    height: int
    t_source: float = Field(description="when the picture was taken, s on the daemon's clock")
    t_source_unix: float = Field(description="the same on the wall clock (Unix s), for a browser")
    positions_mm: list[list[float]] = Field(description="(n, 2) the tracker's positions")
    tracked_px: list[list[float]] = Field(description="(n, 2) the same in the camera's pixels")
    lost: list[bool] = Field(description="(n,) tracking of that robot lost")
    frame: int = Field(description="fresh frames tracked before this one in this run")


class WindingMsg(_Telemetry):
    """The live winding model's estimate (`rigctl.physics.thermal`, docs/certificate.md) of a rig whose
    coils heat, ten times a second: while a run streams, its own model's (what its record's
    `winding` series holds, `t` when it held); between runs the last estimate cooling at zero
    drive by the same model, from which the next run starts."""

    topic: Literal["winding"] = "winding"
    names: list[str] = Field(description="the windings, in the rig file's coil order")
    temperature_C: list[float] = Field(description="each winding's estimated temperature")
    warning_C: list[float] = Field(description="each winding's warning level: a run pauses at "
                                   "the end of the move")
    limit_C: list[float] = Field(description="each winding's limit: a run ramps down")
    state: Literal["ok", "warning", "limit"] = Field(description="the highest level a winding is at")
    source: Literal["run", "cooling"] = Field(description="a run's model, or cooling since one")


class FaultMsg(_Telemetry):
    topic: Literal["fault"] = "fault"
    device: str | None
    reason: str
    kind: str
    run: str | None = None


class LogMsg(_Telemetry):
    topic: Literal["log"] = "log"
    level: str
    message: str


TelemetryMessage = Annotated[
    StateMsg | ActuatorsMsg | FieldMsg | AgentsMsg | StreamMsg | FaultMsg | LogMsg | FrameMsg
    | WindingMsg,
    Field(discriminator="topic"),
]


class _TelemetryEnvelope(_Message):
    message: TelemetryMessage


def parse_telemetry(payload: bytes) -> (StateMsg | ActuatorsMsg | FieldMsg | AgentsMsg | StreamMsg
                                        | FaultMsg | LogMsg | FrameMsg | WindingMsg):
    """A telemetry message from its JSON frame (pydantic ValidationError if it is not one)."""
    return _TelemetryEnvelope.model_validate_json(b'{"message":' + payload + b"}").message


# -- daemon settings and endpoint rules ----------------------------------------------------------


def is_loopback_endpoint(endpoint: str) -> bool:
    """True for endpoints no other machine can reach: ipc://, inproc://, tcp on 127/8 or ::1.
    ConfigError for one that is not a URL (`tcp://[127.0.0.1]:5555`: brackets are for IPv6)."""
    try:
        parts = urlsplit(endpoint)
        parts.port  # noqa: B018 - parses the port: raises on a bad one
    except ValueError as err:
        raise ConfigError(f"endpoint {endpoint!r}: {err} (e.g. tcp://127.0.0.1:5555, "
                          "tcp://[::1]:5555)") from None
    if parts.scheme in ("ipc", "inproc"):
        return True
    if parts.scheme != "tcp":
        return False
    host = (parts.hostname or "").strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # an interface name or "*": reachable from elsewhere
