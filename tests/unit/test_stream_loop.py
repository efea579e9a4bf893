"""The stream loop's schedule: cycles on an absolute grid, and `wake` pulling the next one in."""

import time

from rigctl.core.stream import StreamLoop


def test_cycles_follow_the_schedule_and_stop_when_asked():
    starts = []

    def cycle(k):
        starts.append(time.perf_counter())
        return k < 4

    before = time.perf_counter()
    stats = StreamLoop(50.0).run(cycle)
    assert len(starts) == 5 and stats.cycles == 5
    # cycle k is due (k + 1) periods of 20 ms after the call at the earliest (the first one period
    # from then); a sleep never returns early, however loaded the machine (a late cycle is allowed)
    assert all(s >= before + (k + 1) * 0.020 for k, s in enumerate(starts)), starts


def test_wake_runs_the_next_cycle_at_once_and_the_schedule_follows():
    loop = StreamLoop(2.0)  # a 500 ms period makes the difference unmistakable
    starts = []

    def cycle(k):
        starts.append(time.perf_counter())
        if k == 0:
            loop.wake()  # e.g. the supervisor releasing a hold
        return k < 2

    loop.run(cycle)
    early, regular = starts[1] - starts[0], starts[2] - starts[1]
    assert early < 0.25, early  # would be 0.5 s without the wake
    assert regular > 0.45, regular  # the schedule moved with the early cycle


def test_while_a_loop_runs_the_gil_changes_hands_often_and_the_heap_is_frozen():
    """A thread doing Python for seconds (a re-plan, the tracker) must not keep the stream thread
    waiting 5 ms for the interpreter each time it comes back from a socket, and a full garbage
    collection of the heap that existed before the stream must not stop it: both hold while any
    loop runs (nested loops too) and are undone by the last one out."""
    import gc
    import sys

    from rigctl.core.stream import SWITCH_INTERVAL_S

    before = sys.getswitchinterval()
    assert before > SWITCH_INTERVAL_S  # CPython's default, 5 ms
    seen = []

    def inner(k):
        seen.append(("inner", sys.getswitchinterval(), gc.get_freeze_count()))
        return False

    def outer(k):
        seen.append(("outer", sys.getswitchinterval(), gc.get_freeze_count()))
        StreamLoop(1000.0).run(inner)  # a loop inside a loop's cycle
        seen.append(("outer after inner", sys.getswitchinterval(), gc.get_freeze_count()))
        return False

    StreamLoop(1000.0).run(outer)
    assert [s[0] for s in seen] == ["outer", "inner", "outer after inner"]
    # (the interpreter keeps the interval in whole microseconds)
    assert all(abs(interval - SWITCH_INTERVAL_S) < 1e-6 and frozen > 0
               for _, interval, frozen in seen), seen
    assert sys.getswitchinterval() == before
    assert gc.get_freeze_count() == 0


def test_the_stream_thread_is_favoured_while_it_streams_where_permitted_and_given_back_after(
        monkeypatch):
    import os
    import resource
    import threading

    seen: list[int] = []
    before: list[int] = []
    passed: list[str | None] = []

    def stream() -> None:
        tid = threading.get_native_id()
        before.append(os.getpriority(os.PRIO_PROCESS, tid))
        def cycle(k: int) -> bool:
            seen.append(os.getpriority(os.PRIO_PROCESS, tid))
            passed.append(os.environ.get("RIGCTL_STREAM_NICE"))  # a thread passes nothing on
            return k < 2

        StreamLoop(1000.0).run(cycle)
        seen.append(os.getpriority(os.PRIO_PROCESS, tid))

    for name in ("RIGCTL_STREAM_NICE", "RIGCTL_EMULATOR_NICE"):  # as started from a shell, and
        monkeypatch.setenv(name, "")  # what the loop passes on to later processes undone after
        monkeypatch.delenv(name)
    thread = threading.Thread(target=stream)  # its own thread: this one's niceness is untouched
    thread.start()
    thread.join()
    # ten steps ahead of where it was (not past -20), permitted to root or where RLIMIT_NICE's
    # soft limit reaches 20 - niceness
    during = max(-20, before[0] - 10)
    permitted = os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_NICE)[0] >= 20 - during
    during = during if permitted else before[0]
    assert seen == [during, during, during, before[0]]
    assert passed == [None, None, None]
