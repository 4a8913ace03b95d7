"""The ``simulate:`` section of a run configuration: the simulated data source.

A simulated run renders a rig (``configs/thesis/rig.yaml`` by default) through the
virtual scanner: how each measurement is acquired (:class:`~fringecal.simulate.config.AcquisitionConfig`),
each scanner's prior calibration, where the ball-bar and the acceptance test's objects
stand, which errors the simulated world holds, and objects to measure afterwards.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

from pydantic import Field, field_validator

from fringecal.artefact import load_artefact
from fringecal.config import RigConfig, StrictModel, load_yaml_model, thesis_dir
from fringecal.engineering.corrections import ArtefactCorrections, apply_corrections
from fringecal.simulate.config import AcquisitionConfig
from fringecal.simulate.errors import SimulationErrors
from fringecal.simulate.objects import SimulatedObject

__all__ = ["SimulationConfig", "PriorCalibrationConfig", "SimulatedVerificationConfig", "SimulatedAcceptanceConfig"]


class PriorCalibrationConfig(StrictModel):
    """Each simulated scanner's own (prior) calibration, as from a planar artefact
    (thesis section 6.1): parameters in the scanner's own frame (its camera's), with
    errors of the sizes given here (Gaussian standard deviations; the baseline scale
    uniform in ``scale_error_range``). See :mod:`fringecal.simulate.prior`.

    The defaults are thesis-sized: the thesis's registrations of four sphere centres
    left 0.2-0.5 mm RMS (tables 6-1, 6-4). Real cells can be far worse; the row and
    ring rigs' configs use the documented "real-cell" sizes (centres up to ~3 mm off,
    distances up to 0.6 % short).
    """

    seed: int = 7
    scale_error_range: tuple[float, float] = (0.0, 0.0)
    position_error_mm: float = Field(0.2, ge=0)
    angle_error_rad: float = Field(0.0002, ge=0)
    principal_distance_error_mm: float = Field(0.01, ge=0)
    principal_point_error_mm: float = Field(0.01, ge=0)
    distortion_error_fraction: float = Field(0.1, ge=0)

    @field_validator("scale_error_range")
    @classmethod
    def _range(cls, v):
        if v[0] > v[1] or max(abs(v[0]), abs(v[1])) >= 0.1:
            raise ValueError(f"scale_error_range {list(v)}: need lo <= hi, both within +-0.1")
        return v


class SimulatedVerificationConfig(StrictModel):
    """Where the simulated ball-bar is placed and how it is rendered.

    ``scheme``: ``thesis9`` the nine positions of ``positions`` (thesis table 6-9 by
    default), ``vdi7`` seven positions after VDI/VDE 2634 spanning the thesis's two
    volumes, ``planned`` positions planned for any rig from its measurement volumes
    (:mod:`fringecal.verification.plan`: ``per_pair`` per pair of neighbouring scanners,
    ``per_scanner`` within each scanner's volume where the bar fits). With ``planned``
    only the scanners a position was planned for record it, as an operator would
    trigger them; otherwise every scanner that sees a bar sphere does.
    """

    ballbar: Optional[Path] = None  # default: the rig's ballbar, else configs/thesis/ballbar.csv
    positions: Optional[Path] = None  # default: configs/thesis/ballbar_verification_table6-9.csv
    scheme: Literal["thesis9", "vdi7", "planned"] = "thesis9"
    per_pair: int = Field(3, ge=0)
    per_scanner: int = Field(2, ge=0)
    # camera pixels of the verification measurements (None: as the acquisition); sphere
    # centres of a 50.85 mm ball fitted at 512 px scatter by ~30 um, which would hide
    # the calibration's own error, so the demo verifies at 768 px
    camera_width_px: Optional[int] = Field(None, ge=16)
    seed: int = 99


class SimulatedAcceptanceConfig(StrictModel):
    """The acceptance test's objects in a simulation (VDI/VDE 2634 parts 2 and 3).

    ``standards``: their certificates (default ``configs/thesis/acceptance.yaml``); the
    rendered objects are built exactly to them. Positions are planned per scanner from
    the true rig's measurement volumes (:mod:`fringecal.acceptance.plan`): ``sphere``
    positions of the probing sphere, ``dumbbell`` positions (the guideline's seven:
    four space diagonals and three face diagonals of the volume's box) and ``flat``
    positions of the flat [U: about 10, 7 and 6 in the guideline]. ``enabled: false``
    renders none (the run then has no acceptance test). ``camera_width_px``: as the
    ball-bar's (``simulate.verification.camera_width_px``) when None.
    """

    enabled: bool = True
    standards: Optional[Path] = None
    sphere: int = Field(10, ge=0)
    dumbbell: int = Field(7, ge=0, le=7)
    flat: int = Field(6, ge=0)
    camera_width_px: Optional[int] = Field(None, ge=16)
    seed: int = 98

    def standards_path(self) -> Path:
        return self.standards or thesis_dir() / "acceptance.yaml"


class SimulationConfig(StrictModel):
    """The simulated data source: a rig rendered by the virtual scanner.

    ``artefact_corrections`` (gravity sag between the CMM's supports and the use
    condition, thermal expansion from the CMM's 20 C to ``temperature_c``; see
    ``fringecal.engineering.corrections``) turn the CMM coordinates into the artefact
    the run renders, fits and adjusts against.

    ``objects`` (default none) are objects to measure with the finished calibration
    (:mod:`fringecal.simulate.objects`: a curved ``panel``, the ``artefact`` at a new
    pose); ``fringecal simulate`` writes them into the data set's ``objects/`` folder.
    The simulated run itself does not render them.

    ``outputs`` (scanner -> ``images`` or ``cloud``; default images) makes a scanner a
    black box: it delivers its triangulated points, with their noise, in its own frame
    (its camera's), not fringe images, and has no prior calibration
    (:mod:`fringecal.simulate.black_box`; ``fringecal simulate`` writes its ``.ply``).
    """

    rig: Path = Field(default_factory=lambda: thesis_dir() / "rig.yaml")
    artefact_corrections: Optional["ArtefactCorrections"] = None
    temperature_c: Optional[float] = None
    acquisition: AcquisitionConfig = Field(default_factory=AcquisitionConfig)
    prior: PriorCalibrationConfig = Field(default_factory=PriorCalibrationConfig)
    verification: SimulatedVerificationConfig = Field(default_factory=SimulatedVerificationConfig)
    errors: SimulationErrors = Field(default_factory=SimulationErrors)
    acceptance: SimulatedAcceptanceConfig = Field(default_factory=SimulatedAcceptanceConfig)
    objects: list[SimulatedObject] = Field(default_factory=list)
    outputs: dict[str, Literal["images", "cloud"]] = Field(default_factory=dict)

    def black_boxes(self) -> tuple[str, ...]:
        """The scanners that deliver clouds (``outputs``), in name order."""
        return tuple(sorted(s for s, o in self.outputs.items() if o == "cloud"))

    @field_validator("objects")
    @classmethod
    def _unique_object_names(cls, v):
        names = [o.name for o in v]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"object names must be unique (each is a folder objects/<name>/): {dup}")
        return v

    def rig_config(self) -> RigConfig:
        return load_yaml_model(self.rig, RigConfig)

    def ballbar_path(self) -> Path:
        return self.verification.ballbar or self.rig_config().ballbar or thesis_dir() / "ballbar.csv"

    def positions_path(self) -> Path:
        return self.verification.positions or thesis_dir() / "ballbar_verification_table6-9.csv"

    def artefact(self):
        """The artefact of the run: the CMM definition with the configured corrections."""
        return apply_corrections(load_artefact(self.rig_config().artefact), self.artefact_corrections,
                                 self.temperature_c)
