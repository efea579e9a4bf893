"""The one emulated-bench base: an `EmulatorServer`, one simulated clock, one backdoor command table
and the `rigctl emulate KIND` flow, shared by the six-coil bench (`bench.py`), the coil-board bench
(`coilboard/bench.py`) and the dual-EPM bench (`depm.py`); a rig kind names its bench in its
`RigKind.bench` (`bench_class` asks the registry).

A bench subclasses `EmulatedBench`: `_serve()` puts its devices on `self.server` (registering each
with `add_device`) and returns the rig file that points at them, `advance()` steps its physics to
`self.clock.now()` (lazily, before a device command or a backdoor read, and every `tick_s`), and
its backdoor commands go into `self.commands`. `self.clock` is a `SimClock`: simulated seconds are
real monotonic seconds times the speed factor, and every model of the bench steps from it.

Backdoor (JSON lines over TCP at the rig file's `emulation.backdoor`; one request per line, one
reply per line, `{"ok": true, ...}` or `{"ok": false, "error": "..."}`). A bench whose host is not
loopback makes a token when it is built (`token`) and refuses every request without it
(`emulators/backdoor.py`); its rig file's `[emulation] backdoor_token` carries it, and `rigctl
emulate` writes that file mode 0600. Every bench answers:
- `{"cmd": "ping"}`;
- `{"cmd": "help"}`: `{"commands": [...]}`, the names in its table (an unknown command's error
  lists them too);
- `{"cmd": "speed", "factor": f}`: simulated seconds per real second from now on, for all of the
  bench's physics;
- `{"cmd": "fault", "device": D, "kind": K, "n": n}`: a fault on one device. A device with a link
  takes `drop_link` (connections reset, new ones refused), `stall` (no replies), `corrupt` (the
  next `n` replies garbage) and `restore`; the benches add their devices' own kinds. The camera's
  are `drop_frames` (`n`), `freeze`, `black_out`, `occlude` (`"robot": index`), `drop_link`,
  `restore`, also as `{"cmd": "camera", "kind": K, ...}`. The reply is `{"device", "kind"}`.
A bench with a camera also answers `{"cmd": "floor", "workspace": {...plan workspace...}}`: the
workspace laid on the floor (its walls, as a real rig's floor shows them, for `rigctl calibrate
camera`); the camera shows it while nothing is placed.
Each bench's module lists the devices, fault kinds and commands it adds (`place`, `truth`, ...).
"""

from __future__ import annotations

import argparse
import importlib
import ipaddress
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from rigctl.core.config import CameraSettings, RigConfig, dump_rig
from rigctl.core.errors import EXIT_OK, ConfigError
from rigctl.core.priority import BENCH_NICE_ENV, favour
from rigctl.core.tokens import new_token
from rigctl.emulators.backdoor import json_lines
from rigctl.emulators.process import READY_PREFIX
from rigctl.emulators.server import EmulatorServer, Endpoint

if TYPE_CHECKING:  # the camera (OpenCV) is imported by the benches that have one
    from rigctl.emulators.camera.mjpeg import MjpegCamera
    from rigctl.emulators.camera.render import Scene

log = logging.getLogger(__name__)

Command = Callable[[dict], dict]  # a backdoor request -> the reply's fields
Fault = Callable[[dict], object]  # injects one fault; gets the request (for "n", "robot", ...)

def _loopback(host: str) -> bool:
    """Whether `host` (an address, or a name looked up) is this machine's loopback."""
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        try:
            return ipaddress.ip_address(socket.gethostbyname(host)).is_loopback
        except OSError as err:
            raise ConfigError(f"--host {host}: {err}") from None


def bench_names() -> list[str]:
    """The installed rig kinds that have an emulated bench (`RigKind.bench`), sorted."""
    from rigctl.core.registry import kinds

    return [name for name, kind in kinds().items() if kind.bench is not None]


def bench_class(kind: str) -> type[EmulatedBench]:
    """The bench class that emulates rig kind `kind` (its `RigKind.bench`, imported now)."""
    from rigctl.core.registry import kinds

    found = kinds().get(kind)
    if found is None or found.bench is None:
        raise ConfigError(f"no emulated bench for rig kind {kind!r}; there are "
                          f"{', '.join(bench_names())}")
    module, name = found.bench.split(":")
    bench = getattr(importlib.import_module(module), name)
    if not (isinstance(bench, type) and issubclass(bench, EmulatedBench)):
        raise ConfigError(f"rig kind {kind!r}: its bench {found.bench} is not an EmulatedBench")
    return bench


