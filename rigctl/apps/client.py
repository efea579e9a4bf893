"""The Python client for operator scripts: `from rigctl.apps.client import Rig`.

Requests follow the lazy-pirate pattern: send on a REQ socket, wait for the reply with a timeout
(the socket's send and receive timeouts: a poll before each receive cost ~10 us of a ~170 us round
trip), and on silence close the socket (LINGER 0), open a new one and send again, a bounded number
of times, then raise `DaemonUnreachable`. A retried request keeps its id, and the daemon answers a
repeated id from its cache of recent replies, so a retried `execute` cannot start a second run.

    with Rig("tcp://127.0.0.1:7810") as rig:
        plan_id = rig.load(json.load(open("plan.json")))
        rig.execute(plan_id)
        with rig.telemetry(["state", "actuators"]) as feed:
            for msg in feed:
                ...

A refused command raises `CommandRefused` with the daemon's error code and message.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import orjson
import zmq

from rigctl.apps.daemon.keys import load_public, secure_client
from rigctl.apps.daemon.messages import (
    DATA_TOPICS,
    DEFAULT_COMMAND_ENDPOINT,
    EVENT_TOPICS,
    Topic,
    parse_telemetry,
    read_json,
)
from rigctl.core.errors import Disconnected, RigError

log = logging.getLogger(__name__)


class CommandRefused(RigError):
    """The daemon refused a request; `code` is one of `rigctl.apps.daemon.messages.ErrorCode`'s values."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.reason = message


class DaemonUnreachable(Disconnected):
    """No reply after every retry: the daemon is down, unreachable, or refuses our key."""


class _Curve:
    def __init__(self, server_key: str | Path | None, client_key: str | Path | None) -> None:
        if (server_key is None) != (client_key is None):
            raise ValueError("CURVE needs both server_key (.key) and client_key (.key_secret)")
        self.server_public = load_public(server_key) if server_key is not None else None
        self.client_key = client_key

    def apply(self, sock: zmq.Socket) -> None:
        if self.server_public is not None and self.client_key is not None:  # both or neither
            secure_client(sock, self.server_public, self.client_key)


