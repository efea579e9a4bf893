"""The shared emulator server: one asyncio loop in a background thread serving emulated devices.

Each emulated device is a pure model plus a protocol object whose `handle(line) -> reply | None`
the server calls for every received line, always in the loop thread, so a device's state is only
ever touched by one thread. Tests and benches reach into that thread with `call(fn)` (backdoors:
read ground truth, inject device faults) and run periodic work with `every(period, fn)`.

Link faults are independent of the transport: `LinkFaults` says what a link does with incoming
lines and outgoing replies (dropped, stalled, corrupting), and each transport (TCP here, a pty
later) implements only "cut every connection and refuse new ones" and "accept again". The
`Endpoint` a test holds is the same for every transport:

- `drop_link()`  every connection is reset and new connections are refused until `restore()`
- `stall()`      lines are still read but ignored: no reply ever comes (a hung device)
- `corrupt(n)`   the next n replies are replaced by garbage bytes (still terminated)
- `restore()`    back to normal

Every fault method returns once the fault is in force, so tests never sleep to wait for it.
Time is taken from `time.monotonic()`.

A device that may speak unasked (a robot server that acknowledges a move and reports its end
later, a board that streams samples) is served with `serve_sessions_tcp`: its `SessionHandler` is
told of each client (`connected`, `received(session, line)`, `disconnected`) and may call
`session.send(line)` at any time from the loop thread; `serve_lines_tcp` is the special case of
one reply per line. Both share the framing, the faults and `Endpoint.close()`.

Byte protocols without lines (the coil board's binary frames) are served on a pty with
`serve_bytes_pty`: the handler gets every chunk as it arrives and returns bytes to send back. Its
`PtyEndpoint` adds `inject(data)` (bytes to the host, unasked); `drop_link()` is an unplug (the pty
is closed and its stable path removed) and `restore()` a replug (a new pty behind the same path).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
import pty
import socket
import struct
import tempfile
import threading
import time
import tty
from collections.abc import Awaitable, Callable
from typing import Any, Protocol, TypeVar, cast

log = logging.getLogger(__name__)

T = TypeVar("T")

LineHandler = Callable[[str], "str | None"]
ByteHandler = Callable[[bytes], "bytes | None"]

GARBAGE = b"\xfe\x81#%!\x00\xff\x9c"  # not ASCII, no terminator inside
MAX_LINE_BYTES = 65536
MAX_BACKLOG_BYTES = 1 << 20  # a client that leaves this much unread is cut, not queued for
MAX_CLIENTS = 64
CALL_TIMEOUT_S = 5.0


class LinkFaults:
    """What one emulated link does with traffic; shared by every transport's server."""

    def __init__(self) -> None:
        self.dropped = False
        self.stalled = False
        self.corrupt_remaining = 0

    def handles_input(self) -> bool:
        """Whether a received line reaches the device at all (not while dropped or stalled)."""
        return not (self.dropped or self.stalled)

    def outgoing(self, reply: bytes, terminator: bytes) -> bytes | None:
        """The bytes to send for `reply` (without terminator), or None to send nothing."""
        if self.dropped or self.stalled:
            return None
        if self.corrupt_remaining > 0:
            self.corrupt_remaining -= 1
            return GARBAGE + terminator
        return reply + terminator

    def clear(self) -> None:
        self.dropped = False
        self.stalled = False
        self.corrupt_remaining = 0


class _Link(Protocol):
    """The transport-specific part of a fault: cut all connections, and accept again."""

    async def cut(self) -> None: ...

    async def reopen(self) -> None: ...

    def connection_count(self) -> int: ...

    async def close(self) -> None: ...


