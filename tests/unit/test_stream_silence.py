"""The daemon's watch on a streaming run's stream process (`RemoteRun._silent_for`): cycles stop
coming when the stream loop ends, and making the devices safe and writing the summary then take
what they take (under load, more than the watch's limit): the stream process says so, and the
watch stops timing there instead of killing a process that is only finishing."""

import time

import numpy as np

from rigctl.apps.daemon.runhost import RemoteRun
from rigctl.apps.daemon.telemetry import CycleBatch
from rigctl.core.registry import rig_kind


def a_remote_run() -> RemoteRun:
    rig = rig_kind("six-coil").bench_rig()
    return RemoteRun(None, ("run",), rig, plan=None, info={}, on_cycles=lambda batch: None,
                     on_state=lambda state, info: None)


def cycles() -> tuple:
    row = CycleBatch.row(time.monotonic(), 0, 0, np.zeros(6), np.zeros(6), 0.0)
    return ("cycles", np.array([row]))


def test_cycles_start_the_watch_and_the_end_of_the_stream_stops_it():
    run = a_remote_run()
    assert run._silent_for() == 0.0  # not streaming yet
    run._receive(cycles())
    time.sleep(0.05)
    assert run._silent_for() >= 0.05  # streaming, and silent since the last cycles
    run._receive(("stream_over",))
    time.sleep(0.05)
    assert run._silent_for() == 0.0  # finishing: not timed
