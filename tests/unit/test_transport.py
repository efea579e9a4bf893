"""The transport layer on real sockets and ptys, and the scripted transport drivers are tested with."""

from __future__ import annotations

import os
import select
import socket
import time

import pytest

from rigctl.apps.testing import ScriptedTransport
from rigctl.core.errors import ConfigError, DeviceTimeout, Disconnected, ProtocolError
from rigctl.core.transport import (
    SerialTransport,
    TcpTransport,
    camera_source,
    canonical_url,
    open_transport,
    parse_url,
)

# -- URLs ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:80",
        "htp:/typo",
        "COM3",
        "tcp://127.0.0.1",
        "tcp://127.0.0.1:notaport",
        "tcp://:5025",
        "tcp://127.0.0.1:0",
        "tcp://127.0.0.1:65536",
        "tcp://127.0.0.1:5025/path",
        "serial://dev/ttyUSB0",
        "serial:///dev/ttyUSB0?baud=fast",
        "serial:///dev/ttyUSB0?parity=E",
        "ttyUSB0",
        "",
        "TCPIP::10.0.0.11::INSTR",
        "TCPIP0::10.0.0.11::99999::SOCKET",
        "TCPIP::::5025::SOCKET",
        "ASRL3::INSTR",
        "GPIB0::5::INSTR",
        "tcp://[::1:5025",
    ],
)
def test_bad_url_names_the_url_and_what_to_write(url: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_url(url)
    message = str(info.value)
    assert repr(url) in message
    assert "tcp://HOST:PORT" in message or "serial:///dev/ttyUSB0?baud=9600" in message
    with pytest.raises(ConfigError):  # and open_transport refuses it the same way, unopened
        open_transport(url)


def test_a_visa_port_number_is_refused_asking_for_the_device_path() -> None:
    with pytest.raises(ConfigError, match="give the device path, e.g. ASRL/dev/ttyUSB0::INSTR"):
        parse_url("ASRL1::INSTR")


@pytest.mark.parametrize(
    "url, parsed",
    [
        ("tcp://10.0.0.11:5025", ("tcp", "10.0.0.11", 5025)),
        ("tcp://bop-1.lab:5025/", ("tcp", "bop-1.lab", 5025)),
        ("tcp://[::1]:5025", ("tcp", "::1", 5025)),
        ("TCPIP::10.0.0.11::5025::SOCKET", ("tcp", "10.0.0.11", 5025)),
        ("TCPIP0::bop-1.lab::5025::SOCKET", ("tcp", "bop-1.lab", 5025)),
        ("tcpip3::10.0.0.12::4000::socket", ("tcp", "10.0.0.12", 4000)),
        ("serial:///dev/ttyUSB0?baud=9600", ("serial", "/dev/ttyUSB0", 9600)),
        ("serial:///dev/ttyACM0", ("serial", "/dev/ttyACM0", 115200)),
        ("/dev/pts/7", ("serial", "/dev/pts/7", 115200)),
        # VISA opens an ASRL resource at 9600 baud unless told otherwise (VI_ATTR_ASRL_BAUD)
        ("ASRL/dev/ttyUSB0::INSTR", ("serial", "/dev/ttyUSB0", 9600)),
    ],
)
def test_device_urls_and_visa_resources_parse_to_one_address(url, parsed) -> None:
    assert parse_url(url) == parsed


def test_one_spelling_per_device() -> None:
    assert canonical_url("TCPIP0::BOP-1.lab::5025::SOCKET") == canonical_url("tcp://bop-1.lab:5025")
    assert canonical_url("ASRL/dev/ttyUSB0::INSTR") == canonical_url("serial:///dev/ttyUSB0?baud=19200")
    assert canonical_url("http://Cam:8080/s.mjpg") == "http://cam:8080/s.mjpg"  # no device URL


@pytest.mark.parametrize(
    "source, kind",
    [(0, ("device", 0)), ("0", ("device", 0)), ("/dev/video0", ("device", "/dev/video0")),
     ("http://10.0.0.5:8080/stream.mjpg", ("stream", "http://10.0.0.5:8080/stream.mjpg")),
     ("https://cam.lab/video", ("stream", "https://cam.lab/video")),
     ("runs/fig4.mp4", ("file", "runs/fig4.mp4")), ("file:///data/run.avi", ("file", "/data/run.avi"))],
)
def test_camera_sources(source, kind) -> None:
    assert camera_source(source) == kind


@pytest.mark.parametrize(
    "source", ["htp:/typo", "COM3", "http://[cam:80/x", "http://:8080/x", "http://cam:99999/x", -1])
def test_bad_camera_source_says_what_to_write(source) -> None:
    with pytest.raises(ConfigError) as info:
        camera_source(source)
    assert repr(source) in str(info.value)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_refused_connection_is_disconnected_naming_the_url() -> None:
    url = f"tcp://127.0.0.1:{_free_port()}"
    with pytest.raises(Disconnected) as info:
        open_transport(url)
    assert url in str(info.value)
    assert "refused" in str(info.value)


def test_missing_serial_device_is_disconnected_naming_the_url() -> None:
    with pytest.raises(Disconnected) as info:
        open_transport("serial:///dev/does-not-exist-rigctl?baud=9600")
    assert "/dev/does-not-exist-rigctl" in str(info.value)


# -- TCP -----------------------------------------------------------------------------------------


@pytest.fixture
def tcp_pair():
    """A TcpTransport and the server side of its connection (no thread: the backlog accepts)."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    url = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
    transport = open_transport(url, timeout_s=0.2)
    peer, _ = listener.accept()
    yield transport, peer, url
    transport.close()
    peer.close()
    listener.close()


def test_tcp_is_a_tcp_transport_with_nagle_off(tcp_pair) -> None:
    transport, _, url = tcp_pair
    assert isinstance(transport, TcpTransport)
    assert transport.url == url
    assert transport._sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0


def test_tcp_write_and_framed_reads(tcp_pair) -> None:
    transport, peer, _ = tcp_pair
    transport.write(b"MEAS:CURR?\n")
    assert peer.recv(100) == b"MEAS:CURR?\n"
    # two messages in one segment, then one split over two segments
    peer.sendall(b"1.0\n2.0\n3.")
    assert transport.read_until(b"\n") == b"1.0\n"
    assert transport.read_until(b"\n") == b"2.0\n"
    peer.sendall(b"5\r\n")
    assert transport.read_until(b"\r\n") == b"3.5\r\n"
    peer.sendall(b"\x01\x02\x03\x04tail")
    assert transport.read_exact(4) == b"\x01\x02\x03\x04"
    assert transport.read_exact(4) == b"tail"


def test_tcp_silence_times_out_after_the_deadline(tcp_pair) -> None:
    transport, peer, _ = tcp_pair
    peer.sendall(b"partial")
    start = time.monotonic()
    with pytest.raises(DeviceTimeout):
        transport.read_until(b"\n", timeout_s=0.1)
    elapsed = time.monotonic() - start
    assert 0.1 <= elapsed < 0.3
    peer.sendall(b" line\n")  # the partial message was kept
    assert transport.read_until(b"\n") == b"partial line\n"
    with pytest.raises(DeviceTimeout):
        transport.read_exact(3, timeout_s=0.05)


def test_tcp_reply_already_waiting_at_the_deadline_is_read_not_a_timeout(tcp_pair) -> None:
    # A reader descheduled past its deadline must still take a reply that arrived in time.
    transport, peer, _ = tcp_pair
    peer.sendall(b"1.0\n\x01\x02")
    select.select([transport._sock], [], [], 1.0)  # the bytes are in the socket buffer
    assert transport.read_until(b"\n", timeout_s=0.0) == b"1.0\n"
    assert transport.read_exact(2, timeout_s=0.0) == b"\x01\x02"
    with pytest.raises(DeviceTimeout):
        transport.read_until(b"\n", timeout_s=0.0)


def test_tcp_overlong_reply_is_a_protocol_error_quoting_it(tcp_pair) -> None:
    transport, peer, _ = tcp_pair
    peer.sendall(b"X" * 300)
    with pytest.raises(ProtocolError) as info:
        transport.read_until(b"\n", max_bytes=100)
    assert "XXXX" in str(info.value)


def test_tcp_discard_input_drops_pending_bytes(tcp_pair) -> None:
    transport, peer, _ = tcp_pair
    peer.sendall(b"stale\nreply\n")
    assert transport.read_exact(2) == b"st"  # some in the buffer, the rest in the socket
    transport.discard_input()
    peer.sendall(b"fresh\n")
    assert transport.read_until(b"\n") == b"fresh\n"


def test_tcp_peer_close_is_disconnected_naming_the_url(tcp_pair) -> None:
    transport, peer, url = tcp_pair
    peer.close()
    with pytest.raises(Disconnected) as info:
        transport.read_until(b"\n")
    assert url in str(info.value)


def test_tcp_closed_transport_refuses_io(tcp_pair) -> None:
    transport, _, _ = tcp_pair
    transport.close()
    transport.close()  # idempotent
    with pytest.raises(Disconnected):
        transport.write(b"x\n")


# -- serial (a pty stands in for the port) ----------------------------------------------------------


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    path = os.ttyname(slave)
    yield master, path
    os.close(master)
    os.close(slave)


@pytest.mark.parametrize("form", ["bare", "url"])
def test_serial_over_a_pty(pty_pair, form: str) -> None:
    master, path = pty_pair
    url = path if form == "bare" else f"serial://{path}?baud=9600"
    transport = open_transport(url, timeout_s=0.2)
    try:
        assert isinstance(transport, SerialTransport)
        transport.write(b"\xaa\x01\x02")
        assert os.read(master, 100) == b"\xaa\x01\x02"
        os.write(master, b"ok\nmore")
        assert transport.read_until(b"\n") == b"ok\n"
        assert transport.read_exact(4) == b"more"
        start = time.monotonic()
        with pytest.raises(DeviceTimeout):
            transport.read_exact(1, timeout_s=0.05)
        assert time.monotonic() - start < 0.2
        os.write(master, b"late\n")  # waiting before the read starts: taken even with no time left
        select.select([transport._port.fd], [], [], 1.0)  # the bytes are in the port buffer
        assert transport.read_until(b"\n", timeout_s=0.0) == b"late\n"
    finally:
        transport.close()


# -- ScriptedTransport -------------------------------------------------------------------------------


def test_scripted_transport_plays_the_script() -> None:
    script = ScriptedTransport(
        [(b"*IDN?\n", b"KEPCO\n"), (b"OUTP ON\n", None), (None, b"late\n")]
    )
    script.write(b"*IDN?\n")
    assert script.read_until(b"\n") == b"KEPCO\n"
    script.write(b"OUTP ON\n")
    assert script.read_until(b"\n") == b"late\n"
    script.assert_done()


def test_scripted_transport_fails_on_a_wrong_write_even_if_swallowed() -> None:
    script = ScriptedTransport([(b"CURR 1.0000\n", None)])
    try:
        script.write(b"CURR 2.0000\n")
    except AssertionError:
        pass
    with pytest.raises(AssertionError, match="CURR 2.0000"):
        script.assert_done()


def test_scripted_transport_fails_on_leftovers() -> None:
    script = ScriptedTransport([(b"A\n", b"1\n"), (b"B\n", None)])
    script.write(b"A\n")
    with pytest.raises(AssertionError, match="left"):
        script.assert_done()
    script.write(b"B\n")
    with pytest.raises(AssertionError, match="never read"):
        script.assert_done()


def test_scripted_transport_silence_and_errors() -> None:
    script = ScriptedTransport([(b"Q?\n", None), (b"R?\n", Disconnected("gone"))])
    script.write(b"Q?\n")
    with pytest.raises(DeviceTimeout):
        script.read_until(b"\n")
    script.write(b"R?\n")
    with pytest.raises(Disconnected, match="gone"):
        script.read_until(b"\n")
    script.assert_done()
