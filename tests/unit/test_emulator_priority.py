"""`rigctl emulate` takes its niceness from RIGCTL_EMULATOR_NICE before it starts a thread, and says
in one line when it cannot (a bad value, or a raise without the right to); unset, 10 steps ahead of
the niceness it was started with where the machine permits it (rigctl.core.priority), quietly."""

import os
import resource
import subprocess
import sys

SHOW = ("from rigctl.emulators.base import _take_priority; import os, threading; _take_priority(); "
        "t = threading.Thread(target=lambda: print(os.getpriority(os.PRIO_PROCESS, 0))); "
        "t.start(); t.join()")


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
