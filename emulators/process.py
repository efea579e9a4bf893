"""Run an emulated bench in its own process, as `rigctl emulate KIND` does, and wait until it is up.

`rigctl execute` without `--rig` uses this, so that path and `rigctl emulate` + `--rig` are the same
code: a separate process that serves the devices on loopback and writes the rig file. Readiness is
the line `READY <rig file>` on the child's stdout, never a sleep.

The bench runs in a session of its own. A terminal's Ctrl-C goes to every process of its
foreground group: a bench in that group stopped with the same keystroke as the run on it, which
then could not make the bench's devices safe (the run faulted "not confirmed safe"). Out of the
terminal's reach, the bench is stopped by whoever started it (`__exit__`, on every exit path),
once the run on it has ended.
"""

from __future__ import annotations

import logging
import os
import select
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, TextIO

from rigctl.core.config import RigConfig, load_rig
from rigctl.core.errors import RigError, shielded_from_interrupts

log = logging.getLogger(__name__)

READY_PREFIX = "READY "


class EmulatedBenchProcess:
    """Context manager: `with EmulatedBenchProcess(kind, rig_path) as rig_file: ...` (any rig
    kind with a `RigKind.bench`)."""

    def __init__(self, kind: str, rig_out: str | Path, *, extra_args: list[str] | None = None,
                 start_timeout_s: float = 60.0) -> None:
        self.kind = kind
        self.rig_out = Path(rig_out)
        self.extra_args = extra_args or []
        self.start_timeout_s = start_timeout_s
        self.proc: subprocess.Popen[bytes] | None = None
        self.log_path = self.rig_out.with_suffix(".log")

    def __enter__(self) -> Path:
        cmd = [sys.executable, "-m", "rigctl", "emulate", self.kind, "--rig-out", str(self.rig_out),
               *self.extra_args]
        # the child's log goes to a file beside the rig file: a pipe nobody drains would block it
        self._log = open(self.log_path, "w")
        # unbuffered bytes: `select` then sees exactly what `readline` has not taken yet (a
        # buffered reader could hold the READY line while select waits for more)
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=self._log, bufsize=0,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            start_new_session=True,  # not stopped by the terminal's Ctrl-C: by us (module doc)
        )
        try:
            ready = self._ready_path()
        except BaseException:  # a Ctrl-C while it starts: `__exit__` will not run, stop it here
            self._terminate()
            raise
        if ready is not None:
            return ready
        self._terminate()
        err = self.log_path.read_text()
        raise RigError(f"the emulated {self.kind} bench did not start: {err.strip()[-2000:]}",
                       device="emulated bench")

    def _ready_path(self) -> Path | None:
        """The rig file the READY line names; None if the child exited or stayed silent."""
        deadline = time.monotonic() + self.start_timeout_s
        assert self.proc is not None and self.proc.stdout is not None
        while True:
            # wait for a line with a deadline: a child that hangs silently must not hang us
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([self.proc.stdout], [], [], remaining)[0]:
                return None
            line = self.proc.stdout.readline().decode(errors="replace")
            if not line:
                return None  # the child exited
            if line.startswith(READY_PREFIX):
                return Path(line[len(READY_PREFIX):].strip())

    def __exit__(self, *exc: object) -> None:
        self._terminate()

    def _terminate(self) -> None:
        # a Ctrl-C meanwhile (`rigctl execute` after its run's end, impatient) is noted, not
        # raised: the bench is stopped, and the summary printed, all the same
        with shielded_from_interrupts():
            self._stop()

    def _stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc is not None and self.proc.stdout is not None:
            self.proc.stdout.close()
        self._log.close()


@contextmanager
def bench_for_run(kind: str, *, extra_args: list[str] | None = None,
                  progress_out: TextIO | None = None, world: str = "") -> Iterator[RigConfig]:
    """The rig a `rigctl execute` without --rig runs on: an emulated bench of `kind` started for
    this run on loopback (so nothing real is energised) and stopped after it."""
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-") as tmp:
        if progress_out:
            print(f"no --rig given: starting the emulated {kind} bench{world} on loopback "
                  "(nothing real is energised)", file=progress_out)
        with EmulatedBenchProcess(kind, Path(tmp) / "bench.toml", extra_args=extra_args) as path:
            yield load_rig(path)
