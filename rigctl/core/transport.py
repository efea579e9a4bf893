"""The one transport layer: a byte stream to a device, opened from a URL.

A driver never opens a socket or a serial port itself; it is handed a `Transport` made by
`open_transport(url)`, the way pyserial's `serial_for_url` picks the implementation from the URL:

- `tcp://host:port`                      a TCP socket (TCP_NODELAY), e.g. a Kepco BOP on port 5025
- `serial:///dev/ttyUSB0?baud=115200`    a serial port through pyserial
- `/dev/pts/7` (a bare device path)      the same, at the default baud rate (ptys, emulated boards)
- `TCPIP[n]::host::port::SOCKET`         a VISA raw-socket resource: the same TCP socket
- `ASRL/dev/ttyUSB0::INSTR`              a VISA serial resource: the same serial port, at VISA's
                                          default 9600 baud (a resource string carries no baud)

VISA strings are mapped here rather than opened through pyvisa: both forms are one socket or one
port with LF-terminated SCPI lines, which these transports already are, with their deadlines.
`parse_url` checks a URL with no I/O (the rig file loader calls it for every device), and
`camera_source` does the same for a camera's source (an index, /dev/video0, a stream, a file).

Every read has a deadline. The errors are the project's own: `Disconnected` when the peer is gone,
`DeviceTimeout` when it stays silent past the deadline, `ProtocolError` when a reply grows past
`max_bytes` without its terminator. These transport errors carry no device name: the driver knows
which device it is talking to and re-raises with `device=`.
"""

from __future__ import annotations

import logging
import re
import select
import socket
import termios
import time
from pathlib import Path
from typing import Protocol, runtime_checkable
from urllib.parse import parse_qs, urlsplit

import serial

from rigctl.core.errors import ConfigError, DeviceTimeout, Disconnected, ProtocolError

log = logging.getLogger(__name__)

SERIAL_EXAMPLE = "serial:///dev/ttyUSB0?baud=9600"
ACCEPTED_FORMS = f"{SERIAL_EXAMPLE} or tcp://HOST:PORT"
DEFAULT_BAUD = 115200
VISA_BAUD = 9600  # VI_ATTR_ASRL_BAUD's default: what a VISA library opens an ASRL resource at
_RECV_CHUNK = 4096
_VISA_SOCKET = re.compile(r"TCPIP\d*::([^:]*)::([^:]*)::SOCKET", re.IGNORECASE)
_VISA_SERIAL = re.compile(r"ASRL(.*)::INSTR", re.IGNORECASE)
STREAM_SCHEMES = ("http", "https", "rtsp", "rtsps", "rtmp", "udp", "tcp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mjpg", ".mjpeg", ".mpg")
CAMERA_FORMS = "0 (a device index), /dev/video0, http://HOST:PORT/stream.mjpg or a video file"


@runtime_checkable
class Transport(Protocol):
    """A bidirectional byte stream with deadlines on every read."""

    url: str

    def write(self, data: bytes) -> None:
        """Send all of `data`; Disconnected if the peer is gone."""

    def read_until(
        self, terminator: bytes = b"\n", *, timeout_s: float | None = None, max_bytes: int = 65536
    ) -> bytes:
        """The next message including its terminator.

        DeviceTimeout after `timeout_s` (default: the transport's timeout) without a complete
        message, Disconnected if the peer closed, ProtocolError if `max_bytes` arrive without it.
        """

    def read_exact(self, n: int, *, timeout_s: float | None = None) -> bytes:
        """Exactly `n` bytes, or DeviceTimeout / Disconnected."""

    def discard_input(self) -> None:
        """Drop everything received and not yet read (resynchronise after garbage or a timeout)."""

    def close(self) -> None:
        """Release the link; idempotent."""


def open_transport(url: str, *, timeout_s: float = 1.0) -> Transport:
    """Open the transport that `url` names; `timeout_s` is the default read deadline.

    ConfigError (naming the URL and the accepted forms) for a URL of no known form;
    Disconnected (naming the URL) when the far end refuses or does not exist.
    """
    if timeout_s <= 0:
        raise ConfigError(f"transport timeout must be positive, got {timeout_s} s for {url!r}")
    kind, target, number = parse_url(url)
    if kind == "tcp":
        return TcpTransport(url, target, number, timeout_s=timeout_s)
    return SerialTransport(url, target, baud=number, timeout_s=timeout_s)


