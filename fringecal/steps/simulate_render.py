"""Simulated source, step 3: render, decode and store every calibration measurement.

Each (measurement, scanner) store is rendered with the true scanner looking at the
artefact as built where the hexapod put it (``truth/poses.csv``), decoded like any
recorded stack, and written to ``measurements/<id>.zarr``; the renderer's per-pixel
truth goes to ``truth/measurements/<id>.zarr``. The key of one store holds only its
own pose row, so adding a pose renders only the new measurements.

The unmodelled errors of ``simulate.errors`` (:mod:`fringecal.simulate.world`) are
keyed per consumer: the render switches (:data:`RENDER_SWITCHES`) by every rendered
store, the session drift (:data:`SESSION_SWITCHES`) by the calibration stores only,
which then also key the poses acquired before their own (the drift is a random walk
over the acquisition order), and the thin prism the rig's sensors file (its pixels).
"""

from __future__ import annotations

import logging

from fringecal.config import RigConfig, load_yaml_model, thesis_dir
from fringecal.frames import frames_from_rows
from fringecal.rundir import RunDir, TableFile
from fringecal.scancloud import write_cloud_store
from fringecal.simulate.black_box import store_points
from fringecal.simulate.config import AcquisitionConfig
from fringecal.simulate.errors import RENDER_SWITCHES, SESSION_SWITCHES, errors_subset, switch_settings
from fringecal.simulate.measurement import simulate_measurement
from fringecal.simulate.scenes import ArtefactHardware, Scene, artefact_scene
from fringecal.simulate.world import drifted_scanner, native_formats, render_errors, session_displacement
from fringecal.store import store_attributes
from fringecal.steps.base import (Rows, Settings, Step, Value, scanner_ripple_read, store_fields,
                                   store_row, stores_of_kind)

__all__ = ["SimulateRender", "RenderStores", "ACQUISITION_SETTINGS", "hardware_file"]

log = logging.getLogger(__name__)

#: What the rendering of a store depends on besides its scene and scanner.
ACQUISITION_SETTINGS = ("simulate.acquisition.render", "simulate.acquisition.sequence",
                        "simulate.acquisition.seed", "simulate.acquisition.backdrop_mm",
                        "simulate.acquisition.store_frames", "decode", "simulate.outputs")


def hardware_file(cfg: Settings):
    """The materials file of the rig (tube and end-cap sizes; the thesis's by default)."""

    return load_yaml_model(cfg.simulate.rig, RigConfig).materials or thesis_dir() / "materials.yaml"


def sensors_file(cfg: Settings):
    """The rig's sensors file (its native formats size the thin-prism error)."""

    return load_yaml_model(cfg.simulate.rig, RigConfig).sensors


