"""A re-plan of the six-coil closed loop is certified like a plan, from the currents being
streamed, at the stream's own rate (issue 35, item 4). Every figure is worked by hand from the rig
below: coils of R = 1.5 ohm, L = 30 mH, 100 V compliance, and a measured actuation matrix of
0.15 mT/A per coil along its axis, so a 3 mT field along x is 10 A in each x coil (minimum norm:
2 x 10 A x 0.15 mT/A = 3 mT) and nothing elsewhere."""

import numpy as np
import pytest

from rigctl.core.config import (
    FieldSettings,
    PreflightSettings,
    RigConfig,
    RigInfo,
    StreamSettings,
    default_six_coil_coils,
)
from rigctl.core.errors import LimitError, PlanError
from rigctl.rigs.six_coil.allocate import CurrentProgram, allocate
from rigctl.rigs.six_coil.certify import current_program_checks
from rigctl.rigs.six_coil.realize import realize_global_moves
from rigctl.rigs.six_coil.settings import SixCoilRig
from rigctl.rigs.six_coil.supervisor import SupervisedSequencer, certified_replan, lead_in

R, L, V = 1.5, 0.03, 100.0
GAIN = 0.15e-3  # T/A of every coil along its own axis
# the certificate takes R at the winding's hottest; over a second the winding stays at the room's
# 25 C (10 A: 180 W into 10 kJ/K, 0.02 K), which copper's 0.393 %/K from 20 C makes:
R_HOT = R * (1 + 0.00393 * (25.0 - 20.0))  # 1.529475 ohm


