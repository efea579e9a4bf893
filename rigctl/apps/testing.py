"""Test doubles for drivers: a transport that plays a scripted exchange byte for byte.

`ScriptedTransport` is built from the exact exchange a driver must produce, as a list of
`(expected_write, reply)` steps (the idea of pymeasure's `expected_protocol`):

    ScriptedTransport([
        (b"*IDN?\\n", b"KEPCO,BOP 50-20GL,E123,3.05\\n"),   # a write, then its reply becomes readable
        (b"OUTP ON\\n", None),                              # a write without a reply
        (None, b"spontaneous\\n"),                          # bytes that arrive without a write
        (b"MEAS:CURR?\\n", DeviceTimeout("silent")),       # the read after this write raises
    ])

Any write that is not the next expected one fails the test at once (AssertionError, remembered so
that `assert_done()` fails too even if the driver swallowed it); `assert_done()` fails if steps or
readable bytes are left over. A read with nothing scripted raises DeviceTimeout, as a silent device
would, so watchdog paths can be tested without waiting.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from importlib.resources import files
from pathlib import Path
from typing import Any

from rigctl.core.errors import DeviceTimeout, Disconnected, ProtocolError

Reply = bytes | BaseException | None


class ScriptedTransport:
    """A `Transport` that checks every write against a script and serves the scripted replies."""

    def __init__(self, steps: list[tuple[bytes | None, Reply]], *, url: str = "scripted://") -> None:
        self.url = url
        self.timeout_s = 1.0
        self.closed = False
        self.writes: list[bytes] = []
        self.discards = 0
        self._steps = deque(steps)
        self._readable = bytearray()
        self._pending_error: BaseException | None = None
        self._failure: AssertionError | None = None
        for expected, reply in steps:
            if expected is not None and not isinstance(expected, bytes):
                raise TypeError(f"expected writes are bytes, got {expected!r}")
            if reply is not None and not isinstance(reply, (bytes, BaseException)):
                raise TypeError(f"replies are bytes, an exception or None, got {reply!r}")

    def _fail(self, message: str) -> None:
        self._failure = AssertionError(message)
        raise self._failure

    def _deliver(self, reply: Reply) -> None:
        if isinstance(reply, BaseException):
            self._pending_error = reply
        elif reply is not None:
            self._readable += reply

    def write(self, data: bytes) -> None:
        if self.closed:
            raise Disconnected(f"transport to {self.url} is closed")
        self.writes.append(bytes(data))
        if not self._steps:
            self._fail(f"unexpected write {bytes(data)!r}: the script is finished")
        expected, reply = self._steps[0]
        if expected is None:
            self._fail(f"unexpected write {bytes(data)!r}: the script expects a read next")
        if bytes(data) != expected:
            self._fail(f"wrong write: expected {expected!r}, got {bytes(data)!r}")
        self._steps.popleft()
        self._deliver(reply)

    def _pull_unprompted(self) -> None:
        while self._steps and self._steps[0][0] is None:
            self._deliver(self._steps.popleft()[1])

    def _raise_pending(self) -> None:
        if self._pending_error is not None:
            error, self._pending_error = self._pending_error, None
            raise error

    def read_until(
        self, terminator: bytes = b"\n", *, timeout_s: float | None = None, max_bytes: int = 65536
    ) -> bytes:
        if self.closed:
            raise Disconnected(f"transport to {self.url} is closed")
        self._raise_pending()
        if self._readable.find(terminator) < 0:
            self._pull_unprompted()
            self._raise_pending()
        index = self._readable.find(terminator)
        if index < 0:
            if len(self._readable) > max_bytes:
                self._readable.clear()
                raise ProtocolError(f"reply from {self.url} exceeds {max_bytes} bytes")
            raise DeviceTimeout(f"no reply within {timeout_s or self.timeout_s:g} s from {self.url}")
        end = index + len(terminator)
        message = bytes(self._readable[:end])
        del self._readable[:end]
        return message

    def read_exact(self, n: int, *, timeout_s: float | None = None) -> bytes:
        if self.closed:
            raise Disconnected(f"transport to {self.url} is closed")
        self._raise_pending()
        if len(self._readable) < n:
            self._pull_unprompted()
            self._raise_pending()
        if len(self._readable) < n:
            raise DeviceTimeout(f"only {len(self._readable)} of {n} bytes from {self.url}")
        message = bytes(self._readable[:n])
        del self._readable[:n]
        return message

    def discard_input(self) -> None:
        self.discards += 1
        self._readable.clear()

    def close(self) -> None:
        self.closed = True

    def assert_done(self) -> None:
        """Fail unless every step was consumed, every reply read, and no write was wrong."""
        if self._failure is not None:
            raise AssertionError(f"the script failed earlier: {self._failure}")
        if self._steps:
            raise AssertionError(f"{len(self._steps)} scripted step(s) left, next: {self._steps[0]!r}")
        if self._readable:
            raise AssertionError(f"reply bytes never read: {bytes(self._readable)!r}")
        if self._pending_error is not None:
            raise AssertionError(f"scripted error never raised: {self._pending_error!r}")


def wait_for(condition: Callable[[], bool], timeout_s: float = 20.0, what: str = "condition") -> None:
    """Wait until `condition()` is true, checking every 10 ms; AssertionError naming `what` after
    `timeout_s`. For tests that wait on a state (a record growing, a current decaying), never on
    a fixed sleep."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