class Endpoint:
    """One served device link: its URL and its fault switches (callable from any thread)."""

    def __init__(self, *, name: str, url: str, faults: LinkFaults, link: _Link,
                 server: "EmulatorServer") -> None:
        self.name = name
        self.url = url
        self.faults = faults
        self._link = link
        self._server = server

    def drop_link(self) -> None:
        """Reset every connection and refuse new ones until `restore()`."""

        async def drop() -> None:
            self.faults.dropped = True
            await self._link.cut()

        self._server._run(drop())
        log.info("%s: link dropped (fault)", self.name)

    def stall(self) -> None:
        """Keep reading, never answer."""
        self._server.call(setattr, self.faults, "stalled", True)
        log.info("%s: link stalled (fault)", self.name)

    def corrupt(self, n_replies: int = 1) -> None:
        """Replace the next `n_replies` replies with garbage bytes."""
        if n_replies < 1:
            raise ValueError("n_replies must be >= 1")
        self._server.call(setattr, self.faults, "corrupt_remaining", n_replies)
        log.info("%s: next %d replies corrupted (fault)", self.name, n_replies)

    def restore(self) -> None:
        """Clear every fault; a dropped link accepts connections again."""

        async def restore() -> None:
            was_dropped = self.faults.dropped
            self.faults.clear()
            if was_dropped:
                await self._link.reopen()

        self._server._run(restore())
        log.info("%s: link restored", self.name)

    def close(self) -> None:
        """Stop serving this link: stop listening and close every client."""
        self._server._run(self._link.close())
        log.info("%s: link closed", self.name)

    @property
    def connection_count(self) -> int:
        """Clients connected now."""
        return self._server.call(self._link.connection_count)


class SessionHandler(Protocol):
    """A device that may write to its clients at any time, not only in reply to a line (a robot
    server that acknowledges a move and reports its end later, a board that streams samples).
    Every call runs in the loop thread; `session.send(line)` may be called from it at any time."""

    def connected(self, session: "Session") -> None: ...

    def received(self, session: "Session", line: str) -> None: ...

    def disconnected(self, session: "Session") -> None: ...


class _ReplyHandler:
    """A `LineHandler` as a `SessionHandler`: each line's reply (if any) goes back at once."""

    def __init__(self, handler: LineHandler) -> None:
        self.handler = handler

    def connected(self, session: "Session") -> None:
        pass

    def received(self, session: "Session", line: str) -> None:
        reply = self.handler(line)
        if reply is not None:
            session.send(reply)

    def disconnected(self, session: "Session") -> None:
        pass


class Session(asyncio.Protocol):
    """One client of a line link: frames incoming lines for the device and sends its lines,
    both through the link's faults."""

    def __init__(self, link: "_TcpLineLink") -> None:
        self.link = link
        self.transport: asyncio.Transport | None = None
        self._buffer = bytearray()

    @property
    def open(self) -> bool:
        return self.transport is not None and not self.transport.is_closing()

    def send(self, line: str) -> None:
        """Send `line` (no terminator) unless the link drops or stalls or the client is gone; a
        client that has stopped reading (MAX_BACKLOG_BYTES queued) is disconnected."""
        if not self.open:
            return
        assert self.transport is not None
        out = self.link.faults.outgoing(line.encode("ascii", errors="replace"), self.link.terminator)
        if out is None:
            return
        if self.transport.get_write_buffer_size() > MAX_BACKLOG_BYTES:
            log.warning("%s: client does not read; closing it", self.link.name)
            self.transport.close()
            return
        self.transport.write(out)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        link = self.link
        if link.faults.dropped or len(link.connections) >= link.max_clients:
            _reset(transport)
            return
        sock = transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.transport = transport
        link.connections.add(self)
        self._notify("connected")

    def connection_lost(self, exc: Exception | None) -> None:
        if self in self.link.connections:  # once per client, whoever noticed first
            self.link.connections.discard(self)
            self._notify("disconnected")

    def data_received(self, data: bytes) -> None:
        link = self.link
        if self.transport is None:
            return
        self._buffer += data
        terminator = link.terminator
        while self.open:
            index = self._buffer.find(terminator)
            if index < 0:
                if len(self._buffer) > MAX_LINE_BYTES:
                    log.warning("%s: line longer than %d bytes; closing", link.name, MAX_LINE_BYTES)
                    self.close()
                return
            raw = bytes(self._buffer[:index])
            del self._buffer[: index + len(terminator)]
            if not link.faults.handles_input():
                continue
            line = raw.decode("ascii", errors="replace").rstrip("\r")
            try:
                link.handler.received(self, line)
            except Exception:
                log.exception("%s: emulator failed on %r; closing the connection", link.name, line)
                self.close()
                return

    def _notify(self, what: str) -> None:
        try:
            getattr(self.link.handler, what)(self)
        except Exception:
            log.exception("%s: emulator failed in %s; closing the connection", self.link.name, what)
            self.close()


