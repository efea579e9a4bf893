"""The control endpoint of a local run (`rigctl execute`): the same ZeroMQ requests as the daemon's
for what a run can do (`ping`, `status`, `pause`, `resume`, `abort`, `estop`), on loopback, named
in the rig's lock (`rigctl.rigs.owner`) so that `rigctl estop --rig RIG.toml` and the `Rig` client reach
a local run exactly as they reach a daemon.

A REP socket on its own thread: a request is answered at once (an e-stop is taken on this thread,
as the daemon takes it, and the stream thread finishes it); anything malformed gets an error
reply and the run goes on.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zmq
from pydantic import ValidationError

from rigctl.daemon.messages import (
    COMMAND_ARGS,
    Command,
    ErrorCode,
    Request,
    error_reply,
    ok_reply,
)
from rigctl.errors import RigError

log = logging.getLogger(__name__)

RUN_COMMANDS = (Command.PING, Command.STATUS, Command.PAUSE, Command.RESUME, Command.ABORT,
                Command.ESTOP)
POLL_MS = 50


class LocalControl:
    """Serve `run`'s control on `tcp://127.0.0.1:<free port>` from `start()` to `close()`."""

    def __init__(self, run: Any, owner: str = "rigctl execute") -> None:
        self.run = run
        self.owner = owner
        self.started = time.monotonic()
        self._context = zmq.Context.instance()
        self._sock = self._context.socket(zmq.REP)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.bind("tcp://127.0.0.1:0")
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="run-control", daemon=True)

    def start(self) -> LocalControl:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._sock.close(linger=0)

    def __enter__(self) -> LocalControl:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self._sock.poll(POLL_MS, zmq.POLLIN):
                continue
            payload = self._sock.recv()
            try:
                reply = self._answer(payload)
            except Exception as err:  # never the run's end: say so and go on
                log.exception("control request failed")
                reply = error_reply(None, ErrorCode.INTERNAL, f"internal error: {err}")
            self._sock.send(reply.model_dump_json().encode())

    def _answer(self, payload: bytes):
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
                run.pause(immediate=args.immediate)
            elif cmd == Command.RESUME:
                run.resume()
            elif cmd == Command.ABORT:
                run.abort()
            elif cmd == Command.ESTOP:
                unreached = run.estop()
                return ok_reply(request.id, {"state": "estopped", "unreached": unreached})
        except RigError as err:
            return error_reply(request.id, ErrorCode.WRONG_STATE, str(err))
        return ok_reply(request.id, self.status())

    def status(self) -> dict:
        run = self.run
        state, info = run.state.value, run.state_info
        ended = state in ("faulted", "estopped", "aborted", "done")
        fault = {"device": info.get("device"), "reason": info.get("reason")} if state == "faulted" \
            else None
        return {"state": state, "reason": info.get("reason"), "owner": self.owner,
                "rig": run.rig.rig.kind, "run": None if ended else dict(run.info),
                "last_fault": fault, "uptime_s": round(time.monotonic() - self.started, 3)}
