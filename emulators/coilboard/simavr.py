"""The real coil-board firmware running in simavr, with its host link and its SyRen bus on ptys.

    from rigctl.emulators.coilboard.simavr import SimavrBoard, SimavrUnavailable

    with SimavrBoard() as board:           # builds if needed, starts, waits for READY
        driver_url = board.uart_path       # /dev/pts/N: the board's USB serial port
        bus = open(board.syren_path, "rb") # /dev/pts/M: the bytes the firmware put on PD3

`SimavrBoard` builds `firmware/coilboard` (the ELF) and its harness (`sim/harness.c`) with `make`
into a cache directory (`build/coilboard-firmware/` in the repository, or `build_dir=`; a variant
built with `extra_cflags=` gets a directory of its own), starts the harness and waits for its
`READY uart=... syren=...` line with a real deadline. The harness paces
the simulated 16 MHz core to the wall clock, so the firmware's 200 ms link watchdog and its 2 s
SyRen start-up are real milliseconds. `stop()` ends it (SIGTERM, then SIGKILL); `restart()` is a
power cycle with new pty paths (an unplug and replug of the board).

When avr-gcc, make, a host C compiler or the simavr headers/library are missing, constructing
the board raises `SimavrUnavailable` (a `DeviceError`) naming what is missing and the Debian
packages that provide it; tests catch it and skip with that message.
"""

from __future__ import annotations

import fcntl
import logging
import os
import select
import shutil
import subprocess
import time
from importlib.resources import files
from pathlib import Path
from typing import TextIO

from rigctl.core.errors import DeviceError

log = logging.getLogger(__name__)

DEVICE = "coil board (simavr)"
# the firmware's sources are package data (`rigctl.firmware`: firmware/ in a checkout); the build
# goes to the checkout's build/ or, installed from a wheel, to the user's cache
FIRMWARE_DIR = Path(str(files("rigctl.firmware") / "coilboard"))
_CHECKOUT = FIRMWARE_DIR.parents[1]
DEFAULT_BUILD_DIR = (_CHECKOUT / "build" / "coilboard-firmware" if (_CHECKOUT / "pyproject.toml").is_file()
                     else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rigctl"
                     / "coilboard-firmware")
SIMAVR_HEADER = Path("/usr/include/simavr/sim_avr.h")
LIBELF_HEADER = Path("/usr/include/libelf.h")
APT_PACKAGES = "gcc-avr avr-libc simavr libsimavr-dev libelf-dev make gcc"
READY_PREFIX = "READY "


class SimavrUnavailable(DeviceError):
    """The AVR toolchain or simavr is not installed, so the firmware cannot be built or run."""


def missing_tools() -> list[str]:
    """What is missing to build and run the firmware under simavr (empty when all is there)."""
    missing = [tool for tool in ("avr-gcc", "avr-objcopy", "make", "cc") if shutil.which(tool) is None]
    if not SIMAVR_HEADER.exists():
        missing.append(f"the simavr headers ({SIMAVR_HEADER})")
    if not LIBELF_HEADER.exists():
        missing.append(f"the libelf headers ({LIBELF_HEADER})")
    if not (FIRMWARE_DIR / "Makefile").exists():
        missing.append(f"the firmware sources ({FIRMWARE_DIR}: reinstall rigctl, they ship with it)")
    return missing


def require_tools() -> None:
    """Raise SimavrUnavailable naming every missing tool; return quietly when all are present."""
    missing = missing_tools()
    if missing:
        raise SimavrUnavailable(
            f"cannot build the firmware: {', '.join(missing)} not found; install them with "
            f"`apt-get install {APT_PACKAGES}`", device=DEVICE)