class _TcpLineLink:
    """A TCP listener whose connections carry terminator-framed text lines."""

    def __init__(self, handler: SessionHandler, *, name: str, host: str, port: int,
                 terminator: bytes, faults: LinkFaults, max_clients: int = MAX_CLIENTS) -> None:
        self.handler = handler
        self.name = name
        self.host = host
        self.port = port
        self.terminator = terminator
        self.faults = faults
        self.max_clients = max_clients
        self.connections: set[Session] = set()
        self._server: asyncio.AbstractServer | None = None

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            lambda: Session(self), self.host, self.port, reuse_address=True
        )
        self.port = self._server.sockets[0].getsockname()[1]

    def connection_count(self) -> int:
        return len(self.connections)

    async def _stop_listening(self) -> None:
        if self._server is not None:
            await _settle_accepts()
            self._server.close()  # no await between: no accept can slip in
            self._server = None

    async def cut(self) -> None:
        await self._stop_listening()
        for connection in list(self.connections):
            if connection.transport is not None:
                _reset(connection.transport)
            connection.connection_lost(None)  # the device hears of it now, not a loop turn later

    async def reopen(self) -> None:
        if self._server is None:
            await self.open()

    async def close(self) -> None:
        await self._stop_listening()
        for connection in list(self.connections):
            if connection.transport is not None:
                connection.transport.close()
        self.connections.clear()


async def _settle_accepts() -> None:
    """Let connections asyncio has accepted but not yet set up finish setting up.

    asyncio (3.11) sets an accepted connection up in a task of its own; if the listener closes
    before that task runs, the set-up fails silently and the socket is leaked. Closing right after
    this returns, without awaiting in between, avoids that.
    """
    for _ in range(100):
        if not any(
            not task.done() and "_accept_connection" in getattr(task.get_coro(), "__qualname__", "")
            for task in asyncio.all_tasks()
        ):
            return
        await asyncio.sleep(0)


def _reset(transport: asyncio.Transport) -> None:
    """Close with RST (SO_LINGER 0), as a device that reboots or drops the session does."""
    sock = transport.get_extra_info("socket")
    if sock is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        except OSError:
            pass
    transport.abort()


