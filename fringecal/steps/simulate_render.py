"""Simulated source, step 3: render, decode and store every calibration measurement.

Each (measurement, scanner) store is rendered with the true scanner looking at the
artefact where the hexapod put it (``truth/poses.csv``), decoded like any recorded
stack, and written to ``measurements/<id>.zarr``; the renderer's per-pixel truth goes
to ``truth/measurements/<id>.zarr``. The key of one store holds only its own pose
row, so adding a pose renders only the new measurements.
"""

from __future__ import annotations

import logging

from ..acquisition import frames_from_rows, simulate_measurement
from ..artefact import Artefact
from ..rundir import RunDir
from ..simulate.scenes import ArtefactHardware, artefact_scene
from .base import Rows, Settings, Step, store_fields, store_row, stores_of_kind

__all__ = ["SimulateRender", "ACQUISITION_SETTINGS", "hardware_file", "log_summary"]

log = logging.getLogger(__name__)

#: What the rendering of a store depends on besides its scene and scanner.
ACQUISITION_SETTINGS = ("simulate.acquisition.render", "simulate.acquisition.sequence",
                        "simulate.acquisition.seed", "simulate.acquisition.backdrop_mm",
                        "simulate.acquisition.store_frames", "decode")


def hardware_file(cfg: Settings):
    """The materials file of the rig (tube and end-cap sizes; the thesis's by default)."""
    from ..config import RigConfig, load_yaml_model, thesis_dir

    return load_yaml_model(cfg.simulate.rig, RigConfig).materials or thesis_dir() / "materials.yaml"


def log_summary(summary: dict) -> None:
    log.info("%s: render %.1f s, decode + store %.1f s, %.1f %% valid", summary["measurement"], summary["render_s"],
             summary["decode_store_s"], 100 * summary["valid_fraction"])


class SimulateRender(Step):
    name = "simulate-render"
    title = "render measurements"
    settings = ACQUISITION_SETTINGS
    locations = ("simulate.rig",)
    modules = ("fringecal.acquisition.measure", "fringecal.simulate")

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return stores_of_kind(rd, "artefact")

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        row = store_fields(rd, item)
        return [store_row(rd, item), Rows(rd.truth.poses, {"measurement": row["pose"]}), rd.truth.sensors,
                rd.truth.artefact, rd.rods, hardware_file(cfg)]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.store(item), rd.truth.store(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        row = store_fields(rd, item)
        T = frames_from_rows(Rows(rd.truth.poses, {"measurement": row["pose"]}).load())[row["pose"]]
        artefact: Artefact = rd.truth.artefact.load()
        rods = rd.rods.load(artefact) if rd.rods.exists() else None
        scene = artefact_scene(artefact, rods, T, ArtefactHardware.from_materials(hardware_file(cfg)))
        scanner = rd.truth.sensors.load().scanner(row["scanner"])
        acq = cfg.simulate.acquisition
        result = simulate_measurement(item, scanner, scene, acq, cfg.decode, rd.store(item).path,
                                      rd.truth.store(item).path, {"pose": row["pose"], "kind": "artefact"})
        log_summary(result.summary)
