"""The error hierarchy: small, and each class also inherits the built-in a caller would catch.

RigError comes first in each MRO so its constructor (with `device=`) is the one that runs.
Every error carries the device (where one is involved) and a reason a person can act on; the CLI
and the daemon print `str(err)` and never a stack trace.
"""

from __future__ import annotations

EXIT_OK, EXIT_NOT_REACHED, EXIT_BAD_INPUT, EXIT_FAULT = 0, 1, 2, 3
"""Exit status of every command, the one table: 0 success (for `execute`: every agent reached its
goal; for a planner: solved), 1 the job ran but did not succeed (a goal missed; for a planner, not
solved, its best plan still written: the same number, so it has no name of its own), 2 bad input
(nothing was energised), 3 a device fault stopped the run."""


class RigError(Exception):
    """Anything rigctl reports as a fault: device, reason, and what to do about it."""

    def __init__(self, message: str, *, device: str | None = None) -> None:
        super().__init__(message)
        self.device = device

    def __str__(self) -> str:
        message = super().__str__()
        return f"{self.device}: {message}" if self.device else message


class PlanError(RigError, ValueError):
    """A plan (or workspace) is malformed or cannot be realized; the message names the field."""


class ConfigError(RigError, ValueError):
    """A rig file is malformed or incomplete; the message names the key."""


class LimitError(RigError, ValueError):
    """A command would exceed a limit (current, voltage, field, speed); nothing was sent."""


class DeviceError(RigError):
    """The device reported an error (SCPI error queue, board error code, robot error)."""


class DeviceTimeout(RigError, TimeoutError):
    """The device did not answer within its timeout (the watchdog fired)."""


class Disconnected(RigError, ConnectionError):
    """The link to the device is gone (socket closed, serial port unplugged)."""


class ProtocolError(RigError):
    """The device answered something that does not parse (garbage on the line)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised on the main thread (`abort_on_sigterm`) so that a run ends as on Ctrl-C:
    an abort that ramps down, records and summarises."""


class _Interrupts:
    """The last Ctrl-C or SIGTERM taken by `on_interrupt_signal` and not yet handled, and how
    many `shielded_from_interrupts` blocks the main thread is in."""

    pending: KeyboardInterrupt | None = None
    shields = 0


def on_interrupt_signal(signum: int, frame: object) -> None:
    """The handler of SIGINT and SIGTERM on the main thread (`abort_on_sigterm`): remembers the
    interrupt, then raises it unless a ramp to safe is under way (`shielded_from_interrupts`).
    Remembering is what makes it reliable: Python drops an exception raised where nobody can
    catch it (a weakref callback of the import machinery, a `__del__`), printing "Exception
    ignored", and a run that polls `take_interrupt` every cycle still ends."""
    import signal

    interrupt = Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()
    _Interrupts.pending = interrupt
    if not _Interrupts.shields:
        raise interrupt


def take_interrupt() -> KeyboardInterrupt | None:
    """The interrupt signalled and not yet handled (None if none), now handled."""
    interrupt, _Interrupts.pending = _Interrupts.pending, None
    return interrupt


class shielded_from_interrupts:
    """A block that a Ctrl-C or SIGTERM must not cut short (a ramp to safe): one arriving meanwhile
    is remembered (`take_interrupt`), not raised. Main thread only, as signal handlers are."""

    def __enter__(self) -> None:
        _Interrupts.shields += 1

    def __exit__(self, *exc: object) -> None:
        _Interrupts.shields -= 1


def abort_on_sigterm() -> None:
    """From now on SIGTERM interrupts the main thread as Ctrl-C does (as `Terminated`), and SIGINT
    is Ctrl-C even where the process was started with it ignored (a shell's background job), both
    through `on_interrupt_signal`; called off the main thread (a test driving the CLI), it leaves
    the signals alone."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    take_interrupt()  # one from before (handled or not) is not this run's
    signal.signal(signal.SIGTERM, on_interrupt_signal)
    signal.signal(signal.SIGINT, on_interrupt_signal)


def interrupt_name(interrupt: KeyboardInterrupt) -> str:
    return "SIGTERM" if isinstance(interrupt, Terminated) else "Ctrl-C"
