"""Made-up electromagnet stations as MPEMs, sized from published ones (never copied files): for
benches, tests and emulated truths.

`octomag_like`: eight iron-core electromagnets around a spherical workspace, as in ETH's OctoMag
(Kummer et al., IEEE T-RO 26(6), 2010): four with their axes in the horizontal plane at azimuths
0, 90, 180, 270 deg, four tilted 45 deg up at azimuths 45, 135, 225, 315 deg, every core tip
100 mm from the centre and pointing at it. Each coil is one B source at its tip, of order 1-3
(dipole, quadrupole, octupole), of about 1 mT/A at the centre, positive current making field
there along the coil's axis away from its tip; the Offset a uniform 50 uT along -z.

`navion_like`: three iron-core electromagnets below and around the workspace, as in ETH's Navion
(Gervasoni et al., "A Human-Scale Clinically Ready Electromagnetic Navigation System for
Magnetically Responsive Biomaterials and Medical Devices", Adv. Mater. 36, 2024): a mobile
three-coil system whose field reaches tens of mT at a workspace some 0.2 m from its cores. Here:
core tips 0.2 m from the centre at azimuths 90, 210 and 330 deg, 30 deg below the horizontal,
pointing at the centre; one dipole source each of 1 mT/A at the centre (B_1 = 4e-6 T m^3/A,
2 B_1 / r^3 at r = 0.2 m), so 20 A make 20 mT; three coils make the field, no gradient on demand.

`helmholtz_triad`: three orthogonal Helmholtz pairs, each pair wired in series and fed as one coil
(as such triads are built: three supplies, a uniform field; six independent coils would add
gradients a pair cancels by design). A pair of radius R and N turns a side makes
(4/5)^(3/2) mu0 N I / R at its centre (the Helmholtz formula, e.g. Jackson, Classical
Electrodynamics, 3rd ed., problem 5.7); R = 0.1, 0.12, 0.14 m (nested) and N = 100 give
0.90, 0.75, 0.64 mT/A, the few mT of lab triads for helical swimmers (Abbott et al., "How should
microrobots swim?", Int. J. Robot. Res. 28(11-12), 2009). Each pair is an order-1 A source (a
uniform field per ampere); the Offset is the earth's field, about 50 uT.

With `seed` each station is as built, not as drawn: every coil's strength +-5 %, tip +-2 mm and
direction +-2 deg off (the emulated bench's truth, `rigctl emulate six-coil --truth NAME`).
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


EARTH_FIELD_T = (2e-5, 0.0, -4.5e-5)
"""A mid-latitude earth's field (T): 20 uT north (+x here), 45 uT down."""


def _earth_offset() -> list[Source]:
    """The earth's field as the Offset: an order-1 A source is the uniform field -A_1 z."""
    b = np.asarray(EARTH_FIELD_T)
    return [Source((0.0, 0.0, 0.0), tuple(-b / np.linalg.norm(b)), "A", (float(np.linalg.norm(b)),))]


def _as_built(position, direction, gain_1, rng):
    """A coil's tip, direction and strength off its drawing by the seeded tolerances."""
    position, direction = np.asarray(position, dtype=float), np.asarray(direction, dtype=float)
    if rng is not None:
        position = position + rng.uniform(-2e-3, 2e-3, 3)
        direction = direction + rng.uniform(-1, 1, 3) * np.radians(2.0)
        gain_1 = gain_1 * (1.0 + rng.uniform(-0.05, 0.05))
    return tuple(position), tuple(direction / np.linalg.norm(direction)), gain_1


NAVION_TIP_DISTANCE_M = 0.2
NAVION_DIPOLE = 4e-6
"""B_1 (T m^3 / A): 2 B_1 / r^3 = 1 mT/A on the axis at r = 0.2 m."""


def navion_like(*, seed: int | None = None) -> MPEM:
    """A 3-coil Navion-like MPEM (dipole sources; see the module docstring)."""
    rng = np.random.default_rng(seed) if seed is not None else None
    coils = []
    el = np.radians(-30.0)
    for az_deg in (90.0, 210.0, 330.0):
        az = np.radians(az_deg)
        tip = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        position, direction, b1 = _as_built(NAVION_TIP_DISTANCE_M * tip, -tip, NAVION_DIPOLE, rng)
        coils.append([Source(position, direction, "B", (b1,))])
    return MPEM(["N1", "N2", "N3"], coils, _earth_offset(), name="Navion-like",
                workspace_m=((-0.05, 0.05), (-0.05, 0.05), (-0.05, 0.05)))


HELMHOLTZ_T_PER_A = tuple((4 / 5) ** 1.5 * 4e-7 * np.pi * 100 / r for r in (0.10, 0.12, 0.14))
"""The x, y and z pairs' field at the centre per ampere (T/A): N = 100, R = 0.10, 0.12, 0.14 m."""


def helmholtz_triad(*, seed: int | None = None) -> MPEM:
    """Three Helmholtz pairs along x, y, z, each one coil (see the module docstring)."""
    rng = np.random.default_rng(seed) if seed is not None else None
    coils = []
    for axis, gain in zip(np.eye(3), HELMHOLTZ_T_PER_A):
        position, direction, a1 = _as_built(np.zeros(3), -axis, gain, rng)
        coils.append([Source((0.0, 0.0, 0.0), direction, "A", (a1,))])  # B = -A_1 z = +a1 axis
    return MPEM(["HX", "HY", "HZ"], coils, _earth_offset(), name="Helmholtz triad",
                workspace_m=((-0.05, 0.05), (-0.05, 0.05), (-0.05, 0.05)))


STATIONS = {"helmholtz-triad": helmholtz_triad, "octomag-like": octomag_like,
            "navion-like": navion_like}
"""The stations `rigctl emulate six-coil --truth NAME` builds (a keyword `seed`: as built)."""
