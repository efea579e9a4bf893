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
- `{"cmd": "speed", "factor": f}`: simulated seconds per real second;
- `{"cmd": "mismatch", "slip": 0.85, "speed_spread": 0.05, "drift_mm_per_s": 0.0, "noise_mm": 0.2,
  "seed": 3, "field_at_robots": true}`: how the world departs from the model from the next `place`
  on (keys left out keep their value); replies with the settings in force.

Model mismatch (`Mismatch`, set at construction, by `rigctl emulate --slip ...`, or through the
backdoor) is applied when the robots are placed; with `field_at_robots` each robot feels the coils'
field at its own position on the floor (the workspace's centre is the coils' centre).
Replies are `{"ok": true, ...}` or `{"ok": false, "error": "..."}`.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np
from rigctl.emulators.backdoor import json_lines
from rigctl.emulators.camera.mjpeg import serve_camera
from rigctl.emulators.camera.render import (
    PAPER_RESOLUTION,
    CameraModel,
    Renderer,
    Scene,
)
from rigctl.emulators.kepco_bop.model import BopCoilModel
from rigctl.emulators.kepco_bop.protocol import BopScpi
from rigctl.emulators.server import EmulatorServer, Endpoint
from rigctl.emulators.world.pair import PairWorld
from rigctl.emulators.world.rolling import Mismatch, RollingMagnetWorld
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.pair import PairPhysics
from rigctl.plans.schema import parse_workspace
from rigctl.plans.workspace import Workspace

from rigctl.config import (
    CameraSettings,
    Emulation,
    RigConfig,
    RigInfo,
    default_six_coil_coils,
)
from rigctl.magnetics import loop_field

log = logging.getLogger(__name__)

PHYSICS_STEP_S = 1e-3  # simulated time per sub-step: the field turns < 3 degrees per step at 8 turns/s
TICK_S = 5e-3  # how often the server advances the simulation when no command arrives
CAMERA_FIELD_MM = (0.0, 0.0, 400.0, 400.0)  # what the emulated camera's picture covers
PAIR_CAMERA_FIELD_MM = (0.0, 0.0, 20.0, 15.0)  # world "pair": a microscope over the coils' centre
FIELD_REFRESH_MM = 1.0  # recompute the per-robot field maps when a robot moved this far


@dataclass
class _Supply:
    name: str
    model: BopCoilModel
    endpoint: Endpoint
    field_per_amp_T: np.ndarray  # (3,) this coil's field at the workspace centre for 1 A


