"""The emulated dual-EPM bench (seed 003): two KUKA LBR arms carrying EPMs, each behind its own KST
server on TCP, the Hall-sensor board streaming on TCP, and a JSON backdoor, on one emulator loop.

The field the board measures comes from the arms' *actual* joints, not from any plan: forward
kinematics of each arm (`rigctl.physics.kinematics`, the bases and EPM tool of the rig file) gives each
EPM's centre and moment direction, and the field at every sensor is that of the EPMs as they are:
finite axially magnetised cylinders (`world/epm.py`, seed 003's 101.6 mm N52 magnets, magpylib's
closed form), not the planner's point dipole (seed 003 eq. 2), which is 1-13 % off within 15 cm
(`magnets="dipole"` makes the bench the planner's model again). An arm that lags, stalls or stops
therefore shows up in the measurement, and so does the planner's model error.

Simulated time is the bench's `SimClock` (`speed` simulated seconds per real second), the same for
the arms and the board's timestamps; the arms are stepped lazily (before each command and on a
periodic tick) in 4 ms sub-steps.

Backdoor: the table of `emulators/base.py` (`ping`, `help`, `speed`, `fault`) with devices "left",
"right" (each arm: its link's faults, `stall_joint` with `"joint": j`, `unstall`) and "hall" (its
link's faults, `skip` with `"n": samples`), plus:
- `{"cmd": "truth"}`: sim time, each arm's joints, speeds, mode, watchdog state, each EPM's
  centre (m) and moment (A m^2), and the exact U at the workspace centre (mT, mT/m) of the
  bench's magnets (`"magnets"`: "cylinder" or "dipole");
- `{"cmd": "place", "arm": "left", "q": [7 rad]}`: put an arm's joints somewhere (at rest).
"""

from __future__ import annotations

import argparse

import numpy as np

from rigctl.core.config import DepmSettings, Emulation, PreflightSettings, RigConfig, RigInfo, settings_of
from rigctl.core.errors import ConfigError
from rigctl.emulators.base import EmulatedBench
from rigctl.emulators.hall.board import HallBoardServer
from rigctl.emulators.kuka.arm import KST_PORT, EmulatedArm
from rigctl.emulators.kuka.model import ArmLimits
from rigctl.emulators.world.epm import CylinderEpms
from rigctl.physics.kinematics import DEFAULT_BASES
from rigctl.physics.magnetics import dipole_field, field_vector
from rigctl.plans.depm import default_rig, rig_from_settings

TICK_S = 5e-3
HALL_RATE_HZ = 100.0  # samples per real second
EMULATED_REPLY_TIMEOUT_S = 3.0
SERVO_WATCHDOG_S = 2.0  # real seconds of stream silence before an emulated arm stops itself
PARKED_Q = np.zeros(7)  # the arms start upright ("candle"), far from the workspace
# the emulated arms' answer to a servo target on loopback, for the pre-flight's link check
# (`[preflight] kst_round_trip_ms`): both arms' `jpJP_` exchanges of a cycle measured p50 0.7 ms,
# p99 3.9 ms over 3000 cycles on the loaded 2-core CI machine
LOOPBACK_ROUND_TRIP_MS = 4.0


def default_settings() -> DepmSettings:
    """The bench's rig: the planner's default arms, magnets and limits (`plans.depm.default_rig`),
    so a plan made with the defaults runs on it as it is."""
    rig = default_rig()
    limits = rig.limits
    return DepmSettings(
        arm_names=[name for name, _, _ in DEFAULT_BASES],
        arm_urls=[f"tcp://127.0.0.1:{KST_PORT + i}" for i in range(len(DEFAULT_BASES))],
        arm_positions_mm=[tuple(1e3 * v for v in position) for _, position, _ in DEFAULT_BASES],
        arm_rpy_deg=[tuple(rpy) for _, _, rpy in DEFAULT_BASES],
        epm_moment_Am2=rig.moment_Am2, tool_offset_mm=rig.arms[0].model.tool_offset_m * 1e3,
        hall_url="tcp://127.0.0.1:30010",
        keep_out_radius_mm=limits.keep_out_radius_m * 1e3, epm_radius_mm=limits.epm_radius_m * 1e3,
        epm_min_distance_mm=limits.epm_min_distance_m * 1e3, speed_fraction=limits.speed_fraction,
        # an emulated bench shares its computer with rigctl (and, in CI, with everything else):
        # allow it more time to answer than a real cabinet needs
        reply_timeout_s=EMULATED_REPLY_TIMEOUT_S)


