"""The owner's guardian: a small process that makes the rig safe when its owner dies without a word.

A Kepco BOP holds its last setpoint for as long as it is powered: a `rigctl execute` or a
`rigctl daemon` killed by SIGKILL (the OOM killer, `kill -9`) or by a lost SSH session's hang-up
runs none of its own clean-up and leaves the coils carrying current. So whoever owns a rig starts
a guardian first (`Guardian`, a context manager): a child process in a session of its own (a
terminal's Ctrl-C and hang-up reach the owner's process group, not it) whose stdin is a pipe from
the owner. The kernel closes that pipe however the owner ends; the words the owner wrote on it
before say whether the end was normal. One word a line:

    rig <the RigConfig as JSON>   the rig the owner now holds (sent once it holds the rig's lock)
    bench <pid>                   an emulated bench the owner started itself, to stop as well
    ended                         the owner is done and has left the rig as it should be

A guardian that reads the end of the pipe after `ended` exits quietly. One that reads it without
(the last complete line is something else, or a line was cut off by the owner's death) does
what `rigctl estop --rig` does when no owner answers: every device of the rig opened anew and
made safe through the rig kind's `make_safe` (supplies 0 A and output off, confirmed; the board
told STOP; each arm out of direct servo). Then it stops the bench the owner had started, says
what it did on stderr (the owner's terminal or journal) and appends it to `guardian.log` in the
rig lock folder (`rigctl.rigs.owner.lock_dir`), where the locks of the devices it made safe are.

It never opens a device while the owner lives (one process owns a rig): the rig's configuration
is all it holds. Its start is kept off the owner's path: the owner starts it before its own
imports, and it imports the configuration and the rig registry (0.5 s on a quiet machine, 1.4-3.4
s on a 2-core one at load 11: too slow to begin only once the owner is gone, when the deadline is
1.5 s from the owner's death to every device safe) while the owner imports, starts its bench and
checks its devices. It answers `armed` on stdout, which the owner waits for before it energises
anything (0 s at load 10: it is always there first). Only the rig kind's make-safe is imported
when it acts (20-140 ms more at that load, once the rest is loaded).
"""

from __future__ import annotations

import json
import logging
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterable
from typing import IO, Any

from rigctl.core.errors import RigError

ARMED = b"armed\n"
ARM_TIMEOUT_S = 60.0  # the guardian's imports on a loaded machine (quiet: 0.5 s)
END_TIMEOUT_S = 5.0  # a guardian told `ended` exits at once; this long before it is killed
BENCH_STOP_S = 5.0  # a bench asked to stop (SIGTERM) gets this long before SIGKILL
LOG_NAME = "guardian.log"
REACH_AGAIN_S = 0.1  # a device the make-safe did not reach is reached again this often


