"""Scheduling priority for what keeps a rig's time, where the machine allows it.

A run's process (the stream, the camera's tracking, the run's own re-plans, all behind one GIL)
and an emulated bench standing for devices with processors of their own are scheduled ahead of
ordinary work: niceness `FAVOURED_NICE` instead of the caller's. On a computer whose cores other
work keeps busy (a build, a study, a test suite), a cycle is then late by a time slice rather than
by its share of the cores, and a supply's 0.25 s reply watchdog measures the link, not the
computer. The whole process and not one thread: a thread of ours at normal priority that the
scheduler parks while it holds the GIL would stall a favoured stream thread just the same.

Raising a priority needs root, CAP_SYS_NICE or an RLIMIT_NICE that reaches it (`LimitNICE=` in a
unit, `nice` in /etc/security/limits.conf); without it nothing changes and nothing is said.
SCHED_FIFO (`rigctl daemon --realtime`) goes further where permitted. Linux keeps a niceness per
thread, and a new thread or process inherits its creator's: `favour` is called before a process
starts its threads.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)

FAVOURED_NICE = -10
RUN_NICE_ENV = "RIGCTL_STREAM_NICE"  # another niceness for a run's process and stream thread
BENCH_NICE_ENV = "RIGCTL_EMULATOR_NICE"  # another niceness for an emulated bench


def favour(what: str, env: str = RUN_NICE_ENV) -> Callable[[], None]:
    """Give the calling thread (and what it starts from now on) niceness `FAVOURED_NICE`, or the
    one `env` names (0: leave it be), if that is ahead of its own and permitted; return what gives
    back the one it had. Never raises. A value in `env` that cannot be taken is said in one line
    on the log (the default goes quietly: most machines do not permit it)."""
    value = os.environ.get(env, "").strip()
    if value == "0":  # asked to leave it be
        return _nothing
    try:
        wanted = int(value) if value else FAVOURED_NICE
    except ValueError:
        log.warning("%s=%s not taken (not a niceness): the %s keeps its own", env, value, what)
        return _nothing
    tid = threading.get_native_id()
    try:
        before = os.getpriority(os.PRIO_PROCESS, tid)
        if wanted >= before:  # only ever ahead of where it was
            return _nothing
        os.setpriority(os.PRIO_PROCESS, tid, wanted)
    except OSError as err:
        (log.warning if value else log.debug)("%s=%s not taken (%s): the %s keeps its own",
                                              env, wanted, err, what)
        return _nothing
    log.debug("the %s at niceness %d", what, wanted)

    def restore() -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, tid, before)  # lowering a priority is always permitted
        except OSError:
            pass

    return restore


def _nothing() -> None:
    pass
