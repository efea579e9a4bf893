"""Scheduling priority for what keeps a rig's time, where the machine allows it.

A run's process (the stream, the camera's tracking, the run's own re-plans, all behind one GIL) and
an emulated bench standing for devices with processors of their own are scheduled ahead of ordinary
work: `FAVOURED_STEP` below the niceness they were started with (-10 from a shell's 0; one started
with `nice -n 10` comes level with ordinary work, as whoever started it meant). On a computer whose
cores other work keeps busy (a build, a study, a test suite), a cycle is then late by a time slice
rather than by its share of the cores, and a supply's 0.25 s reply watchdog measures the link, not
the computer. The whole process and not one thread: a thread of ours at normal priority that the
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
import resource
import threading
import time
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

FAVOURED_STEP = -10
RUN_NICE_ENV = "RIGCTL_STREAM_NICE"  # another niceness for a run's process and stream thread
BENCH_NICE_ENV = "RIGCTL_EMULATOR_NICE"  # another niceness for an emulated bench
BASE_NICE_ENV = "RIGCTL_BASE_NICE"  # where a favoured process started: its computing helpers' own


def favour(what: str, env: str = RUN_NICE_ENV, *, pass_on: bool = False) -> Callable[[], None]:
    """Put the calling thread (and what it starts from now on) `FAVOURED_STEP` ahead of its niceness,
    or at the niceness `env` names (0: leave it be), if that is ahead of its own and permitted;
    return what gives back the one it had (and the variables as they were). Never raises. With
    `pass_on` (a whole process: called before its threads start), what it took is passed on in
    both variables to the processes started from here on (a bench `rigctl execute` starts comes
    level with it, not another step ahead); a thread alone passes nothing on. A value in `env`
    that cannot be taken is said in one line on the log (the default goes quietly: most
    machines do not permit it)."""
    value = os.environ.get(env, "").strip()
    if value == "0":  # asked to leave it be
        return _nothing
    tid = threading.get_native_id()
    try:
        before = os.getpriority(os.PRIO_PROCESS, tid)
        wanted = int(value) if value else max(-20, before + FAVOURED_STEP)
    except ValueError:
        log.warning("%s=%s not taken (not a niceness): the %s keeps its own", env, value, what)
        return _nothing
    except OSError:
        return _nothing
    group = _favour_group(wanted) if pass_on else _nothing
    try:
        if wanted >= before:  # only ever ahead of where it was
            return group
        os.setpriority(os.PRIO_PROCESS, tid, wanted)
    except OSError as err:
        (log.warning if value else log.debug)("%s=%s not taken (%s): the %s keeps its own",
                                              env, wanted, err, what)
        return group
    log.debug("the %s at niceness %d", what, wanted)
    taken = {RUN_NICE_ENV: wanted, BENCH_NICE_ENV: wanted, BASE_NICE_ENV: before}
    passed_on = [name for name in taken if pass_on and name not in os.environ]
    for name in passed_on:  # a value someone set stays theirs
        os.environ[name] = str(taken[name])

    def restore() -> None:
        group()
        for name in passed_on:
            os.environ.pop(name, None)
        try:
            os.setpriority(os.PRIO_PROCESS, tid, before)  # lowering a priority is always permitted
        except OSError:
            pass

    return restore


AUTOGROUP = Path("/proc/self/autogroup")
AUTOGROUP_ENABLED = Path("/proc/sys/kernel/sched_autogroup_enabled")


def computer_notes() -> list[str]:
    """What the computer permits a run that `rigctl doctor` says (one line each): whether a run can
    be put ahead of ordinary work, and whether CPU time is shared by session, so that a
    `rigctl execute` typed in a terminal gets the cores turn about with every other session."""
    notes = []
    base = os.getpriority(os.PRIO_PROCESS, 0)
    wanted = max(-20, base + FAVOURED_STEP)
    soft = resource.getrlimit(resource.RLIMIT_NICE)[0]
    ahead = _may_take(wanted)
    if ahead:
        notes.append(f"priority: a run is put at niceness {wanted}, ahead of ordinary work")
    else:
        notes.append(f"priority: a run keeps niceness {base}, level with ordinary work (RLIMIT_NICE "
                     f"{soft} allows {20 - soft}; `LimitNICE=-10` in a unit or a `nice` line in "
                     "/etc/security/limits.conf puts it ahead: docs/safety.md)")
    try:
        grouped = AUTOGROUP_ENABLED.read_text().strip() == "1"
    except OSError:
        grouped = False
    if grouped and ahead:
        notes.append("scheduling: CPU time is shared by session (autogroup): a run puts its "
                     "session ahead too (a terminal's, with the terminal's other jobs, while the "
                     "run lasts)")
    elif grouped:
        notes.append("scheduling: CPU time is shared by session (autogroup): a run gets the cores "
                     "turn about with every other busy session")
    return notes


def _may_take(nice: int) -> bool:
    """Whether this process may take niceness `nice`: tried by a thread of its own (Linux keeps a
    niceness per thread), which ends with it; root, CAP_SYS_NICE and RLIMIT_NICE all count."""
    taken = []

    def trial() -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
            taken.append(True)
        except OSError:
            pass

    thread = threading.Thread(target=trial, name="priority-trial")
    thread.start()
    thread.join()
    return bool(taken)


def _favour_group(wanted: int) -> Callable[[], None]:
    """Where the kernel groups tasks by session (`CONFIG_SCHED_AUTOGROUP`, on by default on most
    distributions), a niceness only orders the threads of one session: each session shares the
    cores as one, at its group's niceness. So a favoured process sets its session's group's
    niceness too: a bench, a stream process, a run a study or a campaign starts (each leads a
    session of its own), and a `rigctl execute` or `rigctl emulate` typed in a terminal (its
    session is the terminal's: the terminal's other jobs come along for the run). Measured with
    other sessions busy: two of three runs lost to a supply's watchdog without it, none with it.
    What gives it back is returned; it gives back only what it set (another process of the
    session may have changed it since)."""
    try:
        before = int(AUTOGROUP.read_text().split("nice")[1])  # the default group's file is empty
        if wanted >= before:
            return _nothing
        _write_group(wanted)
    except (OSError, ValueError, IndexError):  # no autogroups, or not permitted
        return _nothing

    def restore() -> None:
        try:
            if int(AUTOGROUP.read_text().split("nice")[1]) == wanted:
                _write_group(before)
        except (OSError, ValueError, IndexError):
            pass

    return restore


def _write_group(nice: int, tries: int = 3) -> None:
    """The kernel takes one group niceness in a tenth of a second from a process without
    CAP_SYS_ADMIN, machine-wide, and says EAGAIN to the others (a run and its bench start
    together): a few tries a tenth apart."""
    for left in range(tries - 1, -1, -1):
        try:
            AUTOGROUP.write_text(str(nice))
            return
        except BlockingIOError:
            if not left:
                raise
            time.sleep(0.11)


def _nothing() -> None:
    pass


def step_back(what: str) -> None:
    """A helper process that only computes for a favoured one (the run's re-plans): back to the
    niceness that one started at (`BASE_NICE_ENV`, which `favour(pass_on=True)` passes on), so a
    burst of planning waits behind the stream and the bench rather than beside them; left as it is
    without the variable. Lowering a priority is always permitted; never raises."""
    value = os.environ.get(BASE_NICE_ENV, "").strip()
    try:
        base, now = int(value), os.getpriority(os.PRIO_PROCESS, 0)
        if base > now:
            os.setpriority(os.PRIO_PROCESS, 0, base)
            log.debug("the %s back at niceness %d", what, base)
    except (ValueError, OSError):
        pass
