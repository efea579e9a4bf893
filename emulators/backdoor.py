"""An emulated bench's test backdoor: JSON lines, one request per line, one reply per request.

`json_lines(command)` is the server side every bench serves with `serve_lines_tcp`; `BackdoorClient`
is the client side, over the one transport layer.

Only emulated rig files carry a backdoor URL; rigctl uses it to place the robots where the plan
starts (what an operator does by hand on a real rig) and, until the camera loop exists, to read
ground truth.

A bench serving beyond loopback takes requests only with its token (`rigctl.core.tokens`, the
console's): every request carries it as `"token"`, and one without it, or with another, is answered
`{"ok": false, "error": "refused: ..."}` and not run. The bench writes the token into the rig file's
`[emulation] backdoor_token` (the file then mode 0600), so a client opened with
`BackdoorClient.of(rig.emulation)` sends it. On loopback there is no token, as for the console's
watching: whoever can reach loopback already runs as a user of this machine.
"""

from __future__ import annotations

import json
import logging
from typing import TYPE_CHECKING, Any, Callable

from rigctl.core.errors import DeviceError
from rigctl.core.tokens import token_matches
from rigctl.core.transport import open_transport

if TYPE_CHECKING:
    from rigctl.core.config import Emulation

log = logging.getLogger(__name__)

REFUSED = ("refused: this bench serves beyond loopback and its backdoor needs the token of the rig "
           "file it wrote ([emulation] backdoor_token)")


def json_lines(command: Callable[[dict], dict], *, token: str | None = None
               ) -> Callable[[str], str]:
    """A line handler that decodes a request object, runs `command(request)` and encodes
    `{"ok": true, **result}`; anything that goes wrong, bad JSON included, is answered as
    `{"ok": false, "error": ...}` so the backdoor never dies on a line. With a `token`, a request
    whose `"token"` is not that one is refused (`REFUSED`) without running."""

    def handle(line: str) -> str:
        try:
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ValueError("a request is a JSON object")
            given = request.pop("token", None)
            if token is not None and not token_matches(given, token):
                log.warning("backdoor: refused a request without the bench's token")
                return json.dumps({"ok": False, "error": REFUSED})
            reply = command(request)
        except Exception as err:  # the backdoor answers every line, whatever it was
            return json.dumps({"ok": False, "error": f"{type(err).__name__}: {err}"})
        return json.dumps({"ok": True, **reply})

    return handle


class BackdoorClient:
    """One connection to a bench's backdoor at `url`; `token`: the bench's, if it has one (a bench
    beyond loopback). `BackdoorClient.of(rig.emulation)` takes both from an emulated rig file."""

    def __init__(self, url: str, *, timeout_s: float = 5.0, token: str | None = None) -> None:
        self.url = url
        self.token = token
        self._transport = open_transport(url, timeout_s=timeout_s)

    @classmethod
    def of(cls, emulation: Emulation, *, timeout_s: float = 5.0) -> BackdoorClient:
        """The backdoor an emulated rig file's `[emulation]` names, with its token if it has one."""
        return cls(emulation.backdoor, timeout_s=timeout_s, token=emulation.backdoor_token)

    def request(self, cmd: str, **args: Any) -> dict:
        """Send `{"cmd": cmd, **args}` (and the token); the reply's fields, DeviceError if the
        bench refused or failed the request."""
        sent = {"cmd": cmd, **args, **({"token": self.token} if self.token is not None else {})}
        self._transport.write((json.dumps(sent) + "\n").encode())
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
