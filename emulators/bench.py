"""The emulated six-coil bench: six Kepco BOP supplies on their own TCP ports, the coils' field, the
rolling magnets, an overhead camera serving MJPEG over HTTP, and a backdoor for tests, all on one
asyncio server thread.

The simulation is advanced lazily and in fixed sub-steps of simulated time: before every SCPI command
and on a periodic tick, `advance()` steps every supply's R-L model and the world up to "now"
(the bench's `SimClock`: monotonic time times the speed factor). The world feels the field made by
the supplies' *actual*
currents, computed from each coil's own geometry with the closed-form loop field, not through the
allocator's actuation matrix, so an error in allocation or in the realizer shows up as a magnet in
the wrong place.

Backdoor: the table of `emulators/base.py` (`ping`, `help`, `speed`, `fault`, `camera`) with
devices "x+" ... "z-" (each supply: its link's faults and `overtemp`; `restore` clears both),
"camera", and "probe" (the Hall probe board: its link's faults and `skip`), plus:
- `{"cmd": "place", "workspace": {...plan workspace, image paths absolute...}, "agents":
  [{"position": [x, y], "radius": r}], "contact": "slide", "min_separation_mm": 0}`: put the robots
  down (what an operator does by hand); world "pair": `"pair": {physics}` and two agents;
- `{"cmd": "truth"}`: agents' true positions (mm), axis, field (T), each coil's current (A) and
  winding temperature (C, now and its peak; the windings heat by `rigctl.physics.thermal`),
  simulated time (world "pair": the moments and the agents' separation instead of the axis);
- `{"cmd": "coil_errors", "size": 0.05, "seed": 0}`: rebuild the coils as built (`coil_errors.py`:
  gain, centre and axis off the rig file's by up to `size`; 0 is the ideal bench) at once;
  replies with each true coil (`name`, `centre_mm`, `axis`, `gain`); `{"cmd": "coil_errors"}` only
  reads them;
- `{"cmd": "coil_fields", "points_mm": [[x, y, z], ...]}`: ground truth for tests, each true
  coil's field per ampere at the points, `"T_per_A"` (n, 3, n_coils);
- `{"cmd": "probe", "points_mm": [[x, y, z], ...]}`: put the Hall probe array's sensors there
  (mm from the workspace centre; default the 27 points of a 3 x 3 x 3 grid at +-100 mm); a client
  that connects to the probe board afterwards reads them in its `hello`;
- `{"cmd": "mismatch", "slip": 0.85, "speed_spread": 0.05, "drift_mm_per_s": 0.0, "noise_mm": 0.2,
  "seed": 3, "field_at_robots": true}`: how the world departs from the model from the next `place`
  on (keys left out keep their value); replies with the settings in force.

The coils' field is their true field (`CoilErrors`, default 5 %, `rigctl emulate six-coil
--coil-error F --coil-seed N`): the world and the Hall probe (a Hall board on its own TCP port,
`[field_probe]` in the rig file, docs/hall-board.md's stream) feel it; the rig file still
describes the coils as drawn.

With a calibration as its truth (`rigctl emulate six-coil --truth FILE.yaml`, a mag_manip MPEM
file, or `--truth NAME` of a station in `rigctl.physics.fields.stations`: helmholtz-triad,
octomag-like, navion-like, built as `--coil-seed` says) the bench is an electromagnetic navigation
system of that file's N coils: one Kepco supply per coil, and the world, the Hall probe and
`coil_fields` feel the file's field, its Offset included (`coil_fields` also replies
`"offset_T"` (n, 3)). The rig file it writes describes the coils as drawn (`nominal_coils`: one
loop per coil, where its first source sits and along its field at the centre, as strong there
as the drawing says; for a station the unperturbed one), so the allocator's loops disagree with
the world (strength, direction, gradients, the Offset) until `rigctl calibrate field`.

Model mismatch (`Mismatch`, set at construction, by `rigctl emulate --slip ...`, or through the
backdoor) is applied when the robots are placed; with `field_at_robots` each robot feels the coils'
field at its own position on the floor (the workspace's centre is the coils' centre).
"""

