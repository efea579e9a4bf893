"""Client side of an emulated bench's test backdoor: JSON lines over the one transport layer.

Only emulated rig files carry a backdoor URL; rigctl uses it to place the robots where the plan
starts (what an operator does by hand on a real rig) and, until the camera loop exists, to read
ground truth.
"""

from __future__ import annotations

import json
from typing import Any

from rigctl.errors import DeviceError
from rigctl.transport import open_transport


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
