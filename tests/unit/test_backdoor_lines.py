"""The benches' shared backdoor line handler: every line gets exactly one JSON reply."""

from __future__ import annotations

import json

from rigctl.emulators.backdoor import json_lines


def _command(request: dict) -> dict:
    if request["cmd"] == "boom":
        raise RuntimeError("the world is on fire")
    return {"echo": request["cmd"]}


def test_a_request_object_is_answered_with_ok_and_the_result() -> None:
    assert json.loads(json_lines(_command)('{"cmd": "ping"}')) == {"ok": True, "echo": "ping"}


def test_bad_lines_and_failing_commands_are_answered_not_raised() -> None:
    handle = json_lines(_command)
    for line, expected in (
        ("not json", "JSONDecodeError"),
        ("[1, 2]", "ValueError: a request is a JSON object"),
        ('{"cmd": "boom"}', "RuntimeError: the world is on fire"),
        ("{}", "KeyError"),
    ):
        reply = json.loads(handle(line))
        assert reply["ok"] is False and reply["error"].startswith(expected), (line, reply)
