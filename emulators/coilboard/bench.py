"""The emulated coil-board bench: the board's firmware on a pty, the SyRen wire, four coils pulling
particles through syrup, an overhead camera serving MJPEG over HTTP, and a backdoor for tests.

    with CoilBoardBench() as bench:              # firmware="simavr" runs the real AVR firmware
        bench.rig                                 # RigConfig of kind coil-board: [board], [camera], [emulation]

The chain is the real one: a driver opens `rig.board.url` (a pty) and speaks the board protocol to
the firmware (the Python `FirmwareEmulator`, or the AVR firmware in simavr, whose SyRen pin is
decoded onto a second pty); the SyRen bytes the firmware sends go into a `SyrenBus`, and the world
(`emulators/world/coilboard.py`) moves the particles with the four outputs the bus holds. Nothing
else reaches the world: a wrong command, a wrong address or a missing refresh shows up as a particle
that does not move.

The world steps in its own thread at `PHYSICS_TICK_S`, `speed` simulated seconds per real second.
The camera looks down on a fixed field round the coils' centre (the rig's origin), slightly
tilted; the rig file carries its exact calibration.

Backdoor (JSON lines over TCP, one reply per request, `{"ok": true, ...}` or `{"ok": false,
"error": ...}`):
- `{"cmd": "ping"}`;
- `{"cmd": "place", "workspace": {...plan workspace...}, "agents": [{"position": [x, y], "radius":
  r}], "ring": false, "physics": {...CoilBoardPhysics fields...}}`: put the particles down; with
  `ring` a disk boundary is replaced by the intestine phantom (sixty 2 mm protrusions) of the same
  diameter; `physics` overrides the world's parameters from then on;
- `{"cmd": "truth"}`: particle positions (mm), the SyRen outputs, the firmware's counters (Python
  firmware), simulated time;
- `{"cmd": "fault", "device": "board", "kind": "unplug" | "replug" | "stall" | "restore" |
  "garbage"}`: the board's link (Python firmware); device "camera" as on the six-coil bench
  (`drop_frames`, `freeze`, `black_out`, `occlude`, `drop_link`, `restore`);
- `{"cmd": "speed", "factor": f}`.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
from rigctl.emulators.backdoor import json_lines
from rigctl.emulators.camera.mjpeg import serve_camera
from rigctl.emulators.camera.render import (
    PAPER_RESOLUTION,
    CameraModel,
    Renderer,
    Scene,
)
from rigctl.emulators.coilboard.syren import SyrenBus
from rigctl.emulators.server import EmulatorServer, Endpoint
from rigctl.emulators.world.coilboard import (
    CoilBoardPhysics,
    CoilBoardWorld,
    intestine_ring_spec,
)
from rigctl.plans.schema import parse_workspace
from rigctl.plans.workspace import Workspace

from rigctl.config import (
    CameraSettings,
    CoilBoardSettings,
    Emulation,
    RigConfig,
    RigInfo,
    dump_rig,
)
from rigctl.errors import ConfigError

log = logging.getLogger(__name__)

PHYSICS_TICK_S = 0.005  # the world's clock: real seconds between steps
CAMERA_FIELD_MM = (-30.0, -30.0, 30.0, 30.0)  # what the camera sees, round the coils' centre
CAMERA_FPS = 30.0
BOARD_REPLY_TIMEOUT_S = 0.3


class CoilBoardBench:
    """Start with `start()` (or `with`), read `rig` for the rig file, `stop()` when done.

    firmware: "python" (default) or "simavr"; physics: the world's parameters; speed: simulated
    seconds per real second; syren_startup_s: the Python firmware's SyRen start-up wait (the
    board's 2 s by default).
    """

    def __init__(self, *, firmware: str = "python", host: str = "127.0.0.1",
                 physics: CoilBoardPhysics = CoilBoardPhysics(), speed: float = 1.0,
                 syren_startup_s: float | None = None) -> None:
        if firmware not in ("python", "simavr"):
            raise ConfigError(f"--firmware: python or simavr, got {firmware!r}")
        if not speed > 0:
            raise ConfigError(f"speed must be > 0, got {speed}")
        self.firmware_kind = firmware
        self.host = host
        self.physics = physics
        self.speed = float(speed)
        self.syren_startup_s = syren_startup_s
        self.server = EmulatorServer()
        self.bus = SyrenBus()
        self.board = None  # FirmwareEmulator (python)
        self.harness = None  # the simavr harness
        self._wire_reader = None
        self.world: CoilBoardWorld | None = None
        self.rig: RigConfig | None = None
        self.backdoor: Endpoint | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- life cycle ---------------------------------------------------------------------------
    def start(self) -> RigConfig:
        self.server.start()
        try:
            board_url = self._start_firmware()
            self.backdoor = self.server.serve_lines_tcp(json_lines(self._command), name="backdoor",
                                                  host=self.host)
            camera_model = CameraModel.overhead(CAMERA_FIELD_MM, tilt_deg=4.0)
            self.camera = serve_camera(self.server, self._scene, Renderer(camera_model, seed=4),
                                       fps=CAMERA_FPS, host=self.host)
        except BaseException:
            self.stop()
            raise
        self._thread = threading.Thread(target=self._run_world, name="coilboard-world", daemon=True)
        self._thread.start()
        camera = CameraSettings(url=self.camera.url, stamped=True, fps=CAMERA_FPS,
                                resolution=PAPER_RESOLUTION, calibration=camera_model.calibration())
        self.rig = RigConfig(
            rig=RigInfo(kind="coil-board", name=f"emulated coil-board bench ({self.firmware_kind} "
                        "firmware)"),
            # The emulated board shares a process (and Python's GIL) with the camera's renderer
            # and the world: allow it more than a real board's 2 ms per reply.
            board=CoilBoardSettings(url=board_url, reply_timeout_s=BOARD_REPLY_TIMEOUT_S),
            camera=camera,
            emulation=Emulation(backdoor=self.backdoor.url),
        )
        log.info("coil-board bench up: board %s, backdoor %s", board_url, self.backdoor.url)
        return self.rig

    def _start_firmware(self) -> str:
        if self.firmware_kind == "python":
            from rigctl.emulators.coilboard.firmware import FirmwareEmulator

            options = {} if self.syren_startup_s is None else {"syren_startup_s": self.syren_startup_s}
            self.board = FirmwareEmulator(sink=self.bus.feed, server=self.server, **options).start()
            return self.board.url
        from rigctl.emulators.coilboard.simavr import SimavrBoard
        from rigctl.emulators.coilboard.syren import SyrenWireReader

        self.harness = SimavrBoard().start()
        self._wire_reader = SyrenWireReader(self.harness.syren_path, self.bus)
        return self.harness.uart_path

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        if self._wire_reader is not None:
            self._wire_reader.close()
        if self.harness is not None:
            self.harness.stop()
        if self.board is not None:
            self.board.stop()
        self.server.stop()

    def __enter__(self) -> "CoilBoardBench":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- simulation ---------------------------------------------------------------------------
    def _run_world(self) -> None:
        """The world's clock: every tick, step by the real time elapsed times `speed`."""
        last = time.monotonic()
        while not self._stop.wait(PHYSICS_TICK_S):
            now = time.monotonic()
            outputs = self.bus.outputs(now)
            with self._lock:
                if self.world is not None:
                    self.world.step((now - last) * self.speed, outputs)
            last = now

    def _scene(self) -> Scene | None:
        with self._lock:
            if self.world is None:
                return None
            return Scene(self.world.workspace, self.world.positions_mm.copy(),
                         self.world.radii_mm.copy())

    # -- backdoor -----------------------------------------------------------------------------
    def _command(self, request: dict) -> dict:
        cmd = request.get("cmd")
        if cmd == "ping":
            return {}
        if cmd == "place":
            return self._place(request)
        if cmd == "truth":
            with self._lock:
                world = self.world
                reply = {
                    "agents": [] if world is None else world.positions_mm.tolist(),
                    "sim_time_s": None if world is None else world.time_s,
                }
            reply["outputs"] = list(self.bus.outputs())
            if self.board is not None:
                state = self.board.state()
                reply["firmware"] = {"flags": state.flags, "outputs": list(state.outputs),
                                     "good_frames": state.good_frames,
                                     "bad_frames": state.bad_frames,
                                     "watchdog_trips": state.watchdog_trips}
            return reply
        if cmd == "fault":
            return self._fault(request)
        if cmd == "camera":
            return self._fault({**request, "device": "camera"})
        if cmd == "speed":
            factor = float(request["factor"])
            if not factor > 0:
                raise ValueError("speed factor must be positive")
            self.speed = factor
            return {"factor": factor}
        raise ValueError(f"unknown command {cmd!r}; use ping, place, truth, fault, camera, speed")

    def _place(self, request: dict) -> dict:
        data = request["workspace"]
        if request.get("ring"):
            boundary = data.get("boundary", {})
            if "disk" not in boundary:
                raise ValueError("ring: the workspace's boundary must be a disk (its diameter is "
                                 "the phantom's)")
            cx, cy, r = boundary["disk"]
            data = intestine_ring_spec((cx, cy), inner_diameter_mm=2.0 * r)
        workspace = Workspace.from_spec(parse_workspace(data, "place: workspace"))
        agents = request["agents"]
        positions = np.array([a["position"] for a in agents], dtype=float).reshape(-1, 2)
        radii = np.array([a["radius"] for a in agents], dtype=float)
        if "physics" in request:
            self.physics = dataclasses.replace(self.physics, **{
                k: float(v) for k, v in dict(request["physics"]).items()})
        world = CoilBoardWorld(workspace, positions, radii, self.physics, centre_mm=(0.0, 0.0))
        with self._lock:
            self.world = world
        return {"agents": positions.tolist(), "physics": dataclasses.asdict(self.physics)}

    def _fault(self, request: dict) -> dict:
        device, kind = request.get("device"), request.get("kind")
        if device == "camera":
            camera = self.camera
            actions = {"drop_frames": lambda: camera.drop_frames(int(request.get("n", 1))),
                       "freeze": camera.freeze, "black_out": camera.black_out,
                       "occlude": lambda: camera.occlude(int(request["robot"])),
                       "drop_link": camera.endpoint.drop_link, "restore": camera.restore}
        elif device == "board":
            if self.board is None:
                raise ValueError("board faults need the Python firmware (the simavr harness is "
                                 "stopped and restarted by its own tests)")
            board = self.board
            actions = {"unplug": board.unplug, "replug": board.replug, "stall": board.stall,
                       "restore": board.restore,
                       "garbage": lambda: board.inject(bytes.fromhex(request.get("hex", "a5ff00")))}
        else:
            raise ValueError(f"no device {device!r}; use board or camera")
        if kind not in actions:
            raise ValueError(f"unknown {device} fault {kind!r}; use {', '.join(actions)}")
        actions[kind]()
        return {"device": device, "kind": kind}


def emulate_cli(args: argparse.Namespace) -> int:
    """`rigctl emulate coil-board [--firmware simavr] --rig-out F`: serve the bench until Ctrl-C;
    `READY <rig file>` on stdout once it is up."""
    from rigctl.emulators.process import READY_PREFIX

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    rig_out = Path(args.rig_out)
    firmware = getattr(args, "firmware", None) or "python"
    with CoilBoardBench(firmware=firmware, host=args.host) as bench:
        assert bench.rig is not None and bench.rig.emulation is not None
        rig = bench.rig.model_copy(update={"emulation": bench.rig.emulation.model_copy(
            update={"pid": os.getpid()})})
        rig_out.write_text(dump_rig(rig))
        print(f"{READY_PREFIX}{rig_out.resolve()}", flush=True)
        print(f"emulated coil-board bench up ({firmware} firmware); rig file: {rig_out}; stop with "
              f"Ctrl-C\n  board      {rig.board.url}\n  camera     {rig.camera.url}\n"
              f"  backdoor   {rig.emulation.backdoor}", file=sys.stderr, flush=True)
        stop.wait()
    return 0
