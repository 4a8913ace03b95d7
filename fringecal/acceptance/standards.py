"""The calibrated test objects of the acceptance test (VDI/VDE 2634 parts 2 and 3) and
its settings.

A cell is accepted with four objects, each with a calibration certificate:

* a **sphere** (probing errors P_F and P_S): its calibrated diameter, the diameter's
  standard uncertainty and its form deviation;
* a **dumbbell** (sphere-spacing error SD inside one scanner's volume): two spheres
  of one diameter at a calibrated centre distance;
* the **ball-bar** (length measurement error E across scanners): the verification
  bar of ``ballbar.csv``, measured at the verification positions;
* a **flat** (flatness measurement error F): its size and calibrated flatness.

The certificate of a real cell's objects is ``verification/acceptance/standards.yaml``
of the data set (:class:`AcceptanceStandards`); a simulation renders the objects of
``simulate.acceptance.standards`` (``configs/thesis/acceptance.yaml`` by default) as
built exactly to their certificates.

Settings whose detail the guideline leaves to the user or that could not be confirmed
from a readable copy of it (REFERENCES.md marks them) are fields of
:class:`AcceptanceConfig`, never constants in code: the outlier fraction that may be
discarded before taking the ranges P_F and F, the limits (MPE) of every parameter and
the coverage factor of the expanded uncertainties.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
from pydantic import Field, field_validator

from fringecal.artefact import Artefact
from fringecal.config import StrictModel, load_yaml_model

__all__ = ["SphereStandard", "DumbbellStandard", "FlatStandard", "AcceptanceStandards", "AcceptanceLimits",
           "ScannerSpecification", "AcceptanceConfig", "load_standards", "PARAMETERS", "STANDARDS_FILE"]

#: Name of the certificate file of a data set's ``verification/acceptance/`` folder.
STANDARDS_FILE = "standards.yaml"

#: The quality parameters as VDI/VDE 2634 writes them, with what each is.
PARAMETERS = {
    "P_F": "probing error form",
    "P_S": "probing error size",
    "SD": "sphere-spacing error",
    "E": "length measurement error",
    "F": "flatness measurement error",
}


class SphereStandard(StrictModel):
    """The calibrated sphere (mm): diameter, its standard uncertainty and the sphere's
    form deviation (peak to valley, from its certificate)."""

    diameter_mm: float = Field(gt=0)
    diameter_u_mm: float = Field(0.001, ge=0)
    form_mm: float = Field(0.002, ge=0)


class DumbbellStandard(StrictModel):
    """Two spheres of ``diameter_mm`` at the calibrated centre distance ``length_mm``
    (with its standard uncertainty), joined by a rod of ``rod_diameter_mm``."""

    length_mm: float = Field(gt=0)
    length_u_mm: float = Field(0.001, ge=0)
    diameter_mm: float = Field(gt=0)
    rod_diameter_mm: float = Field(20.0, gt=0)

    def artefact(self):
        """The dumbbell as an :class:`~fringecal.artefact.Artefact` with spheres ``A`` and
        ``B`` on its x axis (what the ball-bar measurement code takes)."""

        return Artefact(("A", "B"), np.array([[0.0, 0.0, 0.0], [self.length_mm, 0.0, 0.0]]),
                        np.array([self.diameter_mm, self.diameter_mm]))


class FlatStandard(StrictModel):
    """A rectangular flat (mm): its measured face is ``length_mm`` x ``width_mm``, with
    the calibrated flatness deviation (peak to valley) and its standard uncertainty."""

    length_mm: float = Field(gt=0)
    width_mm: float = Field(gt=0)
    thickness_mm: float = Field(20.0, gt=0)
    flatness_mm: float = Field(0.003, ge=0)
    flatness_u_mm: float = Field(0.001, ge=0)


class AcceptanceStandards(StrictModel):
    """The certificates of the acceptance objects; an object left out is not tested."""

    sphere: Optional[SphereStandard] = None
    dumbbell: Optional[DumbbellStandard] = None
    flat: Optional[FlatStandard] = None


def load_standards(path) -> AcceptanceStandards:
    """Read a ``standards.yaml`` (errors name the file and the key)."""
    return load_yaml_model(Path(path), AcceptanceStandards)


class AcceptanceLimits(StrictModel):
    """Maximum permissible errors (mm) of the quality parameters; None: not limited
    (the value is reported, its verdict is the uncertainty zone).

    The defaults are placeholders of no specification; a cell states its scanners'
    specification (``acceptance.specification`` with these limits), as the demo does in
    ``configs/run_thesis.yaml`` (docs/acceptance.md).
    """

    P_F: Optional[float] = Field(0.5, gt=0)
    P_S: Optional[float] = Field(0.1, gt=0)
    SD: Optional[float] = Field(0.1, gt=0)
    E: Optional[float] = Field(0.1, gt=0)
    F: Optional[float] = Field(0.5, gt=0)


class ScannerSpecification(StrictModel):
    """The scanner specification the acceptance test checks the cell against, beside its
    MPEs (:class:`AcceptanceLimits`): what it is (``name``: a data sheet, a model and
    its options) and its specified measuring volume.

    ``depth_range_mm`` (near, far): the measuring volume as a range of depths along
    each scanner's camera axis (its camera frame's z, mm), over the field both the
    camera and the projector see. The MPEs hold inside it: a position whose object lies
    outside (the sphere's or a dumbbell sphere's centre, the flat's centroid, at the
    calibrated camera's depth) is listed as not judged, never part of a verdict, and a
    simulation places its objects inside it. None: the volume the calibration covered.
    """

    name: Optional[str] = None
    depth_range_mm: Optional[tuple[float, float]] = None

    @field_validator("depth_range_mm")
    @classmethod
    def _near_before_far(cls, v):
        if v is not None and not 0 < v[0] < v[1]:
            raise ValueError(f"depth_range_mm {list(v)}: need 0 < near < far (mm along the camera axis)")
        return v

    def contains(self, depth_mm: float) -> bool:
        """Whether a camera depth (mm) lies in the specified measuring volume (always,
        without one; never for NaN).

        >>> ScannerSpecification(depth_range_mm=(2300, 3000)).contains(2999.5), ScannerSpecification().contains(9e9)
        (True, True)
        """
        if self.depth_range_mm is None:
            return True
        return bool(self.depth_range_mm[0] <= depth_mm <= self.depth_range_mm[1])


class AcceptanceConfig(StrictModel):
    """How the acceptance test evaluates (``acceptance`` of a run config).

    ``exclude_fraction``: the fraction of points of one sphere or flat measurement
    that may be discarded as outliers before the ranges P_F and F are taken (0.3 %
    after the guideline [U]; half from each end of the residuals). ``coverage_factor``
    expands the standard uncertainties (k = 2). ``max_incidence_deg``: points of a
    sphere seen more obliquely than this (angle between the line of sight and the
    fitted normal) are not part of the probed surface [U], as the calibration does.
    ``specification``: the scanner specification whose MPEs ``limits`` are, with its
    measuring volume (:class:`ScannerSpecification`).
    """

    enabled: bool = True
    specification: ScannerSpecification = Field(default_factory=ScannerSpecification)
    limits: AcceptanceLimits = Field(default_factory=AcceptanceLimits)
    exclude_fraction: float = Field(0.003, ge=0, lt=0.5)
    coverage_factor: float = Field(2.0, gt=0)
    max_incidence_deg: float = Field(70.0, gt=0, le=90)