class SimClock:
    """Simulated seconds since the clock started: real (monotonic) seconds elapsed times `speed`.
    A new speed applies from the instant it is set; the time already elapsed never jumps."""

    def __init__(self, speed: float = 1.0, *, monotonic: Callable[[], float] = time.monotonic) -> None:
        self._monotonic = monotonic
        # (real, simulated, speed) at the last change: replaced whole, so any thread reads it whole
        self._origin = (monotonic(), 0.0, _positive(speed))

    @property
    def speed(self) -> float:
        return self._origin[2]

    def now(self) -> float:
        real, sim, speed = self._origin
        return sim + (self._monotonic() - real) * speed

    def set_speed(self, speed: float) -> None:
        speed = _positive(speed)
        real = self._monotonic()
        then, sim, old = self._origin
        self._origin = (real, sim + (real - then) * old, speed)


def _positive(speed: float) -> float:
    if not float(speed) > 0:
        raise ValueError(f"speed factor must be positive, got {speed}")
    return float(speed)


class EmulatedBench:
    """Start with `start()` (or `with`), read `rig` for the rig file that points at the bench,
    `stop()` when done. Subclasses set `title` and implement `_serve()`."""

    title = "bench"  # for the operator: "six-coil bench"
    tick_s: ClassVar[float | None] = None  # advance() on this period too (None: only lazily)

    def __init__(self, *, host: str = "127.0.0.1", speed: float = 1.0) -> None:
        self.host = host
        # the backdoor's token: only beyond loopback (the console's rule for watching)
        self.token: str | None = None if _loopback(host) else new_token()
        self.server = EmulatorServer()
        self.clock = SimClock(speed)
        self.rig: RigConfig | None = None
        self.backdoor: Endpoint | None = None
        self.camera: MjpegCamera | None = None
        self.devices: dict[str, dict[str, Fault]] = {}  # device -> fault kind -> injector
        self.commands: dict[str, Command] = {"ping": lambda _: {}, "help": self._help,
                                             "speed": self._speed, "fault": self._fault}

    # -- life cycle ---------------------------------------------------------------------------
    def start(self) -> RigConfig:
        self.server.start()
        try:
            self.clock = SimClock(self.clock.speed)  # simulated time starts with the bench
            self.backdoor = self.server.serve_lines_tcp(json_lines(self.command, token=self.token),
                                                        name="backdoor", host=self.host)
            rig = self._serve()
            if self.token is not None and rig.emulation is not None:
                rig = rig.model_copy(update={"emulation": rig.emulation.model_copy(
                    update={"backdoor_token": self.token})})
            self.rig = rig
            if self.tick_s is not None:
                self.server.every(self.tick_s, self.advance)
        except BaseException:
            self.stop()
            raise
        log.info("%s up: backdoor %s", self.title, self.backdoor.url)
        return self.rig

    def stop(self) -> None:
        """Stop the bench's own parts (`_release`), then the server; idempotent."""
        self._release()
        self.server.stop()

    def __enter__(self):  # -> the subclass
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self) -> RigConfig:
        """Serve every device on `self.server`; the rig file pointing at them (backdoor included)."""
        raise NotImplementedError

    def _release(self) -> None:
        """What `stop()` ends before the server (threads, harnesses, sessions)."""

    def advance(self) -> None:
        """Step the physics to `self.clock.now()`."""

    # -- devices and their faults -------------------------------------------------------------
    def add_device(self, name: str, link: Endpoint | None = None, **kinds: Fault) -> None:
        """Make `name` a `fault` target: its link's faults (if it has one) and its own `kinds`."""
        faults: dict[str, Fault] = {}
        if link is not None:
            faults = {"drop_link": lambda _: link.drop_link(), "stall": lambda _: link.stall(),
                      "corrupt": lambda r: link.corrupt(int(r.get("n", 1))),
                      "restore": lambda _: link.restore()}
        self.devices[name] = {**faults, **kinds}

    def _serve_camera(self, field_mm: tuple[float, float, float, float], *, tilt_deg: float,
                      seed: int, fps: float) -> CameraSettings:
        """The overhead camera over a fixed field, slightly tilted as a real one is mounted (not
        re-aimed when robots are placed), serving `_scene()` as MJPEG; its faults go into the
        table (device "camera" and the `camera` command). Returns the rig file's [camera]."""
        from rigctl.emulators.camera import (
            PAPER_RESOLUTION,
            CameraModel,
            Renderer,
            serve_camera,
        )

        model = CameraModel.overhead(field_mm, tilt_deg=tilt_deg)
        floor: list[Scene] = []  # the workspace on the floor, shown until something is placed
        camera = self.camera = serve_camera(
            self.server, lambda: self._scene() or (floor[0] if floor else None),
            Renderer(model, seed=seed), fps=fps, host=self.host)
        self.add_device("camera", drop_frames=lambda r: camera.drop_frames(int(r.get("n", 1))),
                        freeze=lambda _: camera.freeze(), black_out=lambda _: camera.black_out(),
                        occlude=lambda r: camera.occlude(int(r["robot"])),
                        drop_link=lambda _: camera.endpoint.drop_link(),  # type: ignore[union-attr]
                        restore=lambda _: camera.restore())
        self.commands["camera"] = lambda r: self._fault({**r, "device": "camera"})

        def lay_floor(request: dict) -> dict:
            from rigctl.emulators.camera.render import Scene
            from rigctl.plans.schema import parse_workspace
            from rigctl.plans.workspace import Workspace

            spec = parse_workspace(request["workspace"], "floor: workspace")
            floor[:] = [Scene(Workspace.from_spec(spec), np.zeros((0, 2)), np.zeros(0))]
            return {}

        self.commands["floor"] = lay_floor
        return CameraSettings(url=camera.url, stamped=True, fps=fps, resolution=PAPER_RESOLUTION,
                              calibration=model.calibration())

    def _scene(self) -> Scene | None:
        """What the camera sees now (None: nothing placed yet, a black frame)."""
        return None

    # -- backdoor -----------------------------------------------------------------------------
    def command(self, request: dict) -> dict:
        """Answer one backdoor request from the table (in the server's loop thread)."""
        cmd = request.get("cmd")
        handler = self.commands.get(cmd) if isinstance(cmd, str) else None
        if handler is None:
            raise ValueError(f"unknown command {cmd!r}; use {', '.join(self.commands)}")
        return handler(request)

    def _help(self, request: dict) -> dict:
        return {"commands": list(self.commands)}

    def _speed(self, request: dict) -> dict:
        factor = float(request["factor"])
        _positive(factor)
        self.advance()  # the physics up to now at the old speed
        self.clock.set_speed(factor)
        return {"factor": factor}

    def _fault(self, request: dict) -> dict:
        device, kind = request.get("device"), request.get("kind")
        faults = self.devices.get(device) if isinstance(device, str) else None
        if faults is None:
            raise ValueError(f"no device {device!r}; the bench has {', '.join(self.devices)}")
        if kind not in faults:
            raise ValueError(f"unknown {device} fault {kind!r}; use {', '.join(faults)}")
        faults[kind](request)
        return {"device": device, "kind": kind}

    # -- rigctl emulate KIND ------------------------------------------------------------------
    @classmethod
    def from_args(cls, args: argparse.Namespace) -> EmulatedBench:
        """The bench `rigctl emulate KIND`'s options ask for (bad options: ConfigError)."""
        return cls(host=args.host)

    def served(self, rig: RigConfig) -> list[tuple[str, str]]:
        """(what, URL) of each device served, for the operator."""
        return []

    @classmethod
    def emulate_cli(cls, args: argparse.Namespace) -> int:
        """`rigctl emulate KIND --rig-out F`: serve the bench until SIGTERM or Ctrl-C; the rig
        file (with this process's pid) written and `READY <rig file>` on stdout once it is up."""
        if not _loopback(args.host):
            print(f"warning: serving the emulated devices on {args.host}: any host that reaches "
                  "them can drive them (the default, 127.0.0.1, keeps them on this machine); the "
                  f"backdoor takes only the token written in {args.rig_out} (mode 0600)",
                  file=sys.stderr, flush=True)
        give_back = _take_priority()
        try:
            return cls._serve_until_stopped(args)
        finally:
            give_back()  # a terminal's session it shared is no longer ahead of the others

    @classmethod
    def _serve_until_stopped(cls, args: argparse.Namespace) -> int:
        bench = cls.from_args(args)
        stop = threading.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
        rig_out = Path(args.rig_out)
        with bench:
            assert bench.rig is not None and bench.rig.emulation is not None
            rig = bench.rig.model_copy(update={"emulation": bench.rig.emulation.model_copy(
                update={"pid": os.getpid()})})
            _write_rig(rig_out, dump_rig(rig), private=bench.token is not None)
            print(f"{READY_PREFIX}{rig_out.resolve()}", flush=True)
            lines = [f"emulated {bench.title} up; rig file: {rig_out}; stop with Ctrl-C",
                     *(f"  {what:<10} {url}" for what, url in bench.served(rig)),
                     f"  backdoor   {bench.rig.emulation.backdoor}"]  # the copy's (pid aside)
            print("\n".join(lines), file=sys.stderr, flush=True)
            stop.wait()
        return EXIT_OK


def _write_rig(path: Path, text: str, *, private: bool) -> None:
    """Write the rig file; `private` (it holds the backdoor's token): readable by its owner only,
    from the first byte on, a file already there included."""
    if not private:
        path.write_text(text)
        return
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as out:
        os.fchmod(fd, 0o600)  # a file that existed kept its mode through O_CREAT
        out.write(text)


def _take_priority() -> Callable[[], None]:
    """The bench ahead of ordinary work where the machine permits it (`rigctl.core.priority`;
    RIGCTL_EMULATOR_NICE for another niceness), before it starts a thread; what gives it back.
    Real supplies, boards and arms answer from processors of their own: a bench starved by other
    work makes the run's 0.25 s reply watchdog measure the starvation instead of the link."""
    return favour("emulated bench", BENCH_NICE_ENV, pass_on=True)
