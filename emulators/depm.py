"""The emulated dual-EPM bench (seed 003): two KUKA LBR arms carrying EPMs, each behind its own KST
server on TCP, the Hall-sensor board streaming on TCP, and a JSON backdoor, on one emulator loop.

The field the board measures comes from the arms' *actual* joints, not from any plan: forward
kinematics of each arm (`rigctl.kinematics`, the bases and EPM tool of the rig file) gives each
EPM's centre and moment direction, and the dipole model (seed 003 eq. 2, superposed, eq. 8) the
field at every sensor. An arm that lags, stalls or stops therefore shows up in the measurement.

Simulated time runs at `speed` simulated seconds per real second (backdoor `speed`), the same for
the arms and the board's timestamps; the arms are stepped lazily (before each command and on a
periodic tick) in 4 ms sub-steps.

Backdoor (JSON lines over TCP; replies `{"ok": true, ...}` or `{"ok": false, "error": ...}`):
- `{"cmd": "ping"}`;
- `{"cmd": "truth"}`: sim time, each arm's joints, speeds, mode, watchdog state, each EPM's
  centre (m) and moment (A m^2), and the exact U at the workspace centre (mT, mT/m);
- `{"cmd": "place", "arm": "left", "q": [7 rad]}`: put an arm's joints somewhere (at rest);
- `{"cmd": "fault", "device": "left" | "right" | "hall", "kind": "drop_link" | "stall" |
  "corrupt" | "restore" | "stall_joint" | "unstall" | "skip", "joint": j, "n": n}`;
- `{"cmd": "speed", "factor": f}`.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path

import numpy as np
from rigctl.emulators.backdoor import json_lines
from rigctl.emulators.hall.board import HallBoardServer
from rigctl.emulators.kuka.arm import KST_PORT, EmulatedArm, SimClock
from rigctl.emulators.kuka.model import ArmLimits
from rigctl.emulators.process import READY_PREFIX
from rigctl.emulators.server import EmulatorServer
from rigctl.plans.depm import default_rig, rig_from_settings

from rigctl.config import DepmSettings, Emulation, RigConfig, RigInfo, dump_rig
from rigctl.errors import ConfigError
from rigctl.kinematics import DEFAULT_BASES
from rigctl.magnetics import dipole_field, field_vector

log = logging.getLogger(__name__)

TICK_S = 5e-3
HALL_RATE_HZ = 100.0  # samples per real second
EMULATED_REPLY_TIMEOUT_S = 3.0
SERVO_WATCHDOG_S = 2.0  # real seconds of stream silence before an emulated arm stops itself
PARKED_Q = np.zeros(7)  # the arms start upright ("candle"), far from the workspace


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


class DepmBench:
    """Start with `start()`; `rig` is the rig file that points at it; `stop()` when done."""

    def __init__(self, settings: DepmSettings | None = None, *, host: str = "127.0.0.1",
                 speed: float = 1.0, real_ports: bool = False, seed: int = 0,
                 initial_q: np.ndarray | None = None, hall_rate_hz: float = HALL_RATE_HZ) -> None:
        self.settings = settings or default_settings()
        self.host = host
        self.clock = SimClock(speed)
        self.real_ports = real_ports
        self.seed = seed
        self.initial_q = PARKED_Q if initial_q is None else np.asarray(initial_q, dtype=float)
        self.hall_rate_hz = hall_rate_hz
        self.server = EmulatorServer()
        self.kinematics = rig_from_settings(self.settings).arms
        self.arms: list[EmulatedArm] = []
        self.hall: HallBoardServer | None = None
        self.rig: RigConfig | None = None

    def start(self) -> RigConfig:
        self.server.start()
        limits = ArmLimits.of(self.kinematics[0].model)
        for index, kin in enumerate(self.kinematics):
            port = KST_PORT + index if self.real_ports else 0
            self.arms.append(EmulatedArm(self.server, name=kin.name, clock=self.clock,
                                         q0=self.initial_q, limits=limits, host=self.host,
                                         port=port, servo_timeout_s=SERVO_WATCHDOG_S,
                                         tick_s=TICK_S))
        self.hall = HallBoardServer(self.server, field_at=self.field_at, now=self.clock.now,
                                    offsets_mm=self.settings.sensor_offsets_mm,
                                    rate_hz=self.hall_rate_hz, seed=self.seed, host=self.host)
        backdoor = self.server.serve_lines_tcp(json_lines(self._command), name="backdoor",
                                              host=self.host)
        self.server.every(TICK_S, self.advance)
        depm = self.settings.model_copy(update={"arm_urls": [a.url for a in self.arms],
                                                "hall_url": self.hall.url})
        self.rig = RigConfig(rig=RigInfo(kind="depm", name="emulated dEPM bench"), depm=depm,
                             emulation=Emulation(backdoor=backdoor.url, seed=self.seed))
        log.info("depm bench up: arms %s, hall %s, backdoor %s",
                 [a.url for a in self.arms], self.hall.url, backdoor.url)
        return self.rig

    def stop(self) -> None:
        if self.rig is not None:  # started: close the session links, then the loop
            for arm in self.arms:
                arm.close()
            if self.hall is not None:
                self.hall.close()
            self.rig = None
        self.server.stop()

    def __enter__(self) -> "DepmBench":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

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
        return dipole_field(np.asarray(points_m)[:, None, :], centres, moments).sum(axis=1)

    # -- backdoor -------------------------------------------------------------------------------
    def _arm(self, name: object) -> EmulatedArm:
        for arm in self.arms:
            if arm.name == name:
                return arm
        raise ValueError(f"no arm {name!r}; the bench has {[a.name for a in self.arms]}")

    def _command(self, request: dict) -> dict:
        cmd = request.get("cmd")
        if cmd == "ping":
            return {}
        if cmd == "truth":
            self.advance()
            centres, moments = self.epms()
            u = field_vector(np.zeros(3), centres, moments) * 1e3
            return {"sim_time_s": self.clock.now(), "arms": {a.name: a.truth() for a in self.arms},
                    "epm_centres_m": centres.tolist(), "epm_moments_Am2": moments.tolist(),
                    "U": u.tolist()}
        if cmd == "place":
            self._arm(request.get("arm")).place(np.asarray(request["q"], dtype=float))
            return {}
        if cmd == "fault":
            return self._fault(request)
        if cmd == "speed":
            factor = float(request["factor"])
            self.advance()
            self.clock.set_speed(factor)
            return {"factor": factor}
        raise ValueError(f"unknown command {cmd!r}; use ping, truth, place, fault, speed")

    def _fault(self, request: dict) -> dict:
        device, kind = request.get("device"), request.get("kind")
        if device == "hall":
            assert self.hall is not None
            endpoint = self.hall.endpoint
            if kind == "skip":
                self.hall.skip(int(request.get("n", 1)))
                return {"device": device, "kind": kind}
        else:
            arm = self._arm(device)
            endpoint = arm.endpoint
            if kind == "stall_joint":
                arm.stall(int(request["joint"]))
                return {"device": device, "kind": kind}
            if kind == "unstall":
                arm.unstall()
                return {"device": device, "kind": kind}
        if kind == "drop_link":
            endpoint.drop_link()
        elif kind == "stall":
            endpoint.stall()
        elif kind == "corrupt":
            endpoint.corrupt(int(request.get("n", 1)))
        elif kind == "restore":
            endpoint.restore()
        else:
            raise ValueError(f"unknown fault kind {kind!r}; use drop_link, stall, corrupt, restore, "
                             "stall_joint, unstall (arms), skip (hall)")
        return {"device": device, "kind": kind}


def emulate_cli(args: argparse.Namespace) -> int:
    """`rigctl emulate depm --rig-out F`: serve the bench, write its rig file, print READY."""
    if args.seed is not None and args.seed < 0:
        raise ConfigError("--seed must be >= 0")
    rig_out = Path(args.rig_out)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with DepmBench(host=args.host, seed=args.seed or 0) as bench:
        assert bench.rig is not None
        rig = bench.rig.model_copy(update={"emulation": bench.rig.emulation.model_copy(
            update={"pid": os.getpid()})})
        rig_out.write_text(dump_rig(rig))
        print(f"{READY_PREFIX}{rig_out.resolve()}", flush=True)
        print(f"emulated dEPM bench up; rig file: {rig_out}; stop with Ctrl-C", file=sys.stderr)
        for name, url in zip(rig.depm.arm_names, rig.depm.arm_urls):  # type: ignore[union-attr]
            print(f"  arm {name:<6} {url}  (KUKA Sunrise Toolbox)", file=sys.stderr)
        print(f"  hall board {rig.depm.hall_url}", file=sys.stderr)  # type: ignore[union-attr]
        print(f"  backdoor   {rig.emulation.backdoor}", file=sys.stderr, flush=True)  # type: ignore[union-attr]
        stop.wait()
    return 0
