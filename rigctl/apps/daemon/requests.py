"""The daemon's command thread: the ROUTER socket's loop (`serve_forever`), and each request's way
from bytes to a reply: admission (`rigctl.apps.daemon.admission`), the quick path for a bare
`status` or `estop`, decoding and checking, the replay cache (`rigctl.apps.daemon.replay`), and
the dispatch to a command handler, here, on the worker thread or on a `load` thread of its own."""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import orjson
import zmq
from pydantic import ValidationError

from rigctl.apps.daemon.admission import peek
from rigctl.apps.daemon.messages import (
    COMMAND_ARGS,
    MAX_REQUEST_BYTES,
    STATE_HEARTBEAT_S,
    BadJson,
    Command,
    ErrorCode,
    Reply,
    Request,
    decode_request,
    error_reply,
    ok_reply,
)
from rigctl.apps.daemon.parts import DaemonParts
from rigctl.apps.daemon.replay import replay_key
from rigctl.apps.daemon.runhost import make_realtime
from rigctl.apps.daemon.states import Refusal, S
from rigctl.core.errors import LimitError, PlanError, RigError

log = logging.getLogger(__name__)

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



class RequestServer(DaemonParts):
    """The `Daemon`'s command thread: its socket (`_router`), admission, replay cache, worker and
    `load` thread, and the replies they finish."""

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
        assert self.endpoints is not None  # bound by start()
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
                        if not cast(int, self._router.getsockopt(zmq.EVENTS)) & zmq.POLLIN:
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

    # -- requests -------------------------------------------------------------------------------
    def _admit(self, received: list[Any]) -> None:
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
        key = self._replay_key(request, cmd, payload)
        if key is not None and self._replay.seen(key, envelope, self._send):
            return
        self._dispatch(cmd, args, request.id, envelope, key)

    def _answer_quickly(self, envelope: list[bytes], text_id: bytes | None, number_id: bytes | None,
                        cmd: bytes) -> bool:
        """A `QUICK_REQUEST` answered; False (the general path answers) if its handler failed."""
        try:
            result = getattr(self, QUICK_COMMANDS[cmd])(None)
        except Exception:  # noqa: BLE001 - the general path answers with the error
            log.exception("%s failed on the quick path; answering through the general one",
                          cmd.decode())
            return False
        assert text_id is not None or number_id is not None  # QUICK_REQUEST's id is one of them
        request_id = text_id.decode() if text_id is not None else int(number_id or b"")
        self._send_json(envelope, {"id": request_id, "ok": True, "result": result, "error": None})
        return True

    def _replay_key(self, request: Request, cmd: Command, payload: bytes) -> bytes | None:
        return replay_key(request, cmd, payload)

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
            for target in self._replay.answered(replay_key, reply, envelope):
                self._send(target, reply)

        if cmd is Command.LOAD:
            self._start_load(answer, deliver, request_id)
        elif cmd is Command.PLAN_GOALS:  # seconds of planning: a thread of its own (goals.py)
            self.goals.answer_on_thread(answer, deliver, request_id)
        elif cmd in (Command.RUNS, Command.RUN, Command.HOLD, Command.SET_FIELD, Command.TELEOP):
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

    def _send_json(self, envelope: list[bytes], reply: dict[str, Any]) -> None:
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



def _describe(err: ValidationError) -> str:
    problems = []
    for problem in err.errors():
        where = ".".join(str(p) for p in problem["loc"]) or "(top level)"
        problems.append(f"{where}: {problem['msg']}")
    return "; ".join(problems)

