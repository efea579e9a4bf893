"""`rigctl daemon`: the long-running service that owns a rig's devices and runs plans one at a time.

Threads and who does what:
- the *command thread* serves a ROUTER socket, so any number of REQ clients can talk at once and a
  client that vanishes mid-request costs nothing (its reply is dropped by ZeroMQ). Quick commands
  are answered on this thread; slow ones (`runs` and `run` read the disk, `hold` and `set_field`
  wait for the rig to stream the hold) go to a worker thread and are answered when it is done, so
  nothing ever waits behind them; `load` (it realizes and allocates a whole plan) runs on a thread
  of its own, one at a time, and is answered `deadline` when it takes over LOAD_DEADLINE_S.
  `estop` is carried out the moment it is read: the command thread hands it to the stream
  process, which writes 0 A and output off to every supply of the active run from its own command
  thread (the drivers latch at zero, so the stream can send nothing else after it) and answers
  with the supplies it could not reach; with nothing active the command thread starts zeroing the
  supplies directly;
- plan runs and manual holds stream in the *stream process* (`rigctl.apps.daemon.runhost`, spawned when the
  daemon starts), so that no Python of the daemon's competes with the stream for a GIL, nor the
  stream with a reply to a client. The daemon's *run thread* (one at a time) waits for the job
  and passes on what the stream process reports;
- the *telemetry thread* (`rigctl.apps.daemon.telemetry`) publishes what the runs hand it (a plan run's cycles
  arrive from the stream process in batches, on the host's reader thread).

States are those of `DaemonState`; every change goes through `TRANSITIONS`, an explicit table of
(state, event) -> state, and is published on the `state` topic and logged. A repeated request
(same id and body within `REPLAY_WINDOW_S`) gets the first reply again instead of running twice,
which makes the client's lazy-pirate retries safe.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import orjson
import zmq
from pydantic import ValidationError

from rigctl.apps.daemon.admission import REQUEST_RATE_HZ, Admission, peek
from rigctl.apps.daemon.keys import CurveServer
from rigctl.apps.daemon.messages import (
    COMMAND_ARGS,
    HARD_MAX_MESSAGE_BYTES,
    MAX_REQUEST_BYTES,
    PROTOCOL,
    STATE_HEARTBEAT_S,
    BadJson,
    Command,
    DaemonState,
    ErrorCode,
    HoldArgs,
    Reply,
    Request,
    Topic,
    decode_request,
    error_reply,
    is_loopback_endpoint,
    ok_reply,
)
from rigctl.apps.daemon.runhost import (
    RemoteRun,
    RunHost,
    make_realtime,
    realtime_permitted,
)
from rigctl.apps.daemon.sdnotify import SystemdNotifier
from rigctl.apps.daemon.telemetry import CycleBatch, TelemetryPublisher, WindingEstimate
from rigctl.core import errors
from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError, LimitError, PlanError, RigError
from rigctl.physics.thermal import Windings
from rigctl.rigs import prepare_run, rig_kind
from rigctl.run.hold import CANNOT_PAUSE, HoldPlan

log = logging.getLogger(__name__)

S = DaemonState
ACTIVE = (S.RUNNING, S.PAUSED, S.SUSPENDED)

TRANSITIONS: dict[tuple[DaemonState, str], DaemonState] = {
    (S.IDLE, "execute"): S.RUNNING,
    (S.IDLE, "hold"): S.RUNNING,
    (S.RUNNING, "paused"): S.PAUSED,
    (S.PAUSED, "running"): S.RUNNING,
    (S.RUNNING, "suspended"): S.SUSPENDED,
    (S.PAUSED, "suspended"): S.SUSPENDED,
    (S.SUSPENDED, "running"): S.RUNNING,
    (S.SUSPENDED, "paused"): S.PAUSED,
    **{(s, "finished"): S.IDLE for s in ACTIVE},
    **{(s, "fault"): S.FAULTED for s in (*ACTIVE, S.IDLE)},
    **{(s, "estop"): S.ESTOPPED for s in S},
    (S.FAULTED, "reset"): S.IDLE,
    (S.ESTOPPED, "reset"): S.IDLE,
}
"""Every allowed state change. Anything else is refused (`wrong_state`) or, when a run reports
it late (a run that ends after an e-stop), ignored."""

RUN_EVENTS = {"running": "running", "paused": "paused", "suspended": "suspended",
              "faulted": "fault", "estopped": "estop", "aborted": "finished", "done": "finished"}
"""A `RunState` value -> the daemon event it causes (`prepared` causes none)."""

HOLD_START_TIMEOUT_S = 30.0  # hold waits this long for the rig to stream the hold

QUICK_COMMANDS = {b"status": "_cmd_status", b"estop": "_cmd_estop"}
"""Commands answered without decoding the request or the pydantic models when its bytes are
exactly a bare request for one (`QUICK_REQUEST`, the form `rigctl.apps.client.Rig` and `json.dumps`
write; any other form takes the general path to the same reply): `status`, which scripts poll
hundreds of times a second, and `estop`, which must reach the supplies as soon as it can. Neither
is replayed (`_replay_key`), and neither raises a `Refusal`. With the caches cold, as a `status`
after an idle 5 ms finds them, decoding took 37 us at p50."""

_WS = rb"[ \t\n\r]*"
QUICK_REQUEST = re.compile(
    _WS + rb'\{' + _WS + rb'"id"' + _WS + rb':' + _WS
    + rb'(?:"([\x20\x21\x23-\x5b\x5d-\x7e]{0,128})"|(-?[1-9][0-9]{0,17}|0))'  # a plain id
    + _WS + rb',' + _WS + rb'"cmd"' + _WS + rb':' + _WS + rb'"(status|estop)"' + _WS
    + rb'(?:,' + _WS + rb'"args"' + _WS + rb':' + _WS + rb'\{' + _WS + rb'\}' + _WS + rb')?\}' + _WS)
"""`{"id": ID, "cmd": "status" or "estop"[, "args": {}]}`, ID a string of printable ASCII with
no escape, or an integer of at most 18 digits: what `Request` accepts with no decoding to check."""

LOAD_DEADLINE_S = 20.0
"""A `load` not answered within this is answered `deadline` (the plan is not loaded); it runs on a
thread of its own, so no other command waits behind it, and shutdown does not wait for it."""

REPLAY_WINDOW_S = 60.0
REPLAY_CACHE = 256
MAX_PLANS = 32
AGENTS_HZ = 10.0
REZERO_S = 0.5  # how often a device not confirmed safe is tried again


class Refusal(Exception):
    """Raised by a command handler: becomes an error reply with this code."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = code


