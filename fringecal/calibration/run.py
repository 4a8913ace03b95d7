"""The ``fringecal calibrate --run RUN_DIR`` step without Prefect: read, adjust, write.

Inputs (see the README's RUN_DIR contract): ``artefact.csv``, ``tables/control_points.csv``,
``tables/poses_initial.csv``, ``tables/sensors_initial.csv`` and optionally
``calibrate.yaml`` (:class:`CalibrateConfig`). Outputs: :data:`.results.OUTPUT_FILES`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

from pydantic import Field

from schemas import ControlPointsTable, PosePlanTable, read_table

from ..artefact import load_artefact
from ..config import StrictModel, load_yaml_model
from ..rig import load_rig
from .bundle import BundleOptions, BundleResult, bundle_adjust
from .model import BundleProblem
from .results import write_outputs

__all__ = ["CalibrateConfig", "RUN_INPUTS", "load_config", "load_problem", "calibrate_run"]

#: input files of a calibration run, relative to the run directory
RUN_INPUTS = {
    "artefact": "artefact.csv",
    "control_points": "tables/control_points.csv",
    "poses": "tables/poses_initial.csv",
    "sensors": "tables/sensors_initial.csv",
    "config": "calibrate.yaml",
}


class CalibrateConfig(StrictModel):
    """Options of ``calibrate.yaml`` (all optional)."""

    gamma1: float = Field(1.0, gt=0, description="weight of the epsilon-1 term of F")
    gamma2: float = Field(1.0, gt=0, description="weight of the epsilon-2 term of F")
    robust_loss: Literal["none", "huber", "cauchy"] = "none"
    robust_scale_mm: Optional[float] = Field(None, gt=0, description="robust-loss scale; default from the residuals")
    reference_scanner: Optional[str] = None
    max_iterations: int = Field(100, ge=1)
    start: Literal["given", "data", "auto", "best"] = "auto"
    volume_diagonal_mm: Optional[float] = Field(None, gt=0, description="for the one-part-in-N figure")

    def options(self) -> BundleOptions:
        return BundleOptions(max_iterations=self.max_iterations, loss=self.robust_loss,
                             loss_scale_mm=self.robust_scale_mm, start=self.start)


def load_config(run_dir) -> CalibrateConfig:
    path = Path(run_dir) / RUN_INPUTS["config"]
    return load_yaml_model(path, CalibrateConfig) if path.exists() else CalibrateConfig()


def load_problem(run_dir, config: CalibrateConfig | None = None) -> BundleProblem:
    """Read and check every input of a run; one clear error naming file, line and column."""
    run_dir = Path(run_dir)
    config = load_config(run_dir) if config is None else config
    paths = {k: run_dir / v for k, v in RUN_INPUTS.items()}
    missing = [str(p) for k, p in paths.items() if k != "config" and not p.exists()]
    if missing:
        raise FileNotFoundError(f"calibration inputs missing: {', '.join(missing)}")
    artefact = load_artefact(paths["artefact"])
    rig = load_rig(paths["sensors"])
    if config.reference_scanner is not None:
        names = [s.name for s in rig.scanners]
        if config.reference_scanner not in names:
            from ..config import ConfigError

            raise ConfigError(f"{paths['config']}: reference_scanner {config.reference_scanner!r} is not one of "
                              f"the scanners in {paths['sensors']} ({names})")
        rig = load_rig(paths["sensors"], reference=config.reference_scanner)
    cp = read_table(paths["control_points"], ControlPointsTable)
    poses = read_table(paths["poses"], PosePlanTable)
    return BundleProblem.from_tables(rig, artefact, cp, poses, config.gamma1, config.gamma2,
                                     source=str(paths["control_points"]), poses_source=str(paths["poses"]))


def calibrate_run(run_dir) -> tuple[BundleResult, dict]:
    """Adjust the run's inputs and write its outputs; returns the result and output paths."""
    config = load_config(run_dir)
    problem = load_problem(run_dir, config)
    result = bundle_adjust(problem, config.options())
    return result, write_outputs(result, run_dir, config.volume_diagonal_mm)