class RenderStores(Step):
    """Render, decode and store the acquisition stores of one ``kind``; subclasses say
    where the scene stands, what it holds and how the scanner records it."""

    kind: str
    settings = ACQUISITION_SETTINGS + switch_settings(RENDER_SWITCHES)
    locations = ("simulate.rig",)
    modules = ("fringecal.simulate.measurement", "fringecal.simulate")

    def placements(self, rd: RunDir) -> TableFile:
        """The table of ``T_world_<object>`` per measurement or position."""
        raise NotImplementedError

    def objects(self, rd: RunDir) -> list:
        """The files of the scene's objects."""
        raise NotImplementedError

    def scene(self, rd: RunDir, T, hardware: ArtefactHardware) -> Scene:
        raise NotImplementedError

    def recording(self, rd: RunDir, cfg: Settings, scanner: str, pose: str):
        """The scanner (true sensors) and the acquisition settings it records ``pose`` with."""
        acq = cfg.simulate.acquisition
        return rd.truth.sensors.load().scanner(scanner), AcquisitionConfig(
            render=acq.render, sequence=acq.sequence, seed=acq.seed, backdrop_mm=acq.backdrop_mm,
            store_frames=acq.store_frames)

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return stores_of_kind(rd, self.kind)

    def _placement(self, rd: RunDir, item: str) -> Rows:
        return Rows(self.placements(rd), {"measurement": store_fields(rd, item)["pose"]})

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        prism = [sensors_file(cfg)] if cfg.simulate.errors.thin_prism_corner_px else []
        return [store_row(rd, item), self._placement(rd, item), rd.truth.sensors, *self.objects(rd),
                hardware_file(cfg), *prism, *self._scanner_ripple(rd, cfg, item)]

    def _scanner_ripple(self, rd: RunDir, cfg: Settings, item: str) -> list:
        """The scanner's phase ripple from its calibration stores, which corrects a stack
        too small for a fit of its own (none for the calibration stores themselves)."""
        if self.kind == "artefact":
            return []
        return [scanner_ripple_read(rd, store_fields(rd, item)["scanner"], cfg.simulate.acquisition.sequence.build())]

    def errors(self, cfg: Settings, scanner, T, scene: Scene):
        """The unmodelled errors of one store (None: the ideal renderer)."""
        e = errors_subset(cfg.simulate.errors, RENDER_SWITCHES)
        native = native_formats(sensors_file(cfg)) if e.thin_prism_corner_px else None
        return render_errors(e, scanner, T, self.kind, scene.sphere_ids, native)

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.store(item), rd.truth.store(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        row = store_fields(rd, item)
        T = frames_from_rows(self._placement(rd, item).load())[row["pose"]]
        scene = self.scene(rd, T, ArtefactHardware.from_materials(hardware_file(cfg)))
        scanner, acquisition = self.recording(rd, cfg, row["scanner"], row["pose"])
        fits = rd.phase_ripple_fits(row["scanner"]) if self.kind != "artefact" else []
        s = simulate_measurement(item, scanner, scene, acquisition, cfg.decode, rd.store(item).path,
                                 rd.truth.store(item).path, {"pose": row["pose"], "kind": self.kind},
                                 self.errors(cfg, scanner, T, scene), scanner_fits=fits).summary
        log.info("%s: render %.1f s, decode + store %.1f s, %.1f %% valid", item, s["render_s"], s["decode_store_s"],
                 100 * s["valid_fraction"])
        if cfg.simulate.outputs.get(row["scanner"]) == "cloud":
            store_black_box_cloud(rd.store(item).path, scanner)


def store_black_box_cloud(path, scanner) -> None:
    """Replace a black box's decoded store by its cloud (:mod:`fringecal.simulate.black_box`)."""
    attrs = store_attributes(path)
    points = store_points(path, scanner)
    keep = {k: attrs[k] for k in ("source", "measurement", "scanner", "pose", "kind") if k in attrs}
    write_cloud_store(path, points, attrs=keep)


def poses_until(rd: RunDir, pose: str) -> list[str]:
    """The poses of ``truth/poses.csv`` in acquisition order, up to and including ``pose``."""
    order = [str(r["measurement"]) for r in Rows(rd.truth.poses).text()]
    return order[:order.index(str(pose)) + 1]


class SimulateRender(RenderStores):
    name = "simulate-render"
    title = "render measurements"
    kind = "artefact"
    settings = RenderStores.settings + tuple(p for p in switch_settings(SESSION_SWITCHES)
                                             if p not in RenderStores.settings)

    def _drift(self, cfg: Settings):
        e = errors_subset(cfg.simulate.errors, SESSION_SWITCHES)
        return e if e.session_drift_mm or e.session_drift_mrad else None

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        reads = super().reads(rd, cfg, item)
        if self._drift(cfg) is not None:
            reads.append(Value("poses acquired so far", poses_until(rd, store_fields(rd, item)["pose"])))
        return reads

    def recording(self, rd: RunDir, cfg: Settings, scanner: str, pose: str):
        """The true scanner as it has drifted by ``pose`` (``simulate.errors.session_drift_*``)."""
        true_scanner, acquisition = super().recording(rd, cfg, scanner, pose)
        drift = self._drift(cfg)
        if drift is not None:
            true_scanner = drifted_scanner(true_scanner, session_displacement(drift, scanner, poses_until(rd, pose)))
        return true_scanner, acquisition

    def placements(self, rd: RunDir) -> TableFile:
        return rd.truth.poses

    def objects(self, rd: RunDir) -> list:
        return [rd.truth.artefact, rd.rods]

    def scene(self, rd: RunDir, T, hardware: ArtefactHardware) -> Scene:
        artefact = rd.truth.artefact.load()
        return artefact_scene(artefact, rd.rods.load(artefact) if rd.rods.exists() else None, T, hardware)
