"""Session set-up shared by every test, and the tiers.

Every test is in exactly one tier, so none falls out of every run:

- `quick`: unit tests, and integration tests that start no emulator process, browser or simavr
  (`pytest -m quick`, a few minutes on two cores: the loop to run after every change);
- `integration`: emulators on real transports (TCP, ptys, HTTP), in threads or processes;
- `e2e`: the CLI and the daemon run as processes, as a user runs them;
- `browser`: the operator console in headless Chromium.

A test's folder gives its tier (`tests/unit` quick, `tests/integration` integration, `tests/e2e`
e2e, `tests/browser` browser); a module may say otherwise with `pytestmark = pytest.mark.quick`
(an integration module whose emulators all run in this process). A test anywhere else without a
tier marker, or with two, fails the collection.
"""

from __future__ import annotations

from pathlib import Path

import pytest

TIERS = ("quick", "integration", "e2e", "browser")
FOLDER_TIER = {"unit": "quick", "integration": "integration", "e2e": "e2e", "browser": "browser"}
TESTS = Path(__file__).resolve().parent
# modules whose tests take long and mostly share no bench: spread over the workers test by test
# (a test that shares one names its group itself, as test_run_control's per rig kind do)
SPREAD = {"e2e/test_bench_smoke.py", "e2e/test_run_control.py"}
# the modules that take longest (wall time summed over their tests, measured with
# RIGCTL_TEST_CPU), started first so that no worker is left with a long one at the end; the rest
# follow in the order collected
LONGEST_FIRST = ("test_run_control", "test_bench_smoke", "test_console_six_coil", "test_execute_cli",
                 "test_coilboard_run", "test_depm_execute", "test_daemon_bench", "test_faults_cli",
                 "test_daemon_cli", "test_closed_loop_1khz", "test_closed_loop",
                 "test_terminal_interrupts", "test_coilboard_heating", "test_readonly_install",
                 "test_study", "test_identify_closed_loop", "test_pair_progress", "test_guardian")


def pytest_configure(config) -> None:
    import os

    # What keeps real time runs ahead of what computes, where the machine permits it (CI is root;
    # rigctl.core.priority): every process a test starts (a run, a bench, a daemon) at one niceness,
    # FAVOURED, and the worker itself there too while it runs a module that drives devices from
    # this process (`_real_time_first`); a quick test computes at the niceness the worker started
    # with. Without it a driver in the worker (a board's keep-alive) waits behind the other
    # worker's favoured run and the board's own watchdog stops its coils.
    _PRIORITY["base"] = os.getpriority(os.PRIO_PROCESS, 0)
    favoured = max(-20, _PRIORITY["base"] - 10)
    try:
        os.setpriority(os.PRIO_PROCESS, 0, favoured)  # permitted? (then given back at once)
        os.setpriority(os.PRIO_PROCESS, 0, _PRIORITY["base"])
    except OSError:
        pass
    else:
        _PRIORITY["favoured"] = favoured
        for name in ("RIGCTL_STREAM_NICE", "RIGCTL_EMULATOR_NICE"):
            os.environ.setdefault(name, str(favoured))
        os.environ.setdefault("RIGCTL_BASE_NICE", str(_PRIORITY["base"]))  # a re-planning child's
    # Compile (or load from numba's on-disk cache) the workspace geometry kernels once, before any
    # test starts an emulator or a re-planning child that would otherwise compile them mid-run.
    from rigctl.plans.workspace import warm_up

    seconds = warm_up()
    if seconds > 1.0:
        print(f"geometry kernels compiled in {seconds:.1f} s (cached for later processes)")
    from rigctl.plans.depm import warm_up as warm_up_depm  # the dEPM planner's kernels, likewise

    seconds = warm_up_depm()
    if seconds > 1.0:
        print(f"dEPM planner kernels compiled in {seconds:.1f} s (cached for later processes)")


_PRIORITY: dict[str, int] = {}  # "base": the worker's niceness; "favoured": where permitted


@pytest.fixture(scope="module", autouse=True)
def _real_time_first(request):
    """The worker's main thread (and the threads it starts) at the favoured niceness for a module
    outside the quick tier, at its own for a quick one (`pytest_configure`). Module-scoped and
    autouse: set before the module's own fixtures start a bench or a driver's threads."""
    import os
    import threading

    favoured = _PRIORITY.get("favoured")
    if favoured is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    tiers = tier_of(request.node)
    wanted = _PRIORITY["base"] if tiers == ["quick"] else favoured
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), wanted)
    except OSError:
        pass
    yield


def tier_of(item: pytest.Item) -> list[str]:
    """The tiers a test names by marker, or else the one its folder gives."""
    marked = [name for name in TIERS if item.get_closest_marker(name) is not None]
    if marked:
        return marked
    folder = Path(item.path).resolve().relative_to(TESTS).parts[0]
    return [FOLDER_TIER[folder]] if folder in FOLDER_TIER else []


