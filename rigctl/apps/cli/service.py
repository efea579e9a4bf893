"""`rigctl service install`: the systemd unit and system user of a rig's daemon, for this install.

The unit runs the daemon with the interpreter of the environment rigctl is installed in (a venv's
`bin/python3`: `/usr/bin/env rigctl` finds nothing there), and confines it to what the rig file
names: the serial adapters and cameras its devices sit on (`DeviceAllow=`, every other device
closed), the hosts of its networked devices and of the daemon's endpoints (`IPAddressAllow=`,
resolved when the unit is written), the system calls of an ordinary service. What it keeps, and
why: realtime scheduling (the stream thread runs SCHED_FIFO: `RestrictRealtime=` stays off and the
`@resources` calls allowed), writable executable memory (numba compiles kernels:
`MemoryDenyWriteExecute=` would stop it), the real `/proc` files (`ProcSubset=` stays all: LLVM
reads `/proc/cpuinfo` on some machines), and the `dialout`/`video` groups a serial adapter's or a
camera's node belongs to. `systemd/rigctl.service` is this command's unit for an install in
`/opt/rigctl/venv` and the seed hardware's network (tests/unit/test_service.py keeps them equal).
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import socket
import sys
from importlib.metadata import PackageNotFoundError, metadata
from pathlib import Path
from urllib.parse import urlsplit

from rigctl.core.errors import EXIT_OK, ConfigError

UNIT_RIG = "/etc/rigctl/rig.toml"
RUNS = "/var/lib/rigctl/runs"
DEFAULT_VENV = "/opt/rigctl/venv"
DOCS_URL = "https://github.com/rigctl/rigctl/blob/main/docs/daemon-protocol.md"

# the kernel's device classes (/proc/devices) of what a rig's devices sit on: a USB serial adapter
# may come back under another number after a replug, so the class is allowed, not one node
SERIAL_CLASSES = {"ttyUSB": "char-ttyUSB", "ttyACM": "char-ttyACM", "ttyS": "char-ttyS"}
CAMERA_CLASS = "char-video4linux"


def device_classes(urls: list[str]) -> list[str]:
    """The device classes (`DeviceAllow=`) of the local devices among a rig's URLs: serial ports
    (`serial:///dev/...`, VISA `ASRL/dev/...::INSTR`) and V4L2 cameras (`/dev/videoN`, an OpenCV
    index). A `/dev/serial/by-id/` name is resolved if the adapter is plugged in; otherwise both
    USB serial classes are allowed (an FTDI adapter is ttyUSB, an Arduino's own USB is ttyACM)."""
    classes: set[str] = set()
    for url in urls:
        text = str(url)
        path = None
        if text.startswith("serial://"):
            path = urlsplit(text).path
        elif text.upper().startswith("ASRL/DEV/"):
            path = text[4:].split("::")[0]
        elif text.isdigit() or text.startswith("/dev/video"):
            classes.add(CAMERA_CLASS)
            continue
        if not path:
            continue
        node = os.path.realpath(path) if os.path.exists(path) else path
        name = Path(node).name
        found = [c for prefix, c in SERIAL_CLASSES.items() if name.startswith(prefix)]
        classes.update(found or [SERIAL_CLASSES["ttyUSB"], SERIAL_CLASSES["ttyACM"]])
    return sorted(classes)


def _host(url: str) -> str | None:
    parts = urlsplit(str(url))
    if parts.scheme in ("tcp", "http", "https", "rtsp") and parts.hostname not in (None, "*"):
        return parts.hostname
    if str(url).upper().startswith("TCPIP"):  # VISA: TCPIP0::192.168.1.11::5025::SOCKET
        return str(url).split("::")[1]
    return None


def allowed_addresses(urls: list[str], endpoints: list[str], operators: list[str]) -> list[str]:
    """`IPAddressAllow=`: loopback, each networked device's address, and the operators' networks
    (`--allow-from`), which a daemon serving beyond loopback must name. ConfigError for a host that
    does not resolve, or a daemon bound beyond loopback with no operators' network named."""
    allowed: list[str] = ["localhost"]
    for url in urls:
        host = _host(url)
        if host is None:
            continue
        try:
            for info in socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP):
                address = str(ipaddress.ip_address(info[4][0]))
                if not ipaddress.ip_address(address).is_loopback and address not in allowed:
                    allowed.append(address)
        except (OSError, ValueError):
            raise ConfigError(f"service: device address {host!r} ({url}) does not resolve; "
                              "use its IP address in the rig file") from None
    for network in operators:
        try:
            allowed.append(str(ipaddress.ip_network(network, strict=False)))
        except ValueError:
            raise ConfigError(f"service: --allow-from {network!r} is not an address or network "
                              "(e.g. 192.168.1.0/24)") from None
    beyond = [e for e in endpoints if _host(e) is not None and not _is_loopback(_host(e))]
    if beyond and not operators:
        raise ConfigError(f"service: the daemon serves beyond loopback ({beyond[0]}); name the "
                          "operators' networks with --allow-from CIDR")
    return allowed