# -- end-to-end helpers ----------------------------------------------------------------------------

def run_rigctl(*args: str, cwd: str | Path, timeout_s: float = 600.0,
               **kwargs: Any) -> subprocess.CompletedProcess:
    """`rigctl ARGS` in a fresh interpreter, as a user types it; output captured as text unless
    `stdout`/`stderr` say where it goes."""
    if "stdout" not in kwargs and "stderr" not in kwargs:
        kwargs["capture_output"] = True
    return subprocess.run([sys.executable, "-m", "rigctl", *args], check=False, cwd=cwd, text=True,
                          timeout=timeout_s, **kwargs)


@contextmanager
def daemon_on(bench, runs: Path) -> Iterator[tuple[Any, Any, Path]]:
    """(client, backdoor, runs folder) of a daemon on the emulated `bench` (not yet started),
    both in this process, the daemon on loopback ports of its own."""
    from rigctl.apps.client import Rig
    from rigctl.apps.daemon.server import Daemon
    from rigctl.emulators.backdoor import BackdoorClient

    with bench:
        daemon = Daemon(bench.rig, command="tcp://127.0.0.1:0", telemetry="tcp://127.0.0.1:0",
                        events="tcp://127.0.0.1:0", runs_dir=runs)
        daemon.start_thread()
        assert daemon.endpoints is not None  # bound by start_thread
        try:
            with Rig(daemon.endpoints.command, timeout_s=10.0) as rig, \
                    BackdoorClient.of(bench.rig.emulation) as backdoor:
                yield rig, backdoor, runs
        finally:
            daemon.stop()


PAIR_WORKSPACE = Path(str(files("rigctl.plans") / "examples" / "pair-formation-change-workspace.json"))


def plan_pair(folder: Path, *, goal: str, hold_s: float, start: str = "8,7,2,0",
              seed: int = 2) -> Path:
    """A pair-formation plan made by `rigctl plan pair` in the example workspace (x, y, separation
    in body lengths and heading in degrees for `start` and `goal`); its path."""
    plan = folder / "short.json"
    result = run_rigctl("plan", "pair", "--workspace", str(PAIR_WORKSPACE), "--start", start,
                        "--goal", goal, "--seed", str(seed), "--hold", str(hold_s), "-o", str(plan),
                        "--json", cwd=folder)
    assert result.returncode == 0, result.stdout + result.stderr
    return plan


def descendants(pid: int) -> list[int]:
    """Every process below `pid` (from /proc: a daemon's stream process, a run's bench, anything
    they started), at this moment."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        parents.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        children = parents.get(todo.pop(), [])
        found += children
        todo += children
    return found
