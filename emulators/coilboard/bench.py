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

The world steps from the bench's `SimClock` (`speed` simulated seconds per real second) every
`PHYSICS_TICK_S` and before every backdoor read, in the server's loop thread. The camera looks down
on a fixed field round the coils' centre (the rig's origin), slightly tilted; the rig file carries
its exact calibration.

Backdoor: the table of `emulators/base.py` (`ping`, `help`, `speed`, `fault`, `camera`) with
devices "board" (Python firmware: its link's faults and `unplug`, `replug`, `garbage` with `"hex":
bytes`) and "camera", plus:
- `{"cmd": "place", "workspace": {...plan workspace...}, "agents": [{"position": [x, y], "radius":
  r}], "ring": false, "physics": {...CoilBoardPhysics fields...}}`: put the particles down; with
  `ring` a disk boundary is replaced by the intestine phantom (sixty 2 mm protrusions) of the same
  diameter; `physics` overrides the world's parameters from then on (`mobility_spread` and
  `mobility_seed` make each particle's mobility its own); replies with the positions, the physics
  and each particle's mobility factor;
- `{"cmd": "truth"}`: particle positions (mm) and mobility factors, the SyRen outputs, each coil's
  winding temperature (C, now and its peak; the windings heat by `rigctl.physics.thermal`, `coils.py`) and
  whether its thermal cut-out is open, the firmware's counters (Python firmware), simulated time;
- `{"cmd": "windings", "size": 0.05, "seed": 0, "thermal": {...CoilThermal fields...}}`: rebuild
  the windings with R_th and C_th off the rig file's by up to `size` (`ThermalErrors`; their
  temperatures are kept); with `thermal`, from that winding data instead, at the room's
  temperature (the rig file keeps its own: a run must be given the same); replies with each
  winding as built and its data; `{"cmd": "windings"}` only reads them.
"""

from __future__ import annotations

import argparse
import dataclasses
import os

import numpy as np

from rigctl.core.config import CoilBoardSettings, CoilThermal, Emulation, RigConfig, RigInfo, settings_of
from rigctl.core.errors import ConfigError
from rigctl.emulators.base import EmulatedBench
from rigctl.emulators.camera.render import Scene
from rigctl.emulators.coilboard.coils import BoardCoils, ThermalErrors
from rigctl.emulators.coilboard.syren import SyrenBus
from rigctl.emulators.world.coilboard import (
    CoilBoardPhysics,
    CoilBoardWorld,
    intestine_ring_spec,
)
from rigctl.plans.schema import parse_workspace
from rigctl.plans.workspace import Workspace

PHYSICS_TICK_S = 0.005  # real seconds between two world steps when nothing asks
CAMERA_FIELD_MM = (-30.0, -30.0, 30.0, 30.0)  # what the camera sees, round the coils' centre
CAMERA_FPS = 30.0
BOARD_REPLY_TIMEOUT_S = 0.3


class CoilBoardBench(EmulatedBench):
    """The coil-board bench (`EmulatedBench`).

    firmware: "python" (default) or "simavr"; physics: the world's parameters; speed: simulated
    seconds per real second; syren_startup_s: the Python firmware's SyRen start-up wait (the
    board's 2 s by default); coil_thermal: the rig file's winding data (default the board's);
    thermal_errors: how far the emulated windings are from it.
    """

    tick_s = PHYSICS_TICK_S

    def __init__(self, *, firmware: str = "python", host: str = "127.0.0.1",
                 physics: CoilBoardPhysics | None = None, speed: float = 1.0,
                 syren_startup_s: float | None = None, coil_thermal: CoilThermal | None = None,
                 thermal_errors: ThermalErrors | None = None) -> None:
        if firmware not in ("python", "simavr"):
            raise ConfigError(f"--firmware: python or simavr, got {firmware!r}")
        if not speed > 0:
            raise ConfigError(f"speed must be > 0, got {speed}")
        super().__init__(host=host, speed=speed)
        self.firmware_kind = firmware
        self.title = f"coil-board bench ({firmware} firmware)"
        self.physics = physics or CoilBoardPhysics()
        self.syren_startup_s = syren_startup_s
        self.bus = SyrenBus()
        self.board = None  # FirmwareEmulator (python)
        self.harness = None  # the simavr harness
        self._wire_reader = None
        self.world: CoilBoardWorld | None = None
        self._stepped = 0.0  # simulated time the coils and the world have been stepped to
        # the rig file's [board] but its url (the firmware's pty, known once it runs)
        thermal = {} if coil_thermal is None else {"coil_thermal": coil_thermal}
        self.board_settings = CoilBoardSettings(url=os.devnull, reply_timeout_s=BOARD_REPLY_TIMEOUT_S,
                                                **thermal)
        self.coils = BoardCoils(self.board_settings, thermal_errors or ThermalErrors())
        self.commands.update(place=self._place, truth=self._truth, windings=self._windings)

    def _serve(self) -> RigConfig:
        board_url = self._start_firmware()
        camera = self._serve_camera(CAMERA_FIELD_MM, tilt_deg=4.0, seed=4, fps=CAMERA_FPS)
        assert self.backdoor is not None
        return settings_of("coil-board")(
            rig=RigInfo(kind="coil-board", name=f"emulated {self.title}"),
            # The emulated board shares a process (and Python's GIL) with the camera's renderer
            # and the world: allow it more than a real board's 2 ms per reply.
            board=self.board_settings.model_copy(update={"url": board_url}),
            camera=camera,
            emulation=Emulation(backdoor=self.backdoor.url,
                                thermal_mismatch=self.coils.errors.size),
        )

    def _start_firmware(self) -> str:
        if self.firmware_kind == "python":
            from rigctl.emulators.coilboard.firmware import FirmwareEmulator

            options = {} if self.syren_startup_s is None else {"syren_startup_s": self.syren_startup_s}
            self.board = board = FirmwareEmulator(sink=self.bus.feed, server=self.server,
                                                  **options).start()
            self.add_device("board", board.endpoint, unplug=lambda _: board.unplug(),
                            replug=lambda _: board.replug(), garbage=lambda r: board.inject(
                                bytes.fromhex(r.get("hex", "a5ff00"))))
            return board.url
        from rigctl.emulators.coilboard.simavr import SimavrBoard
        from rigctl.emulators.coilboard.syren import SyrenWireReader

        self.harness = SimavrBoard().start()
        self._wire_reader = SyrenWireReader(self.harness.syren_path, self.bus)
        return self.harness.uart_path

    def _release(self) -> None:
        if self._wire_reader is not None:
            self._wire_reader.close()
        if self.harness is not None:
            self.harness.stop()
        if self.board is not None:
            self.board.stop()

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> CoilBoardBench:
        """`rigctl emulate coil-board [--firmware simavr]`."""
        return cls(firmware=getattr(args, "firmware", None) or "python", host=args.host)

    def served(self, rig: RigConfig) -> list[tuple[str, str]]:
        return [("board", str(rig.board.url)), ("camera", str(rig.camera.url))]  # type: ignore[union-attr]

    # -- simulation (the server's loop thread) ------------------------------------------------
    def advance(self) -> None:
        """Step the coils' windings and the world to the clock's now with the four outputs the
        SyRen bus holds (a coil whose cut-out is open pulls nothing)."""
        now = self.clock.now()
        if now > self._stepped:
            pulls = self.coils.step(now - self._stepped, self.bus.outputs())
            if self.world is not None:
                self.world.step(now - self._stepped, pulls)
        self._stepped = now

    def _scene(self) -> Scene | None:
        if self.world is None:
            return None
        return Scene(self.world.workspace, self.world.positions_mm.copy(),
                     self.world.radii_mm.copy())

    # -- backdoor -----------------------------------------------------------------------------
    def _truth(self, request: dict) -> dict:
        self.advance()
        world = self.world
        reply = {
            "agents": [] if world is None else world.positions_mm.tolist(),
            "mobility_factors": [] if world is None else world.mobility_factors.tolist(),
            "sim_time_s": None if world is None else world.time_s,
            "outputs": list(self.bus.outputs()),
            **self.coils.truth(),
        }
        if self.board is not None:
            state = self.board.state()
            reply["firmware"] = {"flags": state.flags, "outputs": list(state.outputs),
                                 "good_frames": state.good_frames,
                                 "bad_frames": state.bad_frames,
                                 "watchdog_trips": state.watchdog_trips}
        return reply

    def _windings(self, request: dict) -> dict:
        if not {"size", "seed", "thermal"} & set(request):
            return self.coils.describe()
        self.advance()  # the windings heated as they were until now
        errors = ThermalErrors(size=float(request.get("size", self.coils.errors.size)),
                               seed=int(request.get("seed", self.coils.errors.seed)))
        if "thermal" in request:
            self.board_settings = self.board_settings.model_copy(
                update={"coil_thermal": CoilThermal(**request["thermal"])})
            self.coils = BoardCoils(self.board_settings, errors)
        else:
            self.coils.rebuild(errors)
        return self.coils.describe()

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
        self.advance()
        self.world = CoilBoardWorld(workspace, positions, radii, self.physics, centre_mm=(0.0, 0.0))
        return {"agents": positions.tolist(), "physics": dataclasses.asdict(self.physics),
                "mobility_factors": self.world.mobility_factors.tolist()}
