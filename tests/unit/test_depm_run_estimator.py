"""The DEPM run's sensor estimator, built once per run from the Hall board's fixed offsets: the
matrix of seed 003 eq. 24 written out by hand for the paper's board, and exact on a linear field."""

import numpy as np

from rigctl.rigs.depm.sensors import sensor_estimator


def test_is_eq24_written_as_a_matrix_on_the_papers_board():
    delta = 0.05  # sensor 2 at +delta x, sensor 3 at +delta y from sensor 1
    offsets = np.array([[0, 0, 0], [delta, 0, 0], [0, delta, 0.0]])
    # columns: B1x B1y B1z B2x B2y B2z B3x B3y B3z
    # rows: Bx By Bz dBx/dx dBx/dy dBx/dz dBy/dy dBy/dz
    by_hand = np.zeros((8, 9))
    by_hand[0, 0] = by_hand[1, 1] = by_hand[2, 2] = 1.0
    by_hand[3, [3, 0]] = [1 / delta, -1 / delta]  # (B2x - B1x) / delta
    by_hand[4, [6, 0, 4, 1]] = [0.5 / delta, -0.5 / delta, 0.5 / delta, -0.5 / delta]  # both dBx/dy
    by_hand[5, [5, 2]] = [1 / delta, -1 / delta]  # (B2z - B1z) / delta
    by_hand[6, [7, 1]] = [1 / delta, -1 / delta]  # (B3y - B1y) / delta
    by_hand[7, [8, 2]] = [1 / delta, -1 / delta]  # (B3z - B1z) / delta
    np.testing.assert_allclose(sensor_estimator(offsets), by_hand, atol=1e-9)


def test_recovers_a_linear_field_from_any_offsets():
    g = np.array([[0.1, -0.05, 0.02], [-0.05, 0.07, -0.03], [0.02, -0.03, -0.17]])  # traceless
    b0 = np.array([1e-3, -2e-3, 5e-4])
    offsets = np.array([[0.01, 0.0, 0.002], [0.03, 0.01, -0.004], [-0.005, 0.02, 0.01]])
    fields = b0 + (offsets - offsets[0]) @ g.T  # (3, 3): the field at each sensor
    batch = np.stack([fields, 2 * fields])  # a batch of samples, as a run reads them
    U = batch.reshape(len(batch), -1) @ sensor_estimator(offsets).T
    expected = np.array([*b0, g[0, 0], g[0, 1], g[0, 2], g[1, 1], g[1, 2]])
    np.testing.assert_allclose(U, [expected, 2 * expected], atol=1e-12)