# -- the owner's side ----------------------------------------------------------------------------
class Guardian:
    """`with Guardian("rigctl execute") as guardian:` around everything the owner does with a
    rig (entered first, before the owner's own imports, which the guardian's then overlap; left
    last: after the run, the lock and the bench); once the rig is held,
    `guardian.guard(rig, bench_pid=...)`, and `guardian.wait_armed()` before anything is
    energised. Leaving the `with` block by any path (an exception too: the blocks inside have
    made the rig safe by then) is a normal end; a guardian not armed yet is simply ended."""

    def __init__(self, owner: str) -> None:
        self.owner = owner
        self.proc: subprocess.Popen[bytes] | None = None
        self.armed = False

    def __enter__(self) -> Guardian:
        # its own session: a terminal's Ctrl-C or hang-up goes to the owner's group, not here;
        # stderr is the owner's (where the operator looks), the pipes are closed on exec in any
        # other child (a bench, the stream process), so only this owner's death ends them
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rigctl.rigs.guardian", self.owner, str(os.getpid())],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, start_new_session=True)
        return self

    def _say(self, line: str) -> None:
        assert self.proc is not None and self.proc.stdin is not None
        try:
            self.proc.stdin.write(line.encode() + b"\n")
            self.proc.stdin.flush()
        except OSError as err:  # the guardian died: the rig is unguarded, say so
            raise RigError(f"the guardian of {self.owner} is gone ({err})",
                           device="guardian") from None

    def guard(self, rig: Any, bench_pid: int | None = None) -> None:
        """From now on the guardian makes `rig` (a RigConfig) safe if the owner dies, and stops
        the emulated bench `bench_pid` (one the owner started itself) after it."""
        words = ["rig " + rig.model_dump_json()]
        if bench_pid is not None:
            words.append(f"bench {bench_pid}")
        self._say("\n".join(words))  # in one write: no death between the rig and its bench

    def wait_armed(self, timeout_s: float = ARM_TIMEOUT_S) -> None:
        """Return once the guardian has the rig and its imports (RigError if it never does)."""
        assert self.proc is not None and self.proc.stdout is not None
        ready = select.select([self.proc.stdout], [], [], timeout_s)[0]
        line = self.proc.stdout.readline() if ready else b""
        self.armed = line == ARMED
        if not self.armed:
            raise RigError(f"the guardian of {self.owner} did not start"
                           + (f" (exit {self.proc.poll()})" if self.proc.poll() is not None
                              else f" within {timeout_s:g} s"), device="guardian")

    def __exit__(self, *exc: object) -> None:
        proc = self.proc
        if proc is None:
            return
        assert proc.stdin is not None and proc.stdout is not None
        if not self.armed:  # it guards nothing yet (nothing was energised): no need to wait for
            proc.kill()  # its imports to end before it reads the word (bad input ends at once)
        try:
            proc.stdin.write(b"ended\n")
            proc.stdin.close()
        except OSError:  # it died; the owner is ending normally anyway
            pass
        try:
            proc.wait(END_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()


# -- the guardian's side -------------------------------------------------------------------------
def owner_words(stream: IO[bytes]) -> Iterable[tuple[str, str]]:
    """The owner's complete lines as (word, argument) until the pipe ends; a last line without
    its newline was cut off by the owner's death and is not a word."""
    for line in iter(stream.readline, b""):
        if not line.endswith(b"\n"):
            return
        word, _, argument = line.decode(errors="replace").rstrip("\n").partition(" ")
        yield word, argument


def ended_normally(words: Iterable[tuple[str, str]], ward: Any) -> bool:
    """Follow the owner's words (`rig` -> `ward.arm(json)`, `bench` -> `ward.bench(pid)`) until
    the pipe ends; True when the last word was `ended`."""
    ended = False
    for word, argument in words:
        ended = word == "ended"
        if word == "rig":
            ward.arm(argument)
        elif word == "bench":
            ward.bench(int(argument))
    return ended


class Ward:
    """What the guardian guards: the rig (parsed when the owner names it, so that acting needs no
    imports of the configuration) and the bench the owner started."""

    def __init__(self, owner: str, owner_pid: int, armed_out: IO[bytes]) -> None:
        self.owner, self.owner_pid = owner, owner_pid
        self.armed_out = armed_out
        self.rig: Any = None
        self.make_safe: Any = None
        self.bench_pid: int | None = None
        self.bench_fd: int | None = None  # a pidfd: the bench, not whatever reuses its pid later
        self.since = time.monotonic()

    def arm(self, rig_json: str) -> None:
        from rigctl.core.config import parse_rig
        from rigctl.rigs import rig_kind

        self.rig = parse_rig(json.loads(rig_json), "the owner's rig")
        self.make_safe = rig_kind(self.rig.rig.kind).make_safe
        self.since = time.monotonic()
        try:
            self.armed_out.write(ARMED)
            self.armed_out.flush()
        except OSError:  # the owner is gone already: the pipe's end says so next
            pass

    def bench(self, pid: int) -> None:
        self.bench_pid = pid
        try:  # taken now, while the bench is surely alive (the owner has not reaped it)
            self.bench_fd = os.pidfd_open(pid)
        except (OSError, AttributeError):  # an old kernel: its pid it is
            self.bench_fd = None

    def act(self) -> list[str]:
        """Make the rig safe, then stop the bench; the lines that say what was done."""
        gone_s = time.monotonic() - self.since
        t0 = time.monotonic()
        result = self.make_safe(self.rig)
        left = [name for name, why in result.items() if why is not None]
        later: dict[str, float] = {}  # device -> s after the first try that it was reached
        # a device that serves one client at a time (a KUKA Sunrise server) refuses anyone until
        # it has seen the dead owner's connection close, a few ms; a link that is down stays so:
        # each is reached again for as long as the rig file says to try (`unsafe_retry_s`)
        while left and time.monotonic() - t0 < self.rig.stream.unsafe_retry_s:
            time.sleep(REACH_AGAIN_S)
            again = self.make_safe(self.rig)
            for name in [name for name in left if again.get(name, "not reached") is None]:
                result[name] = None
                left.remove(name)
                later[name] = time.monotonic() - t0
        safe_s = time.monotonic() - t0
        rig = f"{self.rig.rig.name!r} ({self.rig.rig.kind})"
        reached = all(why is None for why in result.values())
        lines = [f"{self.owner} (pid {self.owner_pid}) ended without a word after {gone_s:.1f} s "
                 f"holding rig {rig}: its guardian made "
                 + ("every device safe directly" if reached else "the devices it reached safe")
                 + f" in {safe_s:.2f} s"]
        lines += [f"  {name:<12} " + ("NOT REACHED: " + why if why is not None else
                                       f"safe (reached again after {later[name]:.2f} s)"
                                       if name in later else "safe")
                  for name, why in result.items()]
        if not reached:
            lines.append(f"  some devices could not be reached (tried for {safe_s:.1f} s): check "
                         "them by hand")
        if self.bench_pid is not None:
            lines.append(f"  the emulated bench it had started (pid {self.bench_pid}) "
                         + self._stop_bench(self.bench_pid))
        return lines

    def _stop_bench(self, pid: int) -> str:
        def send(sig: int) -> None:
            if self.bench_fd is not None:
                signal.pidfd_send_signal(self.bench_fd, sig)
            else:
                os.kill(pid, sig)

        def gone_within(timeout_s: float) -> bool:
            if self.bench_fd is not None:  # readable once the process has exited
                return bool(select.select([self.bench_fd], [], [], timeout_s)[0])
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    return True
                time.sleep(0.05)
            return False

        try:
            send(signal.SIGTERM)
            if gone_within(BENCH_STOP_S):
                return "stopped"
            send(signal.SIGKILL)
            return "killed" if gone_within(BENCH_STOP_S) else "did not stop: kill it by hand"
        except ProcessLookupError:
            return "had already stopped"
        except OSError as err:
            return f"could not be stopped: {err}"


def _record(lines: list[str]) -> str:
    """Append `lines` to the guardian log in the rig lock folder; returns where, or why not."""
    from rigctl.rigs.owner import lock_dir

    path = lock_dir() / LOG_NAME
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            if os.fstat(fd).st_uid == os.getuid():
                os.fchmod(fd, 0o666)  # the next to write may be another user, as with the locks
            os.write(fd, "".join(f"{stamp} {line}\n" for line in lines).encode())
        finally:
            os.close(fd)
        return str(path)
    except OSError as err:
        return f"not written to {path}: {err.strerror}"


def main(argv: list[str]) -> int:
    owner, owner_pid = argv[0], int(argv[1])
    # no terminal sends it Ctrl-C or a hang-up (a session of its own); sent by hand they are
    # ignored too: only its owner's end (or SIGTERM, SIGKILL) ends it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    # its report names every device and what became of it; the make-safe's own log lines for a
    # device it cannot reach would repeat that at every try
    logging.disable(logging.ERROR)
    import rigctl.core.config  # noqa: F401  the slow imports, done before the owner needs us
    from rigctl.core.registry import kinds

    kinds()

    ward = Ward(owner, owner_pid, sys.stdout.buffer)
    if ended_normally(owner_words(sys.stdin.buffer), ward) or ward.rig is None:
        return 0  # a normal end, or gone before it held a rig: nothing to make safe
    lines = ward.act()
    where = _record(lines)
    try:
        print("\n".join(lines) + f"\n  (logged in {where})", file=sys.stderr, flush=True)
    except OSError:  # the terminal went with the session
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
