"""The stream process's loop (`rigctl.apps.daemon.runhost.host_main`, here in this process) against the
six emulated supplies: an ended run leaves nothing of itself behind for the next. A run is a web of
reference cycles (its callbacks hold it) that the stream's frozen heap moves into CPython's oldest
generation, which is collected only when that has grown by a quarter: without a collection
between runs, every ended run's objects stayed (0.3 MB a run, `bench/soak.py`)."""

import gc
import logging
import multiprocessing
import signal
import sys
import threading

from rigctl.apps.daemon import runhost
from rigctl.emulators.bench import SixCoilBench
from rigctl.plans.schema import parse_plan
from rigctl.rigs.six_coil.global_moves import GlobalMovesProgram
from rigctl.run.engine import Run


def _run_objects() -> int:
    """Runs and programs the interpreter still tracks, garbage or not (no collection here)."""
    return sum(isinstance(o, (Run, GlobalMovesProgram)) for o in gc.get_objects())


def test_the_stream_process_keeps_nothing_of_an_ended_run(tmp_path):
    plan = parse_plan({
        "schema": "rigctl.plan/1", "kind": "global-moves", "rig": "six-coil", "name": "short",
        "workspace": {"boundary": {"rect": [-100, -100, 200, 200]}},
        "agents": [{"start": [0.0, 0.0], "goal": [0.0, 0.0], "radius": 3.0}],
        "moves": [[10.0, 0.0], [-10.0, 0.0]]}, "plan")
    down_r, down_w = multiprocessing.Pipe(duplex=False)
    up_r, up_w = multiprocessing.Pipe(duplex=False)
    acks_r, acks_w = multiprocessing.Pipe(duplex=False)
    outcomes: list[str] = []

    def operator(rig) -> None:
        try:
            for _ in range(3):
                down_w.send(("run", plan, rig, str(tmp_path), None))
                message = ("no answer within 60 s",)
                while up_r.poll(60) and (message := up_r.recv())[0] not in ("done", "failed"):
                    pass
                outcomes.append(message[0])
                if message[0] != "done":
                    break
        finally:
            down_w.send(("exit",))

    with SixCoilBench() as bench:
        rig = bench.rig.model_copy(update={"camera": None})
        gc.collect()  # earlier tests' garbage: the host's own collection would take it too
        before = _run_objects()
        driver = threading.Thread(target=operator, args=(rig,), daemon=True)
        driver.start()
        saved = (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT),
                 logging.getLogger().handlers[:], logging.getLogger().level, sys.getswitchinterval())
        try:
            runhost.host_main(down_r, up_w, acks_w, None)  # it sets what the process's are
        finally:
            signal.signal(signal.SIGTERM, saved[0])
            signal.signal(signal.SIGINT, saved[1])
            logging.getLogger().handlers[:] = saved[2]
            logging.getLogger().setLevel(saved[3])
            sys.setswitchinterval(saved[4])
            driver.join(60)
    assert outcomes == ["done", "done", "done"]
    assert _run_objects() == before, "an ended run's objects are still in the interpreter"