from __future__ import annotations

import argparse
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rigctl.core.config import (
    Coil,
    Emulation,
    FieldProbe,
    RigConfig,
    RigInfo,
    default_six_coil_coils,
    settings_of,
)
from rigctl.core.errors import ConfigError
from rigctl.emulators.base import EmulatedBench
from rigctl.emulators.camera.render import Scene
from rigctl.emulators.coil_errors import (
    CoilErrors,
    TrueCoil,
    as_calibration,
    true_coils,
)
from rigctl.emulators.hall.board import HallBoardServer, SensorSpec
from rigctl.emulators.kepco_bop.model import BopCoilModel
from rigctl.emulators.kepco_bop.protocol import BopScpi
from rigctl.emulators.server import Endpoint
from rigctl.emulators.world.pair import PairWorld
from rigctl.emulators.world.rolling import Mismatch, RollingMagnetWorld
from rigctl.physics.coils import MPEMCalibration
from rigctl.physics.field_calibration import probe_grid_mm
from rigctl.physics.fields import MPEM, load_mpem, mpem_to_yaml
from rigctl.physics.fields.stations import STATIONS
from rigctl.physics.magnetics import loop_field
from rigctl.plans.model import GlobalInputModel
from rigctl.plans.pair import PairPhysics
from rigctl.plans.schema import parse_workspace
from rigctl.plans.workspace import Workspace

PHYSICS_STEP_S = 1e-3  # simulated time per sub-step: the field turns < 3 degrees per step at 8 turns/s
TICK_S = 5e-3  # how often the server advances the simulation when no command arrives
CAMERA_FIELD_MM = (0.0, 0.0, 400.0, 400.0)  # what the emulated camera's picture covers
PAIR_CAMERA_FIELD_MM = (0.0, 0.0, 20.0, 15.0)  # world "pair": a microscope over the coils' centre
FIELD_REFRESH_MM = 1.0  # recompute the per-robot field maps when a robot moved this far
PROBE_RATE_HZ = 50.0  # Hall probe samples per real second
# the emulated supplies' answer to `CURR x;:MEAS:CURR?` on loopback, for the pre-flight's link
# check (`[preflight] scpi_round_trip_ms`; a real BOP's LAN answer is the rig file's): measured p50
# 0.09 ms, p99 0.27 ms over 3000 round trips on the 2-core CI machine
LOOPBACK_ROUND_TRIP_MS = 0.3


def emulated_winding(coil, mismatch: float) -> dict:
    """The emulated coil's winding (`rigctl.physics.thermal`): the rig file's R_th and C_th `mismatch`
    off, tripping its supply 10 K above the winding's limit (the cut-out behind rigctl's own
    limit)."""
    from rigctl.physics.thermal import Windings

    winding = Windings.of([coil.name], [coil.resistance_ohm], [coil.thermal]).off_by(mismatch)
    return {"winding": winding, "trip_C": coil.thermal.max_winding_C + 10.0}


NOMINAL_LOOP_RADIUS_M = 0.05
NOMINAL_DISTANCE_M = 0.2
"""Where `nominal_coils` draws a coil whose sources are all A (made far away: a Helmholtz pair)."""


def truth_model(truth: str, seed: int = 0) -> tuple[MPEM, MPEM]:
    """(the truth, the drawing) for `--truth`: a station's name (built with `seed`, drawn without)
    or an MPEM file (its own drawing). ConfigError naming the file's key if it is malformed."""
    if truth in STATIONS:
        return STATIONS[truth](seed=seed), STATIONS[truth]()
    model = load_mpem(truth)
    return model, model


