"""The operator's requests to a running program, from any thread: pause (at the end of the
present move, or at once), resume, abort. The program reads them on the stream thread and decides
when each takes effect; `wake` (the stream loop's) makes the next cycle leave at once."""

from __future__ import annotations

import threading
from collections.abc import Callable


class Requests:
    """`pause_wanted`, `immediate` (pause now) and `abort_wanted`, as the operator asked."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.pause_wanted = False
        self.immediate = False
        self.abort_wanted = False
        self.wake: Callable[[], None] = lambda: None

    def pause(self, immediate: bool = False) -> None:
        with self._lock:
            self.pause_wanted = True
            self.immediate = self.immediate or immediate

    def resume(self) -> None:
        with self._lock:
            self.pause_wanted = self.immediate = False
        self.wake()  # a hold: the next command may as well leave now

    def abort(self) -> None:
        self.abort_wanted = True
        self.wake()


class RequestedControl:
    """A program's `pause`, `resume` and `abort` (the engine's calls, from any thread), kept in
    its `requests` for the stream thread to act on."""

    requests: Requests

    def pause(self, immediate: bool = False) -> None:
        self.requests.pause(immediate)

    def resume(self) -> None:
        self.requests.resume()

    def abort(self) -> None:
        self.requests.abort()
