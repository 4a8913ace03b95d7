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

from pydantic import Field, field_validator, model_validator

from .config import (ConfigError, RigConfig, StrictModel, deep_update, load_yaml_model, package_root,
                     read_yaml_mapping, thesis_dir, validate_model)
from .fringe.decode import DecodeSettings
from .fringe.sequence import FringeSequence
from .simulate.config import RenderConfig
from .simulate.errors import SimulationErrors
from .simulate.objects import SimulatedObject

__all__ = ["RunConfig", "SimulationConfig", "load_run_config", "default_run_config_path", "SequenceConfig",
           "AcquisitionConfig", "PriorCalibrationConfig", "ExtractionConfig", "ControlPointConfig", "BundleConfig",
           "VerificationConfig", "LengthUncertaintyConfig", "SimulatedVerificationConfig", "RunnerConfig", "HexapodStepConfig"]


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
    """Each simulated scanner's own (prior) calibration, as from a planar artefact
    (thesis section 6.1): parameters in the scanner's own frame (its camera's), with
    errors of the sizes given here (Gaussian standard deviations; the baseline scale
    uniform in ``scale_error_range``). See :mod:`fringecal.pipeline.prior`.

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
        from .spheres.candidates import CandidateConfig

        return _check_dataclass(CandidateConfig, v, "candidates")

    @field_validator("rejection")
    @classmethod
    def _rej(cls, v):
        import math

        from .spheres.robust import RejectionConfig

        noise = v.get("noise_mm", RejectionConfig.noise_mm)
        if not (isinstance(noise, (int, float)) and math.isfinite(noise) and noise > 0):
            raise ValueError(f"rejection.noise_mm: must be a finite length > 0 (mm), got {noise!r}")
        return _check_dataclass(RejectionConfig, v, "rejection")

    @field_validator("labelling")
    @classmethod
    def _lab(cls, v):
        from .spheres.labelling import LabellingConfig

        return _check_dataclass(LabellingConfig, v, "labelling")


class ControlPointConfig(StrictModel):
    """Control-point selection on each fitted sphere (thesis 6.4: 10 px at 2048 px)."""

    spacing_px: int = Field(3, ge=1)
    rim_px: int = Field(1, ge=0)
    max_incidence_deg: Optional[float] = Field(60.0, gt=0, le=90)
    #: side (px) of the camera pixel's uniform response: the decoded phases are
    #: corrected for its integration over the sphere (thesis chapter 5,
    #: :mod:`fringecal.spheres.pixel_integration`); 0 leaves them as decoded
    pixel_integration_px: float = Field(1.0, ge=0, le=10)


class BundleConfig(StrictModel):
    """Weights and solver settings of the bundle adjustment (eq. 2-24).

    ``start``: which start values to adjust from (see
    :class:`fringecal.calibration.BundleOptions`). ``volume_diagonal_mm``: the
    measurement volume's diagonal for the one-part-in-N figures (None: the bounding
    box of the control points triangulated with the result).
    """

    gamma1: float = Field(1.0, gt=0)
    gamma2: float = Field(1.0, gt=0)
    robust_loss: Literal["none", "huber", "cauchy"] = "none"
    robust_scale_mm: Optional[float] = Field(None, gt=0, description="robust-loss scale; default from the residuals")
    max_iterations: int = Field(100, ge=1)
    start: Literal["given", "data", "auto", "best"] = "auto"
    volume_diagonal_mm: Optional[float] = Field(None, gt=0)
    #: wild-bootstrap re-adjustments for the calibration's bias and spread
    #: (:mod:`fringecal.calibration.bootstrap`); 0: none, the lengths are then
    #: not corrected for the adjustment's non-linearity
    bootstrap_draws: int = Field(32, ge=0, le=1000)
    bootstrap_seed: int = 0

    def options(self):
        from .calibration.bundle import BundleOptions

        return BundleOptions(max_iterations=self.max_iterations, loss=self.robust_loss,
                             loss_scale_mm=self.robust_scale_mm if self.robust_loss != "none" else None,
                             start=self.start)


class LengthUncertaintyConfig(StrictModel):
    """What the task-specific uncertainty of every measured length takes from outside
    the data (:mod:`fringecal.length_uncertainty`): the artefact's and the bar's
    temperature uncertainty and expansion coefficients, the coverage factor of the
    expanded uncertainty, and the Monte Carlo check (JCGM 101; 0 draws turns it off).

    Defaults: the thesis's carbon-fibre rods expand by 1.9e-6 /K (section 3.4.1, the
    heated ball-bar) and its laboratory held the temperature to about +-0.5 K, taken
    here as a standard uncertainty of 0.5 K (a rectangular +-0.5 K would be 0.29 K;
    0.5 K allows for the artefact lagging the air). ``artefact_u_factor`` multiplies the
    artefact table's own ``u_mm`` (the CMM's standard uncertainty per coordinate); the
    budget states the world it is made for, so a simulation whose artefact is exactly
    its table at 20 C (the ideal profile) is described by a factor and temperature
    uncertainties of 0.
    """

    artefact_u_factor: float = Field(1.0, ge=0)
    artefact_temperature_u_c: float = Field(0.5, ge=0)
    artefact_cte_per_c: float = Field(1.9e-6, ge=-1e-4, le=1e-4)
    ballbar_temperature_u_c: float = Field(0.5, ge=0)
    ballbar_cte_per_c: float = Field(1.9e-6, ge=-1e-4, le=1e-4)
    coverage_factor: float = Field(2.0, gt=0)
    monte_carlo_draws: int = Field(1000, ge=0)
    seed: int = 0


class VerificationConfig(StrictModel):
    """Evaluation of the ball-bar lengths (thesis 6.9.3; VDI/VDE 2634): limit, the
    GUM statement of the certified length, and each length's own uncertainty."""

    mpe_mm: float = Field(0.1, gt=0)
    certificate_u_mm: float = Field(0.0004, ge=0)
    certificate_k: float = Field(2.0, gt=0)
    coverage_factor: float = Field(1.96, gt=0)
    uncertainty: LengthUncertaintyConfig = Field(default_factory=LengthUncertaintyConfig)