def _is_loopback(host: str | None) -> bool:
    if host in ("localhost", None):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def docs_url() -> str:
    """The daemon's protocol page at the project's documentation URL (the package's metadata)."""
    try:
        urls = dict(u.split(", ", 1) for u in metadata("rigctl").get_all("Project-URL") or [])
    except PackageNotFoundError:
        return DOCS_URL
    base = urls.get("Documentation")
    return f"{base.rstrip('/')}/daemon-protocol.md" if base else DOCS_URL


def unit_text(*, python: str, devices: list[str], addresses: list[str], groups: list[str],
              rig: str = UNIT_RIG, realtime: int = 40) -> str:
    """The daemon's unit file."""
    rig_command = f"--rig {rig}"
    allow = "\n".join(f"DeviceAllow={c} rw" for c in devices) or (
        "# (none: written for no rig file; `rigctl service install --rig FILE` opens a rig's)")
    ips = "\n".join(f"IPAddressAllow={a}" for a in addresses)
    supplementary = f"SupplementaryGroups={' '.join(groups)}\n" if groups else ""
    return f"""\
# rigctl daemon for one rig, written by `rigctl service install` (rigctl/apps/cli/service.py says
# what each setting keeps and why): `systemctl enable --now rigctl`. Reads {rig}, writes run
# records to {RUNS}. Loopback only unless CURVE keys are configured there.
[Unit]
Description=rigctl daemon: magnetic micro-robot rig control (ZeroMQ commands and telemetry)
Documentation={docs_url()}
After=network-online.target
Wants=network-online.target

[Service]
Type=notify
NotifyAccess=main
ExecStart={python} -m rigctl daemon {rig_command} --runs {RUNS} --realtime {realtime}
# READY=1 comes once the sockets are bound; WATCHDOG=1 from the command loop every WatchdogSec/3,
# withheld when a running plan's stream thread stops cycling.
WatchdogSec=5s
TimeoutStartSec=60s
# SIGTERM: the active run ramps down (stream.ramp_down_s), supplies go off, exit 0.
KillSignal=SIGTERM
# SIGTERM to the daemon alone, which ramps the run down and stops its stream process; whatever
# is left when it has exited gets SIGKILL
KillMode=mixed
TimeoutStopSec=20s
Restart=on-failure
RestartSec=2s
# Make every device of the rig safe once the service's processes are gone, however they ended
# (stop, crash, SIGKILL, the OOM killer): a Kepco BOP has no link watchdog and holds its last
# current when nothing talks to it. With no owner's lock left (the kernel dropped the flock
# with the processes), `rigctl estop --rig` zeroes and switches off every device directly.
ExecStopPost={python} -m rigctl estop {rig_command}

User=rigctl
Group=rigctl
{supplementary}StateDirectory=rigctl
# numba's compiled kernels (/var/cache/rigctl, $CACHE_DIRECTORY); the install itself is read-only
CacheDirectory=rigctl
ConfigurationDirectory=rigctl
WorkingDirectory=/var/lib/rigctl

# realtime scheduling (SCHED_FIFO) for what must not wait behind other processes: with
# --realtime {realtime}, the stream thread at {realtime}, the stream process's command thread (it takes the
# e-stop) at {realtime + 1}, the daemon's command thread and ZeroMQ I/O thread at {realtime - 1}; nothing else
LimitRTPRIO={realtime + 1}
# without --realtime, the stream process still runs ten steps of niceness ahead of ordinary work
# (rigctl.core.priority): a busy computer delays a cycle by a time slice, not its share of the cores
LimitNICE=-10

# the devices the rig file names (serial adapters, cameras); every other device is closed
DevicePolicy=closed
{allow}
# loopback, the rig's networked devices, the operators' networks; nothing else
IPAddressDeny=any
{ips}
RestrictAddressFamilies=AF_INET AF_INET6 AF_UNIX
# an ordinary service's system calls (@resources stays: SCHED_FIFO); a refused call fails with
# EPERM rather than killing the daemon in the middle of a run
SystemCallFilter=@system-service
SystemCallFilter=~@privileged
SystemCallErrorNumber=EPERM
SystemCallArchitectures=native

NoNewPrivileges=yes
ProtectSystem=strict
# the rig's device locks (rigctl.rigs.owner): in the machine's lock folder, not in /tmp, which
# PrivateTmp hides from an operator's `rigctl estop --rig` / `rigctl execute`
ReadWritePaths=/run/lock
ProtectHome=yes
PrivateTmp=yes
PrivateMounts=yes
ProtectProc=invisible
ProtectKernelTunables=yes
ProtectKernelModules=yes
ProtectKernelLogs=yes
ProtectControlGroups=yes
ProtectClock=yes
ProtectHostname=yes
RestrictNamespaces=yes
RestrictSUIDSGID=yes
LockPersonality=yes
RemoveIPC=yes
CapabilityBoundingSet=
UMask=0027

[Install]
WantedBy=multi-user.target
"""


