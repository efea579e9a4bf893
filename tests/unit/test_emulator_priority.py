"""`rigctl emulate` takes its niceness from RIGCTL_EMULATOR_NICE before it starts a thread, and says
in one line when it cannot (a bad value, or a raise without the right to); unset, 10 steps ahead of
the niceness it was started with where the machine permits it (rigctl.core.priority), quietly."""

import os
import resource
import subprocess
import sys

SHOW = ("from rigctl.emulators.base import _take_priority; import os, threading; "
        "give_back = _take_priority(); "
        "t = threading.Thread(target=lambda: print(os.getpriority(os.PRIO_PROCESS, 0))); "
        "t.start(); t.join(); give_back()")  # the test's session's CPU group as it was


def nice_of_a_bench_thread(value: str | None) -> tuple[int, str]:
    env = {k: v for k, v in os.environ.items() if k != "RIGCTL_EMULATOR_NICE"}
    if value is not None:
        env["RIGCTL_EMULATOR_NICE"] = value
    done = subprocess.run([sys.executable, "-c", SHOW], env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    return int(done.stdout), done.stderr


def test_the_bench_and_its_threads_take_the_niceness_asked_for():
    base = os.getpriority(os.PRIO_PROCESS, 0)
    # niceness n is permitted to root, or where RLIMIT_NICE's soft limit reaches 20 - n
    permitted = os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_NICE)[0] >= 20 - (base - 10)
    assert nice_of_a_bench_thread(None) == (max(-20, base - 10) if permitted else base, "")
    asked = nice_of_a_bench_thread("-3")
    if base <= -3:  # already ahead of it (a worker a favoured run left behind): left as it is
        assert asked == (base, "")
    elif permitted:
        assert asked == (-3, "")
    else:
        assert asked[0] == base and "not taken" in asked[1]
    assert nice_of_a_bench_thread("0") == (base, "")  # 0: the priority it was started with


def test_a_value_it_cannot_take_is_said_in_one_line_and_the_bench_goes_on():
    base = os.getpriority(os.PRIO_PROCESS, 0)
    nice, err = nice_of_a_bench_thread("fast")
    assert nice == base
    assert err.count("\n") == 1 and "RIGCTL_EMULATOR_NICE=fast not taken" in err