def nominal_coils(drawing: MPEM) -> list[Coil]:
    """The rig file's coils for an MPEM station as drawn: per coil one loop of radius
    `NOMINAL_LOOP_RADIUS_M`, centred on its first B source (else `NOMINAL_DISTANCE_M` back from
    the centre), its axis along the coil's field per ampere at the centre and its turns such that
    the loop's field there is the drawing's (to a turn). A loop is not a core's multipole: off the
    centre, in gradients and without the Offset, it is the nominal model a calibration corrects."""
    at_centre = drawing.field_actuation(np.zeros(3))  # (3, N) T/A
    coils = []
    for k, name in enumerate(drawing.coil_names):
        b = at_centre[:, k]
        axis = b / np.linalg.norm(b)
        firsts = [s for s in drawing.coil_sources[k] if s.kind == "B"]
        centre = np.asarray(firsts[0].position_m) if firsts else -NOMINAL_DISTANCE_M * axis
        per_turn = float(np.linalg.norm(loop_field(np.zeros(3), centre, axis,
                                                   NOMINAL_LOOP_RADIUS_M, 1, 1.0)))
        coils.append(Coil(name=name, url=f"tcp://127.0.0.1:{5025 + k}",
                          centre_mm=tuple((centre * 1e3).tolist()), axis=tuple(axis.tolist()),
                          loop_radius_mm=NOMINAL_LOOP_RADIUS_M * 1e3,
                          turns=max(1, round(float(np.linalg.norm(b)) / per_turn)),
                          resistance_ohm=1.0, inductance_H=0.01))
    return coils


@dataclass
class _Supply:
    name: str
    model: BopCoilModel
    endpoint: Endpoint
    field_per_amp_T: np.ndarray  # (3,) this coil's field at the workspace centre for 1 A


