"""The pre-flight certificate (`rigctl.run.certificate` and each rig's checks): values against hand
calculations, refusals that say what would pass, the rig file's hash, and `rigctl validate --rig`."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq

from rigctl.apps.testing import run_rigctl
from rigctl.core.config import (
    CoilBoardSettings,
    CoilThermal,
    Emulation,
    ExposurePoint,
    RigConfig,
    RigInfo,
    StreamSettings,
    default_six_coil_coils,
    dump_rig,
)
from rigctl.physics.thermal import Windings
from rigctl.plans.schema import load_plan
from rigctl.rigs.coil_board.certify import board_checks, drive_for_limit
from rigctl.rigs.coil_board.run import CoilBoardRunSettings
from rigctl.rigs.coil_board.settings import CoilBoardRig
from rigctl.rigs.depm.settings import DepmRig
from rigctl.rigs.six_coil.certify import current_program_checks
from rigctl.rigs.six_coil.settings import SixCoilRig
from rigctl.run.certificate import exposure_checks, rig_hash

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
MU0 = 4e-7 * math.pi


def six_coil(**update) -> RigConfig:
    return SixCoilRig(**{"rig": RigInfo(kind="six-coil"), "coils": default_six_coil_coils(), **update})


def by(checks, check, subject):
    return next(c for c in checks if c.check == check and c.subject == subject)


def test_the_hash_names_the_rig_file_exactly():
    rig = six_coil()
    assert rig_hash(rig) == rig_hash(six_coil())
    warmer = rig.model_copy(update={"coils": [
        rig.coils[0].model_copy(update={"thermal": CoilThermal(ambient_C=26.0)}), *rig.coils[1:]]})
    assert rig_hash(warmer) != rig_hash(rig)


def test_a_supply_s_voltage_is_checked_with_its_winding_hot():
    thermal = CoilThermal(thermal_resistance_K_per_W=0.5, thermal_capacity_J_per_K=50.0,
                          max_winding_C=150.0, warning_C=140.0)
    rig = six_coil(coils=[c.model_copy(update={"thermal": thermal}) for c in default_six_coil_coils()])
    currents = np.zeros((60000, 6))
    currents[:, 0] = 8.0  # 10 min at 8 A: tau = 25 s, the winding reaches its steady state
    checks = current_program_checks(rig, currents, 100.0, move_ends=[])
    # steady state of C dT/dt = I^2 R0 (1 + a (T - 20)) - (T - 25)/R_th, by hand, with the
    # closed loop's 20 % more power: T = (p (1 - 20 a) + 25 g) / (g - p a), p = 1.2 I^2 R0
    p, g, a = 1.2 * 8.0**2 * 1.5, 2.0, 0.00393
    steady = (p * (1 - 20 * a) + 25 * g) / (g - p * a)
    assert by(checks, "winding temperature", "coil x+").value == pytest.approx(steady, abs=1e-6)
    # the bound: R at that temperature throughout, times the current, plus L dI/dt (0 but for the
    # first sample: 0.03 H x 800 A/s = 24 V from 0 A)
    hot = 1.5 * (1 + a * (steady - 20))
    assert by(checks, "voltage R(T) I + L dI/dt", "supply x+").value == pytest.approx(
        hot * 8.0 + 0.03 * 800, rel=1e-9)
    assert by(checks, "current", "coil x+").margin == pytest.approx(12.0)


def test_a_serial_supply_link_cannot_carry_100_Hz_at_9600_baud():
    urls = [f"serial:///dev/ttyUSB{i}?baud=9600" for i in range(6)]
    rig = six_coil(coils=default_six_coil_coils(urls))
    checks = current_program_checks(rig, np.zeros((10, 6)), 100.0, move_ends=[])
    link = by(checks, "link time per cycle", "supply x+ (9600 baud)")
    # "CURR -20.0000;:MEAS:CURR?\n" (26 bytes) and "-2.000000E+01\n" (14), 10 bits a byte
    assert link.value == pytest.approx(40 * 10 / 9600 * 1e3)
    assert not link.passed and link.limit == pytest.approx(8.0)  # 80 % of 10 ms
    slow = current_program_checks(rig, np.zeros((10, 6)), 10.0, move_ends=[])
    assert by(slow, "link time per cycle", "supply x+ (9600 baud)").passed


def test_the_coil_board_s_links_and_heating_against_hand_figures():
    board = CoilBoardSettings(url="serial:///dev/ttyACM0?baud=115200")
    rig = CoilBoardRig(rig=RigInfo(kind="coil-board"), board=board)
    settings = CoilBoardRunSettings()  # 50 Hz, full drive, 60 moves of at most 30 s
    checks = board_checks(rig, settings, n_moves=4)
    host = by(checks, "link time per cycle", "host link (115200 baud, SET + ACK)")
    assert host.value == pytest.approx((10 + 11) * 10 / 115200 * 1e3)  # SET 6+4, ACK 6+5 bytes
    bus = by(checks, "link time per cycle", "SyRen bus (9600 baud, a packet per coil)")
    assert bus.value == pytest.approx(4 * 4 * 10 / 9600 * 1e3) and bus.passed  # < 20 ms
    fast = board_checks(rig, CoilBoardRunSettings(rate_hz=100.0), n_moves=4)
    assert not by(fast, "link time per cycle", "SyRen bus (9600 baud, a packet per coil)").passed
    assert all(c.passed for c in checks if c.check == "winding temperature")

    hot = CoilBoardRig(rig=RigInfo(kind="coil-board"), board=board.model_copy(update={"supply_V": 24.0}))
    refused = [c for c in board_checks(hot, settings, 4) if not c.passed]
    assert refused and all(c.check == "winding temperature" for c in refused)

    def steady(volts):  # (T - 25)/R_th = V^2 / (R0 (1 + a (T - 20))), by a root finder
        return brentq(lambda t: (t - 25) / 2.5 - volts**2 / (6.0 * (1 + 0.00393 * (t - 20))),
                      25, 1000)

    best = drive_for_limit(Windings.of_board(hot.board), 24.0, 127)
    assert steady(24.0 * best / 127) < 100.0 <= steady(24.0 * (best + 1) / 127)
    assert f"a drive of at most {best}" in refused[0].detail


def test_the_field_of_a_dipole_at_an_exposure_point_on_its_axis():
    # B = mu0 / (4 pi) 2 m / r^3 on the axis of a dipole: 970 A m^2 at 0.5 m
    t = np.array([0.0, 1.0])
    centres = np.zeros((2, 1, 3))
    moments = np.array([[[0.0, 0.0, 970.0]], [[0.0, 0.0, 485.0]]])
    point = ExposurePoint(name="operator", position_mm=(0.0, 0.0, 500.0))
    check, = exposure_checks([point], t, centres, moments, 400.0)
    assert check.value == pytest.approx(1e3 * MU0 / (4 * math.pi) * 2 * 970.0 / 0.5**3)
    assert check.passed and "t = 0.00 s" in check.detail
    check, = exposure_checks([point], t, centres, moments, 1.0)
    assert not check.passed and check.margin < 0


EMULATED = Emulation(backdoor="tcp://127.0.0.1:1")
"""A dEPM rig file as `rigctl emulate depm` writes it: real arms are refused (the next test)."""


def test_a_field_sequence_on_real_arms_is_refused_until_the_arm_model_is_corrected():
    """rigctl's LBR iiwa chain turns A4 the opposite way from KUKA's (docs/depm.md): on real arms
    the magnets would not be where the plan and its checks put them. Refused in one line."""
    from rigctl.core.errors import ConfigError
    from rigctl.emulators.depm import default_settings
    from rigctl.rigs.depm.run import FieldSequenceProgram

    plan = load_plan(EXAMPLES / "depm-plan.json")
    with pytest.raises(ConfigError, match="refused on real arms: .* A4"):
        FieldSequenceProgram(plan, DepmRig(rig=RigInfo(kind="depm"), depm=default_settings()))


def test_the_depm_example_plan_is_certified_and_a_tighter_exposure_limit_refuses_it():
    from rigctl.emulators.depm import default_settings
    from rigctl.rigs.depm.run import FieldSequenceProgram

    plan = load_plan(EXAMPLES / "depm-plan.json")
    rig = DepmRig(rig=RigInfo(kind="depm"), depm=default_settings(), emulation=EMULATED)
    checks = FieldSequenceProgram(plan, rig).checks()
    assert all(c.passed for c in checks)
    kinds = {c.check for c in checks}
    assert kinds >= {"joint range", "joint speed", "joint acceleration", "keep-out clearance",
                     "EPM-EPM distance", "static field exposure", "field |B| at the centre"}
    edge = by(checks, "static field exposure", "patient table edge")
    assert 10.0 < edge.value < 400.0  # the EPMs pass within ~0.3 m of the table's edge
    strict = rig.model_copy(update={"depm": rig.depm.model_copy(update={"exposure_limit_mT": 10.0})})
    refused = [c for c in FieldSequenceProgram(plan, strict).checks() if not c.passed]
    assert [c.subject for c in refused] == ["patient table edge"]


def test_validate_with_a_rig_prints_the_certificate_and_refuses_with_exit_2(tmp_path):
    rig = six_coil(stream=StreamSettings())
    (tmp_path / "rig.toml").write_text(dump_rig(rig))
    plan = str(EXAMPLES / "fig4-quick.json")
    done = run_rigctl("validate", plan, "--rig", "rig.toml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("pre-flight certificate: passed:")
    assert "winding temperature of coil x+" in done.stdout
    as_json = run_rigctl("validate", plan, "--rig", "rig.toml", "--json", cwd=tmp_path)
    document = json.loads(as_json.stdout)
    assert document["passed"] and document["rig_hash"] == rig_hash(rig)
    cold = CoilThermal(thermal_resistance_K_per_W=0.5, thermal_capacity_J_per_K=5.0,
                       max_winding_C=40.0, warning_C=35.0)
    hot = six_coil(coils=[c.model_copy(update={"thermal": cold}) for c in default_six_coil_coils()])
    (tmp_path / "hot.toml").write_text(dump_rig(hot))
    refused = run_rigctl("validate", plan, "--rig", "hot.toml", cwd=tmp_path)
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1 and "Traceback" not in refused.stderr
    assert refused.stderr.startswith("error: pre-flight: refused, nothing energised: REFUSED: "
                                     "winding temperature of coil")
    assert "REFUSED" in refused.stdout.splitlines()[1]  # the certificate, refused checks first


def test_each_arm_s_link_is_checked_against_the_servo_period():
    from rigctl.core.config import PreflightSettings
    from rigctl.emulators.depm import default_settings
    from rigctl.rigs.depm.run import FieldSequenceProgram

    plan = load_plan(EXAMPLES / "depm-plan.json")
    rig = DepmRig(rig=RigInfo(kind="depm"), depm=default_settings(), emulation=EMULATED,
                  preflight=PreflightSettings(kst_round_trip_ms=6.0))
    links = [c for c in FieldSequenceProgram(plan, rig).checks() if c.check == "link time per cycle"]
    assert [c.subject for c in links] == ["arm left (KST servo target and answer)",
                                          "arm right (KST servo target and answer)"]
    # 50 targets a second: 80 % of 20 ms is 16 ms for one 6 ms round trip (the arms overlap)
    assert all(c.passed and c.value == pytest.approx(6.0) and c.limit == pytest.approx(16.0)
               for c in links)
    fast = rig.model_copy(update={"depm": rig.depm.model_copy(update={"servo_rate_hz": 200.0})})
    refused = [c for c in FieldSequenceProgram(plan, fast).checks() if not c.passed]
    # at 200 Hz the link may take 4 ms of each 5 ms cycle: 6 ms does not fit
    assert [c.check for c in refused] == ["link time per cycle"] * 2
    assert refused[0].limit == pytest.approx(4.0) and refused[0].margin == pytest.approx(-2.0)
