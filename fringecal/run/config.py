"""The run configuration of ``fringecal run`` (pydantic + YAML): one object from the
command line to every step.

One YAML file describes a whole run: where the measurements come from (``simulate`` a
rig, :class:`~fringecal.simulate.settings.SimulationConfig`; or a recorded ``dataset``
folder) and how each part processes them. Each section is the settings model of the
package that uses it, so a setting keeps its name from the YAML file down to the
function that reads it:

===================  ===================================================================
``decode``           :class:`fringecal.fringe.decode.DecodeSettings`
``extraction``       :class:`fringecal.spheres.settings.ExtractionConfig`
``control_points``   :class:`fringecal.spheres.settings.ControlPointConfig`
``bundle``           :class:`fringecal.calibration.bundle.BundleOptions`
``verification``     :class:`fringecal.verification.settings.VerificationConfig`
``acceptance``       :class:`fringecal.acceptance.standards.AcceptanceConfig`
``runner``           :class:`RunnerConfig`
===================  ===================================================================

Unknown keys anywhere are errors naming the file and the key path; relative paths
resolve against the YAML file's folder. The command line builds one :class:`RunConfig`
(:func:`load_run_config`); the flow, the tasks and the steps receive that object, a
step seeing only the parts it declares (:class:`fringecal.steps.base.Settings`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

from pydantic import Field, model_validator

from fringecal.acceptance.identity import CertificateIdentity
from fringecal.acceptance.standards import AcceptanceConfig
from fringecal.calibration.bundle import BundleOptions
from fringecal.config import (
    ConfigError,
    StrictModel,
    bundled_config,
    configs_dir,
    deep_update,
    load_yaml_model,
    read_yaml_mapping,
    validate_model,
    validate_section,
)
from fringecal.dataset import DATASET_FILE, DatasetConfig
from fringecal.fringe.decode import DecodeSettings
from fringecal.simulate.settings import SimulationConfig
from fringecal.spheres.settings import ControlPointConfig, ExtractionConfig
from fringecal.threads import ThreadPolicy
from fringecal.verification.settings import VerificationConfig

__all__ = ["RunConfig", "RunnerConfig", "load_run_config", "default_run_config_path"]


def default_run_config_path() -> Path:
    """The default run: the simulated thesis rig, ideal profile."""
    return configs_dir() / "run_thesis.yaml"


class RunnerConfig(StrictModel):
    """Where tasks run: bounded threads here, or a Dask cluster through prefect-dask.

    ``cores``: the cores the run may use (None: all the process may run on); with
    ``max_workers`` (step instances at once, at most ``cores``) it sizes the worker
    pool, numba's threads and BLAS together (:mod:`fringecal.threads`).
    """

    kind: Literal["threads", "dask"] = "threads"
    cores: Optional[int] = Field(None, ge=1)
    max_workers: int = Field(2, ge=1)
    dask_address: Optional[str] = None
    dask_workers: int = Field(2, ge=1)


class RunConfig(StrictModel):
    """Everything ``fringecal run`` does: where the measurements come from (``simulate``
    a rig, or a recorded ``dataset`` folder; exactly one) and how they are processed.

    ``reference_scanner`` (the scanner whose frame is the world) comes from the rig or
    the data set's ``dataset.yaml`` unless given here. ``certificate``: the identity
    block of the report's certificate page (customer, cell, serial numbers, reference
    certificates, temperatures, approval; :class:`~fringecal.acceptance.identity.CertificateIdentity`),
    merged over the data set's own; no step reads it.
    """

    name: Optional[str] = None
    simulate: Optional[SimulationConfig] = None
    dataset: Optional[Path] = None
    reference_scanner: Optional[str] = None
    decode: DecodeSettings = Field(default_factory=DecodeSettings)
    extraction: ExtractionConfig = Field(default_factory=ExtractionConfig)
    control_points: ControlPointConfig = Field(default_factory=ControlPointConfig)
    bundle: BundleOptions = Field(default_factory=BundleOptions)
    verification: VerificationConfig = Field(default_factory=VerificationConfig)
    acceptance: AcceptanceConfig = Field(default_factory=AcceptanceConfig)
    runner: RunnerConfig = Field(default_factory=RunnerConfig)
    certificate: Optional[CertificateIdentity] = None

    @model_validator(mode="before")
    @classmethod
    def _one_source(cls, data):
        if isinstance(data, dict):
            if data.get("simulate") is not None and data.get("dataset") is not None:
                raise ValueError("give either simulate (a simulated rig) or dataset (a recorded data set), not both")
            if data.get("simulate") is None and data.get("dataset") is None:
                data = {**data, "simulate": {}}
        return data

    def thread_policy(self, workers: int | None = None) -> ThreadPolicy:
        """The run's :class:`~fringecal.threads.ThreadPolicy` (``workers``: instead of
        ``runner.max_workers``, e.g. from ``--workers``)."""
        return ThreadPolicy.of(self.runner.cores, workers or self.runner.max_workers)

    @property
    def source(self) -> str:
        """``"simulated"`` or ``"dataset"``."""
        return "dataset" if self.dataset is not None else "simulated"




def load_run_config(path: Path | None = None, overrides: dict | None = None, dataset: Path | None = None) -> RunConfig:
    """Resolve a run config: the YAML at ``path`` (default ``configs/run_thesis.yaml``
    unless a data set is given), ``overrides`` merged in, and with ``dataset`` that data
    set as the source (it replaces the file's own source).

    A data set's ``dataset.yaml`` supplies the name, the reference scanner and its
    processing overrides; keys written in the run config take precedence over them.
    """
    if path is None and dataset is None:
        path = default_run_config_path()
    path = None if path is None else bundled_config(path)
    data = read_yaml_mapping(path, "omit --config to run the default configuration "
                                   f"({default_run_config_path().name}), or start from a "
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
        processing = ds.processing.model_dump(exclude_none=True)
        for section, values in processing.items():  # its errors name dataset.yaml, not the run config
            validate_section(values, RunConfig.model_fields[section].annotation, root / DATASET_FILE,
                             f"processing.{section}.")
        data = deep_update(processing, data)
        if ds.certificate is not None:
            data["certificate"] = deep_update(ds.certificate.model_dump(mode="json", exclude_none=True),
                                              data.get("certificate") or {})
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
