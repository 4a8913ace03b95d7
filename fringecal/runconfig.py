"""The run configuration of ``fringecal run`` (pydantic + YAML).

One YAML file describes a whole run: the rig data set (``configs/thesis/rig.yaml``
by default), how measurements are acquired (simulated here), decoded, turned into
sphere fits, control points and a calibration, and how the result is verified.
Unknown keys anywhere are errors naming the file and the key path; relative paths
resolve against the YAML file's folder.

Step settings that live as dataclasses in fringecal (sphere candidates, robust
fitting, labelling) are given as mappings and checked by constructing them, so a
misspelt key fails before any work starts.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal, Optional

from pydantic import Field, field_validator

from .config import ConfigError, RigConfig, StrictModel, load_yaml_model, package_root, thesis_dir
from .fringe.decode import DecodeSettings
from .fringe.sequence import FringeSequence
from .simulate.config import RenderConfig

__all__ = ["RunConfig", "load_run_config", "default_run_config_path", "SequenceConfig", "AcquisitionConfig",
           "PriorCalibrationConfig", "ExtractionConfig", "ControlPointConfig", "BundleConfig",
           "VerificationConfig", "RunnerConfig", "HexapodStepConfig"]


def default_run_config_path() -> Path:
    return package_root() / "configs" / "run_thesis.yaml"


class SequenceConfig(StrictModel):
    """The projected fringe sequence (thesis: 7 counts x 7 steps x 2 orientations)."""

    fringe_counts: list[int] = Field(default_factory=lambda: [64, 63, 62, 60, 56, 48, 32])
    n_steps: int = 7
    orientations: list[str] = Field(default_factory=lambda: ["x", "y"])

    def build(self) -> FringeSequence:
        return FringeSequence(tuple(self.fringe_counts), self.n_steps, tuple(self.orientations))


class HexapodStepConfig(StrictModel):
    """Move the (simulated) hexapod before each pose; the reached pose is what is rendered."""

    enabled: bool = True
    config: Optional[Path] = None  # default: configs/hexapod/thesis_platform.yaml
    url: str = "hexsim://acquisition"


class AcquisitionConfig(StrictModel):
    """Simulated acquisition of every (pose, scanner) measurement."""

    camera_width_px: int = Field(512, ge=16)
    render: RenderConfig = Field(default_factory=RenderConfig)
    sequence: SequenceConfig = Field(default_factory=SequenceConfig)
    seed: int = 2026
    backdrop_mm: Optional[float] = None
    hexapod: HexapodStepConfig = Field(default_factory=HexapodStepConfig)
    store_frames: bool = False


class PriorCalibrationConfig(StrictModel):
    """Each simulated scanner's own (prior) calibration, as the thesis had from a planar
    artefact (section 6.1): parameters in the scanner's own frame, with errors.

    The reference scanner's frame is the world; another scanner's frame is the world
    moved by ``frame_offset_mm`` along x and turned by ``frame_rotation_rad`` about y.
    A scanner's own calibration fixes its camera-projector geometry well, so the errors
    are small; they are sized so the prior point clouds are about as good as the
    thesis's, whose registrations of four sphere centres left 0.2-0.5 mm RMS (tables
    6-1, 6-4). The non-reference scanners' placement in the world is then unknown
    until the artefact links them.
    """

    seed: int = 7
    frame_offset_mm: float = 1500.0
    frame_rotation_rad: float = 0.02
    position_error_mm: float = 0.2
    angle_error_rad: float = 0.0002
    principal_distance_error_mm: float = 0.01
    principal_point_error_mm: float = 0.01
    keep_distortion: bool = True


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
    # centres from prior (uncalibrated) scanners are good to ~0.15 mm (thesis: 0.2-0.5 mm)
    labelling: dict = Field(default_factory=lambda: {"centre_u_mm": 0.15, "scale_tol": 0.002})
    use_planned_poses: bool = True
    second_pass_rod_cones: bool = True

    @field_validator("candidates")
    @classmethod
    def _cand(cls, v):
        from .spheres.candidates import CandidateConfig

        return _check_dataclass(CandidateConfig, v, "candidates")

    @field_validator("rejection")
    @classmethod
    def _rej(cls, v):
        from .spheres.robust import RejectionConfig

        return _check_dataclass(RejectionConfig, v, "rejection")

    @field_validator("labelling")
    @classmethod
    def _lab(cls, v):
        from .spheres.labelling import LabellingConfig

        return _check_dataclass(LabellingConfig, v, "labelling")

    def candidate_config(self):
        from .spheres.candidates import CandidateConfig

        return CandidateConfig(**self.candidates)

    def rejection_config(self):
        from .spheres.robust import RejectionConfig

        return RejectionConfig(**self.rejection)

    def labelling_config(self):
        from .spheres.labelling import LabellingConfig

        return LabellingConfig(**self.labelling)


class ControlPointConfig(StrictModel):
    """Control-point selection on each fitted sphere (thesis 6.4: 10 px at 2048 px)."""

    spacing_px: int = Field(3, ge=1)
    rim_px: int = Field(1, ge=0)
    max_incidence_deg: Optional[float] = Field(60.0, gt=0, le=90)


class BundleConfig(StrictModel):
    """Weights and solver settings of the bundle adjustment (eq. 2-24)."""

    gamma1: float = Field(1.0, gt=0)
    gamma2: float = Field(1.0, gt=0)
    robust_loss: Literal["none", "huber", "cauchy"] = "none"
    robust_scale_mm: float = Field(0.1, gt=0)
    max_iterations: int = Field(100, ge=1)


class VerificationConfig(StrictModel):
    """Ball-bar verification (thesis 6.9.3; VDI/VDE 2634)."""

    ballbar: Optional[Path] = None  # default: configs/thesis/ballbar.csv
    positions: Optional[Path] = None  # default: configs/thesis/ballbar_verification_table6-9.csv
    scheme: Literal["thesis9", "vdi7"] = "thesis9"
    # camera pixels of the verification measurements (None: as the acquisition); sphere
    # centres of a 50.85 mm ball fitted at 512 px scatter by ~30 um, which would hide
    # the calibration's own error, so the demo verifies at 768 px
    camera_width_px: Optional[int] = Field(None, ge=16)
    volume_diagonal_mm: Optional[float] = Field(None, gt=0)
    mpe_mm: float = Field(0.1, gt=0)
    certificate_u_mm: float = Field(0.0004, ge=0)
    certificate_k: float = Field(2.0, gt=0)
    coverage_factor: float = Field(1.96, gt=0)
    seed: int = 99


class RunnerConfig(StrictModel):
    """Where tasks run: bounded threads here, or a Dask cluster through prefect-dask."""

    kind: Literal["threads", "dask"] = "threads"
    max_workers: int = Field(2, ge=1)
    dask_address: Optional[str] = None
    dask_workers: int = Field(2, ge=1)


class RunConfig(StrictModel):
    """Everything ``fringecal run`` does.

    ``artefact_corrections`` (gravity sag between the CMM's supports and the use
    condition, thermal expansion from the CMM's 20 C to ``temperature_c``; see
    ``fringecal.engineering.corrections``) turn the CMM coordinates into the artefact
    the run uses everywhere (and, when simulated, renders).
    """

    name: str = "thesis"
    rig: Path = Field(default_factory=lambda: thesis_dir() / "rig.yaml")
    artefact_corrections: Optional["ArtefactCorrections"] = None
    temperature_c: Optional[float] = None
    acquisition: AcquisitionConfig = Field(default_factory=AcquisitionConfig)
    prior: PriorCalibrationConfig = Field(default_factory=PriorCalibrationConfig)
    decode: DecodeSettings = Field(default_factory=DecodeSettings)
    extraction: ExtractionConfig = Field(default_factory=ExtractionConfig)
    control_points: ControlPointConfig = Field(default_factory=ControlPointConfig)
    bundle: BundleConfig = Field(default_factory=BundleConfig)
    verification: VerificationConfig = Field(default_factory=VerificationConfig)
    runner: RunnerConfig = Field(default_factory=RunnerConfig)

    def rig_config(self) -> RigConfig:
        return load_yaml_model(self.rig, RigConfig)

    def artefact(self):
        """The artefact of the run: the CMM definition with the configured corrections."""
        from .artefact import load_artefact
        from .engineering.corrections import apply_corrections

        return apply_corrections(load_artefact(self.rig_config().artefact), self.artefact_corrections,
                                 self.temperature_c)


from .engineering.corrections import ArtefactCorrections  # noqa: E402  (after RunConfig's forward reference)

RunConfig.model_rebuild()


def load_run_config(path: Path | None = None, overrides: dict | None = None) -> RunConfig:
    """Load a run config (default ``configs/run_thesis.yaml``); ``overrides`` are merged in."""
    path = Path(path) if path is not None else default_run_config_path()
    cfg = load_yaml_model(path, RunConfig, overrides)
    try:
        cfg.rig_config()
    except ConfigError as err:
        raise ConfigError(f"{path}: rig {cfg.rig}: {err}") from None
    return cfg