class SimulatedVerificationConfig(StrictModel):
    """Where the simulated ball-bar is placed and how it is rendered.

    ``scheme``: ``thesis9`` the nine positions of ``positions`` (thesis table 6-9 by
    default), ``vdi7`` seven positions after VDI/VDE 2634 spanning the thesis's two
    volumes, ``planned`` positions planned for any rig from its measurement volumes
    (:mod:`fringecal.ballbar_plan`: ``per_pair`` per pair of neighbouring scanners,
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


class RunnerConfig(StrictModel):
    """Where tasks run: bounded threads here, or a Dask cluster through prefect-dask."""

    kind: Literal["threads", "dask"] = "threads"
    max_workers: int = Field(2, ge=1)
    dask_address: Optional[str] = None
    dask_workers: int = Field(2, ge=1)


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
        from .artefact import load_artefact
        from .engineering.corrections import apply_corrections

        return apply_corrections(load_artefact(self.rig_config().artefact), self.artefact_corrections,
                                 self.temperature_c)


class RunConfig(StrictModel):
    """Everything ``fringecal run`` does: where the measurements come from (``simulate``
    a rig, or a recorded ``dataset`` folder; exactly one) and how they are processed.

    ``reference_scanner`` (the scanner whose frame is the world) comes from the rig or
    the data set's ``dataset.yaml`` unless given here.
    """

    name: Optional[str] = None
    simulate: Optional[SimulationConfig] = None
    dataset: Optional[Path] = None
    reference_scanner: Optional[str] = None
    decode: DecodeSettings = Field(default_factory=DecodeSettings)
    extraction: ExtractionConfig = Field(default_factory=ExtractionConfig)
    control_points: ControlPointConfig = Field(default_factory=ControlPointConfig)
    bundle: BundleConfig = Field(default_factory=BundleConfig)
    verification: VerificationConfig = Field(default_factory=VerificationConfig)
    acceptance: "AcceptanceConfig" = Field(default_factory=lambda: AcceptanceConfig())
    runner: RunnerConfig = Field(default_factory=RunnerConfig)

    @model_validator(mode="before")
    @classmethod
    def _one_source(cls, data):
        if isinstance(data, dict):
            if data.get("simulate") is not None and data.get("dataset") is not None:
                raise ValueError("give either simulate (a simulated rig) or dataset (a recorded data set), not both")
            if data.get("simulate") is None and data.get("dataset") is None:
                data = {**data, "simulate": {}}
        return data

    @property
    def source(self) -> str:
        """``"simulated"`` or ``"dataset"``."""
        return "dataset" if self.dataset is not None else "simulated"


from .acceptance.standards import AcceptanceConfig  # noqa: E402  (after the forward reference)
from .engineering.corrections import ArtefactCorrections  # noqa: E402  (after the forward reference)

SimulationConfig.model_rebuild()
RunConfig.model_rebuild()


def load_run_config(path: Path | None = None, overrides: dict | None = None, dataset: Path | None = None) -> RunConfig:
    """Resolve a run config: the YAML at ``path`` (default ``configs/run_thesis.yaml``
    unless a data set is given), ``overrides`` merged in, and with ``dataset`` that data
    set as the source (it replaces the file's own source).

    A data set's ``dataset.yaml`` supplies the name, the reference scanner and its
    processing overrides; keys written in the run config take precedence over them.
    """
    from .dataset import DATASET_FILE, DatasetConfig

    if path is None and dataset is None:
        path = default_run_config_path()
    path = None if path is None else Path(path)
    data = read_yaml_mapping(path, "omit --config to run the default configuration "
                                   f"({default_run_config_path().relative_to(package_root())}), or start from a "
                                   "copy of it") if path is not None else {}
    base = path.parent if path is not None else Path.cwd()
    source = path if path is not None else "run configuration"
    if overrides:
        data = deep_update(data, overrides)
    if data.get("simulate") is not None and data.get("dataset") is not None:
        raise ConfigError(f"{source}: give either simulate (a simulated rig) or dataset (a recorded data set), "
                          "not both")
    if dataset is not None:
        data = {k: v for k, v in data.items() if k != "simulate"}
        data["dataset"] = str(Path(dataset).resolve())
    if data.get("dataset") is not None:
        root = (base / str(data["dataset"])).resolve()
        ds = load_yaml_model(root / DATASET_FILE, DatasetConfig) if root.is_dir() else None
        if ds is None:
            raise ConfigError(f"{root}: no such data set folder")
        data = deep_update(ds.processing.model_dump(exclude_none=True), data)
        data.setdefault("name", ds.name)
        data.setdefault("reference_scanner", ds.reference_scanner)
    cfg = validate_model(data, RunConfig, source, base)
    if cfg.simulate is not None:
        try:
            rig = cfg.simulate.rig_config()
        except ConfigError as err:
            raise ConfigError(f"{source}: rig {cfg.simulate.rig}: {err}") from None
        cfg = cfg.model_copy(update={"name": cfg.name or rig.name,
                                     "reference_scanner": cfg.reference_scanner or rig.reference_scanner})
    return cfg
