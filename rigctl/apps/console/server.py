"""The operator console: a web page served from inside `rigctl daemon --console`, live from the
daemon's own telemetry, controlling the rig through the daemon's own command socket.

No second state machine: the console is a client of the daemon like any other. It subscribes to
both telemetry sockets and forwards every message to each page over a WebSocket as it came (the
`frame` and `agents` messages with the plan's pixels added, see `rigctl.apps.console.scene`), polls
`status` for all pages at once (`STATUS_POLL_S`, however many pages watch), and carries a page's
buttons to the command socket as the same requests `rigctl pause|resume|abort|estop|...` send.

It runs in a thread of its own with its own asyncio loop (aiohttp: the HTTP server and the
WebSocket in one well-kept library), so a page never delays the daemon's command thread or the
stream, and a slow page only loses its own oldest messages (`PAGE_QUEUE`). Requests to the daemon
go through three single-threaded clients: the e-stop's own (never queued behind a `load`), the
status poll's, and one for every other command.

Security (docs/console.md): the page and watching need no key on loopback; every control, the
e-stop included, needs the token printed at start-up (compared in constant time), which a page
sends in its first WebSocket message; beyond loopback the console refuses to start without TLS
(`cert`, `key`) and then watching needs the token too. A WebSocket whose `Origin` is not the
console's own is refused (another site's page in the operator's browser cannot reach it), and on
loopback so is a request whose `Host` is not a loopback name (DNS rebinding).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import re
import ssl
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rigctl.apps.console.records import add_record_routes
from rigctl.apps.console.scene import ArmsSketch, CameraScene
from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError
from rigctl.core.tokens import new_token, token_matches
from rigctl.rigs.base import RigKind

log = logging.getLogger(__name__)

STATIC = Path(__file__).resolve().parent / "static"
DEFAULT_ADDRESS = "127.0.0.1:7820"
STATUS_POLL_S = 0.25  # one `status` for every page this often
ARMS_HZ = 10.0  # the dual-EPM sketch from the measured joints at most this often
PAGE_QUEUE = 256  # messages queued per page (a few MB of frames at most); a slower page loses its oldest
HELLO_TIMEOUT_S = 5.0
MAX_UPLOAD_BYTES = 4 * 1024 * 1024  # the daemon's own request bound
CONTROL_COMMANDS = {"load", "load_file", "execute", "pause", "resume", "abort", "reset", "estop",
                    "teleop", "steer", "plan_goals"}
WATCH_COMMANDS = {"runs", "run", "plans"}
LOOPBACK_NAMES = {"localhost", "127.0.0.1", "::1"}
_RUN_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,254}$")


def parse_address(text: str | None) -> tuple[str, int]:
    """`HOST:PORT`, `[IPv6]:PORT`, `:PORT` or `PORT` (loopback) -> (host, port); ConfigError
    naming the address otherwise."""
    text = (text or DEFAULT_ADDRESS).strip()
    host, port = "127.0.0.1", text
    if not text.isdigit():
        match = re.fullmatch(r"(?:\[(?P<v6>[0-9a-fA-F:.]+)\]|(?P<host>[^:\[\]]*)):(?P<port>\d{1,5})",
                             text)
        if match is None:
            raise ConfigError(f"--console {text!r}: expected HOST:PORT, e.g. 127.0.0.1:7820")
        host = match.group("v6") or match.group("host") or host
        port = match.group("port")
    if int(port) > 65535:
        raise ConfigError(f"--console {text!r}: port {port} is over 65535")
    return host, int(port)


def check_options(address: str | None, cert: str | Path | None, key: str | Path | None,
                  plans_dir: str | Path | None = None) -> tuple[str, int]:
    """The console's options checked before anything starts (ConfigError naming the wrong one):
    the address, TLS for anything beyond loopback, both TLS files, the plans folder."""
    host, port = parse_address(address)
    if (cert is None) != (key is None):
        raise ConfigError("TLS needs both --console-cert and --console-key")
    if not is_loopback_host(host) and cert is None:
        raise ConfigError(f"--console {host}:{port} is reachable from other machines: it needs "
                          "TLS (--console-cert CERT.pem --console-key KEY.pem) and the token; "
                          "on loopback it needs neither to watch")
    for path, what in ((cert, "--console-cert"), (key, "--console-key")):
        if path is not None and not Path(path).is_file():
            raise ConfigError(f"{what} {path}: no such file")
    if plans_dir is not None and not Path(plans_dir).is_dir():
        raise ConfigError(f"--console-plans {plans_dir}: not a folder")
    return host, port


def is_loopback_host(host: str) -> bool:
    import ipaddress

    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(eq=False)  # a page is itself: hashed by identity
class _Page:
    """One page's WebSocket and what waits for it: messages in order (at most PAGE_QUEUE, the
    oldest lost first) and the newest camera frame alone (a page that falls behind skips frames
    rather than drawing old ones late)."""

    ws: Any
    queue: deque = field(default_factory=lambda: deque(maxlen=PAGE_QUEUE))
    frame: bytes | None = None
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    authenticated: bool = False


def console_scene(kind: RigKind, rig: RigConfig) -> tuple[str, dict | None]:
    """(the page's scene, what an "arms" scene draws) for a rig of `kind`, as the kind says
    (`RigKind.scene`, `scene_of`): "camera" (the overhead image and the plan over it) unless
    the kind asks for its "arms" and says what they are; a scene the console does not know is
    shown as the camera's, with a warning."""
    if kind.scene == "arms" and kind.scene_of is not None:
        return "arms", kind.scene_of(rig)
    if kind.scene != "camera":
        log.warning("rig kind %s asks for a %r scene, which the console does not draw%s: shown "
                    "as the camera's", kind.name, kind.scene,
                    "" if kind.scene != "arms" else " without scene_of")
    return "camera", None


class Console:
    """The console of one daemon: `start()` binds and returns the page's URL, `stop()` ends it.

    rig: the daemon's rig; command_endpoint: its command socket; runs_dir: its run records;
    clock_origin: the daemon's `t0` (monotonic s), which telemetry times count from.
    """

    def __init__(self, rig: RigConfig, *, command_endpoint: str, runs_dir: str | Path,
                 clock_origin: float, address: str | None = None, token: str | None = None,
                 cert: str | Path | None = None, key: str | Path | None = None,
                 plans_dir: str | Path | None = None, server_key: str | Path | None = None,
                 client_key: str | Path | None = None) -> None:
        self.rig = rig
        self.command_endpoint = command_endpoint
        self.runs_dir = Path(runs_dir)
        self.t0 = clock_origin
        self.host, self.port = check_options(address, cert, key, plans_dir)
        self.loopback = is_loopback_host(self.host)
        self.ssl: ssl.SSLContext | None = None
        if cert is not None:
            self.ssl = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            try:
                self.ssl.load_cert_chain(str(cert), str(key))
            except (OSError, ssl.SSLError) as err:
                raise ConfigError(f"cannot use the console's TLS certificate {cert}: {err}") from None
        self.scheme = "https" if self.ssl else "http"
        self.token = token or new_token()
        self.plans_dir = Path(plans_dir) if plans_dir is not None else None
        self._curve = (server_key, client_key)
        from rigctl.core.registry import rig_kind

        self.scene = console_scene(rig_kind(rig.rig.kind), rig)
        self.camera = CameraScene(rig)
        self.arms = ArmsSketch(self.scene[1])
        self._pages: set[_Page] = set()
        self._commands: set[asyncio.Task] = set()  # commands in flight (kept until done)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._failure: BaseException | None = None
        self._stopping: asyncio.Event | None = None
        self._pools = {name: ThreadPoolExecutor(1, thread_name_prefix=f"console-{name}")
                       for name in ("estop", "status", "control", "steer")}
        self._clients: dict[str, Any] = {}
        self._plans: dict[str, dict] = {}  # plan_id -> document, for plans loaded here
        self._scene_for: str | None = None
        self._scene: dict = {}
        self._status: dict | None = None
        self._last_arms = 0.0
        self._expected: list | None = None  # the running plan's positions after each move
        self._last_move = -1
        self.url: str | None = None

    # -- life cycle (any thread) ---------------------------------------------------------------
    def start(self, timeout_s: float = 10.0) -> str:
        """Bind and serve in a thread of its own; returns the page's URL (without the token)."""
        self._thread = threading.Thread(target=self._serve, name="console", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise ConfigError(f"the console did not start within {timeout_s:g} s")
        if self._failure is not None:
            raise ConfigError(f"cannot serve the console on {self.host}:{self.port}: "
                              f"{self._failure}") from None
        return self.url or ""

    def stop(self) -> None:
        loop, stopping = self._loop, self._stopping
        if loop is not None and stopping is not None and not loop.is_closed():
            loop.call_soon_threadsafe(stopping.set)
        if self._thread is not None:
            self._thread.join(5)
        for name, pool in self._pools.items():
            client = self._clients.pop(name, None)
            if client is not None:
                pool.submit(client.close)
            pool.shutdown(wait=False, cancel_futures=True)  # a request in flight ends by its timeout

    def _serve(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._main())
        except BaseException as err:  # reported by start(), or logged once serving
            if not self._ready.is_set():
                self._failure = err
                self._ready.set()
            else:
                log.exception("the console stopped")
        finally:
            loop.close()

    async def _main(self) -> None:
        from aiohttp import web

        self._stopping = asyncio.Event()
        app = web.Application(client_max_size=MAX_UPLOAD_BYTES + 4096)
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/runs/{run}/report.png", self._report)
        app.router.add_static("/static/", STATIC, show_index=False)
        add_record_routes(app, self.runs_dir,  # the run viewer: /viewer?run=ID, /records/...
                          lambda r: self._host_allowed(r) and self._may_watch(r))
        app.on_response_prepare.append(self._headers)
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        site = web.TCPSite(runner, self.host, self.port, ssl_context=self.ssl)
        await site.start()
        sockets = site._server.sockets if site._server is not None else []  # the port of :0
        port = sockets[0].getsockname()[1] if sockets else self.port
        host = f"[{self.host}]" if ":" in self.host else self.host
        self.port = port
        self.url = f"{self.scheme}://{host}:{port}/"
        tasks = [asyncio.create_task(self._telemetry()), asyncio.create_task(self._poll_status()),
                 asyncio.create_task(self._warm_estop())]
        self._ready.set()
        try:
            await self._stopping.wait()
        finally:
            for task in tasks:
                task.cancel()
            for page in list(self._pages):
                await page.ws.close()
            await runner.cleanup()

    # -- the daemon's command socket ------------------------------------------------------------
    def _client(self, name: str) -> Any:
        """The client of pool `name`, made on that pool's one thread (a REQ socket stays there)."""
        client = self._clients.get(name)
        if client is None:
            from rigctl.apps.client import Rig

            server_key, client_key = self._curve
            # the e-stop: short and retried once; the status poll: never retried (the next poll
            # is the retry, and a daemon that stopped must not hold the console's shutdown)
            # steering (teleop.js, every 50 ms): never behind a `load`, never retried (an input
            # sent again late would drive the rig again after it was let go)
            timeout_s, retries = {"estop": (0.5, 1), "status": (2.0, 0),
                                  "steer": (0.5, 0)}.get(name, (5.0, 2))
            client = self._clients[name] = Rig(self.command_endpoint, timeout_s=timeout_s,
                                               retries=retries, server_key=server_key,
                                               client_key=client_key)
        return client

    async def _request(self, pool: str, cmd: str, timeout_s: float | None = None,
                       **args: Any) -> Any:
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(
            self._pools[pool], lambda: self._client(pool).request(cmd, timeout_s=timeout_s, **args))

    async def _warm_estop(self) -> None:
        """The e-stop's connection to the daemon made now (once the daemon serves), not at the
        first e-stop."""
        from rigctl.core.errors import RigError

        while True:
            try:
                await self._request("estop", "ping")
                return
            except RigError:
                await asyncio.sleep(0.5)

    async def _poll_status(self) -> None:
        from rigctl.core.errors import RigError

        while True:
            try:
                status = await self._request("status", "status")
            except RigError as err:
                status = {"state": "unreachable", "reason": str(err), "device": "daemon"}
            self._status = status
            self._update_scene(status)
            self._broadcast(json.dumps({"topic": "console.status", "status": status,
                                        "t_unix": time.time()}))
            await asyncio.sleep(STATUS_POLL_S)

    def _update_scene(self, status: dict) -> None:
        """When the run changes: the plan's geometry in pixels, to every page."""
        run = status.get("run") or {}
        key = run.get("id") or run.get("plan_id")
        if not key or key == self._scene_for:
            return
        plan = self._plans.get(run.get("plan_id") or "")
        if plan is None and run.get("id") and _RUN_ID.match(run["id"]):
            try:
                plan = json.loads((self.runs_dir / run["id"] / "plan.json").read_text())
            except (OSError, ValueError):
                return  # not written yet: the next poll tries again
        if plan is None:
            return
        self._scene_for = key
        self._expected = plan.get("expected") if isinstance(plan.get("expected"), list) else None
        self._last_move = -1
        self._scene = {"topic": "console.scene", "plan_name": plan.get("name"),
                       "plan_kind": plan.get("kind"), **self.camera.of_plan(plan)}
        self._broadcast(json.dumps(self._scene))

    # -- telemetry ------------------------------------------------------------------------------
    async def _telemetry(self) -> None:
        import zmq
        import zmq.asyncio

        from rigctl.core.errors import RigError

        while True:  # the daemon answers once it serves (it does before the console starts)
            try:
                endpoints = (await self._request("status", "ping"))["telemetry"]
                break
            except RigError as err:
                log.warning("console: no telemetry endpoints yet: %s", err)
                await asyncio.sleep(1.0)
        context = zmq.asyncio.Context()
        sockets = []
        for endpoint in (endpoints["data"], endpoints["events"]):
            sock = context.socket(zmq.SUB)
            sock.setsockopt(zmq.LINGER, 0)
            sock.setsockopt(zmq.RCVHWM, 10_000)
            server_key, client_key = self._curve
            if server_key is not None:
                from rigctl.apps.daemon.keys import load_public, secure_client

                secure_client(sock, load_public(server_key), client_key)
            sock.setsockopt(zmq.SUBSCRIBE, b"")
            sock.connect(endpoint)
            sockets.append(sock)
        poller = zmq.asyncio.Poller()
        for sock in sockets:
            poller.register(sock, zmq.POLLIN)
        try:
            while True:
                newest_frame = None  # of what queued meanwhile, only the newest frame goes on
                for sock, _ in await poller.poll():
                    while True:
                        try:
                            topic, payload = await sock.recv_multipart(flags=zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        if topic == b"frame":
                            newest_frame = payload
                        else:
                            self._forward(topic.decode(), payload)
                if newest_frame is not None:
                    self._forward("frame", newest_frame)
        finally:
            for sock in sockets:
                sock.close(linger=0)
            context.term()

    def _forward(self, topic: str, payload: bytes) -> None:
        """One telemetry message to every page: as it came (a frame's pixels and wall-clock time
        are in it already), `agents` with its positions in the camera's pixels added."""
        if not self._pages:
            return
        if topic == "agents":
            msg = json.loads(payload)
            move = msg.get("move", -1)
            if move >= 0:
                self._last_move = move
            elif self._last_move >= 0 and self._expected is not None:
                # between moves (a pause, a ramp) the daemon says -1 and gives the starts: the
                # agents are expected where the last move left them
                try:
                    msg["expected_mm"] = self._expected[self._last_move]
                except IndexError:
                    pass
            msg["tracked_px"] = self.camera.to_px(msg.get("tracked_mm") or [])
            msg["expected_px"] = self.camera.to_px(msg.get("expected_mm") or [])
            self._broadcast(json.dumps(msg))
        else:
            self._broadcast(payload, frame=topic == "frame")
            if topic == "actuators" and self.arms.available:
                now = time.monotonic()
                if now - self._last_arms >= 1.0 / ARMS_HZ:
                    self._last_arms = now
                    msg = json.loads(payload)
                    if msg.get("measured"):
                        joints = [x if math.isfinite(x) else 0.0 for x in msg["measured"][-1]]
                        if len(joints) == 7 * len(self.arms.arms):
                            self._broadcast(json.dumps({"topic": "console.arms",
                                                        **self.arms.of_joints(joints)}))

    def _broadcast(self, text: str | bytes, frame: bool = False) -> None:
        """Encoded once for every page (UTF-8 JSON, sent as a text frame)."""
        data = text.encode() if isinstance(text, str) else text
        for page in list(self._pages):
            _offer(page, data, frame)

    # -- HTTP -----------------------------------------------------------------------------------
    async def _headers(self, request: Any, response: Any) -> None:
        # the page loads nothing from elsewhere, and no other site may frame it
        response.headers["Content-Security-Policy"] = (
            "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
            "style-src 'self'; script-src 'self'; frame-ancestors 'none'")
        response.headers["X-Content-Type-Options"] = "nosniff"
        response.headers["Cache-Control"] = "no-store"

    def _host_allowed(self, request: Any) -> bool:
        """On loopback, only loopback names in `Host` (a rebinding site's name is refused)."""
        if not self.loopback:
            return True
        host = (request.host or "").rsplit(":", 1)[0].strip("[]") if request.host else ""
        return is_loopback_host(host)

    async def _index(self, request: Any) -> Any:
        from aiohttp import web

        if not self._host_allowed(request):
            raise web.HTTPForbidden(text="refused: not a loopback host name")
        return web.FileResponse(STATIC / "index.html")

    async def _report(self, request: Any) -> Any:
        """A run's report (`rigctl report`), drawn once in a process of its own (matplotlib must
        not hold this process's GIL) and kept in the run's folder."""
        import sys

        from aiohttp import web

        run = request.match_info["run"]
        if not self._host_allowed(request) or not self._may_watch(request):
            raise web.HTTPForbidden(text="refused: the token is needed to watch this console")
        if not _RUN_ID.match(run) or not (self.runs_dir / run).is_dir():
            raise web.HTTPNotFound(text=f"no run {run!r}")
        png = self.runs_dir / run / "report.png"
        if not png.exists():
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "rigctl", "report", str(self.runs_dir / run), "-o", str(png),
                stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
            _, err = await proc.communicate()
            if proc.returncode != 0 or not png.exists():
                raise web.HTTPInternalServerError(
                    text=f"the report could not be drawn: {err.decode()[-300:]}")
        return web.FileResponse(png)

    def _may_watch(self, request: Any) -> bool:
        if self.loopback:
            return True
        given = request.query.get("token") or request.headers.get("Authorization", "").removeprefix(
            "Bearer ")
        return token_matches(given, self.token)

    def _origin_allowed(self, request: Any) -> bool:
        origin = request.headers.get("Origin")
        if origin is None:  # not a browser (a script): the token still gates every control
            return True
        return origin == f"{self.scheme}://{request.host}"

    # -- the page's WebSocket -------------------------------------------------------------------
    async def _websocket(self, request: Any) -> Any:
        from aiohttp import WSMsgType, web

        if not self._host_allowed(request):
            raise web.HTTPForbidden(text="refused: not a loopback host name")
        if not self._origin_allowed(request):
            log.warning("console: refused a WebSocket from origin %s",
                        request.headers.get("Origin"))
            raise web.HTTPForbidden(text="refused: requests from another origin")
        # no permessage-deflate: compressing every frame for every page would cost the daemon's
        # process far more than the bytes it saves on a lab's network
        # a ping every 30 s, the page gone if its pong is not back within 15 s (aiohttp: half the
        # period). At 10 s a busy machine lost a live page: the ping waits behind the camera
        # frames being written to it, and 5 s were not enough (CI, a watching second page)
        ws = web.WebSocketResponse(heartbeat=30.0, max_msg_size=MAX_UPLOAD_BYTES + 4096,
                                   compress=False)
        await ws.prepare(request)
        page = _Page(ws)
        try:
            hello = await ws.receive(timeout=HELLO_TIMEOUT_S)
            token = ""
            if hello.type == WSMsgType.TEXT:
                try:
                    token = str(json.loads(hello.data).get("token") or "")
                except (ValueError, AttributeError):
                    token = ""
            page.authenticated = token_matches(token, self.token)
            if not page.authenticated and not self.loopback:
                await ws.send_str(json.dumps({"topic": "console.refused", "reason":
                                              "this console needs the token to watch"}))
                await ws.close()
                return ws
            await ws.send_str(json.dumps(self._hello(page)))
            if self._scene:
                await ws.send_str(json.dumps(self._scene))
            self._pages.add(page)
            writer = asyncio.create_task(_write(page))
            try:
                async for message in ws:
                    if message.type != WSMsgType.TEXT:
                        break
                    # the loop keeps only a weak reference to a task: a command (the e-stop among
                    # them) is held here until it is done, or it could be collected mid-flight
                    command = asyncio.create_task(self._command(page, message.data))
                    self._commands.add(command)
                    command.add_done_callback(self._commands.discard)
            finally:
                writer.cancel()
        except TimeoutError:
            await ws.close()
        finally:
            self._pages.discard(page)
        return ws

    def _hello(self, page: _Page) -> dict:
        from rigctl.core.registry import rig_kind

        channels = [{"name": c.name, "unit": c.unit, "low": c.low, "high": c.high,
                     "group": c.group} for c in rig_kind(self.rig.rig.kind).channels(self.rig)]
        calibration = self.camera.calibration
        return {"topic": "console.hello", "authenticated": page.authenticated,
                "rig": {"name": self.rig.rig.name, "kind": self.rig.rig.kind,
                        "emulated": self.rig.emulated, "channels": channels,
                        "rate_hz": self.rig.stream.rate_hz,
                        "camera": None if self.rig.camera is None else {
                            "resolution": (calibration.resolution
                                           if calibration is not None else None)},
                        "scene": self.scene[0],
                        "arms": self.arms.names if self.arms.available else None},
                "plans": self._plan_files(), "status": self._status}

    def _plan_files(self) -> list[str]:
        if self.plans_dir is None:
            return []
        return sorted(p.name for p in self.plans_dir.glob("*.json") if p.is_file())[:500]

    async def _command(self, page: _Page, text: str) -> None:
        """One request from a page: `{"id", "cmd", "args"}`, answered `console.reply`."""
        from rigctl.apps.client import CommandRefused
        from rigctl.core.errors import RigError

        request_id = None
        try:
            request = json.loads(text)
            request_id = request.get("id")
            cmd, args = str(request.get("cmd")), dict(request.get("args") or {})
            if cmd not in CONTROL_COMMANDS | WATCH_COMMANDS:
                raise _Refused("unknown_command", f"the console has no command {cmd!r}")
            if cmd in CONTROL_COMMANDS and not page.authenticated:
                raise _Refused("not_authorised", "controlling needs the token printed when "
                               "the daemon started (open the page with its #token=...)")
            result = await self._carry_out(cmd, args)
            reply = {"ok": True, "result": result}
        except _Refused as err:
            reply = {"ok": False, "error": {"code": err.code, "message": err.message}}
        except CommandRefused as err:
            reply = {"ok": False, "error": {"code": err.code, "message": err.reason}}
        except RigError as err:
            reply = {"ok": False, "error": {"code": "device", "message": str(err)}}
        except (ValueError, TypeError, AttributeError) as err:
            reply = {"ok": False, "error": {"code": "bad_request", "message": str(err)}}
        _offer(page, json.dumps({"topic": "console.reply", "id": request_id, **reply}))

    async def _carry_out(self, cmd: str, args: dict) -> Any:
        if cmd == "estop":
            return await self._request("estop", "estop")
        if cmd == "plans":
            return self._plan_files()
        if cmd == "load_file":
            name = str(args.get("name", ""))
            if self.plans_dir is None or name not in self._plan_files():
                raise _Refused("bad_args", f"no plan {name!r} in the console's plans folder")
            try:
                plan = json.loads((self.plans_dir / name).read_text())
            except (OSError, ValueError) as err:
                raise _Refused("plan_invalid", f"{name}: not a readable JSON plan ({err})") from None
            cmd, args = "load", {"plan": plan}
        if cmd == "load":
            plan = args.get("plan")
            if not isinstance(plan, dict):
                raise _Refused("bad_args", "load needs {\"plan\": {...plan document...}}")
            result = await self._request("control", "load", timeout_s=30.0, plan=plan)
            self._plans[result["plan_id"]] = plan
            while len(self._plans) > 32:
                self._plans.pop(next(iter(self._plans)))
            return result
        if cmd == "steer":
            return await self._request("steer", "steer", **args)
        if cmd == "teleop":  # answered once the session streams
            return await self._request("control", "teleop", timeout_s=30.0, **args)
        if cmd == "plan_goals":  # waits for the planner (docs/click-a-goal.md); its plan drawn
            result = await self._request("control", cmd, timeout_s=float(
                args.get("budget_s", 5.0)) + 35.0, **args)  # like a loaded one's when it runs
            self._plans[result["plan_id"]] = result["plan"]
            return result
        return await self._request("control", cmd, **args)


class _Refused(Exception):
    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code, self.message = code, message


def _offer(page: _Page, text: str | bytes, frame: bool = False) -> None:
    """Queue a message (UTF-8 JSON) for a page: a frame replaces the one not yet sent; anything
    else queues (a full queue loses its oldest message)."""
    data = text.encode() if isinstance(text, str) else text
    if frame:
        page.frame = data
    else:
        page.queue.append(data)
    page.wake.set()


async def _write(page: _Page) -> None:
    from aiohttp import WSMsgType

    while not page.ws.closed:
        await page.wake.wait()
        page.wake.clear()
        try:
            while page.queue:
                await page.ws.send_frame(page.queue.popleft(), WSMsgType.TEXT)
            frame, page.frame = page.frame, None
            if frame is not None:
                await page.ws.send_frame(frame, WSMsgType.TEXT)
        except ConnectionError:
            return
