"""The daemon's replay cache: a request repeated (the same id and body within REPLAY_WINDOW_S)
gets the first reply again instead of running twice, which makes a client's lazy-pirate retries
safe; a repeat that arrives while the first is still being worked on is answered with it."""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from collections.abc import Callable

from rigctl.apps.daemon.messages import Command, Reply, Request

REPLAY_WINDOW_S = 60.0
REPLAY_CACHE = 256
NOT_REPLAYED = (Command.PING, Command.STATUS, Command.ESTOP, Command.RUNS, Command.RUN)
"""Read-only, or always carried out (an e-stop)."""


def replay_key(request: Request, cmd: Command, payload: bytes) -> bytes | None:
    """The key a request is replayed by (None: it never is)."""
    if cmd in NOT_REPLAYED:
        return None
    if not isinstance(request.id, str) or len(request.id) < 8:
        return None  # only ids that look unique; short ids are likely reused
    return hashlib.sha256(payload).digest()


class ReplayCache:
    """Replies by `replay_key`, the newest REPLAY_CACHE of the last REPLAY_WINDOW_S; on the
    command thread only."""

    def __init__(self) -> None:
        self._entries: OrderedDict[bytes, tuple[float, Reply | None, list[list[bytes]]]] = OrderedDict()

    def seen(self, key: bytes, envelope: list[bytes],
             send: Callable[[list[bytes], Reply], None]) -> bool:
        """True if `key`'s request was seen before: `envelope` is answered with its reply now
        (`send`), or when it is ready; False (and remembered) if it is new."""
        now = time.monotonic()
        entries = self._entries
        while entries and (len(entries) > REPLAY_CACHE
                           or next(iter(entries.values()))[0] < now - REPLAY_WINDOW_S):
            entries.popitem(last=False)
        entry = entries.get(key)
        if entry is None:
            entries[key] = (now, None, [envelope])
            return False
        _, reply, waiting = entry
        if reply is None:
            waiting.append(envelope)  # still being worked on: answer this one too
        else:
            send(envelope, reply)
        return True

    def answered(self, key: bytes | None, reply: Reply, envelope: list[bytes]) -> list[list[bytes]]:
        """`reply` is the answer to `key`'s request (from `envelope`): kept for repeats; every
        envelope that asked for it so far."""
        if key is None or key not in self._entries:
            return [envelope]
        t, _, waiting = self._entries[key]
        self._entries[key] = (t, reply, [])
        return waiting or [envelope]
