"""Gravity sag between the CMM support condition and the use condition.

The CMM measured the sphere centres of the loaded artefact: ``x_cmm = x_free +
d_cmm``. In use the artefact stands on other supports or is tilted, so its
gravity loads (fixed in the world) act in another direction of the artefact frame:
``x_use = x_free + d_use``. Hence

    x_use = x_cmm + (d_use - d_cmm),

with both displacement fields from the same linear truss model at the CMM
geometry (displacements are microns; second-order terms are far below the CMM's
uncertainty). A support condition fixes both the supports (in the artefact frame:
the supports move with the artefact) and the gravity direction in the artefact
frame; for a pose ``T_world_artefact`` gravity in the artefact frame is
``R g_world`` (:func:`gravity_in_artefact_frame`).

Displacements under different supports differ also by a rigid motion that only
reflects where the truss is held. By default the least-squares rigid motion of the
difference is removed, so the corrected artefact keeps its frame and only its
shape changes (inter-sphere distances are unaffected either way).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.engineering.loads import STANDARD_GRAVITY, mass_loads, unit_vector
from fringecal.engineering.materials import Materials
from fringecal.engineering.supports import Supports, parse_supports
from fringecal.engineering.truss import Truss, TrussSolution, solve_truss
from fringecal.registration import kabsch

__all__ = ["SupportCondition", "SagCorrection", "gravity_sag_correction", "gravity_in_artefact_frame",
           "remove_rigid_motion"]


@dataclass(frozen=True)
class SupportCondition:
    """Supports and gravity direction, both in the artefact frame.

    Attributes
    ----------
    supports : Supports
    gravity : ndarray, shape (3,), unit
    """

    supports: Supports
    gravity: np.ndarray

    def __post_init__(self):
        s = parse_supports(self.supports) if isinstance(self.supports, str) else self.supports
        object.__setattr__(self, "supports", s)
        object.__setattr__(self, "gravity", unit_vector(self.gravity))

    def describe(self) -> str:
        return f"supports {self.supports.describe()}, gravity ({', '.join(f'{g:+.4f}' for g in self.gravity)})"


def gravity_in_artefact_frame(T_world_artefact, gravity_world=(0.0, 0.0, -1.0)) -> np.ndarray:
    """Gravity direction in the artefact frame for a pose (``x_local = R (x_world - t)``).

    >>> from fringecal.frames import Frame
    >>> tilted = Frame.from_params([0, 0, 0, np.pi / 2, 0, 0])
    >>> gravity_in_artefact_frame(tilted).round(12) + 0.0
    array([ 0., -1.,  0.])
    """
    return unit_vector(np.asarray(T_world_artefact.R) @ unit_vector(gravity_world))


def remove_rigid_motion(coords, displacements) -> np.ndarray:
    """``displacements`` (n, 3) without their least-squares rigid motion.

    The displaced points are registered back onto ``coords`` (SVD, a finite
    rotation), so distances between the displaced points are kept exactly.
    """
    X = np.asarray(coords, float)
    d = np.asarray(displacements, float)
    if not np.any(d):
        return np.zeros_like(d)
    moved = X + d
    M, T = kabsch(moved, X)
    return moved @ M.T + T - X


@dataclass(frozen=True)
class SagCorrection:
    """Result of :func:`gravity_sag_correction`.

    Attributes
    ----------
    artefact : Artefact
        The artefact with corrected sphere centres (``name`` gets ``+sag``).
    table : DataFrame
        Per sphere: ``sphere_id``, ``cmm_dx_mm..`` and ``use_dx_mm..`` (displacements
        under each condition) and ``dx_mm, dy_mm, dz_mm, d_mm`` (the correction applied).
    cmm, use : TrussSolution
    """

    artefact: Artefact
    table: pd.DataFrame
    cmm: TrussSolution
    use: TrussSolution

    @property
    def max_correction_mm(self) -> float:
        return float(self.table["d_mm"].max())


def gravity_sag_correction(artefact: Artefact, rods: pd.DataFrame, materials: Materials,
                           cmm: SupportCondition, use: SupportCondition, remove_rigid: bool = True,
                           g: float = STANDARD_GRAVITY) -> SagCorrection:
    """Move the CMM sphere centres to where gravity puts them in the use condition.

    Parameters
    ----------
    artefact : Artefact
        CMM-measured artefact (sphere centres in its own frame).
    rods : DataFrame
        ``rod_id, sphere_a, sphere_b`` (RodsTable).
    materials : Materials
        Tube section and material, masses of spheres, tubes, end caps and magnets.
    cmm, use : SupportCondition
        Supports and gravity direction in the artefact frame during the CMM
        measurement and in use.
    remove_rigid : bool
        Remove the least-squares rigid motion of the correction (see module notes).
    g : float
        m/s^2.
    """
    truss = Truss.from_artefact(artefact, rods, materials)
    sols = []
    for cond in (cmm, use):
        loads = mass_loads(truss, artefact.diameters, materials, cond.gravity, g)
        sols.append(solve_truss(truss, cond.supports, loads.forces_n))
    d_cmm, d_use = sols[0].displacements_mm, sols[1].displacements_mm
    corr = d_use - d_cmm
    if remove_rigid:
        corr = remove_rigid_motion(artefact.centres, corr)
    out = Artefact(artefact.ids, artefact.centres + corr, artefact.diameters, artefact.u, artefact.name + "+sag")
    table = pd.DataFrame({"sphere_id": list(artefact.ids)})
    for name, d in (("cmm_", d_cmm), ("use_", d_use), ("", corr)):
        for k, ax in enumerate("xyz"):
            table[f"{name}d{ax}_mm"] = d[:, k]
    table["d_mm"] = np.linalg.norm(corr, axis=1)
    return SagCorrection(out, table, sols[0], sols[1])
