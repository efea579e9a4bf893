"""The electromagnets' field per ampere, through the rig's one field model (`field_model`).

Electromagnets add linearly, so the field at a point is B = A I + B_off with A the 3 x n actuation
matrix (T/A), each column one coil's field per ampere, and B_off the current-independent Offset
field of an MPEM calibration (zero for loops). The model behind it (`rigctl.physics.fields`) is,
by what the rig file's `field_calibration` names: a mag_manip MPEM file (`MPEMCalibration`), the
loops a "rigctl-loop-v1" file fitted (`rigctl.physics.field_calibration`), or, with none, the rig
file's own loops (`rigctl.physics.magnetics.loop_field`, gain 1); a measured
`actuation_matrix_T_per_A` still overrides the field at the centre. Pulling needs the gradient
too: the 8-vector U (field and the five independent gradient terms, seed 003 eq. 6) per ampere.
Planners, allocation and the emulated world all take their coil fields from here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from numpy.typing import ArrayLike
from pydantic import BaseModel, ConfigDict, PrivateAttr

from rigctl.core.config import CoilRig
from rigctl.core.errors import ConfigError, LimitError
from rigctl.physics.field_calibration import FieldCalibration, parse_field_calibration
from rigctl.physics.fields.loops import GRADIENT_STEP_MM, LoopModel, coil_loops
from rigctl.physics.fields.model import FieldModel
from rigctl.physics.fields.mpem import MPEM
from rigctl.physics.fields.mpem_file import parse_mpem
from rigctl.physics.magnetics import gradient_terms

__all__ = ["GRADIENT_STEP_MM", "MPEMCalibration", "actuation_matrix", "coil_field_and_gradient",
           "coil_loops", "field_model", "field_offset", "load_calibration", "max_planar_gradient",
           "u_actuation_matrix"]


class MPEMCalibration(BaseModel):
    """A rig file's `field_calibration` that is a mag_manip MPEM file: its text (what a run's
    record copies) and where it was read from; `model` is the parsed `MPEM`."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    text: str
    source: str | None = None
    _model: MPEM | None = PrivateAttr(default=None)

    @property
    def model(self) -> MPEM:
        if self._model is None:
            self._model = parse_mpem(yaml.safe_load(self.text), self.source or "MPEM calibration")
        return self._model

    @property
    def coil_list(self) -> list[str]:
        return list(self.model.coil_names)

    def to_yaml(self) -> str:
        return self.text

    def __eq__(self, other: object) -> bool:  # the file, not the parsed model's identity
        return isinstance(other, MPEMCalibration) and (self.text, self.source) == (
            other.text, other.source)

    __hash__ = None  # type: ignore[assignment]


def load_calibration(path: str | Path) -> FieldCalibration | MPEMCalibration:
    """A field calibration file of either format, told apart as `load_field_model` does: a
    "rigctl-loop-v1" file says so in `Calibration_Model`, anything else is read as mag_manip's
    MPEM layout (ConfigError, one line naming the key, if it is neither)."""
    path = Path(path)
    try:
        text = path.read_text()
        data = yaml.safe_load(text)
    except FileNotFoundError:
        raise ConfigError(f"field calibration {path} does not exist") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise ConfigError(f"field calibration {path}: cannot be read as YAML: "
                          f"{str(err).splitlines()[0]}") from None
    if isinstance(data, dict) and "Calibration_Model" in data:
        return parse_field_calibration(data, str(path))
    calibration = MPEMCalibration(text=text, source=str(path))
    calibration._model = parse_mpem(data, str(path))  # checked now, not at first use
    return calibration


def field_model(rig: CoilRig) -> FieldModel:
    """The rig's field model, its coils in `rig.coils` order: the MPEM its `field_calibration`
    names, the loops a "rigctl-loop-v1" calibration fitted, or the rig file's loops (gain 1).

    An MPEM's coils are matched to the rig's by name (the file's Coil_List order need not be
    the rig's); a rig coil the file lacks, or a file coil the rig lacks, is a ConfigError."""
    if not rig.coils:
        raise ConfigError(f"rig '{rig.rig.name}' has no [[coils]]: there is nothing to allocate to")
    names = [c.name for c in rig.coils]
    calibration = getattr(rig, "field_calibration", None)
    if isinstance(calibration, MPEMCalibration):
        mpem = calibration.model
        if list(mpem.coil_names) == names:
            return mpem
        if sorted(mpem.coil_names) != sorted(names):
            raise ConfigError(
                f"field_calibration {calibration.source or mpem.name}: its Coil_List "
                f"({', '.join(mpem.coil_names)}) is not the rig's coils ({', '.join(names)})")
        order = [mpem.coil_names.index(n) for n in names]
        return MPEM(names, [mpem.coil_sources[k] for k in order], mpem.offset_sources,
                    name=mpem.name, workspace_m=mpem.workspace_m)
    return LoopModel(names, coil_loops(rig))


