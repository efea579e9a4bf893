"""Admission: the command thread's budget of requests per second, so that no number of clients
can take more than a bounded share of a core from the stream and from what runs beside it.

Measured (`bench/daemon.py`, status flood): twenty clients asking `status` as fast as they were
answered got 14,860 replies a second, and the command thread, at realtime priority just below the
stream, took a core to give them; the emulated supplies, the camera and everything else the
stream waits on shared the other, and the 1 kHz stream's late share went from 0.3 % to 46 %.

Control commands (`CONTROL`: e-stop, abort, pause, resume, reset, execute, load, hold,
set_field) are never held: an e-stop behind a flood is what the budget is for. Everything else
(status, ping, runs, run, and frames that are no request at all) spends a token from a bucket
refilled at `rate_hz` up to `burst`; with none left it waits in one queue, answered in arrival
order as tokens come, so clients share the budget evenly. A REQ client has one request in flight:
waiting for its reply costs it nothing, so a flood slows down instead of spinning. A client with
`per_client` requests waiting (a DEALER pipelining), or a queue of `max_waiting`, is answered
`busy` at once: memory stays bounded. A control command can so overtake a query sent before it
on the same DEALER socket; replies carry the request's `id`.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterator

MAX_BODY_BYTES = 4 * 1024 * 1024
"""Bodies larger than this are not parsed here (`messages.MAX_REQUEST_BYTES` refuses them)."""
CONTROL = frozenset({"estop", "abort", "pause", "resume", "reset", "execute", "load", "hold",
                     "set_field"})
REQUEST_RATE_HZ = 500.0
"""Queries answered per second at most (the daemon's `--request-rate`), over all clients. Each
costs the command thread, at realtime priority, 170-240 us of a core (a `status`, measured under a
flood: JSON, ZeroMQ, the poll); at 2000 a second that was half a core taken ahead of everything
but the stream, and the 1 kHz stream's late share rose 9.5 points under a 20-client flood with the
emulated devices at realtime priority as hardware of their own would be, 1.3 points at 500
(`bench/daemon.py --rig six-coil --emulator-realtime 45`). Telemetry (`rigctl watch`, the
`actuators`/`state` topics) is the way to follow a run at the stream's rate."""
BURST = 200
PER_CLIENT = 16
MAX_WAITING = 4096


def peek(payload: bytes) -> tuple[str | None, object]:
    """A request body's `cmd` and `id` (None for what it does not have, or is not a request)."""
    # imported here: the CLI reads this module's defaults without loading the wire models
    from rigctl.apps.daemon.messages import BadJson, decode_request

    try:
        data = decode_request(payload)
    except BadJson:
        return None, None
    if not isinstance(data, dict):
        return None, None
    cmd, request_id = data.get("cmd"), data.get("id")
    if not isinstance(request_id, (str, int)) or isinstance(request_id, bool):
        request_id = None
    return (cmd if isinstance(cmd, str) else None), request_id


_CONTROL_NAMES = tuple(name.encode() for name in sorted(CONTROL))


def _names_control(body: bytes) -> bool:
    """Whether `body` holds a control command's name at all: a flood's queries are then told from
    control commands without parsing them (a name spelled with JSON's `\\u` escapes is parsed)."""
    return b"\\u" in body or any(name in body for name in _CONTROL_NAMES)


class Admission:
    """The token bucket and the queue of requests waiting for a token."""

    def __init__(self, rate_hz: float = REQUEST_RATE_HZ, burst: int = BURST,
                 per_client: int = PER_CLIENT, max_waiting: int = MAX_WAITING,
                 now: float | None = None) -> None:
        if not rate_hz > 0:
            raise ValueError(f"the request rate must be > 0, got {rate_hz}")
        if burst < 1:
            raise ValueError(f"the burst must be at least one request, got {burst}")
        self.rate_hz, self.burst = float(rate_hz), float(burst)
        self.per_client, self.max_waiting = per_client, max_waiting
        self._tokens = self.burst
        self._at = time.monotonic() if now is None else now  # full at `now`
        self._waiting: deque[tuple[bytes, list[bytes]]] = deque()
        self._per_client: dict[bytes, int] = {}
        self.held = 0  # requests that waited for a token, since start
        self.refused = 0  # answered `busy` because too many waited

    def _refill(self, now: float) -> None:
        self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate_hz)
        self._at = now

    def offer(self, frames: list[bytes], client: bytes, body: bytes | None,
              now: float) -> str:
        """What to do with one request now: "answer", "wait" (queued) or "busy"."""
        self._refill(now)
        if not self._waiting and self._tokens >= 1.0:
            self._tokens -= 1.0
            return "answer"
        if body is not None and len(body) <= MAX_BODY_BYTES and _names_control(body) \
                and peek(body)[0] in CONTROL:
            return "answer"
        if (self._per_client.get(client, 0) >= self.per_client
                or len(self._waiting) >= self.max_waiting):
            self.refused += 1
            return "busy"
        self._waiting.append((client, frames))
        self._per_client[client] = self._per_client.get(client, 0) + 1
        self.held += 1
        return "wait"

    def ready(self, now: float) -> Iterator[list[bytes]]:
        """The waiting requests whose turn has come, oldest first (each spends a token)."""
        self._refill(now)
        while self._waiting and self._tokens >= 1.0:
            self._tokens -= 1.0
            client, frames = self._waiting.popleft()
            left = self._per_client[client] - 1
            if left:
                self._per_client[client] = left
            else:
                del self._per_client[client]
            yield frames

    def next_s(self, now: float) -> float | None:
        """Seconds until the next waiting request may be answered; None when none waits."""
        if not self._waiting:
            return None
        self._refill(now)
        return max(0.0, (1.0 - self._tokens) / self.rate_hz)

    @property
    def waiting(self) -> int:
        return len(self._waiting)
