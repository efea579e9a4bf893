"""The daemon's `field` telemetry on an MPEM rig: the field at the workspace centre is A I plus
the calibration's Offset field (what the supplies off leave: the earth's field, remanence), so the
console's field plot is true on every electromagnet rig (issue 37)."""

import time

import numpy as np
import zmq

from rigctl.apps.daemon.messages import parse_telemetry
from rigctl.apps.daemon.telemetry import CycleBatch, TelemetryPublisher
from rigctl.core.channels import Channel


def test_the_field_telemetry_adds_the_offset_field():
    context = zmq.Context()
    actuation = np.arange(24.0).reshape(3, 8) * 1e-4
    offset_T = np.array([2e-5, 0.0, -4.5e-5])
    publisher = TelemetryPublisher(context, "tcp://127.0.0.1:0", "tcp://127.0.0.1:0",
                                   channels=[Channel(f"c{i}", "A") for i in range(8)],
                                   actuation_matrix_T_per_A=actuation, field_offset_T=offset_T,
                                   batch_s=0.01, clock_origin=0.0)
    sub = context.socket(zmq.SUB)
    sub.connect(publisher.data_endpoint)
    sub.setsockopt(zmq.SUBSCRIBE, b"field")
    publisher.start()
    try:
        time.sleep(0.3)  # the subscription reaches the publisher
        publisher.reset_stream(1000)
        currents = np.linspace(-2.0, 2.0, 8)
        publisher.offer_cycles(CycleBatch.from_rows(
            [CycleBatch.row(1.0, 0, 0, currents, currents, None)]))
        body = None
        deadline = time.monotonic() + 5.0
        while body is None and time.monotonic() < deadline:
            if sub.poll(100):
                body = sub.recv_multipart()[1]
    finally:
        sub.close(linger=0)
        publisher.stop()
        context.term()
    assert body is not None
    field = parse_telemetry(body)
    want = [(sum(actuation[r, c] * currents[c] for c in range(8)) + offset_T[r]) * 1e3
            for r in range(3)]
    np.testing.assert_allclose(field.commanded_mT, want, atol=1e-6)
    np.testing.assert_allclose(field.measured_mT, want, atol=1e-6)