def parse_url(url: str) -> tuple[str, str, int]:
    """("tcp", host, port) or ("serial", device path, baud) for a device URL, with no I/O;
    ConfigError naming the URL and what to write instead."""
    text = url.strip()
    if text.startswith("/"):
        return "serial", text, DEFAULT_BAUD
    if "::" in text and "://" not in text:  # VISA: TCPIP0::host::port::SOCKET, ASRL...::INSTR
        return _visa_address(text)
    parts = _split(text)
    if parts.scheme == "tcp" and not (parts.path.strip("/") or parts.query):
        return ("tcp", *_tcp_address(text, parts.netloc))
    if parts.scheme == "serial":
        return ("serial", *_serial_address(text, parts))
    raise ConfigError(f"{url!r} is not a device URL; write {ACCEPTED_FORMS}")


def _split(url: str):
    try:
        return urlsplit(url)
    except ValueError as err:  # an unclosed [IPv6 bracket
        raise ConfigError(f"{url!r} is not a URL ({err}); write {ACCEPTED_FORMS}") from None


def canonical_url(url: str) -> str:
    """One spelling per device (`TCPIP::h::5025::SOCKET` and `tcp://h:5025` are one supply):
    tcp://host:port or serial://path (no baud); a source that is no device URL (a camera) as written."""
    try:
        kind, target, number = parse_url(url)
    except ConfigError:
        return url.strip().lower()
    return f"tcp://{target.lower()}:{number}" if kind == "tcp" else f"serial://{target}"


def _tcp_address(url: str, netloc: str) -> tuple[str, int]:
    host, _, port = netloc.rpartition(":")
    host = host.strip("[]")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"{url!r}: needs a host and a port 1-65535: tcp://HOST:PORT, "
                          f"e.g. tcp://192.168.1.11:5025")
    return host, int(port)


def _visa_address(url: str) -> tuple[str, str, int]:
    if match := _VISA_SOCKET.fullmatch(url):
        return ("tcp", *_tcp_address(url, f"{match[1]}:{match[2]}"))
    if (match := _VISA_SERIAL.fullmatch(url)) and match[1].startswith("/"):
        return "serial", match[1], VISA_BAUD
    if match:
        raise ConfigError(f"{url!r}: a VISA port number names no device here; give the device "
                          f"path, e.g. ASRL/dev/ttyUSB0::INSTR or {SERIAL_EXAMPLE}")
    raise ConfigError(f"{url!r}: of the VISA resources only raw sockets, TCPIP::HOST::PORT::SOCKET "
                      f"(tcp://HOST:PORT), and serial ports, ASRL/dev/ttyUSB0::INSTR, are opened")


def _serial_address(url: str, parts) -> tuple[str, int]:
    def refuse(why: str) -> ConfigError:
        return ConfigError(f"{url!r}: {why}; write e.g. {SERIAL_EXAMPLE}")

    if parts.netloc or not parts.path.startswith("/"):
        raise refuse("a serial URL is serial:///dev/NAME?baud=N (three slashes)")
    query = parse_qs(parts.query, keep_blank_values=True)
    unknown = set(query) - {"baud"}
    if unknown:
        raise refuse(f"unknown serial option(s) {sorted(unknown)}, only baud=N")
    try:
        baud = int(query["baud"][-1]) if "baud" in query else DEFAULT_BAUD
    except ValueError:
        raise refuse("baud must be an integer") from None
    if baud <= 0:
        raise refuse("baud must be positive")
    return parts.path, baud