def actuation_matrix(rig: CoilRig, point_mm: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The actuation matrix of the rig's coils at `point_mm`.

    Parameters
    ----------
    rig : CoilRig
        Its `coils` (loop of `turns` turns, `centre_mm`, `axis`, `loop_radius_mm`), the model
        its `field_calibration` names (`field_model`), or its measured
        `actuation_matrix_T_per_A`, which takes precedence.
    point_mm : (3,) array
        Where the field is wanted, workspace frame, mm. A measured matrix only describes the
        workspace centre, so with one any other point is refused.

    Returns
    -------
    np.ndarray, shape (3, n_coils)
        Field per ampere in T/A; column j is coil j in `rig.coils` order. An MPEM's Offset
        field is not in it (`field_offset`).
    """
    point = np.asarray(point_mm, dtype=float).reshape(3)
    if not rig.coils:
        raise ConfigError(f"rig '{rig.rig.name}' has no [[coils]]: there is nothing to allocate to")
    if rig.actuation_matrix_T_per_A is not None:
        if np.any(point != 0.0):
            raise ConfigError(
                f"actuation_matrix_T_per_A is measured at the workspace centre; it cannot give the "
                f"field at {point.tolist()} mm (remove it to compute the matrix from the coils)"
            )
        return np.array(rig.actuation_matrix_T_per_A, dtype=float)
    matrix = field_model(rig).field_and_gradient_per_ampere(point[None] * 1e-3)[0, :-1, 0:3].T
    if not np.isfinite(matrix).all():
        bad = rig.coils[int(np.flatnonzero(~np.isfinite(matrix).all(axis=0))[0])].name
        raise ConfigError(f"point {point.tolist()} mm lies on the winding of coil {bad}")
    return np.ascontiguousarray(matrix)


def field_offset(rig: CoilRig, point_mm: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The current-independent part of U (8,) (T, T/m; `U_COMPONENTS`) at `point_mm`: an MPEM's
    Offset field, zero for loops and for a measured actuation matrix. The currents for a field B
    make B - offset[0:3] through the actuation matrix."""
    if rig.actuation_matrix_T_per_A is not None or not isinstance(
            getattr(rig, "field_calibration", None), MPEMCalibration):
        return np.zeros(8)
    point = np.asarray(point_mm, dtype=float).reshape(3) * 1e-3
    return field_model(rig).offset(point)


def coil_field_and_gradient(rig: CoilRig, point_mm: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Field (3, n) T/A and gradient (3, 3, n) T/m/A of every coil per ampere at `point_mm`
    (through `field_model`: for loops, central differences of `loop_field` with the step
    `GRADIENT_STEP_MM`); returns (B, G) stacked as a (3, 4, n) array: [..., 0, :] the field,
    [:, 1 + j, :] dB/dx_j. An MPEM's Offset is not in it (`field_offset`)."""
    if not rig.coils:
        raise ConfigError(f"rig '{rig.rig.name}' has no [[coils]]: there is nothing to allocate to")
    if rig.actuation_matrix_T_per_A is not None:
        raise ConfigError("a measured actuation_matrix_T_per_A has no gradients: remove it to "
                          "compute fields and gradients from the coils' geometry")
    point = np.asarray(point_mm, dtype=float).reshape(3) * 1e-3
    per_A = field_model(rig).field_and_gradient_per_ampere(point[None])[0, :-1, :]  # (n, 12)
    out = np.empty((3, 4, len(rig.coils)))
    out[:, 0, :] = per_A[:, 0:3].T
    out[:, 1:, :] = per_A[:, 3:].reshape(-1, 3, 3).transpose(1, 2, 0)  # [i, j, k] = dB_i/dx_j
    if not np.isfinite(out).all():
        raise ConfigError(f"point {point_mm!s} mm lies on a coil's winding")
    return out


def u_actuation_matrix(rig: CoilRig, point_mm: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """The 8 x n actuation matrix of U (rows `U_COMPONENTS`) at `point_mm`, per ampere."""
    fg = coil_field_and_gradient(rig, point_mm)
    gradient = np.moveaxis(fg[:, 1:, :], -1, 0)  # (n, 3, 3)
    return np.concatenate([fg[:, 0, :], gradient_terms(gradient).T])


def max_planar_gradient(rig: CoilRig, b0_T: float, *, angles: int = 360) -> float:
    """The largest g (T/m) such that an in-plane field of `b0_T` at any angle together with any
    diagonal gradient |dBx/dx|, |dBy/dy| <= g stays within every coil's current limit (box corners
    suffice: the currents are linear in U); 0 for coils that cannot make those gradients with the
    field. Raises LimitError if the field alone is too strong."""
    A8 = u_actuation_matrix(rig)
    pinv = np.linalg.pinv(A8)
    limits = np.array([c.current_limit_A for c in rig.coils])
    psi = np.linspace(0.0, 2.0 * np.pi, angles, endpoint=False)
    u_field = np.zeros((angles, 8))
    u_field[:, 0], u_field[:, 1] = b0_T * np.cos(psi), b0_T * np.sin(psi)
    i_field = np.abs(u_field @ pinv.T)  # (angles, n)
    room = limits - i_field.max(axis=0)
    if (room <= 0).any():
        j = int(np.argmin(room))
        raise LimitError(f"a {b0_T * 1e3:g} mT field needs {i_field.max(axis=0)[j]:.1f} A on coil "
                         f"{rig.coils[j].name} (limit {limits[j]:.1f} A)")
    worst = np.zeros(len(limits))
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            u = np.zeros(8)
            u[3], u[6] = sx, sy
            i_unit = pinv @ u
            if np.abs(A8 @ i_unit - u).max() > 1e-6:
                # outside the coils' span (a uniform-field triad makes no gradient): the
                # pseudo-inverse would give currents that make none, not an unlimited gradient
                return 0.0
            worst = np.maximum(worst, np.abs(i_unit))
    # |I_field + g I_unit| <= |I_field| + g |I_unit|: conservative, per coil
    per_coil = np.where(worst > 0, room / np.maximum(worst, 1e-300), np.inf)
    return float(per_coil.min())