def rig(rate_hz: float = 1000.0, inductance_H: float = L) -> RigConfig:
    coils = [c.model_copy(update={"resistance_ohm": R, "inductance_H": inductance_H,
                                  "compliance_V": V}) for c in default_six_coil_coils()]
    matrix = np.zeros((3, 6))
    for j in range(6):
        matrix[j // 2, j] = GAIN  # x+, x-, y+, y-, z+, z-
    return SixCoilRig(rig=RigInfo(kind="six-coil"), coils=coils,
                     actuation_matrix_T_per_A=matrix.tolist(),
                     field=FieldSettings(whole_turns=False),  # the closed loop's corrections
                     stream=StreamSettings(rate_hz=rate_hz),
                     # the emulated bench's measured round trip: 2 ms (the default) is refused
                     # at 1 kHz by the link check, whatever the program
                     preflight=PreflightSettings(scpi_round_trip_ms=0.3))


def held_along_x(amps: float = 10.0) -> np.ndarray:
    """What a 1 kHz stream sent before a move end: the x coils ramped up to `amps` over 0.1 s
    (1.5 x 10 + 0.03 x 0.1 x 1000 = 18 V at its top) and held there for 0.1 s."""
    streamed = np.zeros((200, 6))
    streamed[:, :2] = amps * np.minimum(np.arange(1, 201) / 100, 1.0)[:, None]
    return streamed


def voltage(checks, supply):
    return next(c for c in checks if c.check.startswith("voltage") and c.subject == f"supply {supply}")


def test_a_re_plan_s_first_sample_is_checked_from_the_currents_being_streamed():
    """The stream held 10 A (ramped up at 0.1 A a sample: 1.53 x 10 + 0.03 x 0.1 x 1000 = 18.3 V
    at its top), then a re-plan's first sample asks 10.2 A: R I + L dI/dt = 1.529475 x 10.2 +
    0.03 x 0.2 x 1000 = 15.60 + 6.00 = 21.60 V. The same re-plan checked on its own from 0 A, as
    every program was, starts with a step of 10 A in 1 ms: 15.29 + 300 = 315.29 V, refused; at
    100 Hz that phantom step is 15.29 + 30 = 45.29 V and passed, which is why only a 1 kHz rig
    gave up."""
    replan = np.zeros((2, 6))
    replan[:, 0] = [10.0, 10.2]
    streamed = held_along_x()
    streamed[:, 1] = 0.0  # coil x+ alone, for the figures
    stream = np.vstack([streamed, replan])
    whole = voltage(current_program_checks(rig(), stream, 1000.0, move_ends=[]), "x+")
    assert whole.passed and whole.value == pytest.approx(R_HOT * 10.2 + 6.0, rel=1e-5)
    alone = voltage(current_program_checks(rig(), replan, 1000.0, move_ends=[]), "x+")
    assert not alone.passed and alone.value == pytest.approx(R_HOT * 10.0 + 300.0, rel=1e-5)
    at_100_hz = voltage(current_program_checks(rig(), replan, 100.0, move_ends=[]), "x+")
    assert at_100_hz.passed and at_100_hz.value == pytest.approx(R_HOT * 10.0 + 30.0, rel=1e-5)


def test_a_re_plan_from_the_held_field_passes_at_1_khz_where_a_check_from_0_a_refused_it():
    """The issue's failure, by hand: the re-plan starts at the field held, 10 A in each x coil;
    allocated as if from 0 A its first sample needs 1.5 x 10 + 0.03 x 10 x 1000 = 315 V. From
    the held currents there is no step; the highest voltage is where the field rolls at 2 turns/s
    (w = 4 pi rad/s): I = 10 cos(w t), |R I + L dI/dt| <= 10 (R + L w) = 15.29 + 3.77 = 19.06 V,
    and at least R I = 15.29 V while it holds."""
    streamed = held_along_x()
    replan = certified_replan(np.array([[3.3, 0.0]]), rig(), streamed, name="re-plan 1")
    assert replan.lead == 0  # nothing to join: the program starts where the stream is
    np.testing.assert_allclose(replan.currents.currents_A[0], streamed[-1], atol=1e-9)
    highest = max((c for c in replan.certificate.checks if c.check.startswith("voltage")),
                  key=lambda c: c.value)
    assert R_HOT * 10.0 - 1e-6 <= highest.value <= 10.0 * (R_HOT + L * 4 * np.pi) + 1e-6
    assert replan.certificate.passed and replan.certificate.plan_kind == "re-plan"
    assert "highest voltage" in replan.certificate_line()
    program = realize_global_moves(np.array([[3.3, 0.0]]), rig(),
                                   start_field_T=[3e-3, 0.0, 0.0])
    with pytest.raises(LimitError, match=r"needs 315\.0 V on coil x"):
        allocate(program, rig())  # from 0 A: the allocation's check of every program until now


def test_a_re_plan_that_does_not_start_where_the_stream_is_gets_the_plan_s_ramp():
    """Held at 0 A (the field off) and a re-plan whose first sample is 10 A: a straight lead-in
    over the plan's field.ramp_s = 0.1 s, 100 samples at 1 kHz (99 of them before the program's
    first), 0.1 A a sample: L dI/dt = 0.03 x 0.1 x 1000 = 3 V."""
    streamed = np.zeros((3, 6))
    replan = certified_replan(np.array([[3.3, 0.0]]), rig(), streamed, name="re-plan 1")
    assert replan.lead == 99
    steps = np.diff(np.vstack([streamed[-1], replan.currents.currents_A[:101]]), axis=0)
    np.testing.assert_allclose(steps[:100, :2], 0.1, rtol=1e-9)
    assert replan.move_ends == [99 + realize_global_moves(
        np.array([[3.3, 0.0]]), rig(), start_field_T=[0.0, 0.0, 0.0]).move_end_index(0)]


def test_a_lead_in_is_made_long_enough_for_the_supply_s_compliance():
    """With L = 3 H a 10 A step over the plan's 0.1 s would need 3 x 10 / 0.1 = 300 V; the
    lead-in takes L dI / (0.9 V - R I) = 3 x 10 / (90 - 15) = 0.4 s instead, 400 samples at
    1 kHz of 0.025 A: R I + L dI/dt = 15 + 3 x 0.025 x 1000 = 90 V at its top (cold R)."""
    start, first = np.zeros(6), np.zeros(6)
    first[:2] = 10.0
    ramp = lead_in(start, first, rig(inductance_H=3.0))
    assert len(ramp) == 399
    samples = np.vstack([start, ramp, first])
    volts = R * samples[1:, 0] + 3.0 * np.diff(samples[:, 0]) * 1000.0
    assert volts.max() == pytest.approx(90.0, rel=1e-9)
    # at 100 Hz the same 0.4 s is 40 samples of 0.25 A: the same 90 V
    assert len(lead_in(start, first, rig(rate_hz=100.0, inductance_H=3.0))) == 39
    assert len(lead_in(first, first, rig())) == 0


def test_a_re_plan_that_breaks_a_limit_is_refused_by_its_certificate_not_clipped():
    """A check the allocation does not make, the field at the centre (3 mT against a rig file's
    2 mT): the re-plan is refused, named, and nothing is returned to splice."""
    strict = rig()
    strict = strict.model_copy(update={"preflight": strict.preflight.model_copy(
        update={"max_field_mT": 2.0})})
    with pytest.raises(LimitError, match=r"re-plan 1: refused by its certificate, not streamed: "
                                         r"REFUSED: field \|B\| at the centre of workspace: 3 mT"):
        certified_replan(np.array([[3.3, 0.0]]), strict, held_along_x(), name="re-plan 1")


def test_a_splice_made_for_another_sample_is_refused():
    program = CurrentProgram(np.arange(6) / 100.0, np.ones((6, 6)), np.zeros(6, dtype=int),
                             tuple(c.name for c in default_six_coil_coils()))
    seq = SupervisedSequencer(program, move_ends=[3, 6], ramp_samples=2)
    for _ in range(4):
        seq.next()
    assert len(seq.streamed()) == 3  # waits at the move end, holding sample 2
    with pytest.raises(PlanError, match="not spliced"):
        seq.splice(program, [2], at=2)
    assert seq.splice(program, [2], at=3) == 3
