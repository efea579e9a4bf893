"""Running a study's cases on Dask distributed, or one after another in this process (`serial`).

Dask, not a pool of our own: `distributed.LocalCluster` (one single-threaded worker process per
core by default) on one machine, `Client("tcp://HOST:8786")` on a lab's cluster, the same code; its
scheduler hands cases out as workers free up, survives a worker that dies (the case runs again
elsewhere), and serves a dashboard of what each worker does. Ray would also do; Dask is chosen
because its scheduler and workers are plain Python processes started with `dask scheduler` /
`dask worker` (no object store, no resources to declare) and its `LocalCluster` starts in a
second on a laptop (`docs/studies.md`).

Cases go out longest first (`submission_order`: by the options that scale a case's work), so
that the last case to finish is a short one, not a long one started last (the tail, while the
other workers idle). Cases go out one per task while they are long; once the finished ones show
them short (a mean below `CHUNK_TARGET_S`) several go in one task (`chunk_size`), so that the
scheduler's round trip (a few ms a task) is paid per chunk, not per case (1,000 cases of 30 ms
spent 28 % of the workers' time between cases, `bench/study.py`). The chunks shrink as the
cases run out (guided self-scheduling), so that every worker ends at about the same time.

Results go into the study's table (`table.ResultsTable`: its journal at once, the Parquet file at
most every second and at the end) as each case finishes, on the client's side: the one writer.
Cases already in the table are not submitted, so a study stopped at any point (Ctrl-C, a killed
process) resumes by running the same command again.

A terminal's Ctrl-C goes to every process of its foreground group, the local workers included:
they ignore it (`set_up_worker`), and the study, interrupted (Ctrl-C or SIGTERM), stops the
cases' runs in every worker (`cases.stop_cases`: each aborted and recorded, then its bench)
before it closes the cluster, so that nothing it started is left running.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from threadpoolctl import threadpool_limits

from rigctl.apps.study.cases import run_case, stop_cases
from rigctl.apps.study.spec import Case, StudySpec
from rigctl.apps.study.table import ResultsTable
from rigctl.core.errors import on_interrupt_signal, shielded_from_interrupts

log = logging.getLogger(__name__)

STUDY_FILE = "study.json"


@dataclass
class StudyOutcome:
    """What a call of `run_study` did: cases in the spec, skipped (already in the table), run now,
    those of them not `ok`, its wall time, the dashboard's address (Dask) and the workers used."""

    cases: int
    skipped: int
    ran: int
    not_ok: int
    wall_s: float
    dashboard: str | None
    workers: int
    case_wall_s: float  # sum of the wall times of the cases run now (as each worker measured)


CHUNK_TARGET_S = 0.25
"""About this much of cases per task once they are known to be short: a task's round trip through
the scheduler (2-5 ms here) is then about 1-2 % of it. Cases longer than this go one per task, so
that each is in the table as soon as it ends (a study stopped loses no finished case of them)."""

TASKS_PER_WORKER = 2
"""Tasks in flight per worker: one running, one waiting at the scheduler, so that a worker that
finishes a task starts the next one without waiting for the client's answer."""

WORK_OPTIONS = ("cells", "moves", "max-nodes", "time")
"""Options whose value scales a case's work (a planner's grid, its moves, its node or time budget):
`submission_order` runs the largest first."""


def submission_order(cases: list[Case]) -> list[Case]:
    """The cases longest first as far as their options tell (`WORK_OPTIONS`, compared in that
    order); cases that do not differ in them keep the spec's order."""
    def work(case: Case) -> tuple[float, ...]:
        values = (case.options.get(name) for name in WORK_OPTIONS)
        return tuple(-float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else 0.0
                     for v in values)
    return sorted(cases, key=work)