class EmulatorServer:
    """One asyncio loop in a background thread serving any number of emulated devices."""

    def __init__(self) -> None:
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._links: list[_TcpLineLink] = []
        self._tasks: set[asyncio.Task] = set()

    # -- lifetime -------------------------------------------------------------------------------

    def start(self) -> None:
        """Start the loop thread; returns once the loop is running."""
        if self._thread is not None:
            raise RuntimeError("EmulatorServer already started")
        loop = asyncio.new_event_loop()
        ready = threading.Event()

        def run() -> None:
            asyncio.set_event_loop(loop)
            loop.call_soon(ready.set)
            try:
                loop.run_forever()
            finally:
                pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
                for task in pending:
                    task.cancel()
                loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
                loop.run_until_complete(asyncio.sleep(0))  # transports finish closing
                loop.close()

        self._loop = loop
        self._thread = threading.Thread(target=run, name="emulator-server", daemon=True)
        self._thread.start()
        if not ready.wait(CALL_TIMEOUT_S):
            raise RuntimeError("emulator server loop did not start")
        log.debug("emulator server started")

    def stop(self) -> None:
        """Close every link and periodic task and end the loop thread; idempotent."""
        if self._thread is None or self._loop is None:
            return

        async def shutdown() -> None:
            for task in list(self._tasks):
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)
            for link in self._links:
                await link.close()

        try:
            self._run(shutdown())
        finally:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(CALL_TIMEOUT_S)
            self._thread = None
            self._loop = None
            self._links.clear()
            self._tasks.clear()
            log.debug("emulator server stopped")

    def __enter__(self) -> "EmulatorServer":
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    # -- running things in the loop ---------------------------------------------------------------

    def _in_loop_thread(self) -> bool:
        return self._thread is not None and threading.current_thread() is self._thread

    def _run(self, coroutine: Awaitable[T]) -> T | None:
        """Run `coroutine` in the loop and wait for it; from inside the loop (a backdoor handler
        injecting a fault) it is scheduled instead and takes effect once the handler returns."""
        if self._loop is None:
            coroutine.close()  # type: ignore[attr-defined]
            raise RuntimeError("EmulatorServer is not started")
        if self._in_loop_thread():
            self._loop.create_task(coroutine)  # type: ignore[arg-type]
            return None
        loop = self._loop
        future: concurrent.futures.Future[T] = asyncio.run_coroutine_threadsafe(
            coroutine, loop)  # type: ignore[arg-type]
        try:
            return future.result(CALL_TIMEOUT_S)
        except concurrent.futures.TimeoutError:
            future.cancel()
            raise TimeoutError(f"emulator loop did not finish within {CALL_TIMEOUT_S} s") from None

    def call(self, fn: Callable[..., T], *args: Any) -> T:
        """Run `fn(*args)` in the loop thread and return its result (backdoors, ground truth)."""
        if self._in_loop_thread():
            return fn(*args)

        async def invoke() -> T:
            return fn(*args)

        return cast(T, self._run(invoke()))  # not in the loop thread: the result, never None

    def every(self, period_s: float, fn: Callable[[], None]) -> None:
        """Call `fn()` in the loop every `period_s` seconds (monotonic schedule, no drift).

        Missed ticks are skipped, not bunched. An exception is logged and ends this task.
        """
        if period_s <= 0:
            raise ValueError("period_s must be positive")

        async def periodic() -> None:
            next_tick = time.monotonic() + period_s
            while True:
                await asyncio.sleep(max(0.0, next_tick - time.monotonic()))
                try:
                    fn()
                except Exception:
                    log.exception("periodic emulator task %r failed; stopping it", fn)
                    return
                next_tick += period_s
                now = time.monotonic()
                if next_tick < now:
                    next_tick = now + period_s

        def schedule() -> None:
            task = asyncio.get_running_loop().create_task(periodic())
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

        self.call(schedule)

    # -- serving --------------------------------------------------------------------------------

    def serve_bytes_pty(self, handler: ByteHandler, *, name: str, link_path: str | None = None
                        ) -> "PtyEndpoint":
        """Serve a byte protocol on a pty in raw mode; ready when this returns.

        `handler(data)` gets each received chunk (any split: the handler frames) and returns bytes
        to send, or None. The endpoint's URL is `link_path`, a symlink kept pointing at the current
        pty the way udev keeps /dev/serial/by-id/... for a USB board (default: a fresh path in a
        temporary directory), so a driver reopens the same URL after an unplug and replug.
        """
        faults = LinkFaults()
        link = _PtyByteLink(handler, name=name, faults=faults, link_path=link_path)
        self._run(link.open())
        self._links.append(link)  # type: ignore[arg-type]
        log.info("%s: serving on %s (%s)", name, link.link_path, link.pty_path)
        return PtyEndpoint(name=name, url=link.link_path, faults=faults, link=link, server=self)

    def serve_lines_tcp(
        self,
        handler: LineHandler,
        *,
        name: str,
        host: str = "127.0.0.1",
        port: int = 0,
        terminator: bytes = b"\n",
    ) -> Endpoint:
        """Serve a line protocol on TCP; the endpoint's URL carries the bound port (port 0 = any).

        `handler(line)` gets each line without its terminator (and without a trailing CR) and
        returns the reply without terminator, or None for no reply. Listening when this returns.
        """
        return self.serve_sessions_tcp(_ReplyHandler(handler), name=name, host=host, port=port,
                                       terminator=terminator)

    def serve_sessions_tcp(
        self,
        handler: SessionHandler,
        *,
        name: str,
        host: str = "127.0.0.1",
        port: int = 0,
        terminator: bytes = b"\n",
        max_clients: int = MAX_CLIENTS,
    ) -> Endpoint:
        """Serve a line protocol whose device may also speak unasked (see `SessionHandler`): each
        client is a `Session` the device may `send` to at any time from the loop thread. Clients
        beyond `max_clients` are refused (reset). Same framing, faults and URL as
        `serve_lines_tcp`; listening when this returns."""
        if not terminator:
            raise ValueError("terminator must not be empty")
        if max_clients < 1:
            raise ValueError("max_clients must be >= 1")
        faults = LinkFaults()
        link = _TcpLineLink(handler, name=name, host=host, port=port, terminator=terminator,
                            faults=faults, max_clients=max_clients)
        self._run(link.open())
        self._links.append(link)
        shown_host = f"[{host}]" if ":" in host else host
        url = f"tcp://{shown_host}:{link.port}"
        log.info("%s: serving on %s", name, url)
        return Endpoint(name=name, url=url, faults=faults, link=link, server=self)