class Rig:
    """A connection to `rigctl daemon`. Timeouts in s; `retries` extra attempts per request."""

    def __init__(
        self,
        endpoint: str = DEFAULT_COMMAND_ENDPOINT,
        *,
        timeout_s: float = 2.0,
        retries: int = 2,
        server_key: str | Path | None = None,
        client_key: str | Path | None = None,
        context: zmq.Context | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self.retries = retries
        self._curve = _Curve(server_key, client_key)
        self._own_context = context is None
        self.context = context or zmq.Context()
        self._sock: zmq.Socket | None = None
        self._timeouts_ms: tuple[int, int] | None = None  # the socket's (send, receive) timeouts
        self._ids = itertools.count()
        self._prefix = f"{os.getpid():x}-{os.urandom(3).hex()}"

    # -- transport ------------------------------------------------------------------------------
    def _open(self) -> zmq.Socket:
        self._timeouts_ms = None
        sock = self.context.socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        # a request waits for a connection that completed (the CURVE handshake included) instead
        # of being queued for a peer that may never take it; the send timeout bounds the wait
        sock.setsockopt(zmq.IMMEDIATE, 1)
        self._curve.apply(sock)
        sock.connect(self.endpoint)
        return sock

    def _exchange(self, payload: bytes, timeout_ms: int, expect_id: str | None) -> dict | None:
        """Send `payload` and return its reply, or None when no connection took the request, or
        no reply came, within `timeout_ms` in all. A reply to another id (none can come: a REQ
        socket takes one reply per request, and each attempt has a socket of its own) counts as
        none, rather than leaving the socket waiting for a reply it will never get."""
        assert self._sock is not None
        start = time.monotonic()
        try:
            self._timeouts(timeout_ms, timeout_ms)
            self._sock.send(payload)
            waited_ms = int(1000 * (time.monotonic() - start))
            if waited_ms:  # the send waited for a connection: the reply has what is left
                self._timeouts(timeout_ms, max(1, timeout_ms - waited_ms))
            reply = read_json(self._sock.recv())
        except zmq.Again:
            return None
        if expect_id is not None and reply.get("id") != expect_id:
            log.warning("a reply for %r came to the request %r", reply.get("id"), expect_id)
            return None
        return reply

    def _timeouts(self, send_ms: int, receive_ms: int) -> None:
        """Set the socket's timeouts, only when they change: two `setsockopt` a request took 51
        us at p50 with the caches cold, as a `status` after an idle 5 ms finds them."""
        if self._timeouts_ms != (send_ms, receive_ms):
            self._sock.setsockopt(zmq.SNDTIMEO, send_ms)
            self._sock.setsockopt(zmq.RCVTIMEO, receive_ms)
            self._timeouts_ms = (send_ms, receive_ms)

    def _drop(self) -> None:
        if self._sock is not None:
            self._sock.close(linger=0)
            self._sock = None

    def request(self, cmd: str, *, timeout_s: float | None = None, **args: Any) -> Any:
        """Send one command and return its `result`; CommandRefused or DaemonUnreachable."""
        request_id = f"{self._prefix}-{next(self._ids)}"
        payload = (orjson.dumps({"id": request_id, "cmd": cmd, "args": {}}) if not args
                   else json.dumps({"id": request_id, "cmd": cmd, "args": args}).encode())
        reply = self.request_raw(payload, timeout_s=timeout_s, expect_id=request_id)
        if not reply.get("ok"):
            error = reply.get("error") or {}
            raise CommandRefused(str(error.get("code")), str(error.get("message")))
        return reply.get("result")

    def request_raw(self, payload: bytes, *, timeout_s: float | None = None,
                    expect_id: str | None = None) -> dict:
        """Send raw bytes (tests use this for malformed input) and return the decoded reply."""
        timeout_ms = int(1000 * (self.timeout_s if timeout_s is None else timeout_s))
        for attempt in range(self.retries + 1):
            if self._sock is None:
                self._sock = self._open()
            reply = self._exchange(payload, timeout_ms, expect_id)
            if reply is not None:
                return reply
            log.warning("no reply from %s within %d ms (attempt %d of %d)", self.endpoint,
                        timeout_ms, attempt + 1, self.retries + 1)
            self._drop()
        raise DaemonUnreachable(
            f"no reply from the daemon at {self.endpoint} after {self.retries + 1} attempts "
            f"of {timeout_ms} ms (is it running? is this client's key allowed?)",
            device="daemon")

    def close(self) -> None:
        self._drop()
        if self._own_context:
            self.context.term()

    def __enter__(self) -> "Rig":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- commands -------------------------------------------------------------------------------
    def ping(self) -> dict:
        return self.request("ping")

    def status(self) -> dict:
        return self.request("status")

    def load(self, plan: dict) -> str:
        """Validate and check a plan on the daemon; returns its plan_id."""
        return self.request("load", plan=plan)["plan_id"]

    def execute(self, plan_id: str) -> dict:
        return self.request("execute", plan_id=plan_id)

    def pause(self, immediate: bool = False) -> dict:
        return self.request("pause", immediate=immediate)

    def resume(self) -> dict:
        return self.request("resume")

    def abort(self) -> dict:
        return self.request("abort")

    def estop(self) -> dict:
        return self.request("estop")

    def reset(self) -> dict:
        return self.request("reset")

    def hold(self, target: dict, ramp_s: float = 0.1) -> dict:
        """Hold the rig at `target` (`{"field_mT": [3]}`, `{"drive": [4]}`, `{"joints_rad":
        [[7], [7]]}`), reached by a straight ramp of `ramp_s`; again to retarget."""
        return self.request("hold", target=target, ramp_s=ramp_s)

    def release(self, ramp_s: float = 0.1) -> dict:
        """End the manual hold: ramp to the rig's rest (the arms stay where they are)."""
        return self.request("hold", release=True, ramp_s=ramp_s)

    def set_field(self, field_mT: Iterable[float], ramp_s: float = 0.1) -> dict:
        return self.request("set_field", field_mT=[float(b) for b in field_mT], ramp_s=ramp_s)

    def teleop(self, mode: str | None = None) -> dict[str, Any]:
        """Start steering by hand (docs/teleoperation.md): the rig's inputs, their units and
        ranges. Then `steer` every ~50 ms while the input is held; `end_teleop` (or `abort`)."""
        args: dict[str, Any] = {} if mode is None else {"mode": mode}
        return self.request("teleop", **args)

    def steer(self, **values: float) -> dict:
        """The operator's input now (`heading_deg=.., speed=..` rolling, `heading_deg=..,
        drive=..` on the coil board); none: let go. It counts for 200 ms in the daemon's stream
        (the dead-man): send it again while the input is held."""
        return self.request("steer", input={k: float(v) for k, v in values.items()} or None)

    def end_teleop(self) -> dict:
        """Let go, bring the rig to its rest and end the session."""
        return self.request("teleop", end=True)

    def runs(self, limit: int = 20) -> list[dict]:
        return self.request("runs", limit=limit)

    def plan_goals(self, goals: dict[int, Iterable[float]], *, px: bool = False, seed: int = 0,
                   budget_s: float = 5.0, tolerance_mm: float | None = None) -> dict:
        """Plan the agents from where the daemon last tracked them to `goals` (agent index ->
        (x, y) in mm, or in camera pixels with `px`; an agent left out keeps its place) and load
        the plan (docs/click-a-goal.md): its `plan_id` for `execute`, the plan, its paths.
        CommandRefused `unreachable` says why there is none. Waits for the planner: the budget
        and its start."""
        unit = "px" if px else "mm"
        args: dict[str, Any] = {"goals": [{"agent": int(i), unit: [float(v) for v in g]}
                                          for i, g in goals.items()],
                                "seed": seed, "budget_s": budget_s}
        if tolerance_mm is not None:
            args["tolerance_mm"] = tolerance_mm
        return self.request("plan_goals", timeout_s=max(self.timeout_s, budget_s + 35.0), **args)

    def run(self, run_id: str) -> dict:
        return self.request("run", run=run_id)

    def wait_state(self, *states: str, timeout_s: float = 30.0) -> dict:
        """Poll `status` until the daemon is in one of `states`; returns that status."""
        deadline = time.monotonic() + timeout_s
        while True:
            status = self.status()
            if status["state"] in states:
                return status
            if time.monotonic() > deadline:
                raise TimeoutError(f"daemon still {status['state']} after {timeout_s} s, "
                                   f"waiting for {' or '.join(states)}")
            time.sleep(0.02)

    def telemetry(self, topics: Iterable[str] | None = None) -> "Telemetry":
        """Subscribe to telemetry topics (all by default); endpoints come from `ping`."""
        endpoints = self.ping()["telemetry"]
        return Telemetry(endpoints["data"], endpoints["events"], topics, context=self.context,
                         curve=self._curve)


class Telemetry:
    """A subscription to both telemetry sockets. Iterate, or `receive(timeout_s)`; messages are
    the pydantic models of `rigctl.apps.daemon.messages`. `lost` counts sequence gaps per topic."""

    def __init__(self, data_endpoint: str, events_endpoint: str,
                 topics: Iterable[str] | None = None, *, context: zmq.Context | None = None,
                 curve: _Curve | None = None, receive_hwm: int = 100_000) -> None:
        wanted = {Topic(t) for t in topics} if topics is not None else set(Topic)
        self._own_context = context is None
        self.context = context or zmq.Context()
        self.sockets: list[zmq.Socket] = []
        for endpoint, group in ((data_endpoint, DATA_TOPICS), (events_endpoint, EVENT_TOPICS)):
            chosen = wanted & group
            if not chosen:
                continue
            sock = self.context.socket(zmq.SUB)
            sock.setsockopt(zmq.LINGER, 0)
            sock.setsockopt(zmq.RCVHWM, receive_hwm)
            if curve is not None:
                curve.apply(sock)
            for topic in chosen:
                sock.setsockopt(zmq.SUBSCRIBE, topic.value.encode())
            sock.connect(endpoint)
            self.sockets.append(sock)
        self._poller = zmq.Poller()
        for sock in self.sockets:
            self._poller.register(sock, zmq.POLLIN)
        self._next_seq: dict[str, int] = {}
        self.lost: dict[str, int] = {}
        self.received: dict[str, int] = {}

    def receive(self, timeout_s: float = 1.0):
        """The next message, or None after `timeout_s` of silence."""
        ready = dict(self._poller.poll(int(timeout_s * 1000)))
        for sock in self.sockets:
            if sock in ready:
                topic, payload = sock.recv_multipart()
                msg = parse_telemetry(payload)
                name = topic.decode()
                expected = self._next_seq.get(name)
                if expected is not None and msg.seq > expected:
                    self.lost[name] = self.lost.get(name, 0) + msg.seq - expected
                self._next_seq[name] = msg.seq + 1
                self.received[name] = self.received.get(name, 0) + 1
                return msg
        return None

    def __iter__(self) -> Iterator:
        while True:
            msg = self.receive(timeout_s=3600.0)
            if msg is not None:
                yield msg

    def close(self) -> None:
        for sock in self.sockets:
            sock.close(linger=0)
        self.sockets = []
        if self._own_context:
            self.context.term()

    def __enter__(self) -> "Telemetry":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
