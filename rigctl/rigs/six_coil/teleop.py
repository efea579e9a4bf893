"""Steering the rolling magnets by hand (teleoperation, `rigctl.run.teleop`) on the six coils.

The operator gives a heading (the direction to roll in, degrees from +x) and a speed (a fraction
of the rig's `field.rolling_turns_per_s`, negative rolls back). The field is the rolling field of
`rigctl.rigs.six_coil.realize` made live: with d = (cos h, sin h, 0) the heading the field stands
in now, B = b0 m (cos(alpha) d - sin(alpha) z), alpha advancing at 2 pi speed f_roll (a cylinder
rolled by alpha about z x d moves R alpha along d). Changing the heading turns d about z at no
more than `field.steering_deg_per_s` (seed 000 eq. 2: the magnets turn with it), the short way,
and the field rolls only once d stands at the heading asked: steering, then rolling, as a plan's
move is realized, so that a session is a sequence of straight moves that a global-moves plan
can replay (`moves_mm`).

The magnitude m ramps up to 1 over `field.ramp_s` when an input comes, and rolling waits for the
full field; with no input (let go, or the dead-man) m ramps to 0 over `STOP_S` and the currents
end at exactly zero, alpha and d kept, so the next input rolls on from where the field stood.

The pre-flight holds for any input: every coil's current for b0 in any direction (the field
offset of an MPEM rig added), and its supply's compliance R I + L dI/dt with dB/dt bounded by the
fastest the field can change (rolling and steering at full speed while the magnitude ramps).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from rigctl.physics.coils import actuation_matrix, field_offset
from rigctl.run.certificate import Check, ceiling
from rigctl.run.teleop import InputComponent, TeleopDrive

if TYPE_CHECKING:
    from rigctl.rigs.six_coil.settings import SixCoilRig

STOP_S = 0.05
"""How long the field takes from full to zero when the input stops (s)."""

_Z = np.array([0.0, 0.0, 1.0])


def _directions(n: int = 2000) -> np.ndarray:
    """`n` unit vectors spread evenly over the sphere (a Fibonacci lattice), (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = math.pi * (1.0 + math.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


class RollingDrive(TeleopDrive):
    """Heading and speed of the rolling field (see the module docstring)."""

    mode = "rolling"
    late = "slip"
    components = (
        InputComponent("heading_deg", "deg", -360.0, 360.0, "the direction to roll in, from +x"),
        InputComponent("speed", "1", -1.0, 1.0,
                       "the rolling speed as a fraction of the rig's field.rolling_turns_per_s"),
    )

    def __init__(self, rig: SixCoilRig) -> None:
        from rigctl.rigs.six_coil.supplies import CoilSupplies

        self.rig = rig
        self.connect = CoilSupplies.connect
        fs = rig.field
        self.rate_hz = rig.stream.rate_hz
        self.dt = 1.0 / self.rate_hz
        self.b0_T = fs.b0_mT * 1e-3
        self.pinv = np.linalg.pinv(actuation_matrix(rig))  # (n, 3) A/T
        self.offset_T = field_offset(rig)[0:3]
        self.roll_rad_per_s = 2.0 * math.pi * fs.rolling_turns_per_s
        self.steer_rad_per_s = math.radians(fs.steering_deg_per_s)
        self.up_per_cycle = self.dt / max(fs.ramp_s, self.dt)
        self.down_per_cycle = self.dt / STOP_S
        heading = math.radians(fs.initial_heading_deg)
        self.heading = heading  # rad, where d stands now
        self.alpha = 0.0  # rad, the rolling angle
        self.m = 0.0  # the field's magnitude, a fraction of b0
        self._rest = True

    def field_T(self) -> np.ndarray:
        d = np.array([math.cos(self.heading), math.sin(self.heading), 0.0])
        return self.b0_T * self.m * (math.cos(self.alpha) * d - math.sin(self.alpha) * _Z)

    def step(self, values: np.ndarray | None) -> np.ndarray:
        if values is None:
            self.m = self.m - self.down_per_cycle
            self.m = 0.0 if self.m < 1e-9 else self.m  # whole cycles, whatever the rounding
        else:
            heading, speed = math.radians(values[0]), float(values[1])
            turn = (heading - self.heading + math.pi) % (2.0 * math.pi) - math.pi
            most = self.steer_rad_per_s * self.dt
            self.heading += max(-most, min(most, turn))
            if self.m >= 1.0 and abs(turn) <= most:  # steered: roll
                self.alpha += speed * self.roll_rad_per_s * self.dt
            self.m = self.m + self.up_per_cycle
            self.m = 1.0 if self.m > 1.0 - 1e-9 else self.m
        self._rest = self.m == 0.0
        if self._rest:
            return np.zeros(self.pinv.shape[0])
        # the MPEM's offset is the coils' own: the currents make B - offset, scaled with m so that
        # the stop ends at zero amperes
        return self.pinv @ (self.field_T() - self.m * self.offset_T)

    def at_rest(self) -> bool:
        return self._rest

    def moves_mm(self, inputs: dict, events: list[dict]) -> tuple[np.ndarray, list[str]]:
        """The session's moves (m, 2) mm, from its inputs as the stream took them (the record's
        `teleop` series) stepped through this drive anew: each run of inputs at one heading is
        one move, the magnets' roll R alpha along it; whole turns where the rig's field says so
        (`field.whole_turns`). With what the plan differs in, one line each."""
        rate, radius = self.rate_hz, self.rig.magnets.radius_mm
        t, live = inputs["t_s"], inputs["live"] == 1.0
        moves: list[np.ndarray] = []
        last_key = None
        for i in range(len(t)):
            cycles = (round((t[i + 1] - t[i]) * rate) if i + 1 < len(t)
                      else round(STOP_S * rate) + 1)
            values = np.array([inputs["heading_deg"][i], inputs["speed"][i]]) if live[i] else None
            key = None if values is None else float(values[0])
            for _ in range(cycles):
                alpha = self.alpha
                self.step(values)
                rolled = self.alpha - alpha
                if rolled:
                    step = radius * rolled * np.array([math.cos(self.heading),
                                                       math.sin(self.heading)])
                    if key != last_key or not moves:
                        moves.append(np.zeros(2))
                        last_key = key
                    moves[-1] += step
            if values is None:
                last_key = None
        out = np.array(moves).reshape(-1, 2)
        notes = ["the plan steers before each move and holds the field after it "
                 "(field.hold_s), as a plan's moves are realized; the session rolled at the "
                 "operator's speed"]
        if self.rig.field.whole_turns and len(out):
            turn = 2.0 * math.pi * radius
            lengths = np.linalg.norm(out, axis=1)
            turns = np.round(lengths / turn)
            notes.append(f"each move rounded to whole turns of {turn:.3f} mm (field.whole_turns): "
                         f"at most {np.abs(turns * turn - lengths).max():.3f} mm off")
            out = out / np.maximum(lengths, 1e-300)[:, None] * (turns * turn)[:, None]
            out = out[turns > 0]
        return out, notes

    def checks(self) -> list[Check]:
        """Every coil's current at b0 in any direction, and its supply's voltage at the fastest
        dB/dt any input can make (module docstring)."""
        rig = self.rig
        fields = self.b0_T * _directions() - self.offset_T
        currents = np.abs(fields @ self.pinv.T).max(axis=0)  # (n,) A
        # |dB/dt| at most: rolling and steering at full speed while the magnitude ramps
        dbdt = (np.linalg.norm(fields, axis=1).max()
                * (self.roll_rad_per_s + self.steer_rad_per_s
                   + max(self.up_per_cycle, self.down_per_cycle) * self.rate_hz))
        didt = np.linalg.norm(self.pinv, axis=1) * dbdt  # (n,) A/s
        out: list[Check] = []
        for j, coil in enumerate(rig.coils):
            out.append(ceiling("current", f"coil {coil.name}", currents[j], coil.current_limit_A,
                               "A", "b0 in any direction (teleoperation)"))
            volts = coil.resistance_ohm * currents[j] + coil.inductance_H * didt[j]
            out.append(ceiling("voltage", f"coil {coil.name}", volts, coil.compliance_V, "V",
                               "R I + L dI/dt at the fastest any input can change the field; "
                               "a slower field.rolling_turns_per_s or a smaller b0_mT"))
        return out


class PairDrive(TeleopDrive):
    """Field angle and pull, the controls of pair formation (seed 002, `rigctl.rigs.six_coil.pair`):
    an in-plane field of b0 at the angle asked (turned at no more than `field.steering_deg_per_s`)
    and the diagonal gradients dBx/dx = dBy/dy = p g, g the largest this rig's coils make with
    that field at any angle (`max_planar_gradient`), so that a dipole aligned with the field is
    pulled along it by |m| p g. The pull slews at most full scale in STOP_S; with no input the
    whole U (field and gradient) ramps to zero over STOP_S, the currents ending at zero."""

    mode = "pair"
    late = "slip"
    components = (
        InputComponent("field_angle_deg", "deg", -360.0, 360.0, "the in-plane field's angle, "
                       "from +x"),
        InputComponent("pull", "1", -1.0, 1.0, "the pull along the field, a fraction of the "
                       "largest gradient the coils make with it"),
    )

    def __init__(self, rig: SixCoilRig) -> None:
        from rigctl.core.errors import ConfigError
        from rigctl.physics.coils import max_planar_gradient, u_actuation_matrix
        from rigctl.rigs.six_coil.supplies import CoilSupplies

        self.rig = rig
        self.connect = CoilSupplies.connect
        self.rate_hz = rig.stream.rate_hz
        self.dt = 1.0 / self.rate_hz
        self.b0_T = rig.field.b0_mT * 1e-3
        self.g_T_m = max_planar_gradient(rig, self.b0_T)
        if self.g_T_m <= 0:
            raise ConfigError("teleop: this rig's coils make no gradient with the field: no pull "
                              "to steer (mode rolling)")
        self.pinv8 = np.linalg.pinv(u_actuation_matrix(rig))  # (n, 8)
        self.steer_rad_per_s = math.radians(rig.field.steering_deg_per_s)
        self.per_cycle = self.dt / STOP_S
        self.angle = math.radians(rig.field.initial_heading_deg)
        self.pull = 0.0
        self.m = 0.0
        self._rest = True

    def u(self) -> np.ndarray:
        """The 8-vector U now (T, T/m)."""
        u = np.zeros(8)
        u[0], u[1] = self.b0_T * math.cos(self.angle), self.b0_T * math.sin(self.angle)
        u[3] = u[6] = self.pull * self.g_T_m
        return self.m * u

    def step(self, values: np.ndarray | None) -> np.ndarray:
        if values is None:
            self.m = self.m - self.per_cycle
            self.m = 0.0 if self.m < 1e-9 else self.m
        else:
            turn = (math.radians(values[0]) - self.angle + math.pi) % (2.0 * math.pi) - math.pi
            most = self.steer_rad_per_s * self.dt
            self.angle += max(-most, min(most, turn))
            self.pull += max(-self.per_cycle, min(self.per_cycle, float(values[1]) - self.pull))
            self.m = self.m + self.per_cycle
            self.m = 1.0 if self.m > 1.0 - 1e-9 else self.m
        self._rest = self.m == 0.0
        return np.zeros(self.pinv8.shape[0]) if self._rest else self.pinv8 @ self.u()

    def at_rest(self) -> bool:
        return self._rest

    def checks(self) -> list[Check]:
        """Every coil's current for the field at any angle with the pull at either end, and its
        supply's voltage at the fastest U can change (the field turning and ramping, the pull
        slewing, all at once)."""
        psi = np.linspace(0.0, 2.0 * math.pi, 360, endpoint=False)
        us = []
        for p in (-1.0, 1.0):
            u = np.zeros((len(psi), 8))
            u[:, 0], u[:, 1] = self.b0_T * np.cos(psi), self.b0_T * np.sin(psi)
            u[:, 3] = u[:, 6] = p * self.g_T_m
            us.append(u)
        currents = np.abs(np.vstack(us) @ self.pinv8.T).max(axis=0)
        du = np.zeros(8)  # |dU/dt| bound per component
        du[0] = du[1] = self.b0_T * (self.steer_rad_per_s + 1.0 / STOP_S)
        du[3] = du[6] = self.g_T_m * 2.0 / STOP_S
        didt = np.abs(self.pinv8) @ du
        out: list[Check] = []
        for j, coil in enumerate(self.rig.coils):
            out.append(ceiling("current", f"coil {coil.name}", currents[j], coil.current_limit_A,
                               "A", "the field at any angle with the full pull (teleoperation)"))
            out.append(ceiling("voltage", f"coil {coil.name}",
                               coil.resistance_ohm * currents[j] + coil.inductance_H * didt[j],
                               coil.compliance_V, "V", "R I + L dI/dt at the fastest any input "
                               "can change U"))
        return out



def teleop_drive(rig: SixCoilRig, mode: str | None) -> TeleopDrive:
    """The six-coil rig's teleoperation: "rolling" (global moves' rolling field, the default) or
    "pair" (pair formation's field angle and pull)."""
    from rigctl.core.errors import ConfigError

    if mode in (None, "rolling"):
        return RollingDrive(rig)
    if mode == "pair":
        return PairDrive(rig)
    raise ConfigError(f"teleop: a six-coil rig steers in mode rolling or pair, not {mode!r}")