class RunLike(Protocol):
    """What the daemon needs of a run (`rigctl.rigs.six_coil.global_moves.Run` and the tests' stand-ins)."""

    def execute(self) -> Any: ...
    def pause(self, immediate: bool = False) -> None: ...
    def resume(self) -> None: ...
    def abort(self) -> None: ...
    def estop(self) -> list[str]: ...  # the supplies it could not reach

    plan: Any  # the plan being run (agents, expected)
    info: dict  # what `load` and `status` say of it: name, size, planned duration
    record: Any  # the run record once execute() has made it, else None


class RunFactory(Protocol):
    def start(self) -> None: ...  # when the daemon starts (spawn helpers)
    def close(self) -> None: ...  # when it stops
    def parse_plan(self, data: dict) -> Any: ...

    def prepare(self, plan: Any, rig: RigConfig, *, runs_dir: Path,
                on_cycles: Callable[[CycleBatch], None],
                on_state: Callable[[Any, dict], None]) -> RunLike: ...
    # a run hands its stream cycles to on_cycles in batches (t: time.monotonic())


class PlanRuns:
    """The real thing: plans from `rigctl.plans.schema` (any kind the rig's `RigKind` runs), prepared
    here at load (a bad plan is refused before anything else) and streamed in the stream process
    (`rigctl.apps.daemon.runhost`), which `start` spawns and `close` stops."""

    def __init__(self, realtime_priority: int | None = None, on_frame: Any = None,
                 windings: WindingEstimate | None = None) -> None:
        self.host = RunHost(realtime_priority, on_frame, windings)
        self._lock = threading.Lock()
        # id(plan) -> (plan, the plan as prepared, what load says of it): a plan executed again
        # is not realized and allocated again here (on the command thread) just to be described
        self._checked: OrderedDict[int, tuple[Any, Any, dict]] = OrderedDict()

    def start(self) -> None:
        self.host.start()

    def close(self) -> None:
        self.host.close()

    def parse_plan(self, data: dict) -> Any:
        from rigctl.plans.schema import parse_plan

        return parse_plan(data, "plan")

    def prepare(self, plan, rig, *, runs_dir, on_cycles, on_state) -> RunLike:
        """The first time: the run built here refuses a bad plan before anything else happens and
        tells the plan's size. The stream process builds its own from the same prepared plan and
        rig (deterministic, so the same program) and streams that."""
        with self._lock:
            known = self._checked.get(id(plan))
        if known is None or known[0] is not plan:
            # what refuses a plan on a rig (another rig's, a kind it does not run, the rig kind's
            # rules, the pre-flight certificate): the code `rigctl validate` runs
            local = prepare_run(plan, rig, runs_dir=runs_dir)
            certificate = local.certificate
            known = (plan, local.plan, {**local.info, "certificate": {  # its name, size, duration
                "passed": certificate.passed, "checks": len(certificate.checks),
                "rig_sha256": certificate.rig_hash}})
            with self._lock:
                self._checked[id(plan)] = known
                while len(self._checked) > MAX_PLANS:
                    self._checked.popitem(last=False)
        _, prepared, info = known
        return RemoteRun(self.host, ("run", prepared, rig, str(runs_dir)), rig, plan=prepared,
                         info=info, on_cycles=on_cycles, on_state=on_state)


@dataclass(frozen=True)
class DaemonEndpoints:
    command: str
    telemetry: str
    events: str

    def as_dict(self) -> dict:
        return {"command": self.command, "data": self.telemetry, "events": self.events}


@dataclass
class _LoadedPlan:
    plan_id: str
    plan: Any
    info: dict
    prepared: RunLike | None


@dataclass
class _Loading:
    """The `load` being checked on its thread; answered once, by it or by its deadline."""

    deadline: float
    deliver: Callable[[Reply], None]
    request_id: Any
    answered: bool = False

    def answer(self, reply: Reply) -> None:  # on the command thread
        if not self.answered:
            self.answered = True
            self.deliver(reply)


@dataclass
class _ActiveRun:
    """The run (a plan's or a manual hold) on the run thread, and what the stream thread last did."""

    kind: str  # "plan" or "hold"
    job: Any
    plan_id: str | None
    info: dict
    thread: threading.Thread | None = None
    run_id: str | None = None
    sample: int = -1
    move: int = -1
    last_cycle: float = 0.0
    commanded: np.ndarray | None = None  # the latest setpoints the stream reported
    setpoints: np.ndarray | None = None  # a hold's: the target it ramps to and holds
    released: bool = False  # a hold's release was asked for


class _Wakeup:
    """A pipe the command thread polls next to its socket: other threads write a byte to wake it
    (a `load` thread may still do so after the daemon closed it: then nothing happens)."""

    def __init__(self) -> None:
        self.read_fd, self.write_fd = os.pipe()
        os.set_blocking(self.read_fd, False)
        os.set_blocking(self.write_fd, False)
        self._lock = threading.Lock()
        self._closed = False

    def wake(self) -> None:
        with self._lock:
            if self._closed:
                return
            try:
                os.write(self.write_fd, b"x")
            except BlockingIOError:  # already full of wake-ups: the reader will run anyway
                pass

    def drain(self) -> None:
        try:
            while os.read(self.read_fd, 4096):
                pass
        except BlockingIOError:
            pass

    def close(self) -> None:
        with self._lock:
            self._closed = True
            os.close(self.read_fd)
            os.close(self.write_fd)


class _TelemetryLogHandler(logging.Handler):
    """Warnings and errors of rigctl go out on the `log` topic too."""

    def __init__(self, publisher: TelemetryPublisher) -> None:
        super().__init__(level=logging.WARNING)
        self.publisher = publisher

    def emit(self, record: logging.LogRecord) -> None:
        if record.name.startswith("rigctl.apps.daemon.telemetry"):
            return
        try:
            self.publisher.publish_event(Topic.LOG, level=record.levelname,
                                         message=f"{record.name}: {record.getMessage()}")
        except Exception:  # a log handler must never raise into the code that logged
            self.handleError(record)


