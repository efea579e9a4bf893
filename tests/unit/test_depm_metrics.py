"""Table 1 metrics and the Fig. 6 cross-activation on hand-made signals with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.rigs.depm.metrics import Window, cross_activation, table1

T = np.round(np.arange(0.0, 12.0 + 1e-9, 0.01), 2)


def signals():
    """Bx requested 10 mT on [0, 6) (arrives at 2), then dBx/dx 100 mT/m on [6, 12] (arrives at 8)."""
    U = np.zeros((len(T), 8))
    bx = np.interp(T, [0, 1.5, 2, 6, 6.5, 7, 12], [0, 12, 10, 10, -1, 0, 0])
    bx[(T >= 10) & (T < 10.5)] = 3.0  # off-activation while dBx/dx is held
    U[:, 0] = bx
    g = np.interp(T, [0, 6, 8, 8.01, 12], [0, 0, 100, 101, 101])
    g[(T >= 4) & (T < 4.5)] = -50.0  # off-activation while Bx is held
    U[:, 3] = g
    windows = [Window(0.0, 2.0, 6.0, np.array([10.0, 0, 0, 0, 0, 0, 0, 0]), "Bx"),
               Window(6.0, 8.0, 12.0, np.array([0, 0, 0, 100.0, 0, 0, 0, 0]), "dBx/dx")]
    return U, windows


def test_table1_per_component():
    U, windows = signals()
    m = table1(T, U, windows)
    bx, g = m["Bx"], m["dBx/dx"]
    # steady state: mean over the hold after its first quarter ([3, 6] and [9, 12])
    assert bx["steady_state"] == pytest.approx(10.0)
    assert g["steady_state"] == pytest.approx(101.0)
    assert g["steady_state_error_pct"] == pytest.approx(1.0)
    # rise: Bx peaks at 12 (20 % over); fall: Bx dips to -1 (-10 %, an undershoot)
    assert bx["overshoot_rise_pct"] == pytest.approx(20.0)
    assert bx["overshoot_fall_pct"] == pytest.approx(-10.0)
    assert bx["fall_time_s"] == pytest.approx(0.75, abs=0.011)  # |Bx| <= 0.5 mT from 6.75 s
    assert g["overshoot_rise_pct"] == pytest.approx(1.0)
    assert g["overshoot_fall_pct"] is None  # the last component never falls
    # off-activation: Bx's spike of 3 mT while off; dBx/dx's -50 mT/m spike before its request
    assert bx["peak_off_activation"] == pytest.approx(3.0)
    assert g["peak_off_activation"] == pytest.approx(-50.0)
    off_bx = T >= 6.75  # after its fall: Bx is not requested again
    assert bx["sigma_off"] == pytest.approx(np.sqrt(np.mean(U[off_bx, 0] ** 2)), rel=1e-9)
    assert bx["sigma_off"] > 3.0 * np.sqrt(50 / off_bx.sum())  # the spike, plus the fall's tail
    assert m["By"]["peak_off_activation"] == 0.0 and m["By"]["requested"] is None


def test_table1_averages_are_means_of_absolute_values():
    U, windows = signals()
    a = table1(T, U, windows)["average"]
    assert a["peak_off_activation_field_mT"] == pytest.approx((3.0 + 0 + 0) / 3)
    assert a["peak_off_activation_gradient_mT_per_m"] == pytest.approx(50.0 / 5)
    assert a["overshoot_rise_pct"] == pytest.approx((20.0 + 1.0) / 2)
    assert a["steady_state_error_max_pct"] == pytest.approx(1.0)


def test_cross_activation_rows_are_rises_in_percent_of_the_request():
    U, windows = signals()
    ca = cross_activation(T, U, windows)
    assert ca["rows"] == ["Bx", "dBx/dx"]
    bx_row, g_row = ca["percent"]
    assert bx_row[0] == pytest.approx(120.0)  # Bx peaks at 12 mT of 10 during its own rise
    assert bx_row[3] == pytest.approx(0.0)  # no gradient while Bx rises (spike is at 4 s)
    assert g_row[3] == pytest.approx(101.0)
    assert g_row[0] == pytest.approx(100.0)  # Bx is still 10 mT when the gradient's rise starts
