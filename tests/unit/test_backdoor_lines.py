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


def test_with_a_token_only_a_request_carrying_it_is_run() -> None:
    ran: list[dict] = []
    handle = json_lines(lambda request: ran.append(request) or {}, token="s3cret-token")
    for line in ('{"cmd": "ping"}', '{"cmd": "ping", "token": "s3cret-toke"}',
                 '{"cmd": "ping", "token": null}', '{"cmd": "ping", "token": ["s3cret-token"]}'):
        reply = json.loads(handle(line))
        assert reply["ok"] is False and reply["error"].startswith("refused: "), line
    assert ran == []
    assert json.loads(handle('{"cmd": "ping", "token": "s3cret-token"}')) == {"ok": True}
    assert ran == [{"cmd": "ping"}]  # the token is the backdoor's, not a command's argument