def camera_source(source: str | int) -> tuple[str, str | int]:
    """("device", index or /dev path), ("stream", URL) or ("file", path) with no I/O;
    ConfigError naming the source and the forms it may take."""
    if isinstance(source, int) and not isinstance(source, bool) and source >= 0:
        return "device", source
    text = str(source).strip()
    if text.isdigit():
        return "device", int(text)
    if text.startswith("/dev/"):
        return "device", text
    parts = _split(text)
    scheme = parts.scheme.lower() if "://" in text else ""
    if scheme == "file" and parts.path:
        return "file", parts.path
    if scheme in STREAM_SCHEMES:
        netloc = parts.netloc.rpartition("@")[2]
        _tcp_address(text, netloc if ":" in netloc.rpartition("]")[2] else f"{netloc}:80")
        return "stream", text
    is_video = text.lower().endswith(VIDEO_SUFFIXES) or Path(text).is_file()
    if not scheme and ":" not in text and is_video:
        return "file", text
    raise ConfigError(f"{source!r} is not a camera source; write {CAMERA_FORMS}")


class _BufferedReads:
    """Terminator and length framing over a `_receive(deadline)` primitive, shared by both links."""

    url: str
    timeout_s: float

    def __init__(self) -> None:
        self._buffer = bytearray()

    def _receive(self, deadline: float) -> bytes:  # pragma: no cover - implemented by subclasses
        """Bytes that arrive before `deadline`; past it, only those already waiting (no wait)."""
        raise NotImplementedError

    def _deadline(self, timeout_s: float | None) -> tuple[float, float]:
        timeout = self.timeout_s if timeout_s is None else timeout_s
        return timeout, time.monotonic() + timeout

    def read_until(
        self, terminator: bytes = b"\n", *, timeout_s: float | None = None, max_bytes: int = 65536
    ) -> bytes:
        if not terminator:
            raise ValueError("terminator must not be empty")
        timeout, deadline = self._deadline(timeout_s)
        searched, expired = 0, False
        while True:
            index = self._buffer.find(terminator, searched)
            if index >= 0:
                end = index + len(terminator)
                message = bytes(self._buffer[:end])
                del self._buffer[:end]
                return message
            if len(self._buffer) > max_bytes:
                head = bytes(self._buffer[:40])
                self._buffer.clear()
                raise ProtocolError(
                    f"reply from {self.url} exceeds {max_bytes} bytes without terminator "
                    f"{terminator!r} (starts {head!r})"
                )
            searched = max(0, len(self._buffer) - len(terminator) + 1)
            if expired:
                raise DeviceTimeout(f"no reply within {timeout:g} s from {self.url}")
            # Past the deadline, one last look at what has already arrived: a reply that waited
            # while this thread was descheduled is not a timeout.
            expired = time.monotonic() >= deadline
            self._buffer += self._receive(deadline)

    def read_exact(self, n: int, *, timeout_s: float | None = None) -> bytes:
        if n < 0:
            raise ValueError("n must be >= 0")
        timeout, deadline = self._deadline(timeout_s)
        expired = False
        while len(self._buffer) < n:
            if expired:
                raise DeviceTimeout(
                    f"only {len(self._buffer)} of {n} bytes within {timeout:g} s from {self.url}"
                )
            expired = time.monotonic() >= deadline
            self._buffer += self._receive(deadline)
        message = bytes(self._buffer[:n])
        del self._buffer[:n]
        return message


