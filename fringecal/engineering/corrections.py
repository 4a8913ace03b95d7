"""Optional artefact corrections for a calibration config: gravity sag and temperature.

A calibration config can carry an ``artefact_corrections`` block of this model::

    artefact_corrections:
      sag:
        rods: rods.csv
        materials: materials.yaml          # default: the thesis's
        cmm_supports: "5:xyz,1:yz,14:z"
        cmm_gravity: [0, 0, -1]
        use_supports: "5:xyz,1:yz,14:z"
        use_gravity: [0, 0, -1]            # or per pose: apply_corrections(use_gravity=...)
      thermal:
        cte_per_c: 1.9e-6
        reference_c: 20.0

and :func:`apply_corrections` turns the CMM artefact into the one to use at a
measurement temperature and gravity direction. Sag is applied first (its model
uses the CMM geometry), then the isotropic thermal scaling; the two commute to
first order.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from pydantic import Field

from fringecal.artefact import Artefact, load_rods
from fringecal.config import StrictModel
from fringecal.engineering.materials import load_materials
from fringecal.engineering.sag import SupportCondition, gravity_sag_correction
from fringecal.engineering.thermal import DEFAULT_CTE_PER_C, REFERENCE_TEMPERATURE_C, compensate_temperature

__all__ = ["SagSettings", "ThermalSettings", "ArtefactCorrections", "apply_corrections"]

_THESIS_SUPPORTS = "5:xyz,1:yz,14:z"


class SagSettings(StrictModel):
    rods: Path
    materials: Optional[Path] = None
    cmm_supports: str = _THESIS_SUPPORTS
    cmm_gravity: tuple[float, float, float] = (0.0, 0.0, -1.0)
    use_supports: str = _THESIS_SUPPORTS
    use_gravity: tuple[float, float, float] = (0.0, 0.0, -1.0)
    remove_rigid: bool = True


class ThermalSettings(StrictModel):
    cte_per_c: float = DEFAULT_CTE_PER_C
    u_cte_per_c: float = Field(default=0.0, ge=0)
    reference_c: float = REFERENCE_TEMPERATURE_C
    centre: Optional[tuple[float, float, float]] = None


class ArtefactCorrections(StrictModel):
    sag: Optional[SagSettings] = None
    thermal: Optional[ThermalSettings] = None


def apply_corrections(artefact: Artefact, corrections: ArtefactCorrections | None,
                      temperature_c: float | None = None, use_gravity=None) -> Artefact:
    """The artefact for one measurement; unchanged where a correction is absent.

    Parameters
    ----------
    artefact : Artefact
        CMM coordinates.
    corrections : ArtefactCorrections or None
    temperature_c : float, optional
        Temperature recorded with the acquisition; no thermal correction without it.
    use_gravity : array_like, shape (3,), optional
        Gravity in the artefact frame for this measurement (e.g. from its pose by
        :func:`.sag.gravity_in_artefact_frame`), overriding ``sag.use_gravity``.
    """
    if corrections is None:
        return artefact
    out = artefact
    if corrections.sag is not None:
        s = corrections.sag
        rods = load_rods(s.rods, artefact)
        use = SupportCondition(s.use_supports, s.use_gravity if use_gravity is None else use_gravity)
        out = gravity_sag_correction(out, rods, load_materials(s.materials),
                                     SupportCondition(s.cmm_supports, s.cmm_gravity), use,
                                     remove_rigid=s.remove_rigid).artefact
    if corrections.thermal is not None and temperature_c is not None:
        t = corrections.thermal
        out = compensate_temperature(out, temperature_c, t.cte_per_c, t.reference_c, t.centre,
                                     u_cte_per_c=t.u_cte_per_c)
    return out