class SixCoilBench(EmulatedBench):
    """The six-coil bench (`EmulatedBench`); `supplies` are its six supplies."""

    title = "six-coil bench"
    tick_s = TICK_S

    def __init__(self, template: RigConfig | None = None, *, host: str = "127.0.0.1",
                 mismatch: Mismatch | None = None, world: str = "rolling",
                 thermal_mismatch: float = 0.05,
                 coil_errors: CoilErrors | None = None, truth: str | None = None,
                 probe_noise_mT: float | None = None) -> None:
        if world not in ("rolling", "pair"):
            raise ValueError(f"unknown world {world!r}; use rolling or pair")
        if probe_noise_mT is not None and not 0.0 <= probe_noise_mT < 50.0:
            raise ConfigError(f"--probe-noise {probe_noise_mT:g}: an RMS noise in mT, 0 to 50")
        # the Hall probe's sensors (an MLX90395's noise unless asked for another, in mT RMS)
        self.probe_spec = SensorSpec() if probe_noise_mT is None else \
            SensorSpec(noise_T=probe_noise_mT * 1e-3)
        super().__init__(host=host)
        # "rolling": the rolling magnets of seed 000; "pair": two interacting agents (seed 002,
        # emulators/world/pair.py), placed with {"cmd": "place", ..., "pair": {physics}}
        self.world_kind = world
        self.coil_errors = coil_errors or CoilErrors()
        # a calibration as the truth (`truth_model`): the supplies are its coils, the rig file
        # draws them (`nominal_coils`); None: the loops of the template as built (`CoilErrors`)
        self.truth: MPEM | None = None
        self.truth_name = truth
        if truth is not None:
            self.truth, drawing = truth_model(truth, self.coil_errors.seed)
            template = template or settings_of("six-coil")(
                rig=RigInfo(kind="six-coil", name=f"emulated {self.truth.name}"),
                coils=nominal_coils(drawing))
            if [c.name for c in template.coils] != list(self.truth.coil_names):
                raise ConfigError(f"--truth {truth}: its coils ({', '.join(self.truth.coil_names)})"
                                  " are not the template's")
        self.template = template or settings_of("six-coil")(
            rig=RigInfo(kind="six-coil", name="emulated six-coil bench"),
            coils=default_six_coil_coils(),
        )
        self.supplies: list[_Supply] = []
        self._field_matrix: np.ndarray | None = None  # (n_supplies, 3): T per A of each
        self.world: RollingMagnetWorld | PairWorld | None = None
        self._lock = threading.Lock()
        self._stepped = 0.0  # simulated time the models have been stepped to
        self._world_at = 0.0  # simulated time the world has been stepped to
        self.mismatch = mismatch or Mismatch()
        self.true_coils: list[TrueCoil] = true_coils(self.template.coils, self.coil_errors)
        self.probe: HallBoardServer | None = None
        # per-robot field per amp (n, 3, n_coils) T/A, where it was computed (n, 2) mm, and the
        # Offset field there (n, 3) T
        self._robot_maps: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._offset_T = np.zeros(3)  # the Offset field at the centre (`field_T`)
        self._floor_centre_mm = np.array([200.0, 200.0])
        self.thermal_mismatch = thermal_mismatch  # the windings' R_th, C_th off the rig file's
        self.commands.update(place=self._place_pair if world == "pair" else self._place,
                             truth=self._truth, mismatch=self._mismatch,
                             coil_errors=self._set_coil_errors, coil_fields=self._coil_fields,
                             probe=self._place_probe)

    def _serve(self) -> RigConfig:
        coils = []
        for coil in self.template.coils:
            model = BopCoilModel(resistance_ohm=coil.resistance_ohm, inductance_H=coil.inductance_H,
                                 current_limit_A=coil.current_limit_A, compliance_V=coil.compliance_V,
                                 **emulated_winding(coil, self.thermal_mismatch))
            scpi = BopScpi(model, before_command=self.advance)
            endpoint = self.server.serve_lines_tcp(scpi.handle, name=coil.name, host=self.host)
            field = self._maps(np.zeros((1, 3)))[0][0][:, len(self.supplies)]
            self.supplies.append(_Supply(coil.name, model, endpoint, np.asarray(field, dtype=float)))
            # `restore` clears the link's faults and lets the supply cool down (an over-temperature
            # is cleared; its output stays off until turned on again, as a real BOP's)
            self.add_device(coil.name, endpoint, overtemp=lambda _, m=model: self._locked(
                m.inject_overtemperature), restore=lambda _, m=model, e=endpoint: (
                e.restore(), self._locked(m.clear_overtemperature)))
            coils.append(coil.model_copy(update={"url": endpoint.url}))
        camera = self._serve_camera(
            PAIR_CAMERA_FIELD_MM if self.world_kind == "pair" else CAMERA_FIELD_MM, tilt_deg=5.0,
            seed=1, fps=60.0)
        probe = self.probe = HallBoardServer(
            self.server, field_at=self._probe_field, now=self.clock.now,
            offsets_mm=probe_grid_mm(), rate_hz=PROBE_RATE_HZ, seed=self.coil_errors.seed + 1,
            spec=self.probe_spec, host=self.host, name="field probe")
        self.add_device("probe", probe.endpoint, skip=lambda r: probe.skip(int(r.get("n", 1))))
        return self.template.model_copy(
            update={"coils": coils, "camera": camera, "emulation": self._emulation_settings(),
                    "field_probe": FieldProbe(url=probe.url),
                    "preflight": self.template.preflight.model_copy(
                        update={"scpi_round_trip_ms": LOOPBACK_ROUND_TRIP_MS})})

    def _locked(self, fn: Callable[[], object]) -> None:
        with self._lock:
            fn()

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> SixCoilBench:
        """`rigctl emulate six-coil [--world pair] [--slip ...]`."""
        given = {"slip": args.slip, "speed_spread": args.speed_spread, "drift_mm_per_s": args.drift,
                 "noise_mm": args.noise, "seed": args.seed}
        mismatch = Mismatch(**{k: v for k, v in given.items() if v is not None},
                            field_at_robots=args.field_at_robots)
        size, seed = getattr(args, "coil_error", None), getattr(args, "coil_seed", None)
        try:
            errors = CoilErrors(**{k: v for k, v in (("size", size), ("seed", seed)) if v is not None})
        except ValueError as err:
            raise ConfigError(f"--coil-error: {err}") from None
        if mismatch.slip <= 0 or mismatch.speed_spread < 0 or mismatch.drift_mm_per_s < 0 or \
                mismatch.noise_mm < 0:
            raise ConfigError("--slip must be > 0; --speed-spread, --drift and --noise >= 0")
        return cls(host=args.host, mismatch=mismatch, world=args.world or "rolling",
                   coil_errors=errors, truth=getattr(args, "truth", None),
                   probe_noise_mT=getattr(args, "probe_noise", None))

    def served(self, rig: RigConfig) -> list[tuple[str, str]]:
        served = [(f"supply {coil.name}", str(coil.url)) for coil in rig.coils]
        if rig.field_probe is not None:
            errors = self.coil_errors
            what = f"Hall probe; coil errors {errors.size:.0%}, seed {errors.seed}"
            if self.truth is not None:
                what = f"Hall probe; true field: {self.truth.name} ({self.truth_name})"
            what += f"; noise {self.probe_spec.noise_T * 1e3:g} mT RMS"
            served.append(("probe", f"{rig.field_probe.url}  ({what})"))
        return served

    # -- simulation ---------------------------------------------------------------------------
    def advance(self) -> None:
        """Step every supply and the world up to now, in fixed sub-steps of simulated time."""
        with self._lock:
            target = self.clock.now()
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
            self._offset_T = self._maps(np.zeros((1, 3)))[1][0]
        return np.array([s.model.current_A for s in self.supplies]) @ self._field_matrix + \
            self._offset_T

    def _maps(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The true field per ampere of every coil (P, 3, n) T/A at `points_m` (P, 3) and the
        current-independent Offset (P, 3) T: the truth's, or the loops as built (no offset)."""
        points = np.asarray(points_m, dtype=float).reshape(-1, 3)
        if self.truth is not None:
            per_A = self.truth.field_and_gradient_per_ampere(points)
            return per_A[:, :-1, 0:3].transpose(0, 2, 1), per_A[:, -1, 0:3]
        maps = np.stack([c.field_per_amp(points) for c in self.true_coils], axis=-1)
        return maps, np.zeros((len(points), 3))

    def _fields_at_robots(self) -> np.ndarray:
        """The field each robot feels at its own floor position, (n, 3) T (caller holds the lock)."""
        positions = self.world.settled_positions_mm  # type: ignore[union-attr]
        if self._robot_maps is None or len(self._robot_maps[1]) != len(positions) or np.max(
                np.hypot(*(positions - self._robot_maps[1]).T)) > FIELD_REFRESH_MM:
            points = np.zeros((len(positions), 3))
            points[:, :2] = (positions - self._floor_centre_mm) * 1e-3
            maps, offsets = self._maps(points)
            self._robot_maps = (maps, positions.copy(), offsets)
        currents = np.array([s.model.current_A for s in self.supplies])
        return self._robot_maps[0] @ currents + self._robot_maps[2]

    def _emulation_settings(self) -> Emulation:
        m = self.mismatch
        return Emulation(backdoor=self.backdoor.url, slip=m.slip,  # type: ignore[union-attr]
                         speed_spread=m.speed_spread, drift_mm_per_s=m.drift_mm_per_s,
                         noise_mm=m.noise_mm, seed=m.seed, field_at_robots=m.field_at_robots,
                         thermal_mismatch=self.thermal_mismatch)

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
    def _truth(self, request: dict) -> dict:
        self.advance()
        with self._lock:
            world = self.world
            if isinstance(world, PairWorld):
                return {"agents": world.positions_mm.tolist(), "moments_Am2": world.moments.tolist(),
                        "min_separation_mm": world.min_separation_mm, **self._supplies_truth()}
            return {
                "agents": [] if world is None else world.positions_mm.tolist(),
                "axis": None if world is None or world.axis_xy is None else world.axis_xy.tolist(),
                **self._supplies_truth(),
                "distance_scale": None if world is None else world.distance_scale.tolist(),
            }

    def _supplies_truth(self) -> dict:
        return {"field_T": self.field_T().tolist(),
                "currents_A": {s.name: s.model.current_A for s in self.supplies},
                "winding_C": {s.name: s.model.winding_C for s in self.supplies},
                "winding_peak_C": {s.name: s.model.winding_peak_C for s in self.supplies},
                "sim_time_s": self._stepped}

    def _place(self, request: dict) -> dict:
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

    def _mismatch(self, request: dict) -> dict:
        settings = {**self.mismatch.__dict__}
        for key, value in settings.items():
            if key in request:
                settings[key] = type(value)(request[key])
        if settings["slip"] <= 0 or settings["speed_spread"] < 0 or settings["noise_mm"] < 0:
            raise ValueError("slip must be > 0, speed_spread and noise_mm >= 0")
        self.mismatch = Mismatch(**settings)
        return {"mismatch": settings}

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
            self.world = PairWorld(workspace, positions, physics, self._true_rig(),
                                   self._floor_centre_mm, self.mismatch)
        return {"agents": positions.tolist()}

    # -- the coils as built, and the Hall probe --------------------------------------------------
    def _true_rig(self) -> RigConfig:
        """The template with the true coils as its field calibration (the pair world's coils)."""
        if self.truth is not None:
            return self.template.model_copy(update={"field_calibration": MPEMCalibration(
                text=mpem_to_yaml(self.truth), source="truth.yaml")})
        return self.template.model_copy(update={"field_calibration": as_calibration(
            self.true_coils, self.template.coils)})

    def _probe_field(self, points_m: np.ndarray) -> np.ndarray:
        """The true field (n, 3) T at the probe's sensors from the supplies' actual currents."""
        self.advance()
        with self._lock:
            currents = np.array([s.model.current_A for s in self.supplies])
            maps, offsets = self._maps(points_m)
        return maps @ currents + offsets

    def _set_coil_errors(self, request: dict) -> dict:
        if self.truth is not None:
            raise ValueError(f"the bench's truth is {self.truth.name} ({self.truth_name}): coil "
                             "errors apply to the loops of a bench without --truth")
        if "size" in request or "seed" in request:
            errors = CoilErrors(size=float(request.get("size", self.coil_errors.size)),
                                seed=int(request.get("seed", self.coil_errors.seed)))
            coils = true_coils(self.template.coils, errors)
            with self._lock:
                self.coil_errors, self.true_coils = errors, coils
                for supply, coil in zip(self.supplies, coils):
                    supply.field_per_amp_T = coil.field_per_amp(np.zeros(3))
                self._field_matrix = None
                self._robot_maps = None
        return {"size": self.coil_errors.size, "seed": self.coil_errors.seed,
                "coils": [c.truth() for c in self.true_coils]}

    def _coil_fields(self, request: dict) -> dict:
        points = np.asarray(request["points_mm"], dtype=float).reshape(-1, 3) * 1e-3
        with self._lock:
            maps, offsets = self._maps(points)
        reply = {"T_per_A": maps.tolist()}
        if self.truth is not None:
            reply["offset_T"] = offsets.tolist()
        return reply

    def _place_probe(self, request: dict) -> dict:
        points = np.asarray(request["points_mm"], dtype=float)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 1:
            raise ValueError("points_mm must be a list of [x, y, z] (mm)")
        assert self.probe is not None
        self.probe.offsets_mm = points
        self.probe.points_m = points * 1e-3
        return {"points_mm": points.tolist()}