class TcpTransport(_BufferedReads):
    """A TCP connection with Nagle off (small SCPI lines must leave at once)."""

    def __init__(self, url: str, host: str, port: int, *, timeout_s: float) -> None:
        super().__init__()
        self.url = url
        self.timeout_s = timeout_s
        try:
            self._sock: socket.socket | None = socket.create_connection((host, port), timeout=timeout_s)
        except ConnectionRefusedError:
            raise Disconnected(f"connection refused by {url}") from None
        except TimeoutError:
            raise Disconnected(f"no answer from {url} within {timeout_s:g} s (connect)") from None
        except OSError as err:
            raise Disconnected(f"cannot connect to {url}: {err.strerror or err}") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.settimeout(timeout_s)
        self._timeout = timeout_s  # the socket's timeout now (setting it costs system calls)
        log.debug("connected to %s", url)

    def _socket(self) -> socket.socket:
        if self._sock is None:
            raise Disconnected(f"transport to {self.url} is closed")
        return self._sock

    def write(self, data: bytes) -> None:
        sock = self._socket()
        try:
            self._set_timeout(sock, self.timeout_s)
            sock.sendall(data)
        except TimeoutError:
            raise DeviceTimeout(f"could not send to {self.url} within {self.timeout_s:g} s") from None
        except ConnectionResetError:
            raise Disconnected(f"connection reset by {self.url}") from None
        except OSError as err:
            raise Disconnected(f"connection to {self.url} lost: {err.strerror or err}") from None

    def _receive(self, deadline: float) -> bytes:
        sock = self._socket()
        remaining = deadline - time.monotonic()
        if remaining <= 0 and not select.select([sock], [], [], 0)[0]:
            return b""
        try:
            if self._timeout - remaining > 1e-3:  # only shorter: a reply mostly comes at once
                self._set_timeout(sock, max(remaining, 1e-3))
            chunk = sock.recv(_RECV_CHUNK)
        except TimeoutError:
            return b""
        except ConnectionResetError:
            raise Disconnected(f"connection reset by {self.url}") from None
        except OSError as err:
            raise Disconnected(f"connection to {self.url} lost: {err.strerror or err}") from None
        if not chunk:
            raise Disconnected(f"connection closed by {self.url}")
        return chunk

    def _set_timeout(self, sock: socket.socket, timeout_s: float) -> None:
        """`settimeout` switches the descriptor's blocking mode each time, two system calls: a
        stream cycle's twelve exchanges made two dozen of them for nothing."""
        if timeout_s != self._timeout:
            sock.settimeout(timeout_s)
            self._timeout = timeout_s

    def discard_input(self) -> None:
        self._buffer.clear()
        sock = self._socket()
        try:
            while select.select([sock], [], [], 0)[0]:
                if not sock.recv(_RECV_CHUNK):
                    break  # EOF: the next read reports it
        except OSError:
            pass  # a dead link is reported by the next read or write

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None
                log.debug("closed %s", self.url)


class SerialTransport(_BufferedReads):
    """A serial port or pty through pyserial."""

    def __init__(self, url: str, path: str, *, baud: int, timeout_s: float) -> None:
        super().__init__()
        self.url = url
        self.timeout_s = timeout_s
        try:
            self._port: serial.Serial | None = serial.serial_for_url(
                path, baudrate=baud, timeout=timeout_s, write_timeout=timeout_s
            )
        except (serial.SerialException, OSError) as err:
            raise Disconnected(f"cannot open {url}: {err}") from None
        self._timeout_set = timeout_s

    def _serial(self) -> serial.Serial:
        if self._port is None:
            raise Disconnected(f"transport to {self.url} is closed")
        return self._port

    def write(self, data: bytes) -> None:
        port = self._serial()
        try:
            port.write(data)
        except serial.SerialTimeoutException:
            raise DeviceTimeout(f"could not send to {self.url} within {self.timeout_s:g} s") from None
        except (serial.SerialException, OSError) as err:
            raise Disconnected(f"{self.url} lost: {err}") from None

    def _receive(self, deadline: float) -> bytes:
        port = self._serial()
        remaining = deadline - time.monotonic()
        try:
            if remaining <= 0:
                waiting = port.in_waiting
                return port.read(waiting) if waiting else b""
            # Changing pyserial's timeout reconfigures the port: do it only when the deadline
            # is nearer than the current setting (never overshoot) or much farther.
            if self._timeout_set > remaining or remaining - self._timeout_set > 0.05:
                port.timeout = remaining
                self._timeout_set = remaining
            return port.read(max(1, port.in_waiting))
        except (serial.SerialException, OSError) as err:
            raise Disconnected(f"{self.url} lost: {err}") from None

    def discard_input(self) -> None:
        self._buffer.clear()
        try:
            self._serial().reset_input_buffer()
        except (serial.SerialException, OSError, termios.error):  # tcflush on a pty whose peer is gone
            pass  # a dead link is reported by the next read or write

    def close(self) -> None:
        if self._port is not None:
            try:
                self._port.close()
            finally:
                self._port = None