class Daemon:
    """Bind with `start()`, serve with `serve_forever()` (or `start_thread()`), stop with `stop()`.

    Endpoints are ZeroMQ endpoints (`tcp://127.0.0.1:0` picks a free port; `endpoints` tells which).
    Anything but loopback needs CURVE: `server_key` (the daemon's `.key_secret`) and `allowed_keys`
    (a folder of operators' public `.key` files). `realtime_priority` asks SCHED_FIFO for the stream
    thread; `currents_hz` decimates the `currents` topic (0: every cycle).
    """

    def __init__(
        self,
        rig: RigConfig,
        *,
        command: str,
        telemetry: str,
        events: str,
        runs_dir: str | Path = "runs",
        server_key: str | Path | None = None,
        allowed_keys: str | Path | None = None,
        run_factory: RunFactory | None = None,
        realtime_priority: int | None = None,
        currents_hz: float = 0.0,
        notifier: SystemdNotifier | None = None,
        request_rate_hz: float = REQUEST_RATE_HZ,
        camera_frames: bool = False,
    ) -> None:
        self.rig = rig
        self.runs_dir = Path(runs_dir)
        # the windings' estimate (`winding`), a run's live model or cooling since (None: no coil)
        windings = Windings.of_rig(rig)
        self.windings = None if windings is None else WindingEstimate(windings)
        # camera_frames: publish the closed loop's camera frames (`frame`), for the console
        self.factory = run_factory or PlanRuns(
            realtime_priority, on_frame=self._on_frame if camera_frames else None,
            windings=self.windings)
        self.realtime_priority = realtime_priority
        self.currents_hz = currents_hz
        self.notifier = notifier or SystemdNotifier()
        self._wanted = (command, telemetry, events)
        if (server_key is None) != (allowed_keys is None):
            raise ConfigError("CURVE needs both a server key and an allow-list folder")
        if server_key is None:
            for endpoint in self._wanted:
                if not is_loopback_endpoint(endpoint):
                    raise ConfigError(
                        f"refusing to bind {endpoint} without CURVE keys: anything but loopback "
                        "needs --server-key and --allowed-keys (make them with `rigctl keys new`)")
        self._keys = (server_key, allowed_keys)
        self.context = zmq.Context()
        self._command_priority = None
        if realtime_priority and realtime_permitted(realtime_priority - 1):
            # the command path (ZeroMQ's I/O thread and the command thread) just below the
            # stream: a reply, and an e-stop on its way to the stream process, wait for no
            # ordinary process on the machine, yet a flood of requests cannot starve the stream.
            # libzmq aborts when it may not set these, hence the check first.
            self._command_priority = realtime_priority - 1
            self.context.set(zmq.THREAD_SCHED_POLICY, os.SCHED_FIFO)
            self.context.set(zmq.THREAD_PRIORITY, self._command_priority)
        self.curve: CurveServer | None = None
        self.publisher: TelemetryPublisher | None = None
        self.endpoints: DaemonEndpoints | None = None
        self.t0 = time.monotonic()
        self._lock = threading.RLock()
        self.state = DaemonState.IDLE
        self._state_info: dict = {}
        self.last_fault: dict | None = None
        self._active: _ActiveRun | None = None
        self._plans: OrderedDict[str, _LoadedPlan] = OrderedDict()
        self._deliveries: deque[Callable[[], None]] = deque()
        self._replay: OrderedDict[bytes, tuple[float, Reply | None, list[list[bytes]]]] = OrderedDict()
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="daemon-worker")
        self._loading: _Loading | None = None
        self.load_deadline_s = LOAD_DEADLINE_S
        self._wakeup = _Wakeup()
        self.admission = Admission(request_rate_hz)
        self._stop = threading.Event()
        self._shutdown_requested = threading.Event()
        self._serving = threading.Event()
        self._thread: threading.Thread | None = None
        self._router: zmq.Socket | None = None
        self._log_handler: _TelemetryLogHandler | None = None
        self._agents_stop = threading.Event()
        self.unsafe: set[str] = set()  # devices a run could not confirm safe: zeroed once they answer
        self.kind = rig_kind(rig.rig.kind)
        actuators = self.kind.channels(rig)
        if not actuators:
            raise ConfigError(f"the rig file describes a {rig.rig.kind} rig with no actuators "
                              "(a [[coils]], [board] or [depm] table): there is nothing to drive")
        self.channels = actuators
        self.devices = {d.name: {"name": d.name, "url": d.url, "kind": d.kind, "health": "unknown",
                                 "detail": ""} for d in self.kind.devices(rig)}
        self.held: dict | None = None  # the manual hold's target
        self.last_run: dict | None = None
        self._actuation = self._actuation_matrix()
        self._handlers: dict[Command, Callable[[Any], Any]] = {
            Command.PING: self._cmd_ping, Command.STATUS: self._cmd_status,
            Command.LOAD: self._cmd_load, Command.EXECUTE: self._cmd_execute,
            Command.PAUSE: self._cmd_pause, Command.RESUME: self._cmd_resume,
            Command.ABORT: self._cmd_abort, Command.ESTOP: self._cmd_estop,
            Command.RESET: self._cmd_reset, Command.HOLD: self._cmd_hold,
            Command.SET_FIELD: self._cmd_set_field,
            Command.RUNS: self._cmd_runs, Command.RUN: self._cmd_run,
        }

    # -- life cycle -----------------------------------------------------------------------------
    def _actuation_matrix(self) -> np.ndarray | None:
        if not getattr(self.rig, "coils", None):  # a rig of coils fed by supplies
            return None
        from rigctl.physics.coils import actuation_matrix

        return actuation_matrix(self.rig)

    def start(self) -> DaemonEndpoints:
        """Bind every socket and start the telemetry thread; returns the bound endpoints."""
        command, telemetry, events = self._wanted
        secure = None
        if self._keys[0] is not None:
            self.curve = CurveServer(self.context, self._keys[0], self._keys[1])
            secure = self.curve.secure
        router = self.context.socket(zmq.ROUTER)
        router.setsockopt(zmq.LINGER, 0)
        router.setsockopt(zmq.MAXMSGSIZE, HARD_MAX_MESSAGE_BYTES)
        router.setsockopt(zmq.SNDHWM, 10_000)
        router.setsockopt(zmq.RCVHWM, 10_000)
        if secure is not None:
            secure(router)
        try:
            router.bind(command)
            self.publisher = TelemetryPublisher(
                self.context, telemetry, events, channels=self.channels,
                actuation_matrix_T_per_A=self._actuation, currents_hz=self.currents_hz,
                secure=secure, clock_origin=self.t0, windings=self.windings)
        except zmq.ZMQError as err:
            router.close(linger=0)
            raise ConfigError(f"cannot bind the daemon's sockets: {err}") from None
        self._router = router
        self.factory.start()
        self.publisher.start()
        self._log_handler = _TelemetryLogHandler(self.publisher)
        logging.getLogger("rigctl").addHandler(self._log_handler)
        self.endpoints = DaemonEndpoints(router.getsockopt_string(zmq.LAST_ENDPOINT),
                                         self.publisher.data_endpoint,
                                         self.publisher.events_endpoint)
        self._publish_state()
        log.info("daemon up: commands %s, telemetry %s, events %s", *self.endpoints.as_dict().values())
        return self.endpoints

    def start_thread(self) -> DaemonEndpoints:
        """`start()` and serve on a background thread (tests, embedding)."""
        endpoints = self.start()
        self._thread = threading.Thread(target=self.serve_forever, name="daemon-commands")
        self._thread.start()
        self._serving.wait(timeout=10)
        return endpoints

    def request_shutdown(self) -> None:
        """Thread- and signal-safe: ramp down whatever runs, then stop serving."""
        self._shutdown_requested.set()
        self._wakeup.wake()

    def stop(self) -> None:
        self.request_shutdown()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=30)

    # -- the command thread ---------------------------------------------------------------------
    def serve_forever(self) -> None:
        assert self._router is not None, "start() first"
        poller = zmq.Poller()
        poller.register(self._router, zmq.POLLIN)
        poller.register(self._wakeup.read_fd, zmq.POLLIN)
        watchdog = self.notifier.watchdog_s
        next_pet = 0.0
        next_heartbeat = time.monotonic() + STATE_HEARTBEAT_S
        if self._command_priority is not None:
            make_realtime(self._command_priority, "command thread")
        self.notifier.ready(f"serving {self.endpoints.command}")
        self._serving.set()
        try:
            while True:
                now = time.monotonic()
                if watchdog and now >= next_pet:
                    if self._healthy_for_watchdog(now):
                        self.notifier.watchdog()
                    next_pet = now + watchdog / 3
                if now >= next_heartbeat:
                    self._publish_state()
                    next_heartbeat = now + STATE_HEARTBEAT_S
                if self._shutdown_requested.is_set() and self._shut_down_step():
                    break
                self._check_load_deadline(now)
                timeout = min(next_heartbeat, next_pet if watchdog else next_heartbeat) - now
                queued = self.admission.next_s(now)
                if queued is not None:
                    timeout = min(timeout, queued)
                events = dict(poller.poll(max(1, int(1000 * min(timeout, 0.5)))))
                if self._router in events:
                    for _ in range(256):  # bounded batch, then look at wake-ups and timers again
                        try:
                            frames = self._router.recv_multipart(zmq.NOBLOCK,
                                                                 copy=self.curve is None)
                        except zmq.Again:
                            break
                        self._admit(frames)
                        # no more waiting: asked, not found by a receive that raises (40 us cold)
                        if not self._router.getsockopt(zmq.EVENTS) & zmq.POLLIN:
                            break
                for frames in self.admission.ready(time.monotonic()):
                    self._on_message(frames)
                if self._wakeup.read_fd in events:
                    self._wakeup.drain()
                self._flush_replies()
        finally:
            self._close()

    def _healthy_for_watchdog(self, now: float) -> bool:
        """Withhold the watchdog when a streaming run has not cycled for 5 s: systemd restarts
        a daemon whose stream thread hangs (the supplies' own watchdogs make them safe)."""
        active = self._active
        if active is None or active.last_cycle == 0.0 or self.state != S.RUNNING:
            return True
        if now - active.last_cycle > 5.0:
            log.error("the stream thread has not cycled for %.1f s", now - active.last_cycle)
            return False
        return True

    def _shut_down_step(self) -> bool:
        """On shutdown: ask the active run to ramp down and wait for it; True when done."""
        if not self._stop.is_set():
            self._stop.set()
            self.notifier.stopping()
            active = self._active
            if active is not None:
                log.warning("shutting down: ramping the active %s down", active.kind)
                _abort_quietly(active)
        active = self._active
        if active is not None and active.thread is not None and active.thread.is_alive():
            return False  # the run thread wakes us when it ends
        return True

    def _close(self) -> None:
        self._agents_stop.set()
        self._worker.shutdown(wait=True, cancel_futures=True)
        self._flush_replies()
        active = self._active  # started by the worker while shutting down: stop it too
        if active is not None and active.thread is not None:
            _abort_quietly(active)
            active.thread.join(timeout=30)
        if self._log_handler is not None:
            logging.getLogger("rigctl").removeHandler(self._log_handler)
        self.factory.close()
        if self.publisher is not None:
            self.publisher.stop()
        if self._router is not None:
            self._router.close(linger=0)
        if self.curve is not None:
            self.curve.stop()
        self.context.term()
        self._wakeup.close()
        self.notifier.close()
        log.info("daemon stopped")

    # -- requests -------------------------------------------------------------------------------
    def _admit(self, received: list) -> None:
        """Answer a request now, let it wait for the request budget, or answer `busy`
        (`rigctl.apps.daemon.admission`); with CURVE, refuse one from a connection whose key has
        been removed from the allow-list since it connected (frames are `zmq.Frame`s then, for
        their ZAP `User-Id`; bytes otherwise)."""
        user_id = None if self.curve is None else received[-1].get("User-Id")
        frames = received if self.curve is None else [f.bytes for f in received]
        split = _envelope_end(frames)
        body = frames[split] if len(frames) == split + 1 else None
        if self.curve is not None and not self.curve.admits(user_id):
            self._send(frames[:split], error_reply(
                _request_id(body), ErrorCode.FORBIDDEN, "this client's key is no longer in the daemon's "
                "allow-list; ask the daemon's administrator"))
            return
        verdict = self.admission.offer(frames, frames[0], body, time.monotonic())
        if verdict == "answer":
            self._on_message(frames)
        elif verdict == "busy":
            self._send(frames[:split], error_reply(
                _request_id(body), ErrorCode.BUSY,
                f"{self.admission.per_client} requests of this client are waiting already; "
                "wait for their replies before sending more"))

    def _on_message(self, frames: list[bytes]) -> None:
        """One request, answered whatever it holds: an exception here is a bug, answered as
        `internal` and logged with its traceback, and the daemon goes on serving."""
        split = _envelope_end(frames)
        envelope = frames[:split]
        try:
            self._answer_frames(envelope, frames[split:])
        except Exception as err:
            log.exception("a request failed")
            self._send(envelope, error_reply(None, ErrorCode.INTERNAL, f"{type(err).__name__}: {err}"))

    def _answer_frames(self, envelope: list[bytes], body: list[bytes]) -> None:
        if len(body) != 1:
            self._send(envelope, error_reply(None, ErrorCode.BAD_REQUEST,
                                             f"a request is one frame, got {len(body)}"))
            return
        payload = body[0]
        if len(payload) > MAX_REQUEST_BYTES:
            self._send(envelope, error_reply(None, ErrorCode.TOO_LARGE,
                                             f"{len(payload)} bytes; the limit is {MAX_REQUEST_BYTES}"))
            return
        quick = QUICK_REQUEST.fullmatch(payload)
        if quick is not None and self._answer_quickly(envelope, *quick.groups()):
            return
        try:
            data = decode_request(payload)
        except BadJson as err:
            self._send(envelope, error_reply(None, ErrorCode.BAD_JSON, str(err)))
            return
        request_id = data.get("id") if isinstance(data, dict) else None
        if not isinstance(request_id, (str, int)) or isinstance(request_id, bool):
            request_id = None
        try:
            request = Request.model_validate(data)
        except ValidationError as err:
            self._send(envelope, error_reply(request_id, ErrorCode.BAD_REQUEST, _describe(err)))
            return
        try:
            cmd = Command(request.cmd)
        except ValueError:
            known = ", ".join(c.value for c in Command)
            self._send(envelope, error_reply(request.id, ErrorCode.UNKNOWN_COMMAND,
                                             f"unknown command {request.cmd[:40]!r}; known: {known}"))
            return
        try:
            args = COMMAND_ARGS[cmd].model_validate(request.args)
        except ValidationError as err:
            self._send(envelope, error_reply(request.id, ErrorCode.BAD_ARGS,
                                             f"{cmd.value}: {_describe(err)}"))
            return
        replay_key = self._replay_key(request, cmd, payload)
        if replay_key is not None and self._replayed(replay_key, envelope):
            return
        self._dispatch(cmd, args, request.id, envelope, replay_key)

    def _answer_quickly(self, envelope: list[bytes], text_id: bytes | None, number_id: bytes | None,
                        cmd: bytes) -> bool:
        """A `QUICK_REQUEST` answered; False (the general path answers) if its handler failed."""
        try:
            result = getattr(self, QUICK_COMMANDS[cmd])(None)
        except Exception:  # noqa: BLE001 - the general path answers with the error
            log.exception("%s failed on the quick path; answering through the general one",
                          cmd.decode())
            return False
        request_id = text_id.decode() if text_id is not None else int(number_id)
        self._send_json(envelope, {"id": request_id, "ok": True, "result": result, "error": None})
        return True

    def _replay_key(self, request: Request, cmd: Command, payload: bytes) -> bytes | None:
        if cmd in (Command.PING, Command.STATUS, Command.ESTOP, Command.RUNS, Command.RUN):
            return None  # read-only or always carried out
        if not isinstance(request.id, str) or len(request.id) < 8:
            return None  # only ids that look unique; short ids are likely reused
        return hashlib.sha256(payload).digest()

    def _replayed(self, key: bytes, envelope: list[bytes]) -> bool:
        now = time.monotonic()
        while self._replay and (len(self._replay) > REPLAY_CACHE
                                or next(iter(self._replay.values()))[0] < now - REPLAY_WINDOW_S):
            self._replay.popitem(last=False)
        entry = self._replay.get(key)
        if entry is None:
            self._replay[key] = (now, None, [envelope])
            return False
        _, reply, waiting = entry
        if reply is None:
            waiting.append(envelope)  # still being worked on: answer this one too
        else:
            self._send(envelope, reply)
        return True

    def _dispatch(self, cmd: Command, args: Any, request_id: Any, envelope: list[bytes],
                  replay_key: bytes | None) -> None:
        handler = self._handlers[cmd]

        def answer() -> Reply:
            try:
                return ok_reply(request_id, handler(args))
            except Refusal as err:
                return error_reply(request_id, err.code, str(err))
            except LimitError as err:
                return error_reply(request_id, ErrorCode.LIMIT, str(err))
            except PlanError as err:
                return error_reply(request_id, ErrorCode.PLAN_INVALID, str(err))
            except RigError as err:
                return error_reply(request_id, ErrorCode.DEVICE, str(err))
            except Exception as err:  # a bug: keep serving, say so, log the traceback
                log.exception("%s failed", cmd.value)
                return error_reply(request_id, ErrorCode.INTERNAL, f"{type(err).__name__}: {err}")

        def deliver(reply: Reply) -> None:
            targets = [envelope]
            if replay_key is not None and replay_key in self._replay:
                t, _, waiting = self._replay[replay_key]
                self._replay[replay_key] = (t, reply, [])
                targets = waiting or [envelope]
            for target in targets:
                self._send(target, reply)

        if cmd is Command.LOAD:
            self._start_load(answer, deliver, request_id)
        elif cmd in (Command.RUNS, Command.RUN, Command.HOLD, Command.SET_FIELD):
            def work() -> None:
                reply = answer()
                self._deliveries.append(lambda: deliver(reply))  # deque.append is thread-safe
                self._wakeup.wake()

            self._worker.submit(work)
        else:
            deliver(answer())

    def _start_load(self, answer: Callable[[], Reply], deliver: Callable[[Reply], None],
                    request_id: Any) -> None:
        """`load` on a thread of its own, one at a time, answered within `load_deadline_s`."""
        if self._loading is not None and not self._loading.answered:
            deliver(error_reply(request_id, ErrorCode.BUSY,
                                "another plan is being loaded; retry when it is answered"))
            return
        loading = self._loading = _Loading(time.monotonic() + self.load_deadline_s, deliver,
                                           request_id)

        def work() -> None:
            reply = answer()
            self._deliveries.append(lambda: loading.answer(reply))
            self._wakeup.wake()

        threading.Thread(target=work, name="daemon-load", daemon=True).start()

    def _check_load_deadline(self, now: float) -> None:
        loading = self._loading
        if loading is not None and not loading.answered and now > loading.deadline:
            log.error("load missed its deadline (%g s)", self.load_deadline_s)
            loading.answer(error_reply(
                loading.request_id, ErrorCode.DEADLINE,
                f"load: the plan was not checked within {self.load_deadline_s:g} s, so it is not "
                "loaded (a smaller plan: fewer moves, a smaller workspace image)"))

    def _flush_replies(self) -> None:
        """Send the replies the worker finished (on the command thread: it owns the socket)."""
        while self._deliveries:
            self._deliveries.popleft()()

    def _send(self, envelope: list[bytes], reply: Reply) -> None:
        try:
            body = reply.model_dump_json().encode()
        except Exception as err:  # a bug: the client still gets a reply
            log.exception("a reply could not be encoded")
            body = error_reply(None, ErrorCode.INTERNAL,
                               f"the reply could not be encoded: {type(err).__name__}").model_dump_json().encode()
        self._send_bytes(envelope, body)

    def _send_json(self, envelope: list[bytes], reply: dict) -> None:
        """A reply built without the models (`QUICK_COMMANDS`). Its request was checked to be
        exactly what `Request` accepts, and the bytes are what `Reply.model_dump_json` gives (the
        protocol tests compare the two). The models cost 10-40 us each when the caches are cold,
        as they are after an idle 5 ms; orjson writes a `status` in 13 us there, the standard
        library in 88 (p50; 41 against 171 at p99)."""
        try:
            body = orjson.dumps(reply)
        except TypeError:  # not what the models would give (a value of another type, an integer
            # beyond 64 bits): let them say why
            self._send(envelope, Reply.model_validate(reply))
            return
        self._send_bytes(envelope, body)

    def _send_bytes(self, envelope: list[bytes], body: bytes) -> None:
        assert self._router is not None
        try:
            self._router.send_multipart([*envelope, body], zmq.NOBLOCK)
        except zmq.Again:
            log.warning("a client's reply queue is full; reply dropped")

    # -- state ----------------------------------------------------------------------------------
    def _transition(self, event: str, **info: Any) -> bool:
        """Apply `event` if TRANSITIONS allows it from the present state; publish the new state."""
        with self._lock:
            target = TRANSITIONS.get((self.state, event))
            if target is None:
                return False
            changed = target != self.state
            self.state = target
            self._state_info = {k: v for k, v in info.items() if k in ("device", "reason")}
        if changed:
            log.info("state %s (%s)", target.value, event)
            self._publish_state()
            self.notifier.status(f"{target.value}")
        return True

    def _publish_state(self) -> None:
        if self.publisher is None:
            return
        active = self._active
        self.publisher.publish_event(
            Topic.STATE, state=self.state, run=active.run_id if active else None,
            plan_id=active.plan_id if active else None,
            device=self._state_info.get("device"), reason=self._state_info.get("reason"))

    def _require(self, *states: DaemonState, doing: str) -> None:
        if self.state not in states:
            hint = " (send reset first)" if self.state in (S.FAULTED, S.ESTOPPED) else ""
            raise Refusal(ErrorCode.WRONG_STATE,
                          f"cannot {doing} while {self.state.value}{hint}")

    # -- commands -------------------------------------------------------------------------------
    def _cmd_ping(self, _: Any) -> dict:
        return {"protocol": PROTOCOL, "pid": os.getpid(),
                "telemetry": self.endpoints.as_dict() if self.endpoints else None}

    def _cmd_status(self, _: Any) -> dict:
        with self._lock:
            active = self._active
            run = None
            if active is not None:
                run = {"kind": active.kind, "id": active.run_id, "plan_id": active.plan_id,
                       "sample": active.sample, "move": active.move, **active.info}
            return {
                "state": self.state.value,
                "device": self._state_info.get("device"),
                "reason": self._state_info.get("reason"),
                "rig": {"name": self.rig.rig.name, "kind": self.rig.rig.kind,
                        "emulated": self.rig.emulated},
                "run": run,
                "last_run": self.last_run,
                "plans": list(self._plans),
                "devices": [dict(d) for d in self.devices.values()],
                "last_fault": self.last_fault,
                "hold": self.held,
                "manual_field_mT": (self.held or {}).get("field_mT"),  # set_field's, six-coil
                "uptime_s": round(time.monotonic() - self.t0, 3),
            }

    def _cmd_load(self, args: Any) -> dict:
        plan = self.factory.parse_plan(args.plan)
        plan_id = hashlib.sha256(json.dumps(args.plan, sort_keys=True).encode()).hexdigest()[:12]
        prepared = self._prepare(plan)
        info = dict(prepared.info)
        with self._lock:
            self._plans[plan_id] = _LoadedPlan(plan_id, plan, info, prepared)
            self._plans.move_to_end(plan_id)
            while len(self._plans) > MAX_PLANS:
                self._plans.popitem(last=False)
        log.info("plan %s loaded: %s", plan_id, info)
        return {"plan_id": plan_id, **info}

    def _prepare(self, plan: Any) -> RunLike:
        # the daemon reaches a device a run left unconfirmed itself, for as long as it serves
        # (`_make_safe_when_reachable`): the run's own bounded retry is a local run's
        rig = self.rig.model_copy(update={"stream": self.rig.stream.model_copy(
            update={"unsafe_retry_s": 0.0})})
        return self.factory.prepare(plan, rig, runs_dir=self.runs_dir,
                                    on_cycles=self._on_cycles, on_state=self._on_run_state)

    def _cmd_execute(self, args: Any) -> dict:
        with self._lock:
            if self._active is not None and self._active.kind == "hold":
                raise Refusal(ErrorCode.WRONG_STATE,
                              'a manual hold is on: release it first (hold {"release": true})')
            self._require(S.IDLE, doing="execute a plan")
            self._require_safe("execute a plan")
            if self._active is not None:
                raise Refusal(ErrorCode.BUSY, "the last run is still stopping")
            loaded = self._plans.get(args.plan_id)
            if loaded is None:
                raise Refusal(ErrorCode.UNKNOWN_PLAN,
                              f"no plan {args.plan_id!r} loaded; load it first")
            run, loaded.prepared = loaded.prepared, None
        if run is None:  # executed before: prepare again (the plan was checked at load)
            run = self._prepare(loaded.plan)
        active = _ActiveRun("plan", run, loaded.plan_id, dict(loaded.info))
        self._activate(active, "execute")
        if self.rig.emulated and getattr(loaded.plan, "agents", None) is not None:
            threading.Thread(target=self._sample_agents, args=(active,), name="daemon-agents",
                             daemon=True).start()
        return {"plan_id": loaded.plan_id, "state": self.state.value, **loaded.info}

    def _activate(self, active: _ActiveRun, event: str) -> None:
        """`active` becomes the daemon's run (an e-stop reaches it from now on), on its thread."""
        with self._lock:
            self._active = active
            self._transition(event)
            active.thread = threading.Thread(target=self._run_thread, args=(active,),
                                             name=f"daemon-{active.kind}")
            active.thread.start()

    def _cmd_pause(self, args: Any) -> dict:
        with self._lock:
            self._require(*ACTIVE, doing="pause")
            if self._active.kind == "hold":
                raise Refusal(ErrorCode.WRONG_STATE, f'{CANNOT_PAUSE} (hold {{"release": true}})')
            self._active.job.pause(args.immediate)
        return {"state": self.state.value, "pending": "pause now" if args.immediate
                else "pause at the end of the current move"}

    def _cmd_resume(self, _: Any) -> dict:
        with self._lock:
            self._require(S.PAUSED, doing="resume")
            self._active.job.resume()
        return {"state": self.state.value, "pending": "resume"}

    def _cmd_abort(self, _: Any) -> dict:
        with self._lock:
            self._require(*ACTIVE, doing="abort")
            self._active.job.abort()
        return {"state": self.state.value, "pending": "ramp down and stop"}

    def _cmd_estop(self, _: Any) -> dict:
        active = self._active
        unreached: list[str] = []
        if active is not None:  # first, before any lock: the supplies are zeroed from this thread
            unreached = active.job.estop() or []
        with self._lock:
            if self._active is not None and self._active is not active:  # started meanwhile
                active = self._active
                unreached = active.job.estop() or []
            self._transition("estop", reason="emergency stop")
            self.held = None
            for name in unreached:
                self._device(name, "fault", "e-stop could not be sent: link down (its own "
                             "watchdog or interlock must stop it)")
        if active is None:
            threading.Thread(target=self._make_safe_directly, name="daemon-estop").start()
        log.warning("EMERGENCY STOP")
        if active is None:
            zeroing = "directly (no run active)"
        elif unreached:
            zeroing = (f"sent to every device but {', '.join(unreached)} (link down: check that "
                       "supply by hand)")
        else:
            zeroing = "done: every device told to stop (supplies 0 A and off, coils off, arms held)"
        return {"state": self.state.value, "zeroing": zeroing, "unreached": unreached}

    def _cmd_reset(self, _: Any) -> dict:
        with self._lock:
            if self.state == S.IDLE:
                return {"state": "idle"}
            self._require(S.FAULTED, S.ESTOPPED, doing="reset")
            if self._active is not None:
                raise Refusal(ErrorCode.BUSY, "the run is still stopping; retry in a moment")
            self._transition("reset")
        return {"state": self.state.value}

    def _cmd_hold(self, args: Any) -> dict:
        """A manual hold (any rig), retargeted while one is on, released by `release` or by a
        target at the rig's rest (zero). Limits are checked here before anything moves: the
        target's, and the ramp's from what is held now (between the setpoints the stream last
        reported and the target it ramps to: the ramp's checks are linear or convex in its
        start); an arm pose's first ramp is checked in the stream process once the arms' joints
        are read, before they move."""
        with self._lock:
            active = self._active if self._active is not None and self._active.kind == "hold" else None
            if not args.release:
                self._require_safe("hold")
        request = None
        if not args.release:
            try:
                request = self.kind.hold(self.rig, args.target)
            except ConfigError as err:
                raise Refusal(ErrorCode.BAD_ARGS, f"hold: {err}") from None
        if active is not None and active.released:
            raise Refusal(ErrorCode.BUSY, "the hold is being released; retry in a moment")
        if request is None or request.at_rest:
            if active is not None:
                active.job.release(args.ramp_s)
                active.released = True
                self.held = None
            return {"hold": None, "released": active is not None,
                    "setpoints": [0.0] * len(self.channels)}
        if active is not None:
            starts = [s for s in (active.setpoints, active.commanded) if s is not None]
        else:
            starts = [np.zeros(len(self.channels))] if request.pose_now is None else []
        for start in starts:
            request.check_ramp(np.asarray(start, dtype=float), args.ramp_s)
        reply = {"hold": request.target, "channels": [c.name for c in self.channels],
                 "setpoints": request.setpoints.round(4).tolist()}
        with self._lock:
            if active is not None and self._active is active:
                active.job.retarget(request.target, request.setpoints, args.ramp_s)
                active.setpoints, self.held = request.setpoints, request.target
                active.info["target"] = request.target
                return reply
            self._require(S.IDLE, doing="hold")
            if self._active is not None:
                raise Refusal(ErrorCode.BUSY, "the last run is still stopping")
        # streamed by the stream process; this (the worker) waits until it streams or cannot start
        job = self._prepare(HoldPlan(rig=self.rig.rig.kind, target=request.target,
                                     ramp_s=args.ramp_s))
        active = _ActiveRun("hold", job, None, dict(job.info), setpoints=request.setpoints)
        with self._lock:
            if self.state != S.IDLE or self._active is not None or self._stop.is_set():
                raise Refusal(ErrorCode.WRONG_STATE, f"state changed to {self.state.value}")
            self.held = request.target
            self._activate(active, "hold")
        if not job.started.wait(HOLD_START_TIMEOUT_S):
            job.estop()  # still connecting: it must not switch on after hold has failed
        if not job.streaming:  # it could not start (a device, a limit at the arms): say why
            active.thread.join(HOLD_START_TIMEOUT_S)
            raise job.error or _start_error(job.result)
        for name in self.devices:
            self._device(name, "ok", "manual hold")
        return reply

    def _cmd_set_field(self, args: Any) -> dict:
        """The six-coil shorthand of `hold {"target": {"field_mT": ...}}` (zero releases)."""
        result = self._cmd_hold(HoldArgs(target={"field_mT": args.field_mT}, ramp_s=args.ramp_s))
        return {"field_mT": args.field_mT, "currents_A": result["setpoints"]}

    def _cmd_runs(self, args: Any) -> list[dict]:
        from rigctl.core.record import list_runs

        return list_runs(self.runs_dir, limit=args.limit)

    def _cmd_run(self, args: Any) -> dict:
        if "/" in args.run or args.run.startswith(".") or not (self.runs_dir / args.run).is_dir():
            raise Refusal(ErrorCode.UNKNOWN_RUN, f"no run {args.run!r} in {self.runs_dir}")
        from rigctl.core.record import describe_run

        return describe_run(self.runs_dir / args.run)

    # -- the run thread and its callbacks (called on the stream thread) -------------------------
    def _run_thread(self, active: _ActiveRun) -> None:
        if self.publisher is not None:
            self.publisher.reset_stream(self.rig.stream.rate_hz)
        summary = None
        try:
            summary = active.job.execute()
        except RigError as err:  # e.g. the stream process died: it said what it did about it
            log.error("the %s stopped: %s", active.kind, err)
            if active.kind == "plan" or getattr(active.job, "streaming", True):
                self._fault(err.device, str(err), type(err).__name__, active)
            # else a manual hold that never started: hold answers with the error
        except Exception as err:
            log.exception("the %s stopped with an unexpected error", active.kind)
            self._fault(None, f"internal error: {type(err).__name__}: {err}", "Internal", active)
        finally:
            with self._lock:
                self._active = None
                if active.kind == "hold":
                    self.held = None
                if summary is not None:
                    self.last_run = {"id": active.run_id, "plan_id": active.plan_id,
                                     **{k: v for k, v in summary.as_dict().items()
                                        if k in ("reached", "faults", "duration_s", "run")}}
                self._transition("finished")
                for name, device in self.devices.items():
                    if device["health"] == "ok":
                        self._device(name, "off", "safe: ramped down, output off")
                unsafe = [n for n in (summary.unsafe_devices if summary else []) if n in self.devices]
                for name in unsafe:
                    self._device(name, "unsafe", "may still carry current: not confirmed safe; "
                                 "made safe as soon as it answers (check it by hand)")
                self.unsafe.update(unsafe)
            if unsafe:
                threading.Thread(target=self._make_safe_when_reachable, name="daemon-rezero",
                                 daemon=True).start()
            self._agents_stop.set()
            self._wakeup.wake()

    def _make_safe_when_reachable(self) -> None:
        """Every REZERO_S, the rig's direct make-safe until each device a run could not confirm
        safe (its link was down: a Kepco BOP then holds its last setpoint) has been reached; no
        run starts meanwhile (`_require_safe`)."""
        while self.unsafe and not self._stop.wait(REZERO_S):
            result = self.kind.make_safe(self.rig)
            with self._lock:
                for name in list(self.unsafe):
                    if result.get(name, "not reached") is None:
                        self.unsafe.discard(name)
                        self._device(name, "off", "made safe once its link answered again")
                        log.warning("%s: made safe once its link answered again", name)

    def _require_safe(self, doing: str) -> None:
        if self.unsafe:
            raise Refusal(ErrorCode.WRONG_STATE,
                          f"cannot {doing}: {', '.join(sorted(self.unsafe))} may still carry "
                          "current (not confirmed safe); the daemon makes it safe as soon as it "
                          "answers: check its link")

    def _on_cycles(self, batch: CycleBatch) -> None:
        """Cycles a run in the stream process ran (`t` on `time.monotonic()`), about every 20 ms:
        one append for the publisher, so this thread holds the GIL for microseconds."""
        active = self._active
        if active is not None:
            active.sample, active.move = int(batch.sample[-1]), int(batch.move[-1])
            active.last_cycle = float(batch.t[-1])
            active.commanded = batch.commanded[-1]
        if self.publisher is not None:
            self.publisher.offer_cycles(replace(batch, t=batch.t - self.t0))

    def _on_frame(self, *frame: Any) -> None:
        """A camera frame from the stream process (`runhost._FrameTap`), on its reader thread."""
        if self.publisher is not None:
            self.publisher.publish_frame(*frame)

    def _on_run_state(self, run_state: Any, info: dict) -> None:
        value = run_state.value
        active = self._active
        if active is not None and active.run_id is None and active.job.record is not None:
            active.run_id = Path(active.job.record.path).name
        if value == "running" and active is not None:
            for name in self.devices:
                self._device(name, "ok", "streaming")
        if value == "faulted":
            if active is not None and active.kind == "hold" and not active.job.streaming:
                return  # a hold that could not start: `hold` answers with why, the state stays
            self._fault(info.get("device"), str(info.get("reason")), "DeviceFault", active)
            return
        event = RUN_EVENTS.get(value)
        if event is not None and event != "finished":
            self._transition(event, **info)

    def _fault(self, device: str | None, reason: str, kind: str, active: _ActiveRun | None) -> None:
        with self._lock:
            self.last_fault = {"device": device, "reason": reason, "kind": kind,
                               "run": active.run_id if active else None,
                               "t": round(time.monotonic() - self.t0, 3)}
            if device in self.devices:
                self._device(device, "fault", reason)
        if self.publisher is not None:
            self.publisher.publish_event(Topic.FAULT, device=device, reason=reason, kind=kind,
                                         run=active.run_id if active else None)
        self._transition("fault", device=device, reason=reason)

    def _device(self, name: str, health: str, detail: str) -> None:
        self.devices[name] = {**self.devices[name], "health": health, "detail": detail}

    def _sample_agents(self, active: _ActiveRun) -> None:
        """On an emulated rig: the emulator's ground truth, published as `agents` and recorded in
        the run's event log, AGENTS_HZ times a second while the run lasts (a closed-loop run's
        camera positions are the supervisor's, in its own events and the summary)."""
        from rigctl.emulators.backdoor import BackdoorClient

        self._agents_stop.clear()
        plan = active.job.plan
        expected = plan.expected if plan.kind == "global-moves" else None  # positions per move
        starts = [list(a.start) for a in plan.agents] if expected is not None else []
        shown = -1  # the move whose expected positions are shown
        try:
            with BackdoorClient(self.rig.emulation.backdoor, timeout_s=1.0) as backdoor:
                while not self._agents_stop.wait(1.0 / AGENTS_HZ) and self._active is active:
                    truth = backdoor.request("truth")["agents"]
                    move = active.move
                    exp = None
                    if expected is not None:
                        # -1 (ramping, holding, paused): the last move's target, the starts before
                        # the first; a closed loop's re-planned moves past the plan's: its goal
                        if move >= 0:
                            shown = min(move, len(expected) - 1)
                        exp = [list(map(float, p)) for p in
                               (expected[shown] if shown >= 0 else starts)]
                    tracked = [[round(float(x), 4) for x in p] for p in truth]
                    self.publisher.publish_agents(move, tracked, exp, "emulator ground truth")
                    if active.job.record is not None:
                        active.job.record.event("agents", move=move, tracked=tracked)
        except (RigError, OSError, ValueError) as err:
            log.info("agent sampling stopped: %s", err)

    def _make_safe_directly(self) -> None:
        """E-stop with no run active: open every actuator anew and make it safe (the rig kind's
        `make_safe`: supplies to 0 A and off, the board's coils stopped, the arms held); best
        effort."""
        for name, err in self.kind.make_safe(self.rig).items():
            if name not in self.devices:
                continue
            if err is None:
                self._device(name, "off", "e-stop: made safe directly")
            else:
                self._device(name, "fault", f"e-stop could not reach it: {err}")