class SixCoilBench:
    """Start with `start()`, read `rig` for the rig file that points at it, `stop()` when done."""

    def __init__(self, template: RigConfig | None = None, *, host: str = "127.0.0.1",
                 mismatch: Mismatch | None = None, world: str = "rolling") -> None:
        if world not in ("rolling", "pair"):
            raise ValueError(f"unknown world {world!r}; use rolling or pair")
        # "rolling": the rolling magnets of seed 000; "pair": two interacting agents (seed 002,
        # emulators/world/pair.py), placed with {"cmd": "place", ..., "pair": {physics}}
        self.world_kind = world
        self.template = template or RigConfig(
            rig=RigInfo(kind="six-coil", name="emulated six-coil bench"),
            coils=default_six_coil_coils(),
        )
        self.host = host
        self.server = EmulatorServer()
        self.supplies: list[_Supply] = []
        self._field_matrix: np.ndarray | None = None  # (n_supplies, 3): T per A of each
        self.world: RollingMagnetWorld | PairWorld | None = None
        self.speed = 1.0
        self._lock = threading.Lock()
        self._sim_time = 0.0  # simulated time that should have elapsed
        self._stepped = 0.0  # simulated time the models have been stepped to
        self._world_at = 0.0  # simulated time the world has been stepped to
        self._last_real = time.monotonic()
        self.backdoor: Endpoint | None = None
        self.rig: RigConfig | None = None
        self.mismatch = mismatch or Mismatch()
        # per-robot field per amp (n, 3, n_coils) T/A and where it was computed (n, 2) mm
        self._robot_maps: tuple[np.ndarray, np.ndarray] | None = None
        self._floor_centre_mm = np.array([200.0, 200.0])

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
        self.backdoor = self.server.serve_lines_tcp(json_lines(self._backdoor_command), name="backdoor",
                                              host=self.host)
        # The camera looks down on a fixed 400 x 400 mm field from 600 mm, slightly tilted, as a
        # real one would be mounted; it is not re-aimed when robots are placed.
        camera_model = CameraModel.overhead(
            PAIR_CAMERA_FIELD_MM if self.world_kind == "pair" else CAMERA_FIELD_MM, tilt_deg=5.0)
        self.camera = serve_camera(self.server, self._scene, Renderer(camera_model, seed=1),
                                   fps=60.0, host=self.host)
        self._last_real = time.monotonic()
        self.server.every(TICK_S, self.advance)
        camera = CameraSettings(url=self.camera.url, stamped=True, fps=60.0,
                                resolution=PAPER_RESOLUTION, calibration=camera_model.calibration())
        self.rig = self.template.model_copy(
            update={"coils": coils, "camera": camera,
                    "emulation": self._emulation_settings()}
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
                # The world moves in whole PHYSICS_STEP_S steps only: SCPI lines arrive every
                # ~0.2 ms at 1 kHz, and feeling the field at each would cost the replies ~80 us
                # apiece (the stream loop fell behind); the supplies stay exact to the instant.
                if self.world is not None and self._stepped - self._world_at >= PHYSICS_STEP_S - 1e-12:
                    if isinstance(self.world, PairWorld):  # seed 002's agents feel the currents
                        self.world.step(self._stepped - self._world_at,
                                        [s.model.current_A for s in self.supplies])
                        self._world_at = self._stepped
                        continue
                    if self.world.mismatch.field_at_robots:
                        self.world.feel(self._fields_at_robots())
                    else:
                        self.world.feel(self.field_T())
                    self.world.drift(self._stepped - self._world_at)
                    self._world_at = self._stepped

    def field_T(self) -> np.ndarray:
        """The field at the workspace centre from the supplies' actual currents, (3,) in tesla."""
        if self._field_matrix is None or len(self._field_matrix) != len(self.supplies):
            self._field_matrix = np.array([s.field_per_amp_T for s in self.supplies])
        return np.array([s.model.current_A for s in self.supplies]) @ self._field_matrix

    def _fields_at_robots(self) -> np.ndarray:
        """The field each robot feels at its own floor position, (n, 3) T (caller holds the lock)."""
        positions = self.world.settled_positions_mm  # type: ignore[union-attr]
        if self._robot_maps is None or len(self._robot_maps[1]) != len(positions) or np.max(
                np.hypot(*(positions - self._robot_maps[1]).T)) > FIELD_REFRESH_MM:
            points = np.zeros((len(positions), 3))
            points[:, :2] = (positions - self._floor_centre_mm) * 1e-3
            maps = np.stack([
                loop_field(points, np.asarray(c.centre_mm) * 1e-3, np.asarray(c.axis),
                           c.loop_radius_mm * 1e-3, c.turns, 1.0)
                for c in self.template.coils], axis=-1)
            self._robot_maps = (maps, positions.copy())
        currents = np.array([s.model.current_A for s in self.supplies])
        return self._robot_maps[0] @ currents

    def _emulation_settings(self) -> Emulation:
        m = self.mismatch
        return Emulation(backdoor=self.backdoor.url, slip=m.slip,  # type: ignore[union-attr]
                         speed_spread=m.speed_spread, drift_mm_per_s=m.drift_mm_per_s,
                         noise_mm=m.noise_mm, seed=m.seed, field_at_robots=m.field_at_robots)

    def _scene(self) -> Scene | None:
        """What the camera sees now (None: nothing placed yet, a black frame)."""
        self.advance()
        with self._lock:
            if self.world is None:
                return None
            if isinstance(self.world, PairWorld):
                return Scene(self.world.workspace, self.world.positions_mm, self.world.radii.copy())
            return Scene(self.world.model.workspace, self.world.positions_mm.copy(),
                         np.asarray(self.world.model.radii, dtype=float).copy())

    # -- backdoor -----------------------------------------------------------------------------
    def _backdoor_command(self, request: dict) -> dict:
        cmd = request.get("cmd")
        if cmd == "ping":
            return {}
        if cmd == "truth" and isinstance(self.world, PairWorld):
            self.advance()
            with self._lock:
                return {"agents": self.world.positions_mm.tolist(),
                        "moments_Am2": self.world.moments.tolist(),
                        "min_separation_mm": self.world.min_separation_mm,
                        "field_T": self.field_T().tolist(),
                        "currents_A": {s.name: s.model.current_A for s in self.supplies},
                        "sim_time_s": self._stepped}
        if cmd == "place" and self.world_kind == "pair":
            return self._place_pair(request)
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
                    "distance_scale": None if self.world is None
                    else self.world.distance_scale.tolist(),
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
            mismatch = self.mismatch
            if "slip" in request:
                mismatch = Mismatch(**{**mismatch.__dict__, "slip": float(request["slip"])})
            bounds = np.array(model.workspace.bounds, dtype=float)
            with self._lock:
                self._floor_centre_mm = 0.5 * (bounds[:2] + bounds[2:])
                self._robot_maps = None
                self._world_at = self._stepped
                self.world = RollingMagnetWorld(
                    model,
                    positions,
                    rolling_radius_mm=magnets.radius_mm,
                    min_field_T=magnets.min_field_mT * 1e-3,
                    mismatch=mismatch,
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
        if cmd == "mismatch":
            settings = {**self.mismatch.__dict__}
            for key in settings:
                if key in request:
                    settings[key] = type(settings[key])(request[key])
            if settings["slip"] <= 0 or settings["speed_spread"] < 0 or settings["noise_mm"] < 0:
                raise ValueError("slip must be > 0, speed_spread and noise_mm >= 0")
            self.mismatch = Mismatch(**settings)
            return {"mismatch": settings}
        if cmd == "speed":
            factor = float(request["factor"])
            if not factor > 0:
                raise ValueError("speed factor must be positive")
            self.advance()
            self.speed = factor
            return {"factor": factor}
        raise ValueError(f"unknown command {cmd!r}; use ping, place, truth, fault, camera, speed, "
                         "mismatch")

    def _place_pair(self, request: dict) -> dict:
        """Put the two agents down: {"workspace", "agents": [{"position"}, {"position"}],
        "pair": {"body_diameter_mm", "moment_Am2", "viscosity_Pa_s"}}."""
        spec = parse_workspace(request["workspace"], "place: workspace")
        workspace = Workspace.from_spec(spec)
        positions = np.array([a["position"] for a in request["agents"]], dtype=float)
        if positions.shape != (2, 2):
            raise ValueError("the pair world takes exactly two agents")
        physics = PairPhysics(**request.get("pair", {}))
        radius = 0.5 * physics.body_diameter_mm
        if (workspace.clearance(positions) < radius).any() or \
                float(np.hypot(*(positions[1] - positions[0]))) < 2 * radius:
            raise ValueError("the agents do not fit there (overlap or outside free space)")
        bounds = np.array(workspace.bounds, dtype=float)
        with self._lock:
            self._floor_centre_mm = 0.5 * (bounds[:2] + bounds[2:])
            self._world_at = self._stepped
            self.world = PairWorld(workspace, positions, physics, self.template,
                                   self._floor_centre_mm, self.mismatch)
        return {"agents": positions.tolist()}

    def _supply(self, name: object) -> _Supply:
        for supply in self.supplies:
            if supply.name == name:
                return supply
        raise ValueError(f"no supply {name!r}; the bench has {[s.name for s in self.supplies]}")

