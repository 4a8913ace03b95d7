"""The ``extraction:`` and ``control_points:`` sections of a run configuration.

Sphere candidates, robust fitting and labelling take their settings as mappings of
their own dataclasses' fields (:class:`~fringecal.spheres.candidates.CandidateConfig`,
:class:`~fringecal.spheres.robust.RejectionConfig`,
:class:`~fringecal.spheres.labelling.LabellingConfig`), checked by constructing them,
so a misspelt key fails before any work starts.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

from pydantic import Field, field_validator

from fringecal.config import StrictModel
from fringecal.spheres.candidates import CandidateConfig
from fringecal.spheres.labelling import LabellingConfig
from fringecal.spheres.robust import RejectionConfig

__all__ = ["ExtractionConfig", "ControlPointConfig"]


def _check_dataclass(cls, value: dict, name: str) -> dict:
    try:
        cls(**value)
    except TypeError as err:
        fields = sorted(f.name for f in dataclasses.fields(cls))
        raise ValueError(f"{name}: {err}; known keys: {fields}") from None
    return value


class ExtractionConfig(StrictModel):
    """Sphere candidates, robust fitting and labelling (mappings of their settings)."""

    candidates: dict = Field(default_factory=dict)
    # point noise of the simulated scanners along the normal is ~0.1 mm at 512 px
    rejection: dict = Field(default_factory=lambda: {"noise_mm": 0.1})
    # labelling's tolerances are the prior calibrations' stated uncertainty; LabellingConfig's
    # defaults are sized for customers' priors (centres up to 3 mm RMS off, 0.6 % in scale,
    # plans good to 1 mm / 1 mrad), and each scanner's scale and centre uncertainty are then
    # estimated from its measurements (docs/spheres.md)
    labelling: dict = Field(default_factory=dict)
    use_planned_poses: bool = True
    second_pass_rod_cones: bool = True

    @field_validator("candidates")
    @classmethod
    def _cand(cls, v):

        return _check_dataclass(CandidateConfig, v, "candidates")

    @field_validator("rejection")
    @classmethod
    def _rej(cls, v):


        noise = v.get("noise_mm", RejectionConfig.noise_mm)
        if not (isinstance(noise, (int, float)) and math.isfinite(noise) and noise > 0):
            raise ValueError(f"rejection.noise_mm: must be a finite length > 0 (mm), got {noise!r}")
        return _check_dataclass(RejectionConfig, v, "rejection")

    @field_validator("labelling")
    @classmethod
    def _lab(cls, v):

        return _check_dataclass(LabellingConfig, v, "labelling")


class ControlPointConfig(StrictModel):
    """Control-point selection on each fitted sphere (thesis 6.4: 10 px at 2048 px)."""

    spacing_px: int = Field(3, ge=1)
    rim_px: int = Field(1, ge=0)
    max_incidence_deg: Optional[float] = Field(60.0, gt=0, le=90)
    #: side (px) of the camera pixel's uniform response: the decoded phases are
    #: corrected for its integration over the sphere (thesis chapter 5,
    #: :mod:`fringecal.spheres.pixel_integration`), and in a rig with black boxes the
    #: modelled scanners' ball-bar sightings too (docs/blackbox.md); 0 leaves them as decoded
    pixel_integration_px: float = Field(1.0, ge=0, le=10)