def _request_id(body: bytes | None) -> Any:
    """A request's `id` for a reply given before the request is handled (None if it has none)."""
    return peek(body)[1] if body is not None and len(body) <= 64 * 1024 else None


def _envelope_end(frames: list[bytes]) -> int:
    """Where a ROUTER message's body starts: after the empty delimiter (REQ), or after the
    identity (a DEALER that sends none)."""
    try:
        return frames.index(b"", 1) + 1
    except ValueError:
        return 1


def _abort_quietly(active: _ActiveRun) -> None:
    """Abort on the way out; a run whose stream process is already gone was made safe by the
    host's reader (supplies zeroed over new connections), so there is nothing more to do."""
    try:
        active.job.abort()
    except RigError as err:
        log.warning("abort on shutdown: %s", err)


def _start_error(summary: Any) -> RigError:
    """Why a hold that never streamed ended, from its summary's first fault (as the error class
    the stream process named, so a limit is answered as a limit)."""
    if summary is not None and summary.refused:  # a limit where the actuators stand (the arms)
        return errors.LimitError(summary.refused)
    fault = summary.faults[0] if summary is not None and summary.faults else None
    if fault is None:
        return RigError(f"the manual hold did not start within {HOLD_START_TIMEOUT_S:g} s")
    error_class = getattr(errors, fault["kind"], None)
    if not (isinstance(error_class, type) and issubclass(error_class, RigError)):
        error_class = RigError
    return error_class(fault["reason"])


def _describe(err: ValidationError) -> str:
    problems = []
    for problem in err.errors():
        where = ".".join(str(p) for p in problem["loc"]) or "(top level)"
        problems.append(f"{where}: {problem['msg']}")
    return "; ".join(problems)