class DepmBench(EmulatedBench):
    """The dual-EPM bench (`EmulatedBench`); `arms` are its two arms, `hall` its Hall board."""

    title = "dEPM bench"
    tick_s = TICK_S

    def __init__(self, settings: DepmSettings | None = None, *, host: str = "127.0.0.1",
                 speed: float = 1.0, real_ports: bool = False, seed: int = 0,
                 initial_q: np.ndarray | None = None, hall_rate_hz: float = HALL_RATE_HZ,
                 magnets: str = "cylinder") -> None:
        if magnets not in ("cylinder", "dipole"):
            raise ValueError(f"unknown magnets {magnets!r}; use cylinder or dipole")
        super().__init__(host=host, speed=speed)
        self.settings = settings or default_settings()
        self.real_ports = real_ports
        self.seed = seed
        self.initial_q = PARKED_Q if initial_q is None else np.asarray(initial_q, dtype=float)
        self.hall_rate_hz = hall_rate_hz
        self.magnets = magnets
        self.cylinders = CylinderEpms()
        self.kinematics = rig_from_settings(self.settings).arms
        self.arms: list[EmulatedArm] = []
        self.hall: HallBoardServer | None = None
        self.commands.update(truth=self._truth, place=self._place)

    def _serve(self) -> RigConfig:
        limits = ArmLimits.of(self.kinematics[0].model)
        for index, kin in enumerate(self.kinematics):
            port = KST_PORT + index if self.real_ports else 0
            arm = EmulatedArm(self.server, name=kin.name, clock=self.clock, q0=self.initial_q,
                              limits=limits, host=self.host, port=port,
                              servo_timeout_s=SERVO_WATCHDOG_S, tick_s=TICK_S)
            self.arms.append(arm)
            self.add_device(arm.name, arm.endpoint,
                            stall_joint=lambda r, a=arm: a.stall(int(r["joint"])),
                            unstall=lambda _, a=arm: a.unstall())
        hall = self.hall = HallBoardServer(
            self.server, field_at=self.field_at, now=self.clock.now,
            offsets_mm=self.settings.sensor_offsets_mm, rate_hz=self.hall_rate_hz, seed=self.seed,
            host=self.host)
        self.add_device("hall", hall.endpoint, skip=lambda r: hall.skip(int(r.get("n", 1))))
        depm = self.settings.model_copy(update={"arm_urls": [a.url for a in self.arms],
                                                "hall_url": hall.url})
        assert self.backdoor is not None
        return settings_of("depm")(rig=RigInfo(kind="depm", name="emulated dEPM bench"), depm=depm,
                         emulation=Emulation(backdoor=self.backdoor.url, seed=self.seed),
                         preflight=PreflightSettings(kst_round_trip_ms=LOOPBACK_ROUND_TRIP_MS))

    def _release(self) -> None:
        if self.rig is not None:  # started: close the session links, then the loop
            for arm in self.arms:
                arm.close()
            if self.hall is not None:
                self.hall.close()
            self.rig = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> DepmBench:
        """`rigctl emulate depm [--seed N]`."""
        if args.seed is not None and args.seed < 0:
            raise ConfigError("--seed must be >= 0")
        return cls(host=args.host, seed=args.seed or 0)

    def served(self, rig: RigConfig) -> list[tuple[str, str]]:
        depm = rig.depm
        assert depm is not None
        return [*((f"arm {name}", f"{url}  (KUKA Sunrise Toolbox)")
                  for name, url in zip(depm.arm_names, depm.arm_urls)), ("hall board", depm.hall_url)]

    # -- physics (loop thread) ------------------------------------------------------------------
    def advance(self) -> None:
        for arm in self.arms:
            arm.advance()

    def epms(self) -> tuple[np.ndarray, np.ndarray]:
        """Each EPM's centre (2, 3) m and moment (2, 3) A m^2 from the arms' actual joints."""
        centres, moments = [], []
        for arm, kin in zip(self.arms, self.kinematics):
            position, direction = kin.epm_pose(arm.model.q)
            centres.append(position)
            moments.append(self.settings.epm_moment_Am2 * np.asarray(direction))
        return np.array(centres), np.array(moments)

    def field_at(self, points_m: np.ndarray) -> np.ndarray:
        """The EPMs' field (n, 3) T at points (n, 3) m, arms stepped to now first."""
        self.advance()
        centres, moments = self.epms()
        if self.magnets == "cylinder":
            return self.cylinders.field(points_m, centres, moments)
        return dipole_field(np.asarray(points_m)[:, None, :], centres, moments).sum(axis=1)

    # -- backdoor -------------------------------------------------------------------------------
    def _truth(self, request: dict) -> dict:
        self.advance()
        centres, moments = self.epms()
        if self.magnets == "cylinder":
            u = self.cylinders.field_vector(np.zeros(3), centres, moments) * 1e3
        else:
            u = field_vector(np.zeros(3), centres, moments) * 1e3
        return {"sim_time_s": self.clock.now(), "arms": {a.name: a.truth() for a in self.arms},
                "epm_centres_m": centres.tolist(), "epm_moments_Am2": moments.tolist(),
                "U": u.tolist(), "magnets": self.magnets}

    def _place(self, request: dict) -> dict:
        arms = {arm.name: arm for arm in self.arms}
        if request.get("arm") not in arms:
            raise ValueError(f"no arm {request.get('arm')!r}; the bench has {', '.join(arms)}")
        arms[request["arm"]].place(np.asarray(request["q"], dtype=float))
        return {}
