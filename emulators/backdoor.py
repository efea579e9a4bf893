"""An emulated bench's test backdoor: JSON lines, one request per line, one reply per request.

`json_lines(command)` is the server side every bench serves with `serve_lines_tcp`; `BackdoorClient`
is the client side, over the one transport layer.

Only emulated rig files carry a backdoor URL; rigctl uses it to place the robots where the plan
starts (what an operator does by hand on a real rig) and, until the camera loop exists, to read
ground truth.
"""

from __future__ import annotations

import json
from typing import Any, Callable

from rigctl.core.errors import DeviceError
from rigctl.core.transport import open_transport


def json_lines(command: Callable[[dict], dict]) -> Callable[[str], str]:
    """A line handler that decodes a request object, runs `command(request)` and encodes
    `{"ok": true, **result}`; anything that goes wrong, bad JSON included, is answered as
    `{"ok": false, "error": ...}` so the backdoor never dies on a line."""

    def handle(line: str) -> str:
        try:
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ValueError("a request is a JSON object")
            reply = command(request)
        except Exception as err:  # the backdoor answers every line, whatever it was
            return json.dumps({"ok": False, "error": f"{type(err).__name__}: {err}"})
        return json.dumps({"ok": True, **reply})

    return handle


class BackdoorClient:
    def __init__(self, url: str, *, timeout_s: float = 5.0) -> None:
        self.url = url
        self._transport = open_transport(url, timeout_s=timeout_s)

    def request(self, cmd: str, **args: Any) -> dict:
        self._transport.write((json.dumps({"cmd": cmd, **args}) + "\n").encode())
        reply = json.loads(self._transport.read_until(b"\n"))
        if not reply.get("ok"):
            raise DeviceError(reply.get("error", "backdoor refused"), device="bench backdoor")
        return reply

    def close(self) -> None:
        self._transport.close()

    def __enter__(self) -> "BackdoorClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
