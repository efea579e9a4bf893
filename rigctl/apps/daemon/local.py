"""The control endpoint of a local run (`rigctl execute`): the same ZeroMQ requests as the daemon's
for what a run can do (`ping`, `status`, `pause`, `resume`, `abort`, `estop`), on loopback, named
in the rig's lock (`rigctl.rigs.owner`) so that `rigctl estop --rig RIG.toml` and the `Rig` client reach
a local run exactly as they reach a daemon; and the daemon's telemetry (`state`, `fault`,
`actuators`, `stream`) on two PUB sockets that `ping` names, so `rigctl watch` and an operator's
subscriber see a local run as they see the daemon's.

Its replies have the daemon's shapes (docs/daemon-protocol.md): `status` answers with the daemon's
keys and states (a run starting is `running`, one that ended `idle`), `ping` with the protocol,
the pid and the telemetry endpoints, `pause`, `resume` and `abort` with `{"state", "pending"}`,
`estop` with `{"state", "zeroing", "unreached"}`; `owner` says who answers. A client, `rigctl
status` first, reads a local run as it reads the daemon.

A REP socket on its own thread: a request is answered at once (an e-stop is taken on this thread,
as the daemon takes it, and the stream thread finishes it); anything malformed gets an error
reply and the run goes on. The stream thread only appends each cycle to a deque; this thread hands
them to the publisher in batches, as the daemon's reader of its stream process does.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import zmq
from pydantic import ValidationError

from rigctl.apps.daemon.messages import (
    COMMAND_ARGS,
    PROTOCOL,
    Command,
    ErrorCode,
    PauseArgs,
    Reply,
    Request,
    Topic,
    error_reply,
    ok_reply,
)
from rigctl.apps.daemon.telemetry import CycleBatch, TelemetryPublisher
from rigctl.core.errors import RigError
from rigctl.rigs import rig_kind

log = logging.getLogger(__name__)

RUN_COMMANDS = (Command.PING, Command.STATUS, Command.PAUSE, Command.RESUME, Command.ABORT,
                Command.ESTOP)
POLL_MS = 10  # also how often the stream's cycles go to the publisher
# a run's states as the daemon reports them: one being started (agents placed, devices
# connected) is running, as the daemon's is from `execute` on; one that ended is idle
DAEMON_STATE = {"prepared": "running", "done": "idle", "aborted": "idle"}
ENDED = ("faulted", "estopped", "aborted", "done")  # the run's own states that end it
PENDING = {Command.PAUSE: "pause at the end of the current move", Command.RESUME: "resume",
           Command.ABORT: "ramp down and stop"}


class LocalControl:
    """Serve `run`'s control on `tcp://127.0.0.1:<free port>` from `start()` to `close()`."""

    def __init__(self, run: Any, owner: str = "rigctl execute") -> None:
        self.run = run
        self.owner = owner
        self.started = time.monotonic()
        self._context: zmq.Context[zmq.Socket[bytes]] = zmq.Context.instance()
        self._sock = self._context.socket(zmq.REP)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.bind("tcp://127.0.0.1:0")
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.publisher = TelemetryPublisher(
            self._context, "tcp://127.0.0.1:0", "tcp://127.0.0.1:0",
            channels=rig_kind(run.rig.rig.kind).channels(run.rig), clock_origin=self.started)
        self._cycles: deque[list[Any]] = deque()  # appended by the stream thread, drained by this one
        self._streaming = False
        self._at = (-1, -1)  # the last cycle's (sample, move), set by the stream thread
        self._hook(run)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="run-control", daemon=True)

    def _hook(self, run: Any) -> None:
        """The run's cycles and states, also to the publisher (the run's own hooks still called)."""
        on_cycle, on_state = run.on_cycle, run.on_state

        def cycle(sample: int, move: int, commanded: np.ndarray, measured: np.ndarray) -> None:
            if on_cycle is not None:
                on_cycle(sample, move, commanded, measured)
            self._at = (sample, move)  # one tuple: `status` reads both from the same cycle
            self._cycles.append(CycleBatch.row(time.monotonic() - self.started, sample, move,
                                               commanded, measured, run.stream_loop.last_error_s))

        def state(run_state: Any, info: dict[str, Any]) -> None:
            if on_state is not None:
                on_state(run_state, info)
            try:  # telemetry is for watchers: nothing here may end the run
                self._publish_state(run, run_state.value, info)
            except Exception:
                log.exception("state telemetry failed")

        run.on_cycle, run.on_state = cycle, state

    def _publish_state(self, run: Any, state: str, info: dict[str, Any]) -> None:
        record = getattr(run, "record", None)
        name = str(record.path) if record is not None else None
        if state == "faulted":
            self.publisher.publish_event(Topic.FAULT, device=info.get("device"),
                                         reason=str(info.get("reason")), kind="DeviceFault",
                                         run=name)
        self.publisher.publish_event(Topic.STATE, state=DAEMON_STATE.get(state, state), run=name,
                                     device=info.get("device"), reason=info.get("reason"))

    def _hand_over_cycles(self) -> None:
        cycles = [self._cycles.popleft() for _ in range(len(self._cycles))]
        if cycles:
            if not self._streaming:  # period-error statistics from the stream's first cycle on
                self._streaming = True
                self.publisher.reset_stream(self.run.stream_loop.rate_hz)
            self.publisher.offer_cycles(CycleBatch.from_rows(cycles))

    def start(self) -> LocalControl:
        self.publisher.start()
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._sock.close(linger=0)
        self._hand_over_cycles()
        self.publisher.stop()

    def __enter__(self) -> LocalControl:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            self._hand_over_cycles()
            if not self._sock.poll(POLL_MS, zmq.POLLIN):
                continue
            payload = self._sock.recv()
            try:
                reply = self._answer(payload)
            except Exception as err:  # never the run's end: say so and go on
                log.exception("control request failed")
                reply = error_reply(None, ErrorCode.INTERNAL, f"internal error: {err}")
            self._sock.send(reply.model_dump_json().encode())

    def _answer(self, payload: bytes) -> Reply:
        try:
            request = Request.model_validate_json(payload)
        except ValidationError as err:
            return error_reply(None, ErrorCode.BAD_REQUEST, f"not a request: {err.errors()[0]['msg']}")
        try:
            cmd = Command(request.cmd)
        except ValueError:
            cmd = None
        if cmd not in RUN_COMMANDS:
            names = ", ".join(c.value for c in RUN_COMMANDS)
            return error_reply(request.id, ErrorCode.UNKNOWN_COMMAND,
                               f"a local run answers {names}; {request.cmd!r} needs a daemon")
        try:
            args = COMMAND_ARGS[cmd].model_validate(request.args)
        except ValidationError as err:
            return error_reply(request.id, ErrorCode.BAD_ARGS, str(err.errors()[0]["msg"]))
        run = self.run
        try:
            if cmd == Command.PAUSE:
                run.pause(immediate=isinstance(args, PauseArgs) and args.immediate)
            elif cmd == Command.RESUME:
                run.resume()
            elif cmd == Command.ABORT:
                run.abort()
            elif cmd == Command.ESTOP:
                unreached = run.estop()
                zeroing = (f"sent to every device but {', '.join(unreached)} (link down: check "
                           "it by hand)" if unreached else "done: every device told to stop")
                return ok_reply(request.id, {"state": "estopped", "zeroing": zeroing,
                                             "unreached": unreached})
        except RigError as err:
            return error_reply(request.id, ErrorCode.WRONG_STATE, str(err))
        if cmd == Command.PING:
            return ok_reply(request.id, self.ping())
        if cmd == Command.STATUS:
            return ok_reply(request.id, self.status())
        pending = "pause now" if isinstance(args, PauseArgs) and args.immediate else PENDING[cmd]
        return ok_reply(request.id, {"state": self.status()["state"], "pending": pending})

    def _endpoints(self) -> dict[str, Any]:
        return {"command": self.endpoint, "data": self.publisher.data_endpoint,
                "events": self.publisher.events_endpoint}

    def ping(self) -> dict[str, Any]:
        """The daemon's `ping`: the protocol, this process, where its telemetry is."""
        return {"protocol": PROTOCOL, "pid": os.getpid(), "telemetry": self._endpoints(),
                "owner": self.owner}

    def status(self) -> dict[str, Any]:
        """The daemon's `status` (docs/daemon-protocol.md), of the one run this process makes:
        `run` while it is on (`sample` and `move` of the last cycle streamed, -1 before the
        first), `last_run` from its record's summary once it ended; no plans kept, no manual
        hold. Also `owner` and `telemetry` (what `ping` says)."""
        run = self.run
        state, info = run.state.value, run.state_info
        record = getattr(run, "record", None)
        last_run = _last_run(record) if state in ENDED else None
        # done or aborted, its summary not written yet: still stopping, and as the daemon's run
        # it is running until then (idle comes with `last_run`)
        stopping = state in ("done", "aborted") and last_run is None
        ended = state in ENDED and not stopping
        shown = "running" if stopping else DAEMON_STATE.get(state, state)
        fault = {"device": info.get("device"), "reason": info.get("reason")} if state == "faulted" \
            else None
        faulty = info.get("device") if state == "faulted" else None
        devices = [{"name": d.name, "url": d.url, "kind": d.kind,
                    "health": "fault" if d.name == faulty else "ok",
                    "detail": info.get("reason") if d.name == faulty else f"in use by {self.owner}"}
                   for d in rig_kind(run.rig.rig.kind).devices(run.rig)]
        run_id = Path(record.path).name if record is not None else None
        sample, move = self._at
        return {"state": shown, "device": info.get("device"),
                "reason": info.get("reason"),
                "rig": {"name": run.rig.rig.name, "kind": run.rig.rig.kind,
                        "emulated": run.rig.emulated},
                "run": None if ended else {"kind": "plan", "id": run_id, "plan_id": None,
                                           "sample": sample, "move": move, **run.info},
                "last_run": last_run,
                "plans": [], "devices": devices, "last_fault": fault, "hold": None,
                "manual_field_mT": None,
                "uptime_s": round(time.monotonic() - self.started, 3),
                "owner": self.owner, "telemetry": self._endpoints()}


def _last_run(record: Any) -> dict[str, Any] | None:
    """What the daemon's `last_run` says of a run, from its record's summary (None until the
    run has written it: it is written last)."""
    try:
        summary = json.loads((Path(record.path) / "summary.json").read_text())
    except (AttributeError, OSError, ValueError):
        return None
    return {"id": Path(record.path).name, "plan_id": None,
            **{k: v for k, v in summary.items() if k in ("reached", "faults", "duration_s", "run")}}