def test_a_re_planning_child_goes_back_to_where_its_favoured_run_started():
    """`step_back`: the niceness RIGCTL_BASE_NICE names where that is nicer than its own (a
    favoured run's re-planning child computes behind the stream), else left as it is."""
    show = ("from rigctl.core.priority import step_back; import os; step_back('re-plans'); "
            "print(os.getpriority(os.PRIO_PROCESS, 0))")
    base = os.getpriority(os.PRIO_PROCESS, 0)

    def nice_with(value: str | None) -> int:
        env = {k: v for k, v in os.environ.items() if k != "RIGCTL_BASE_NICE"}
        if value is not None:
            env["RIGCTL_BASE_NICE"] = value
        done = subprocess.run([sys.executable, "-c", show], env=env, capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        return int(done.stdout)

    assert nice_with(None) == base
    assert nice_with(str(min(19, base + 5))) == min(19, base + 5)  # nicer: always permitted
    assert nice_with(str(base - 1)) == base  # never ahead of where it was
    assert nice_with("soon") == base


def test_a_bench_raises_its_session_s_niceness_too_and_gives_back_a_shared_one():
    """Where CPU time is shared by session (autogroup), a bench takes its session's niceness down
    with its own: a thread's niceness alone orders it only among its session's threads. In a
    session of its own (as `rigctl execute` and the tests start one) it starts at 0; sharing one
    (typed in a terminal) it takes the terminal's ahead while it serves and gives it back after."""
    import pytest

    autogroup = "/proc/self/autogroup"
    if not os.path.exists(autogroup):
        pytest.skip("this kernel does not group CPU time by session (no /proc/self/autogroup)")
    base = os.getpriority(os.PRIO_PROCESS, 0)
    show = ("from rigctl.emulators.base import _take_priority; give_back = _take_priority(); "
            f"during = open('{autogroup}').read().strip(); give_back(); "
            f"print(during, '|', open('{autogroup}').read().strip())")
    env = {k: v for k, v in os.environ.items() if k != "RIGCTL_EMULATOR_NICE"}

    def group_nice(**popen) -> tuple[int | None, int | None]:
        """The group's niceness as the child saw it after taking its priority and after giving it
        back; None where its session is the kernel's default group (the file is empty: it has
        no niceness of its own, as where a CI runner's session was never made by setsid)."""
        done = subprocess.run([sys.executable, "-c", show], env=env, capture_output=True,
                              text=True, timeout=60, **popen)
        assert done.returncode == 0, done.stderr
        during, after = done.stdout.split("|")
        return _group_nice(during), _group_nice(after)

    permitted = os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_NICE)[0] >= 20 - (base - 10)
    own, _ = group_nice(start_new_session=True)  # a session of its own: its group starts at 0
    if own is None:
        pytest.skip("this kernel gave a new session no CPU group of its own (empty autogroup file)")
    assert own == (min(0, max(-20, base - 10)) if permitted else 0)  # only ever ahead
    with open(autogroup) as mine:
        shared = _group_nice(mine.read())
    if shared is None:  # the default group has no niceness to take: left be
        assert group_nice() == (None, None)
    else:
        wanted = max(-20, base - 10)
        during, after = group_nice()
        assert during == (min(shared, wanted) if permitted else shared)
        assert after == shared
        with open(autogroup) as mine:
            assert _group_nice(mine.read()) == shared  # this session's own, as it was


def _group_nice(text: str) -> int | None:
    """`/autogroup-ID nice N` read as N; None for the empty file of the default group."""
    return int(text.split("nice")[1]) if text.strip() else None


def test_a_group_niceness_the_kernel_defers_is_tried_again_a_tenth_later(monkeypatch):
    """Without CAP_SYS_ADMIN the kernel takes one group niceness per tenth of a second,
    machine-wide, and says EAGAIN to the rest: a run and its bench starting together both get
    theirs, and a kernel that keeps saying so is given up on with the error."""
    import pytest

    from rigctl.core import priority

    class Deferring:
        def __init__(self, refusals: int) -> None:
            self.refusals, self.written = refusals, []

        def write_text(self, text: str) -> None:
            if self.refusals:
                self.refusals -= 1
                raise BlockingIOError(11, "Resource temporarily unavailable")
            self.written.append(text)

    twice = Deferring(2)
    monkeypatch.setattr(priority, "AUTOGROUP", twice)
    priority._write_group(-10)
    assert twice.written == ["-10"]
    always = Deferring(10)
    monkeypatch.setattr(priority, "AUTOGROUP", always)
    with pytest.raises(BlockingIOError):
        priority._write_group(-10)
    assert always.refusals == 7 and not always.written


def test_the_doctor_says_whether_a_run_can_be_put_ahead_and_whether_time_is_shared_by_session():
    """`rigctl doctor`'s computer lines agree with what a process started here may do (it tries
    `os.nice`) and with the kernel's autogroup switch."""
    from rigctl.core.priority import computer_notes

    notes = computer_notes()
    base = os.getpriority(os.PRIO_PROCESS, 0)
    tried = subprocess.run([sys.executable, "-c", f"import os; os.nice({max(-20, base - 10) - base})"],
                           capture_output=True, timeout=60)
    assert ("ahead of ordinary work" in notes[0]) == (tried.returncode == 0)
    try:
        grouped = open("/proc/sys/kernel/sched_autogroup_enabled").read().strip() == "1"
    except OSError:
        grouped = False
    assert any(note.startswith("scheduling: CPU time is shared by session") for note in notes) == grouped