class _PtyByteLink:
    """A pty whose master end the loop reads; the slave end is what the driver opens.

    The link keeps its own slave descriptor open while it is up, so the master never sees a hangup
    between two clients and the raw settings stay. An unplug closes both ends (the client's reads
    and writes then fail, as on a vanished /dev/ttyACM0) and removes the stable symlink.
    """

    def __init__(self, handler: ByteHandler, *, name: str, faults: LinkFaults,
                 link_path: str | None) -> None:
        self.handler = handler
        self.name = name
        self.faults = faults
        self._own_dir: str | None = None
        if link_path is None:
            self._own_dir = tempfile.mkdtemp(prefix="rigctl-pty-")
            link_path = os.path.join(self._own_dir, name.replace("/", "_") or "device")
        self.link_path = link_path
        self.pty_path: str | None = None
        self._master = -1
        self._slave = -1
        self._pending = bytearray()  # replies the pty could not take yet

    async def open(self) -> None:
        master, slave = pty.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.pty_path = os.ttyname(slave)
        temporary = f"{self.link_path}.{os.getpid()}.tmp"
        if os.path.lexists(temporary):
            os.unlink(temporary)
        os.symlink(self.pty_path, temporary)
        os.replace(temporary, self.link_path)  # atomic: a client never sees a missing path
        asyncio.get_running_loop().add_reader(master, self._readable)

    def _readable(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except BlockingIOError:
            return
        except OSError as err:
            log.warning("%s: pty read failed (%s)", self.name, err)
            return
        if not data or not self.faults.handles_input():
            return
        try:
            reply = self.handler(data)
        except Exception:
            log.exception("%s: emulator failed on %r; input dropped", self.name, data[:64])
            return
        if reply:
            self.reply(reply)

    def reply(self, data: bytes) -> None:
        """Send the device's own output (loop thread) through the link's faults (stall, corrupt)."""
        out = self.faults.outgoing(data, b"")
        if out:
            self.send(out)

    def send(self, data: bytes) -> None:
        """Write to the client now (loop thread); what the pty cannot take waits for it."""
        if self._master < 0:
            return
        self._pending += data
        self._flush()

    def _flush(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            written = os.write(self._master, self._pending)
        except BlockingIOError:
            written = 0
        except OSError as err:
            log.warning("%s: pty write failed (%s); %d bytes lost", self.name, err, len(self._pending))
            self._pending.clear()
            return
        del self._pending[:written]
        loop.remove_writer(self._master)
        if self._pending:
            loop.add_writer(self._master, self._flush)

    def connection_count(self) -> int:
        return 1 if self._master >= 0 else 0

    async def cut(self) -> None:
        if self._master >= 0:
            loop = asyncio.get_running_loop()
            loop.remove_reader(self._master)
            loop.remove_writer(self._master)
            os.close(self._master)
            os.close(self._slave)
            self._master = self._slave = -1
            self._pending.clear()
        if os.path.lexists(self.link_path):
            os.unlink(self.link_path)

    async def reopen(self) -> None:
        if self._master < 0:
            await self.open()

    async def close(self) -> None:
        await self.cut()
        if self._own_dir is not None:
            try:
                os.rmdir(self._own_dir)
            except OSError:
                pass


class PtyEndpoint(Endpoint):
    """A served pty: the `Endpoint` faults, plus raw bytes to the host and the current pty path."""

    _link: _PtyByteLink

    def inject(self, data: bytes) -> None:
        """Send `data` to the host now, unasked (garbage on the line); returns once written."""
        self._server.call(self._link.send, bytes(data))

    @property
    def pty_path(self) -> str | None:
        """The /dev/pts/N behind the URL now (None while unplugged)."""
        return self._server.call(lambda: self._link.pty_path if self._link._master >= 0 else None)