def sysusers_text(groups: list[str]) -> str:
    """`sysusers.d` entry: the `rigctl` system user and group, a member of the device groups."""
    lines = ["# the rigctl daemon's system user (systemd-sysusers; `rigctl service install`)",
             'u rigctl - "rigctl daemon" /var/lib/rigctl']
    lines += [f"m rigctl {g}" for g in groups]
    return "\n".join(lines) + "\n"


def render(rig_path: str | None, *, python: str, operators: list[str],
           realtime: int = 40) -> dict[str, str]:
    """The files to install (path under the root -> text), for the rig file at `rig_path` (None:
    the unit allows no device and only loopback until a rig file is named)."""
    urls: list[str] = []
    endpoints: list[str] = []
    if rig_path is not None:
        from rigctl.core.config import load_rig
        from rigctl.rigs import rig_kind

        rig = load_rig(rig_path)
        urls = [d.url for d in rig_kind(rig.rig.kind).devices(rig)]
        daemon = rig.daemon
        if daemon is not None:
            endpoints = [daemon.command, daemon.telemetry, daemon.events]
    devices = device_classes(urls)
    groups = sorted({"dialout" for c in devices if c.startswith("char-tty")}
                    | {"video" for c in devices if c == CAMERA_CLASS})
    addresses = allowed_addresses(urls, endpoints, operators)
    return {
        "etc/systemd/system/rigctl.service": unit_text(python=python, devices=devices,
                                                       addresses=addresses, groups=groups,
                                                       realtime=realtime),
        "etc/sysusers.d/rigctl.conf": sysusers_text(groups),
    }


def _cmd_install(args: argparse.Namespace) -> int:
    venv = Path(args.venv) if args.venv else Path(sys.prefix)
    python = venv / "bin" / "python3"
    if not python.exists():
        raise ConfigError(f"service: --venv {venv}: no bin/python3 there (the environment rigctl "
                          "is installed in, e.g. /opt/rigctl/venv)")
    files = render(args.rig, python=str(python.absolute()), operators=args.allow_from or [])
    if args.print:
        for path, text in files.items():
            sys.stdout.write(f"# /{path}\n{text}\n")
        return EXIT_OK
    root = Path(args.root)
    for path, text in files.items():
        out = root / path
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(text)
        except OSError as err:
            raise ConfigError(f"service: cannot write {out}: {err.strerror} (run as root, or "
                              "--root DIR to write the files somewhere else)") from None
        print(f"wrote {out}")
    rig_note = (f"copy {args.rig} to {UNIT_RIG}" if args.rig
                else f"write the rig file to {UNIT_RIG} (rigctl init KIND -o {UNIT_RIG})")
    print(f"next: {rig_note}; systemd-sysusers; systemctl daemon-reload; "
          "systemctl enable --now rigctl")
    return EXIT_OK


def register_service(sub) -> None:
    p = sub.add_parser(
        "service", help="install the daemon as a systemd service (unit and system user)",
        description="Write the systemd unit and sysusers.d entry that run `rigctl daemon` for one "
        "rig with this environment's interpreter, confined to the devices and hosts the rig file "
        "names. Then: systemd-sysusers; systemctl daemon-reload; systemctl enable --now rigctl.")
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    q = actions.add_parser("install", help="write the unit and the system user's entry",
                           description="Write /etc/systemd/system/rigctl.service and "
                           "/etc/sysusers.d/rigctl.conf (under --root).")
    q.add_argument("--venv", metavar="PATH",
                   help="the environment rigctl is installed in (default: this one, "
                   f"{sys.prefix})")
    q.add_argument("--rig", metavar="FILE",
                   help=f"the rig file the service will run (installed as {UNIT_RIG}): its devices "
                   "and hosts are what the unit allows")
    q.add_argument("--allow-from", action="append", metavar="CIDR",
                   help="an operators' network the daemon answers (needed when its [daemon] "
                   "endpoints are beyond loopback; repeat for more)")
    q.add_argument("--root", default="/", metavar="DIR",
                   help="write under DIR instead of / (packaging, a look before installing)")
    q.add_argument("--print", action="store_true", help="print the files instead of writing them")
    q.set_defaults(func=_cmd_install)
