"""Made-up electromagnet stations as MPEMs, sized from published ones (never copied files): for
benches, tests and emulated truths.

`octomag_like`: eight iron-core electromagnets around a spherical workspace, as in ETH's OctoMag
(Kummer et al., IEEE T-RO 26(6), 2010): four with their axes in the horizontal plane at azimuths
0, 90, 180, 270 deg, four tilted 45 deg up at azimuths 45, 135, 225, 315 deg, every core tip
100 mm from the centre and pointing at it. Each coil is one B source at its tip, of order 1-3
(dipole, quadrupole, octupole), of about 1 mT/A at the centre, positive current making field
there along the coil's axis away from its tip; the Offset a uniform 50 uT along -z.
"""

from __future__ import annotations

import numpy as np

from rigctl.physics.fields.mpem import MPEM, Source

OCTOMAG_TIP_DISTANCE_M = 0.1
OCTOMAG_DIPOLE = 5e-7
"""B_1 (T m^3 / A): 2 B_1 / r^3 = 1 mT/A on the axis at r = 0.1 m."""


def octomag_directions() -> np.ndarray:
    """(8, 3) unit vectors from the centre to each coil's tip."""
    out = []
    for k in range(4):
        az = np.radians(90.0 * k)
        out.append((np.cos(az), np.sin(az), 0.0))
    for k in range(4):
        az = np.radians(45.0 + 90.0 * k)
        el = np.radians(45.0)
        out.append((np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)))
    return np.array(out)


def octomag_like(order: int = 3, *, seed: int | None = None) -> MPEM:
    """An 8-coil OctoMag-like MPEM of `order` 1-3; `seed` perturbs every coil's strength (+-5 %),
    tip (+-2 mm) and direction (+-2 deg) as a real station differs from its drawing."""
    rng = np.random.default_rng(seed) if seed is not None else None
    coils = []
    for k, tip in enumerate(octomag_directions()):
        position = OCTOMAG_TIP_DISTANCE_M * tip
        direction = -tip
        gain = 1.0
        if rng is not None:
            position = position + rng.uniform(-2e-3, 2e-3, 3)
            direction = direction + rng.uniform(-1, 1, 3) * np.radians(2.0)
            gain = 1.0 + rng.uniform(-0.05, 0.05)
        b1 = OCTOMAG_DIPOLE * gain
        coefficients = (b1, 0.3 * b1 * 0.02, 0.1 * b1 * 0.02**2)[:order]
        coils.append([Source(tuple(position), tuple(direction / np.linalg.norm(direction)), "B",
                             coefficients)])
    offset = [Source((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "A", (5e-5,))]
    return MPEM([f"Coil_{k}" for k in range(8)], coils, offset, name=f"OctoMag-like order {order}",
                workspace_m=((-0.03, 0.03), (-0.03, 0.03), (-0.03, 0.03)))
