"""The processes rigctl starts for a user (a `rigctl execute`, a daemon, a bench) and ends itself:
asked first, as a user's SIGTERM asks (a run ramps down and records its end), killed only when it
has not ended in time."""

from __future__ import annotations

import subprocess


def end_child(proc: subprocess.Popen, timeout_s: float = 30.0) -> None:
    """`proc`, if still running, sent SIGTERM, and SIGKILL if it has not ended after `timeout_s`;
    waited for either way (no zombie left)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
