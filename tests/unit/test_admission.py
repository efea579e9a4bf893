"""The request budget: a token bucket refilled at the rate, a queue answered in arrival order,
control commands never held, a bounded queue (`rigctl.apps.daemon.admission`)."""

from __future__ import annotations

import json

from rigctl.apps.daemon.admission import Admission

STATUS = b'{"cmd":"status"}'


def frames(client: bytes, body: bytes = STATUS) -> list[bytes]:
    return [client, b"", body]


def test_a_burst_is_answered_then_requests_wait_and_come_out_at_the_rate_in_arrival_order():
    t = 1000.0
    a = Admission(rate_hz=100.0, burst=5, per_client=4, max_waiting=100, now=t)
    verdicts = [a.offer(frames(b"c%d" % i), b"c%d" % i, STATUS, t) for i in range(12)]
    assert verdicts == ["answer"] * 5 + ["wait"] * 7
    assert list(a.ready(t)) == []  # no time, no token
    assert abs(a.next_s(t) - 0.01) < 1e-9  # one token every 1/100 s
    out = list(a.ready(t + 0.035))  # 3.5 tokens: three requests, the oldest first
    assert [f[0] for f in out] == [b"c5", b"c6", b"c7"]
    out = list(a.ready(t + 1.0))  # the rest; the bucket never holds more than the burst
    assert [f[0] for f in out] == [b"c8", b"c9", b"c10", b"c11"]
    assert a.waiting == 0 and a.next_s(t + 1.0) is None and a.held == 7


def test_control_commands_never_wait_and_a_queued_query_keeps_its_place():
    t = 5.0
    a = Admission(rate_hz=10.0, burst=1, now=t)
    assert a.offer(frames(b"x"), b"x", STATUS, t) == "answer"
    assert a.offer(frames(b"x"), b"x", STATUS, t) == "wait"
    for cmd in ("estop", "abort", "pause", "resume", "reset", "execute", "load", "hold",
                "set_field"):
        body = json.dumps({"id": "op-1", "cmd": cmd}).encode()
        assert a.offer(frames(b"op", body), b"op", body, t) == "answer", cmd
    # spelled with JSON escapes (json.dumps with ensure_ascii writes "\u00e9" too): still control
    escaped = b'{"cmd": "\\u0065stop", "id": "op-\\u00e9"}'
    assert json.loads(escaped)["cmd"] == "estop"
    assert a.offer(frames(b"op", escaped), b"op", escaped, t) == "answer"
    # what is not a control command waits, garbage included, and a query naming one in its id
    for body in (b'{"cmd":"ping"}', b'{"cmd":"runs"}', b"not json", b'{"cmd":["estop"]}',
                 b'{"cmd":"status","id":"after-estop"}'):
        assert a.offer(frames(b"y", body), b"y", body, t) == "wait"
    assert a.waiting == 6


def test_a_client_with_too_many_waiting_and_a_full_queue_are_answered_busy():
    t = 0.0
    a = Admission(rate_hz=1.0, burst=1, per_client=3, max_waiting=5, now=t)
    assert [a.offer(frames(b"d"), b"d", STATUS, t) for _ in range(5)] == \
        ["answer"] + ["wait"] * 3 + ["busy"]
    assert [a.offer(frames(b"e%d" % i), b"e%d" % i, STATUS, t) for i in range(3)] == \
        ["wait", "wait", "busy"]
    assert a.refused == 2 and a.waiting == 5
    assert len(list(a.ready(t + 1.0))) == 1  # one token a second
    assert a.offer(frames(b"d"), b"d", STATUS, t + 1.0) == "wait"  # room again for d
