"""The telemetry publisher under a subscriber that never reads: the stream thread's hand-over stays
cheap, memory stays bounded, and every `state` message still reaches every subscriber, the stalled
one included, while its currents are dropped."""

import time

import numpy as np
import pytest
import zmq

from rigctl.apps.client import Telemetry
from rigctl.apps.daemon.messages import DaemonState, Topic
from rigctl.apps.daemon.telemetry import CycleBatch, TelemetryPublisher
from rigctl.core.channels import Channel

# no process started (emulators, where there are any, serve real sockets from this process): the
# quick tier
pytestmark = pytest.mark.quick


def test_a_stalled_subscriber_loses_currents_but_no_state_and_never_slows_the_stream():
    context = zmq.Context()
    publisher = TelemetryPublisher(context, "tcp://127.0.0.1:0", "tcp://127.0.0.1:0",
                                   channels=[Channel(f"c{i}", "A") for i in range(6)],
                                   actuation_matrix_T_per_A=np.ones((3, 6)) * 1e-4,
                                   queue_batches=100, batch_s=0.005)
    publisher.start()
    stalled = Telemetry(publisher.data_endpoint, publisher.events_endpoint, context=context,
                        receive_hwm=10)
    for sock in stalled.sockets:  # a small kernel buffer, so its queues fill quickly
        sock.setsockopt(zmq.RCVBUF, 4096)
    reader = Telemetry(publisher.data_endpoint, publisher.events_endpoint, ["state"],
                       context=context)
    try:
        # readiness: both subscriptions are in place once a state message reaches them
        seen = {"stalled": False, "reader": False}
        deadline = time.monotonic() + 5
        while not all(seen.values()):
            assert time.monotonic() < deadline, "subscriptions never became ready"
            publisher.publish_event(Topic.STATE, state=DaemonState.IDLE)
            for name, feed in (("stalled", stalled), ("reader", reader)):
                while (msg := feed.receive(timeout_s=0.02)) is not None:
                    seen[name] = seen[name] or msg.topic == "state"
        first_state_seq = publisher._seq["state"]

        n_states, per_batch = 200, 10
        commanded = np.tile(np.arange(6.0), (per_batch, 1))
        for b in range(10_000):  # 100 000 cycles: a stream flooding far faster than any real rig
            k = np.arange(b * per_batch, (b + 1) * per_batch)
            publisher.offer_cycles(CycleBatch(k * 1e-3, k, np.zeros(per_batch, dtype=int),
                                              commanded, commanded * 0.9, np.full(per_batch, 1e-5)))
            if b % 50 == 0:
                publisher.publish_event(Topic.STATE, state=DaemonState.RUNNING if b % 100
                                        else DaemonState.PAUSED)
            assert len(publisher._samples) <= 100  # bounded, whatever the subscribers do
        # (what an offer costs is a speed figure: bench/daemon.py measures the stream under
        # subscribers; a timed assertion here would only flake on a loaded machine)

        states = []
        deadline = time.monotonic() + 10
        while len(states) < n_states and time.monotonic() < deadline:
            msg = reader.receive(timeout_s=0.5)
            if msg is not None and msg.seq >= first_state_seq:
                states.append(msg.seq)
        assert states == list(range(first_state_seq, first_state_seq + n_states))

        # the stalled subscriber now reads: every state is there, currents were dropped
        stalled_states, currents_cycles = [], 0
        while (msg := stalled.receive(timeout_s=1.0)) is not None:
            if msg.topic == "state" and msg.seq >= first_state_seq:
                stalled_states.append(msg.seq)
            elif msg.topic == "actuators":
                currents_cycles += len(msg.samples)
        assert stalled_states == states
        assert currents_cycles < 100_000
    finally:
        stalled.close()
        reader.close()
        publisher.stop()
        context.term()
