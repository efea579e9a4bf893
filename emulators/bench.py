"""The emulated six-coil bench: six Kepco BOP supplies on their own TCP ports, the coils' field, the
rolling magnets, an overhead camera serving MJPEG over HTTP, and a backdoor for tests, all on one
asyncio server thread.

The simulation is advanced lazily and in fixed sub-steps of simulated time: before every SCPI command
and on a periodic tick, `advance()` steps every supply's R-L model and the world up to "now"
(monotonic clock times a speed factor). The world feels the field made by the supplies' *actual*
currents, computed from each coil's own geometry with the closed-form loop field, not through the
allocator's actuation matrix, so an error in allocation or in the realizer shows up as a magnet in
the wrong place.

Backdoor (JSON lines over TCP, one request per line, one reply per line):
- `{"cmd": "ping"}`
- `{"cmd": "place", "workspace": {...plan workspace, image paths absolute...}, "agents":
  [{"position": [x, y], "radius": r}], "contact": "slide", "min_separation_mm": 0}`: put the robots
  down (what an operator does by hand);
- `{"cmd": "truth"}`: agents' true positions (mm), axis, field (T), each coil's current (A);
- `{"cmd": "fault", "device": "x+", "kind": "drop_link" | "stall" | "corrupt" | "overtemp" |
  "restore"}`: inject a fault into one supply;
- `{"cmd": "camera", "kind": "drop_frames" | "freeze" | "black_out" | "occlude" | "drop_link" |
  "restore", "n": frames, "robot": index}`: camera faults (also as `fault` with device "camera");
- `{"cmd": "speed", "factor": f}`: simulated seconds per real second.
Replies are `{"ok": true, ...}` or `{"ok": false, "error": "..."}`.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from rigctl.config import CameraSettings, Emulation, RigConfig, RigInfo, default_six_coil_coils
from rigctl.emulators.camera.mjpeg import serve_camera
from rigctl.emulators.camera.render import PAPER_RESOLUTION, CameraModel, Renderer, Scene
from rigctl.emulators.kepco_bop.model import BopCoilModel
from rigctl.emulators.kepco_bop.protocol import BopScpi
from rigctl.emulators.server import Endpoint, EmulatorServer
from rigctl.emulators.world.rolling import RollingMagnetWorld
from rigctl.magnetics import loop_field
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.schema import parse_workspace
from rigctl.plans.workspace import Workspace

log = logging.getLogger(__name__)

PHYSICS_STEP_S = 1e-3  # simulated time per sub-step: the field turns < 3 degrees per step at 8 turns/s
TICK_S = 5e-3  # how often the server advances the simulation when no command arrives
CAMERA_FIELD_MM = (0.0, 0.0, 400.0, 400.0)  # what the emulated camera's picture covers


@dataclass
class _Supply:
    name: str
    model: BopCoilModel
    endpoint: Endpoint
    field_per_amp_T: np.ndarray  # (3,) this coil's field at the workspace centre for 1 A


class SixCoilBench:
    """Start with `start()`, read `rig` for the rig file that points at it, `stop()` when done."""

    def __init__(self, template: RigConfig | None = None, *, host: str = "127.0.0.1") -> None:
        self.template = template or RigConfig(
            rig=RigInfo(kind="six-coil", name="emulated six-coil bench"),
            coils=default_six_coil_coils(),
        )
        self.host = host
        self.server = EmulatorServer()
        self.supplies: list[_Supply] = []
        self.world: RollingMagnetWorld | None = None
        self.speed = 1.0
        self._lock = threading.Lock()
        self._sim_time = 0.0  # simulated time that should have elapsed
        self._stepped = 0.0  # simulated time the models have been stepped to
        self._last_real = time.monotonic()
        self.backdoor: Endpoint | None = None
        self.rig: RigConfig | None = None

    # -- life cycle ---------------------------------------------------------------------------
    def start(self) -> RigConfig:
        self.server.start()
        coils = []
        for coil in self.template.coils:
            model = BopCoilModel(
                resistance_ohm=coil.resistance_ohm,
                inductance_H=coil.inductance_H,
                current_limit_A=coil.current_limit_A,
                compliance_V=coil.compliance_V,
            )
            scpi = BopScpi(model, before_command=self.advance)
            endpoint = self.server.serve_lines_tcp(scpi.handle, name=coil.name, host=self.host)
            field = loop_field(
                np.zeros(3),
                np.asarray(coil.centre_mm) * 1e-3,
                np.asarray(coil.axis),
                coil.loop_radius_mm * 1e-3,
                coil.turns,
                1.0,
            )
            self.supplies.append(_Supply(coil.name, model, endpoint, np.asarray(field, dtype=float)))
            coils.append(coil.model_copy(update={"url": endpoint.url}))
        self.backdoor = self.server.serve_lines_tcp(self._backdoor, name="backdoor", host=self.host)
        # The camera looks down on a fixed 400 x 400 mm field from 600 mm, slightly tilted, as a
        # real one would be mounted; it is not re-aimed when robots are placed.
        camera_model = CameraModel.overhead(CAMERA_FIELD_MM, tilt_deg=5.0)
        self.camera = serve_camera(self.server, self._scene, Renderer(camera_model, seed=1),
                                   fps=60.0, host=self.host)
        self._last_real = time.monotonic()
        self.server.every(TICK_S, self.advance)
        camera = CameraSettings(url=self.camera.url, stamped=True, fps=60.0,
                                resolution=PAPER_RESOLUTION, calibration=camera_model.calibration())
        self.rig = self.template.model_copy(
            update={"coils": coils, "camera": camera,
                    "emulation": Emulation(backdoor=self.backdoor.url)}
        )
        log.info("six-coil bench up: backdoor %s", self.backdoor.url)
        return self.rig

    def stop(self) -> None:
        self.server.stop()

    def __enter__(self) -> "SixCoilBench":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- simulation ---------------------------------------------------------------------------
    def advance(self) -> None:
        """Step every supply and the world up to now, in fixed sub-steps of simulated time."""
        with self._lock:
            now = time.monotonic()
            self._sim_time += (now - self._last_real) * self.speed
            self._last_real = now
            target = self._sim_time
            while self._stepped < target:
                dt = min(PHYSICS_STEP_S, target - self._stepped)
                for supply in self.supplies:
                    supply.model.step(dt)
                self._stepped += dt
                if self.world is not None:
                    self.world.feel(self.field_T())

    def field_T(self) -> np.ndarray:
        """The field at the workspace centre from the supplies' actual currents, (3,) in tesla."""
        total = np.zeros(3)
        for supply in self.supplies:
            total += supply.field_per_amp_T * supply.model.current_A
        return total

    def _scene(self) -> Scene | None:
        """What the camera sees now (None: nothing placed yet, a black frame)."""
        self.advance()
        with self._lock:
            if self.world is None:
                return None
            return Scene(self.world.model.workspace, self.world.positions_mm.copy(),
                         np.asarray(self.world.model.radii, dtype=float).copy())

    # -- backdoor -----------------------------------------------------------------------------
    def _backdoor(self, line: str) -> str:
        try:
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ValueError("a request is a JSON object")
            reply = self._backdoor_command(request)
        except Exception as err:  # the backdoor answers every line, whatever it was
            return json.dumps({"ok": False, "error": f"{type(err).__name__}: {err}"})
        return json.dumps({"ok": True, **reply})

    def _backdoor_command(self, request: dict) -> dict:
        cmd = request.get("cmd")
        if cmd == "ping":
            return {}
        if cmd == "truth":
            self.advance()
            with self._lock:
                return {
                    "agents": [] if self.world is None else self.world.positions_mm.tolist(),
                    "axis": None if self.world is None or self.world.axis_xy is None
                    else self.world.axis_xy.tolist(),
                    "field_T": self.field_T().tolist(),
                    "currents_A": {s.name: s.model.current_A for s in self.supplies},
                    "sim_time_s": self._stepped,
                }
        if cmd == "place":
            spec = parse_workspace(request["workspace"], "place: workspace")
            agents = request["agents"]
            positions = np.array([a["position"] for a in agents], dtype=float)
            radii = np.array([a["radius"] for a in agents], dtype=float)
            model = GlobalInputModel(
                Workspace.from_spec(spec), radii, contact=request.get("contact", "slide"),
                min_separation_mm=float(request.get("min_separation_mm", 0.0)),
            )
            if not bool(np.all(model.is_free(positions))):
                raise ValueError("the agents do not fit there (overlap or outside free space)")
            magnets = self.template.magnets
            with self._lock:
                self.world = RollingMagnetWorld(
                    model,
                    positions,
                    rolling_radius_mm=magnets.radius_mm,
                    min_field_T=magnets.min_field_mT * 1e-3,
                    slip=float(request.get("slip", 1.0)),
                )
            return {"agents": positions.tolist()}
        if cmd == "fault" and request.get("device") == "camera":
            return self._backdoor_command({**request, "cmd": "camera"})
        if cmd == "fault":
            supply = self._supply(request.get("device"))
            kind = request.get("kind")
            if kind == "drop_link":
                supply.endpoint.drop_link()
            elif kind == "stall":
                supply.endpoint.stall()
            elif kind == "corrupt":
                supply.endpoint.corrupt(int(request.get("n", 1)))
            elif kind == "overtemp":
                with self._lock:
                    supply.model.inject_overtemperature()
            elif kind == "restore":
                supply.endpoint.restore()
            else:
                raise ValueError(
                    f"unknown fault kind {kind!r}; use drop_link, stall, corrupt, overtemp, restore"
                )
            return {"device": supply.name, "kind": kind}
        if cmd == "camera":
            kind = request.get("kind")
            if kind == "drop_frames":
                self.camera.drop_frames(int(request.get("n", 1)))
            elif kind == "freeze":
                self.camera.freeze()
            elif kind == "black_out":
                self.camera.black_out()
            elif kind == "occlude":
                self.camera.occlude(int(request["robot"]))
            elif kind == "drop_link":
                self.camera.endpoint.drop_link()
            elif kind == "restore":
                self.camera.restore()
            else:
                raise ValueError(f"unknown camera fault {kind!r}; use drop_frames, freeze, "
                                 "black_out, occlude, drop_link, restore")
            return {"device": "camera", "kind": kind}
        if cmd == "speed":
            factor = float(request["factor"])
            if not factor > 0:
                raise ValueError("speed factor must be positive")
            self.advance()
            self.speed = factor
            return {"factor": factor}
        raise ValueError(f"unknown command {cmd!r}; use ping, place, truth, fault, camera, speed")

    def _supply(self, name: object) -> _Supply:
        for supply in self.supplies:
            if supply.name == name:
                return supply
        raise ValueError(f"no supply {name!r}; the bench has {[s.name for s in self.supplies]}")