def chunk_size(remaining: int, workers: int, mean_case_s: float | None) -> int:
    """Cases in the next task: one while no case has finished or cases are long; else about
    `CHUNK_TARGET_S` of them, and never more than a share of what is left (remaining / (2 x
    workers): the chunks shrink towards the end, so no worker is left with a long last chunk)."""
    if mean_case_s is None or remaining <= 0:
        return 1
    by_time = int(CHUNK_TARGET_S / max(mean_case_s, 1e-6))
    return max(1, min(by_time, remaining // (2 * workers)))


def run_chunk(function: Callable[..., dict], before: tuple, items: list, after: tuple) -> list[dict]:
    """`function(*before, item, *after)` for each item, in a worker: one task of several cases."""
    return [function(*before, item, *after) for item in items]


def run_on_dask(client, function: Callable[..., dict], items: list, before: tuple, after: tuple,
                workers: int, finished: Callable[[dict], None], futures: list) -> None:
    """Run `function(*before, item, *after)` for every item on the client's workers, in items'
    order, one per task or in chunks (`chunk_size`, from the mean `wall_s` of the rows so far),
    `TASKS_PER_WORKER` tasks in flight per worker; `finished(row)` on this thread for every row
    as its task ends. `futures` gets every task submitted (to cancel them when interrupted)."""
    from distributed import as_completed

    queue = list(reversed(items))  # popped from the end: items' order
    done_s, done_n = 0.0, 0

    def submit() -> None:
        mean = done_s / done_n if done_n else None
        size = chunk_size(len(queue), workers, mean)
        chunk = [queue.pop() for _ in range(min(size, len(queue)))]
        future = client.submit(run_chunk, function, before, chunk, after, pure=False, retries=1)
        futures.append(future)
        running.add(future)

    running = as_completed()
    for _ in range(min(len(queue), TASKS_PER_WORKER * workers)):
        submit()
    for future in running:
        rows = future.result()
        done_s += sum(row["wall_s"] for row in rows)
        done_n += len(rows)
        if queue:  # the next task first: the worker is not kept waiting while the rows are stored
            submit()
        for row in rows:
            finished(row)


def default_workers() -> int:
    """One worker per core this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


ONE_CASE_PER_CORE = 1
"""BLAS threads per case. A study runs one case per core; OpenBLAS's own threads (one per core
by default) then only compete with the other cases, and even alone they do not pay: the 40 cases
of `studies/reachable-quick.toml` took as long on one thread as on two, for half the CPU time
(measured, `bench/study.py`). Dask's nanny sets OMP_NUM_THREADS=1 in its workers for the same
reason; the limit is set here too so that a serial run and a lab's own `dask worker` match."""


LOCAL_CLUSTER_CONFIG = {
    # The nanny's default MALLOC_TRIM_THRESHOLD_=65536 fixes glibc's mmap threshold, so every
    # large numpy temporary is a fresh mmap: the planners ran 3-4x slower in a worker than here
    # (measured). Unset, glibc's own adaptive thresholds apply, as in this process.
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    # On a machine of as many workers as cores, every cycle the scheduler, the nannies (both in
    # this process) and the workers' event loops spend is taken from a case. Dask's own upkeep, at
    # its defaults, kept this process 5 % busy with no case running; with these, 1 % (measured,
    # `LocalCluster` of 2 idle for 5 s): the event-loop health check every 20 ms, the system
    # monitor every 0.5 s and the memory monitor every 0.1 s are slowed, and the statistical
    # profiler (a sample of the case's stack every 10 ms, taking the GIL from it) is off. Work
    # stealing is off: a study's cases are independent, queued at the scheduler and handed to a
    # worker only as it frees up (`worker-saturation`), so there is nothing to steal.
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.scheduler.work-stealing": False,
}
"""Dask settings of the LocalCluster `run_study` starts (a lab's own cluster keeps its own)."""


def set_up_worker(command: str, local: bool = False) -> None:
    """A process that runs cases: one BLAS thread (`ONE_CASE_PER_CORE`), the planners warm; a
    worker of the study's own `LocalCluster` (`local`) also ignores SIGINT: the terminal's Ctrl-C
    reaches it too, and is the study's to handle (its cases stopped, then the cluster closed).
    Called on the worker's event loop, its main thread."""
    if local and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    threadpool_limits(ONE_CASE_PER_CORE)
    _warm_up(command)


def _case_worker(command: str):
    """A Dask worker plugin that sets up (`set_up_worker`) each worker of the study's own cluster,
    those started later too (one the nanny starts again after it died)."""
    from distributed import WorkerPlugin

    class CaseWorker(WorkerPlugin):
        name = "rigctl-study-worker"

        def setup(self, worker) -> None:
            set_up_worker(command, local=True)

    return CaseWorker()


def _warm_up(command: str) -> None:
    """Import the planners and load their compiled kernels (numba's disk cache) before the first
    case, so that no case's wall time includes them."""
    if command.startswith("plan "):
        import rigctl.plans.model
        import rigctl.plans.rrt  # noqa: F401
        from rigctl.apps.study.cases import planner_parser
        from rigctl.plans import wall_contact
        from rigctl.plans.workspace import warm_up

        planner_parser()
        warm_up()
        wall_contact.warm_up()


class Progress:
    """One line on `out` per finished case: done / total, failures, elapsed, time left (ETA from
    the mean rate so far, which counts the workers' parallelism)."""

    def __init__(self, name: str, total: int, out: TextIO | None) -> None:
        self.name, self.total, self.out = name, total, out
        self.done = self.not_ok = 0
        self.started = time.monotonic()

    def case(self, row: dict) -> None:
        self.done += 1
        self.not_ok += row["status"] != "ok"
        if self.out is None:
            return
        elapsed = time.monotonic() - self.started
        left = elapsed / self.done * (self.total - self.done)
        failed = f", {self.not_ok} not ok" if self.not_ok else ""
        last = "" if row["status"] == "ok" else f" (case {row['case_id']}: {row['status']}: {row['message']})"
        print(f"study {self.name}: {self.done}/{self.total} cases ({100 * self.done / self.total:.0f} %)"
              f"{failed}, elapsed {_clock(elapsed)}, left ~{_clock(left)}{last}",
              file=self.out, flush=True)


def _clock(seconds: float) -> str:
    seconds = round(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def run_study(spec: StudySpec, out: str | Path, *, workers: int | None = None,
              scheduler: str | None = None, serial: bool = False, retry_failed: bool = False,
              progress_out: TextIO | None = sys.stderr,
              on_result: Callable[[dict], None] | None = None) -> StudyOutcome:
    """Run the spec's cases not yet in `out`'s table: serially here, on a LocalCluster of `workers`
    (default: one per core), or on the Dask scheduler at `scheduler`. Every finished case is in
    the table's journal before the next result is read, and in the table when this returns or
    raises. SIGTERM ends it as Ctrl-C does (KeyboardInterrupt), with every case's run and bench
    stopped."""
    previous = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.signal(sig, on_interrupt_signal)
                    for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run_study(spec, Path(out), workers=workers, scheduler=scheduler, serial=serial,
                          retry_failed=retry_failed, progress_out=progress_out,
                          on_result=on_result)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run_study(spec: StudySpec, out: Path, *, workers: int | None, scheduler: str | None,
               serial: bool, retry_failed: bool, progress_out: TextIO | None,
               on_result: Callable[[dict], None] | None) -> StudyOutcome:
    out.mkdir(parents=True, exist_ok=True)
    (out / STUDY_FILE).write_text(json.dumps({
        "name": spec.name, "command": spec.command, "parameters": spec.parameter_names,
        "success": spec.success, "error": spec.error,
        "error_label": spec.error_label, "cases": len(spec.cases),
        "spec_folder": str(spec.folder)}, indent=1))
    table = ResultsTable(out)
    done = table.done_ids(retry_failed=retry_failed)
    todo = [c for c in spec.cases if c.id not in done]
    progress = Progress(spec.name, len(todo), progress_out)
    if progress_out is not None and len(todo) < len(spec.cases):
        print(f"study {spec.name}: {len(spec.cases) - len(todo)} of {len(spec.cases)} cases already "
              f"in {table.path}; running the other {len(todo)}", file=progress_out, flush=True)
    arguments = (spec.command, str(spec.folder))
    tail = (str(out.resolve()), spec.success, spec.error)
    case_wall = 0.0

    def finished(result: dict) -> None:
        nonlocal case_wall
        table.add(result)
        case_wall += result["wall_s"]
        progress.case(result)
        if on_result is not None:
            on_result(result)

    if serial or not todo:
        with threadpool_limits(ONE_CASE_PER_CORE):
            if todo:
                _warm_up(spec.command)
            started = time.perf_counter()
            progress.started = time.monotonic()
            try:
                for case in todo:
                    finished(run_case(*arguments, case, *tail))
            finally:
                table.write()
        return StudyOutcome(len(spec.cases), len(spec.cases) - len(todo), len(todo),
                            progress.not_ok, time.perf_counter() - started, None, 1, case_wall)

    import dask
    from distributed import Client, LocalCluster

    logging.getLogger("distributed").setLevel(logging.ERROR)
    cluster = None
    if scheduler is None:
        with dask.config.set(LOCAL_CLUSTER_CONFIG):
            cluster = LocalCluster(n_workers=workers or default_workers(), threads_per_worker=1,
                                   processes=True, dashboard_address="127.0.0.1:0",
                                   silence_logs=logging.ERROR)
    client = Client(cluster if cluster is not None else scheduler)
    futures: list = []
    try:
        dashboard = client.dashboard_link
        n_workers = len(client.scheduler_info()["workers"])
        if progress_out is not None:
            print(f"study {spec.name}: {len(todo)} cases on {n_workers} Dask workers "
                  f"(scheduler {client.scheduler.address}); dashboard {dashboard}",
                  file=progress_out, flush=True)
        if cluster is not None:  # every worker, one started again later too
            client.register_plugin(_case_worker(spec.command))
        else:  # a lab's workers: their own signals are left alone
            client.run(set_up_worker, spec.command)
        started = time.perf_counter()
        progress.started = time.monotonic()  # the time left counts from the first case
        run_on_dask(client, run_case, submission_order(todo), arguments, tail, n_workers,
                    finished, futures)
        wall = time.perf_counter() - started
    except BaseException:
        # interrupted (or the scheduler lost): no case starts, and those running end their
        # runs and benches in their workers, a second Ctrl-C meanwhile noted, not raised
        with shielded_from_interrupts(), contextlib.suppress(Exception):
            client.cancel(futures)
            client.run(stop_cases, tail[0])
        raise
    finally:
        table.write()
        client.close()
        if cluster is not None:
            cluster.close()
    return StudyOutcome(len(spec.cases), len(spec.cases) - len(todo), len(todo), progress.not_ok,
                        wall, dashboard, n_workers, case_wall)
