"""The stream-rate telemetry messages read back as their models (a supply that gave no reading:
null, which `Telemetry.receive` refused until `measured` allowed it) and carry the cycles offered,
rounded as documented, through the rows the stream process sends (`CycleBatch.row`,
`from_rows`)."""

import math
import time

import numpy as np
import zmq

from rigctl.apps.daemon.messages import parse_telemetry
from rigctl.apps.daemon.telemetry import CycleBatch, TelemetryPublisher
from rigctl.core.channels import Channel


def received(sub: zmq.Socket, topics: set[str], timeout_s: float = 5.0) -> dict[str, bytes]:
    found: dict[str, bytes] = {}
    deadline = time.monotonic() + timeout_s
    while topics - found.keys() and time.monotonic() < deadline:
        if sub.poll(100):
            topic, body = sub.recv_multipart()
            found.setdefault(topic.decode(), body)
    return found


def test_stream_rate_messages_are_their_models_bytes_and_carry_the_cycles():
    context = zmq.Context()
    actuation = np.arange(18.0).reshape(3, 6) * 1e-4
    publisher = TelemetryPublisher(context, "tcp://127.0.0.1:0", "tcp://127.0.0.1:0",
                                   channels=[Channel(f"c{i}", "A") for i in range(6)],
                                   actuation_matrix_T_per_A=actuation, batch_s=0.01,
                                   clock_origin=0.0)
    sub = context.socket(zmq.SUB)
    sub.connect(publisher.data_endpoint)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    publisher.start()
    try:
        time.sleep(0.3)  # the subscription reaches the publisher
        publisher.reset_stream(1000)
        rng = np.random.default_rng(3)
        commanded = rng.normal(0, 3, (5, 6))
        measured = commanded + rng.normal(0, 0.01, (5, 6))
        measured[2, 4] = np.nan  # a supply that did not answer
        rows = [CycleBatch.row(10.0 + 1e-3 * i + 1.23e-7, 40 + i, i - 1, commanded[i], measured[i],
                               None if i == 0 else 2e-6 * i) for i in range(5)]
        publisher.offer_cycles(CycleBatch.from_rows(rows))
        bodies = received(sub, {"actuators", "field", "stream"})
    finally:
        sub.close(linger=0)
        publisher.stop()
        context.term()

    assert bodies.keys() == {"actuators", "field", "stream"}
    for body in bodies.values():
        assert parse_telemetry(body).model_dump_json().encode() == body

    actuators = parse_telemetry(bodies["actuators"])
    assert actuators.samples == [40, 41, 42, 43, 44] and actuators.moves == [-1, 0, 1, 2, 3]
    assert actuators.times == [round(10.0 + 1e-3 * i + 1.23e-7, 6) for i in range(5)]
    assert actuators.channels == [f"c{i}" for i in range(6)] and actuators.units == ["A"] * 6
    for i in range(5):
        assert actuators.commanded[i] == [round(float(x), 5) for x in commanded[i]]
        for got, want in zip(actuators.measured[i], measured[i]):
            assert (got is None) if math.isnan(want) else got == round(float(want), 5)

    field = parse_telemetry(bodies["field"])
    want = [sum(actuation[r, c] * commanded[4, c] for c in range(6)) * 1e3 for r in range(3)]
    assert np.allclose(field.commanded_mT, want, atol=1e-6)

    stream = parse_telemetry(bodies["stream"])
    assert stream.rate_hz == 1000.0 and stream.cycles == 5 and stream.late_cycles == 0
    assert stream.period_error_max_us == 8.0  # the largest error offered, 2e-6 * 4 s
