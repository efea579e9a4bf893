"""The emulated camera on the wire: an MJPEG stream over HTTP, as IP cameras and camera servers send.

`serve_camera` puts a camera on the shared `EmulatorServer` loop. A client that GETs `/stream.mjpg`
(or `/`) receives `multipart/x-mixed-replace` parts, one JPEG each, with headers
`X-Timestamp` (the monotonic clock, s, at the instant the scene was captured) and `X-Frame` (the
frame number). The frame number and timestamp are also written into the picture's top rows (see
`rigctl.drivers.camera.write_stamp`), because OpenCV's `VideoCapture` hands over the pixels but not
the part headers.

Each frame: at the tick (in the loop thread) the scene source is called, which is the instant the
frame shows; rendering and JPEG encoding run in one worker thread so the loop keeps serving the
other emulated devices; then the part is written to every client. The camera only renders while a
client is watching. A client that does not keep up loses frames rather than building a queue, as
with a real camera.

Faults (each is in force for every frame captured after the call returns):

- through `camera.endpoint` (the same `Endpoint` as every link): `drop_link()` resets every
  connection and every new one as it connects, `stall()` keeps connections open but sends
  nothing, `corrupt(n)` replaces the next n JPEGs by garbage, `restore()`;
- `drop_frames(n)`: the next n frames are never sent (frame numbers jump);
- `freeze()`: the last frame is sent again and again, with its old timestamp and number;
- `black_out()`: black frames with fresh timestamps (lamp off, lens cap on);
- `occlude(i)`: a glare disc hides robot i (and follows it);
- `restore()` on the camera clears all of these and the link faults.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from rigctl.drivers.camera import write_stamp
from rigctl.emulators.camera.render import Renderer, Scene
from rigctl.emulators.server import CALL_TIMEOUT_S, EmulatorServer, Endpoint, LinkFaults, _reset

log = logging.getLogger(__name__)

SceneSource = Callable[[], "Scene | None"]  # None: nothing to show yet (a black frame)

BOUNDARY = b"rigctlframe"
STREAM_PATHS = ("/", "/stream.mjpg", "/video.mjpg")
MAX_REQUEST_BYTES = 8192
OCCLUDER_SCALE = 1.6  # an occluding glare disc is this many robot radii wide
BACKLOG_FRAMES = 3  # a client more than this many frames behind loses frames


@dataclass
class CameraFaults:
    """The camera-level faults; touched only in the loop thread."""

    drop_remaining: int = 0
    frozen: bool = False
    black: bool = False
    occluded: set[int] = field(default_factory=set)

    def clear(self) -> None:
        self.drop_remaining = 0
        self.frozen = False
        self.black = False
        self.occluded.clear()


@dataclass(frozen=True)
class _Part:
    number: int
    timestamp: float
    jpeg: bytes

    def encode(self, payload: bytes) -> bytes:
        header = (
            b"--" + BOUNDARY + b"\r\nContent-Type: image/jpeg\r\n"
            + b"Content-Length: %d\r\nX-Timestamp: %.6f\r\nX-Frame: %d\r\n\r\n"
            % (len(payload), self.timestamp, self.number)
        )
        return header + payload + b"\r\n"


class _Client(asyncio.Protocol):
    """One HTTP connection: reads the request, then (for the stream path) receives parts."""

    def __init__(self, camera: "MjpegCamera") -> None:
        self.camera = camera
        self.transport: asyncio.Transport | None = None
        self.streaming = False
        self._request = bytearray()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        if self.camera.link_faults.dropped:
            _reset(transport)
            return
        self.transport = transport
        self.camera._clients.add(self)

    def connection_lost(self, exc: Exception | None) -> None:
        self.camera._clients.discard(self)

    def data_received(self, data: bytes) -> None:
        if self.transport is None or self.streaming:
            return  # a streaming client has nothing more to say
        self._request += data
        end = self._request.find(b"\r\n\r\n")
        if end < 0:
            if len(self._request) > MAX_REQUEST_BYTES:
                self.transport.close()
            return
        request_line = bytes(self._request[: self._request.find(b"\r\n")]).decode("latin-1")
        parts = request_line.split()
        path = parts[1].split("?")[0] if len(parts) >= 2 else ""
        if len(parts) < 2 or parts[0] != "GET" or path not in STREAM_PATHS:
            self.transport.write(
                b"HTTP/1.0 404 Not Found\r\nContent-Type: text/plain\r\nConnection: close\r\n\r\n"
                b"the stream is at /stream.mjpg\r\n"
            )
            self.transport.close()
            return
        self.transport.write(
            b"HTTP/1.0 200 OK\r\nServer: rigctl-emulated-camera\r\nCache-Control: no-cache\r\n"
            b"Connection: close\r\nContent-Type: multipart/x-mixed-replace; boundary="
            + BOUNDARY + b"\r\n\r\n"
        )
        self.streaming = True

    def send(self, data: bytes) -> bool:
        """Write one part unless the client is too far behind; False if it was skipped."""
        if self.transport is None or self.transport.is_closing():
            return False
        if self.transport.get_write_buffer_size() > BACKLOG_FRAMES * len(data):
            return False
        self.transport.write(data)
        return True


class MjpegCamera:
    """An emulated overhead camera served as MJPEG over HTTP; start with `serve_camera`.

    source: called in the loop thread at each frame tick, returns the scene at that instant (or None
    before there is anything to show: black frames).
    renderer: draws the scenes (used only by this camera's worker thread).
    """

    def __init__(
        self,
        server: EmulatorServer,
        source: SceneSource,
        renderer: Renderer,
        *,
        name: str = "camera",
        fps: float = 60.0,
        jpeg_quality: int = 85,
        host: str = "127.0.0.1",
        port: int = 0,
    ) -> None:
        if fps <= 0:
            raise ValueError("fps must be positive")
        self.server = server
        self.source = source
        self.renderer = renderer
        self.name = name
        self.fps = float(fps)
        self.jpeg_quality = int(jpeg_quality)
        self.host = host
        self.port = port
        self.faults = CameraFaults()
        self.link_faults = LinkFaults()
        self.frames_captured = 0  # frame numbers handed out, sent or not
        self.frames_sent = 0  # parts written (to at least one client)
        self._clients: set[_Client] = set()
        self._listener: asyncio.AbstractServer | None = None
        self._last_part: _Part | None = None
        self._runner: concurrent.futures.Future | None = None
        self._task: asyncio.Task | None = None
        self.endpoint: Endpoint | None = None

    @property
    def url(self) -> str:
        """The stream URL, e.g. http://127.0.0.1:40123/stream.mjpg."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/stream.mjpg"

    # -- life cycle (called from outside the loop) ------------------------------------------------

    def start(self) -> None:
        """Listen and start the frame clock; returns once the port accepts connections.

        The camera's task lives in the server's loop: `EmulatorServer.stop()` cancels it, which
        closes the listener and every connection. `close()` does the same earlier.
        """
        loop = self.server.call(asyncio.get_running_loop)
        ready: concurrent.futures.Future[int] = concurrent.futures.Future()
        self._runner = asyncio.run_coroutine_threadsafe(self._run(ready), loop)
        try:
            self.port = ready.result(CALL_TIMEOUT_S)
        except BaseException:
            self._runner.cancel()
            raise
        self.endpoint = Endpoint(
            name=self.name, url=self.url, faults=self.link_faults, link=self, server=self.server
        )
        log.info("%s: serving MJPEG on %s at %.0f fps", self.name, self.url, self.fps)

    def close(self) -> None:
        """Stop the camera: the listener and every connection close. Idempotent; after the server
        has stopped there is nothing left to close."""
        runner, self._runner = self._runner, None
        task = self._task
        if runner is None or runner.done() or task is None:
            return

        async def stop() -> None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

        try:
            loop = self.server.call(asyncio.get_running_loop)
        except RuntimeError:  # the server has stopped: its loop already ended the task
            return
        asyncio.run_coroutine_threadsafe(stop(), loop).result(CALL_TIMEOUT_S)

    # -- camera faults --------------------------------------------------------------------------

    def drop_frames(self, n: int) -> None:
        """Never send the next `n` frames."""
        if n < 1:
            raise ValueError("n must be >= 1")
        self.server.call(setattr, self.faults, "drop_remaining", int(n))
        log.info("%s: dropping the next %d frames (fault)", self.name, n)

    def freeze(self) -> None:
        """Send the last frame again and again (old timestamp, old number) until `restore()`."""
        self.server.call(setattr, self.faults, "frozen", True)
        log.info("%s: frozen (fault)", self.name)

    def black_out(self) -> None:
        """Send black frames until `restore()`."""
        self.server.call(setattr, self.faults, "black", True)
        log.info("%s: blacked out (fault)", self.name)

    def occlude(self, robot: int) -> None:
        """Hide robot number `robot` (index into the scene's robots) under a glare disc."""
        self.server.call(self.faults.occluded.add, int(robot))
        log.info("%s: robot %d occluded (fault)", self.name, robot)

    def restore(self) -> None:
        """Clear every camera fault and every link fault."""
        self.server.call(self.faults.clear)
        if self.endpoint is not None:
            self.endpoint.restore()
        log.info("%s: restored", self.name)

    @property
    def clients(self) -> int:
        """Clients receiving the stream now."""
        return self.server.call(lambda: sum(1 for c in self._clients if c.streaming))

    # -- the link interface Endpoint uses (loop thread) ------------------------------------------

    async def cut(self) -> None:
        # The listener stays open: while the link is dropped every new connection is reset as soon
        # as it is accepted (see _Client.connection_made), which a client sees as a refusal.
        for client in list(self._clients):
            if client.transport is not None:
                _reset(client.transport)
        self._clients.clear()

    async def reopen(self) -> None:
        """Nothing to do: the listener never closed."""

    def connection_count(self) -> int:
        return len(self._clients)

    # -- the frame loop (loop thread) -------------------------------------------------------------

    async def _listen(self) -> None:
        loop = asyncio.get_running_loop()
        self._listener = await loop.create_server(
            lambda: _Client(self), self.host, self.port, reuse_address=True
        )
        self.port = self._listener.sockets[0].getsockname()[1]

    def _close_all(self) -> None:
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        for client in list(self._clients):
            if client.transport is not None:
                client.transport.close()
        self._clients.clear()

    async def _run(self, ready: concurrent.futures.Future) -> None:
        self._task = asyncio.current_task()
        executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{self.name}-render")
        try:
            try:
                await self._listen()
            except BaseException as err:
                ready.set_exception(err)
                raise
            ready.set_result(self.port)
            period = 1.0 / self.fps
            next_tick = time.monotonic()
            while True:
                await asyncio.sleep(max(0.0, next_tick - time.monotonic()))
                if any(client.streaming for client in self._clients):
                    try:
                        await self._frame(executor)
                    except Exception:
                        log.exception("%s: making a frame failed; the camera stops", self.name)
                        return
                next_tick += period
                now = time.monotonic()
                if next_tick < now:  # rendering overran: skip ticks rather than bunch frames
                    next_tick = now + period
        finally:
            self._close_all()
            executor.shutdown(wait=False, cancel_futures=True)

    async def _frame(self, executor: ThreadPoolExecutor) -> None:
        """Capture, render and send one frame."""
        timestamp = time.monotonic()
        faults = self.faults
        if faults.frozen and self._last_part is not None:
            self._send(self._last_part)
            return
        number = self.frames_captured
        self.frames_captured += 1
        if faults.drop_remaining > 0:
            faults.drop_remaining -= 1
            return
        scene = None if faults.black else self.source()
        render: Callable[[], np.ndarray]
        if scene is None:
            render = self.renderer.blank
        else:
            if faults.occluded:
                scene = _occlude(scene, faults.occluded)
            render = functools.partial(self.renderer.render, scene)

        loop = asyncio.get_running_loop()
        jpeg = await loop.run_in_executor(executor, self._encode, render, number, timestamp)
        part = _Part(number, timestamp, jpeg)
        self._last_part = part
        self._send(part)

    def _encode(self, render: Callable[[], np.ndarray], number: int, timestamp: float) -> bytes:
        image = render()
        write_stamp(image, timestamp, number)
        ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return buffer.tobytes()

    def _send(self, part: _Part) -> None:
        payload = self.link_faults.outgoing(part.jpeg, b"")
        if payload is None:  # dropped or stalled link
            return
        data = part.encode(payload)
        sent = False
        for client in list(self._clients):
            if client.streaming:
                sent = client.send(data) or sent
        if sent:
            self.frames_sent += 1


def _occlude(scene: Scene, robots: set[int]) -> Scene:
    """The scene with glare discs over the listed robots (indices that exist)."""
    positions = np.asarray(scene.positions_mm, dtype=float).reshape(-1, 2)
    radii = np.broadcast_to(np.asarray(scene.radii_mm, dtype=float), (len(positions),))
    hidden = [i for i in sorted(robots) if 0 <= i < len(positions)]
    if not hidden:
        return scene
    glare = np.column_stack([positions[hidden], OCCLUDER_SCALE * radii[hidden]])
    occluders = np.vstack([np.asarray(scene.occluders_mm).reshape(-1, 3), glare])
    return replace(scene, occluders_mm=occluders)


def serve_camera(
    server: EmulatorServer,
    source: SceneSource,
    renderer: Renderer,
    *,
    name: str = "camera",
    fps: float = 60.0,
    jpeg_quality: int = 85,
    host: str = "127.0.0.1",
    port: int = 0,
) -> MjpegCamera:
    """Serve an emulated camera on `server`; listening when this returns (port 0 = any free port)."""
    camera = MjpegCamera(
        server, source, renderer, name=name, fps=fps, jpeg_quality=jpeg_quality, host=host,
        port=port,
    )
    camera.start()
    return camera
