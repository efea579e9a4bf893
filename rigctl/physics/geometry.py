"""Plane geometry shared by the planners' workspaces and the camera's calibration.

Only what more than one room needs lives here; a polygon is a (V, 2) array of its vertices in
order, the last joined to the first, in whatever unit the caller works in (mm on the floor, px in a
picture).
"""

from __future__ import annotations

import numpy as np


def signed_area(vertices: np.ndarray) -> float:
    """Signed (shoelace) area of a polygon (V, 2), in the square of the vertices' unit: > 0 when it
    runs counter-clockwise with y up (floor coordinates), which in picture coordinates (v down) is
    clockwise on screen."""
    x, y = vertices[:, 0], vertices[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