def build(build_dir: Path | str = DEFAULT_BUILD_DIR, *, extra_cflags: str = "",
          timeout_s: float = 300.0) -> tuple[Path, Path]:
    """Build the firmware ELF and the harness (make decides what is stale); returns their paths.

    `extra_cflags` selects a variant (e.g. "-DCOILBOARD_TEST_HANG"); a variant needs a build
    directory of its own, as make does not rebuild when only the flags change. A lock file in
    `build_dir` serialises concurrent builds (several test processes at once)."""
    require_tools()
    build_dir = Path(build_dir)
    build_dir.mkdir(parents=True, exist_ok=True)
    with open(build_dir / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        result = subprocess.run(
            ["make", "-C", str(FIRMWARE_DIR), f"BUILD={build_dir}", f"EXTRA_CFLAGS={extra_cflags}",
             "all", "harness"],
            capture_output=True, text=True, timeout=timeout_s)
    if result.returncode != 0:
        raise DeviceError(
            f"building the firmware in {FIRMWARE_DIR} failed (make exit {result.returncode}):\n"
            f"{(result.stdout + result.stderr).strip()[-3000:]}", device=DEVICE)
    return build_dir / "coilboard.elf", build_dir / "harness"


class SimavrBoard:
    """The firmware in simavr behind two ptys; a context manager (`with SimavrBoard() as board`)."""

    def __init__(self, *, build_dir: Path | str | None = None, extra_cflags: str = "",
                 start_timeout_s: float = 20.0, build_timeout_s: float = 300.0) -> None:
        if build_dir is None:
            variant = "".join(c if c.isalnum() else "-" for c in extra_cflags).strip("-")
            build_dir = DEFAULT_BUILD_DIR.with_name(f"{DEFAULT_BUILD_DIR.name}-{variant}" if variant
                                                    else DEFAULT_BUILD_DIR.name)
        self.build_dir = Path(build_dir)
        self.extra_cflags = extra_cflags
        self.start_timeout_s = start_timeout_s
        self.build_timeout_s = build_timeout_s
        self.uart_path: str | None = None
        self.syren_path: str | None = None
        self.returncode: int | None = None  # the harness's exit status once stopped (0: clean)
        self.log_path = self.build_dir / f"harness-{os.getpid()}-{id(self):x}.log"
        self._proc: subprocess.Popen[str] | None = None
        self._log: TextIO | None = None
        require_tools()

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self) -> SimavrBoard:
        """Build if needed, start the harness and wait for READY; returns self."""
        if self.running:
            return self
        elf, harness = build(self.build_dir, extra_cflags=self.extra_cflags, timeout_s=self.build_timeout_s)
        self._log = open(self.log_path, "w")
        # stdin is a pipe the harness watches: if this process dies, the harness exits too. A
        # session of its own: a terminal's Ctrl-C must not take the board away from the run that
        # is making it safe; `stop` ends it
        self._proc = subprocess.Popen([str(harness), "--watch-stdin", str(elf)], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=self._log, text=True,
                                      start_new_session=True)
        try:
            line = self._ready_line()
        except BaseException:  # a Ctrl-C while it starts
            self._end_process()
            raise
        if line is None:
            self._end_process()
            raise DeviceError(f"the simavr harness did not start within {self.start_timeout_s:g} s: "
                              f"{self.log_path.read_text().strip()[-2000:]}", device=DEVICE)
        fields = dict(part.split("=", 1) for part in line[len(READY_PREFIX):].split())
        self.uart_path, self.syren_path = fields["uart"], fields["syren"]
        log.info("firmware running in simavr: host link %s, SyRen bus %s", self.uart_path, self.syren_path)
        return self

    def _ready_line(self) -> str | None:
        assert self._proc is not None and self._proc.stdout is not None
        deadline = time.monotonic() + self.start_timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            if not select.select([self._proc.stdout], [], [], remaining)[0]:
                return None
            line = self._proc.stdout.readline()
            if not line:
                return None  # the harness exited
            if line.startswith(READY_PREFIX):
                return line.strip()
        return None

    def stop(self) -> None:
        """Stop the harness (SIGTERM, SIGKILL after 5 s); the ptys vanish. Safe to call twice."""
        self._end_process()
        self.uart_path = self.syren_path = None

    def restart(self) -> SimavrBoard:
        """Power-cycle the board: stop, start again (new pty paths, the firmware boots afresh)."""
        self.stop()
        return self.start()

    def _end_process(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
            self.returncode = proc.returncode
            for pipe in (proc.stdin, proc.stdout):
                if pipe is not None:
                    pipe.close()
        if self._log is not None:
            self._log.close()
            self._log = None

    def harness_log(self) -> str:
        """What the harness wrote to stderr (simavr's messages, its statistics line at exit)."""
        return self.log_path.read_text() if self.log_path.exists() else ""

    def __enter__(self) -> SimavrBoard:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


SimavrFirmware = SimavrBoard  # the name the coil-board bench imports; the same class