def shares_a_fixture(item: pytest.Item) -> bool:
    """Whether the test uses a fixture set up once for more tests than itself (module, class or
    package scope: a started bench): then its module's tests go to one worker, which sets it up
    once; a session fixture is set up once per worker whatever the grouping."""
    defs = getattr(item, "_fixtureinfo", None)
    return defs is not None and any(d.scope in ("module", "class", "package")
                                    for fixture in defs.name2fixturedefs.values() for d in fixture)


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(config, items: list[pytest.Item]):
    wrong = []
    for item in items:
        tiers = tier_of(item)
        if len(tiers) != 1:
            wrong.append(f"{item.nodeid}: " + (f"in {len(tiers)} tiers ({', '.join(tiers)})"
                                              if tiers else "in no tier"))
            continue
        if item.get_closest_marker(tiers[0]) is None:
            item.add_marker(getattr(pytest.mark, tiers[0]))
        # xdist (-n, --dist loadgroup): a module's tests that share a fixture (a bench it starts
        # once) go to one worker, which starts it once; a test that names its group keeps it
        # (test_run_control: one per rig kind); every other test goes to whichever worker is free
        if item.get_closest_marker("xdist_group") is None and shares_a_fixture(item) and \
                Path(item.path).resolve().relative_to(TESTS).as_posix() not in SPREAD:
            item.add_marker(pytest.mark.xdist_group(Path(item.path).stem))
    rank = {stem: i for i, stem in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(Path(item.path).stem, len(rank)))  # stable: in order
    if wrong:
        raise pytest.UsageError("every test is in exactly one tier (tests/conftest.py says how): "
                                + "; ".join(wrong[:10]) + (" ..." if len(wrong) > 10 else ""))
    yield  # the other plugins' hooks: xdist's worker names each test's group in its node id ...
    # ... as `_nodeid`, which pytest 9.2 no longer reads (a node's id is `_id`): every group was
    # ignored and each module's bench started on both workers. Where the two differ, the id
    # xdist meant is the one its scheduler gets.
    for item in items:
        meant = getattr(item, "_nodeid", None)
        if meant is not None and meant != item.nodeid and hasattr(item, "_id"):
            from _pytest.nodeid import coerce_node_id

            item._id = coerce_node_id(meant)


_tier_time: dict[str, list[float]] = {}  # tier -> [tests, seconds in setup + call + teardown]
_tier_span: dict[str, list[float]] = {}  # tier -> [first start, last stop] (epoch seconds)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Sums each tier's test time, also from xdist's workers (their reports arrive here)."""
    tier = next((k for k in TIERS if k in report.keywords), "?")
    totals = _tier_time.setdefault(tier, [0, 0.0])
    totals[1] += report.duration
    if report.when == "call" or (report.when == "setup" and report.outcome != "passed"):
        totals[0] += 1
    start, stop = getattr(report, "start", None), getattr(report, "stop", None)
    if start is not None and stop is not None:
        span = _tier_span.setdefault(tier, [start, stop])
        span[0], span[1] = min(span[0], start), max(span[1], stop)


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    if not _tier_time:
        return
    write = terminalreporter.write_line
    terminalreporter.section("tiers")
    write(f"{'tier':<12} {'tests':>6} {'test time':>10} {'wall span':>10}")
    for tier in (*TIERS, "?"):
        if tier in _tier_time:
            tests, seconds = _tier_time[tier]
            first, last = _tier_span.get(tier, (0.0, 0.0))
            write(f"{tier:<12} {tests:>6} {seconds:>9.1f}s {last - first:>9.1f}s")
    write("test time: setup + call + teardown summed over the tier's tests (over every worker); "
          "wall span: first start to last end of the tier's tests")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """With RIGCTL_TEST_CPU=FILE, each test's CPU time (this process's and its reaped children's,
    user + system, seconds) and wall time appended to FILE as tab-separated lines: where the suite
    spends the two cores, which wall time alone does not tell (a real-time run mostly waits)."""
    import os

    out = os.environ.get("RIGCTL_TEST_CPU")
    if not out:
        yield
        return
    import resource
    import time

    def cpu(who: int) -> float:
        usage = resource.getrusage(who)
        return usage.ru_utime + usage.ru_stime

    before = (cpu(resource.RUSAGE_SELF), cpu(resource.RUSAGE_CHILDREN), time.monotonic())
    yield
    own, children = cpu(resource.RUSAGE_SELF) - before[0], cpu(resource.RUSAGE_CHILDREN) - before[1]
    with open(out, "a") as f:
        f.write(f"{item.nodeid}\t{own:.2f}\t{children:.2f}\t{time.monotonic() - before[2]:.2f}\n")


# what a quick test may not start: an emulated bench, the firmware under simavr, a browser
_NOT_QUICK = ("emulate", "simavr", "chromium", "chromedriver")


@pytest.fixture(autouse=True)
def _quick_starts_no_emulator(request, monkeypatch):
    """A quick test that starts an emulator process, simavr or a browser fails, naming it: the
    quick tier stays quick, and the marker tells the truth."""
    if request.node.get_closest_marker("quick") is None:
        return
    import subprocess

    popen_init = subprocess.Popen.__init__

    def guarded(self, args, *rest, **kwargs):
        words = [str(a) for a in ([args] if isinstance(args, (str, bytes)) else args)]
        hit = next((w for w in words for bad in _NOT_QUICK if bad in Path(w).name), None)
        if hit is not None:
            raise AssertionError(f"a quick test started {' '.join(words)[:200]}: mark its module "
                                 "integration or e2e (tests/conftest.py)")
        popen_init(self, args, *rest, **kwargs)

    monkeypatch.setattr(subprocess.Popen, "__init__", guarded)
