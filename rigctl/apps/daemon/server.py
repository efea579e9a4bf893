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

`Daemon` is here: its life cycle (bind, serve, shut down) and the state its parts share. Each part
is a module of its own, and a base class of `Daemon`: the command thread and each request's path
to a reply (`requests`, with the replay cache in `replay`), the command handlers (`commands`),
the active run and what the stream process reports of it (`active_run`), the states and their
transition table (`states`); what it runs comes from a `RunFactory` (`plan_runs`).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from rigctl.apps.daemon.active_run import ActiveRun, RunWatch, _abort_quietly
from rigctl.apps.daemon.admission import REQUEST_RATE_HZ, Admission
from rigctl.apps.daemon.commands import Commands, _LoadedPlan
from rigctl.apps.daemon.goals import GoalPlanning
from rigctl.apps.daemon.keys import CurveServer
from rigctl.apps.daemon.messages import (
    HARD_MAX_MESSAGE_BYTES,
    Command,
    DaemonState,
    Topic,
    is_loopback_endpoint,
)
from rigctl.apps.daemon.plan_runs import PlanRuns, RunFactory
from rigctl.apps.daemon.replay import ReplayCache
from rigctl.apps.daemon.requests import LOAD_DEADLINE_S, RequestServer, _Loading, _Wakeup
from rigctl.apps.daemon.runhost import realtime_permitted
from rigctl.apps.daemon.sdnotify import SystemdNotifier
from rigctl.apps.daemon.states import RunStates
from rigctl.apps.daemon.telemetry import TelemetryPublisher, WindingEstimate
from rigctl.apps.daemon.teleop import TeleopCommands
from rigctl.core.config import CoilRig, RigConfig
from rigctl.core.errors import ConfigError
from rigctl.physics.thermal import Windings
from rigctl.rigs import rig_kind

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DaemonEndpoints:
    command: str
    telemetry: str
    events: str

    def as_dict(self) -> dict[str, Any]:
        return {"command": self.command, "data": self.telemetry, "events": self.events}


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


class Daemon(RequestServer, Commands, TeleopCommands, RunWatch, RunStates):
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
        self._state_info: dict[str, Any] = {}
        self.last_fault: dict[str, Any] | None = None
        self._active: ActiveRun | None = None
        self._plans: OrderedDict[str, _LoadedPlan] = OrderedDict()
        self._deliveries: deque[Callable[[], None]] = deque()
        self._replay = ReplayCache()
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="daemon-worker")
        self._loading: _Loading | None = None
        self.load_deadline_s = LOAD_DEADLINE_S
        self._wakeup = _Wakeup()
        self.admission = Admission(request_rate_hz)
        self._stop = threading.Event()
        self._shutdown_requested = threading.Event()
        self._serving = threading.Event()
        self._thread: threading.Thread | None = None
        self._router: zmq.Socket[bytes] | None = None
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
        self.held: dict[str, Any] | None = None  # the manual hold's target
        self.last_run: dict[str, Any] | None = None
        self.goals = GoalPlanning(self)  # plan_goals, and where the last run left the agents
        self._actuation = self._actuation_matrix()
        self._field_offset = None
        if self._actuation is not None:  # the field plot shows B = A I + an MPEM's Offset field
            from rigctl.physics.coils import field_offset

            assert isinstance(self.rig, CoilRig)  # it has an actuation matrix
            self._field_offset = field_offset(self.rig)[0:3]
        self._handlers: dict[Command, Callable[[Any], Any]] = {
            Command.PING: self._cmd_ping, Command.STATUS: self._cmd_status,
            Command.LOAD: self._cmd_load, Command.EXECUTE: self._cmd_execute,
            Command.PAUSE: self._cmd_pause, Command.RESUME: self._cmd_resume,
            Command.ABORT: self._cmd_abort, Command.ESTOP: self._cmd_estop,
            Command.RESET: self._cmd_reset, Command.HOLD: self._cmd_hold,
            Command.SET_FIELD: self._cmd_set_field,
            Command.RUNS: self._cmd_runs, Command.RUN: self._cmd_run,
            Command.TELEOP: self._cmd_teleop, Command.STEER: self._cmd_steer,
            Command.PLAN_GOALS: self.goals.command,
        }

    # -- life cycle -----------------------------------------------------------------------------
    def _actuation_matrix(self) -> np.ndarray | None:
        rig = self.rig
        if not isinstance(rig, CoilRig) or not rig.coils:  # a rig of coils fed by supplies
            return None
        from rigctl.physics.coils import actuation_matrix

        return actuation_matrix(rig)

    def start(self) -> DaemonEndpoints:
        """Bind every socket and start the telemetry thread; returns the bound endpoints."""
        command, telemetry, events = self._wanted
        secure = None
        server_key, allowed_keys = self._keys
        if server_key is not None and allowed_keys is not None:  # both or neither (__init__)
            self.curve = CurveServer(self.context, server_key, allowed_keys)
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
                actuation_matrix_T_per_A=self._actuation,
                field_offset_T=self._field_offset, currents_hz=self.currents_hz,
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
        self.goals.planner.close()
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



















































