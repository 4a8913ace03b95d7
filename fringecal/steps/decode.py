"""Recorded data set, steps 2 and 3: decode every image stack into its measurement store.

Every stack of the acquisition table is decoded alike, whatever its kind: first the
calibration measurements (``decode``), then the ball-bar positions and the acceptance
test's positions, sphere, dumbbell, flat (``decode-positions``), since a stack too small
for a phase-ripple fit of its own is corrected with its scanner's ripple from the
calibration stacks (:func:`fringecal.fringe.ripple.scanner_ripple`).

A frame folder (``sequence.yaml`` + frames) is read and decoded
(:func:`fringecal.fringe.measurement.decode_folder`); a stack the data set already
holds decoded (``<scanner>.zarr``) is copied in (hard links where possible); a
black-box scanner's cloud (``<scanner>.ply``, ``.e57``) is read, checked and stored as
the run's cloud store (:func:`fringecal.scancloud.cloud_store_from_file`). Either
way the run gets ``measurements/<id>.zarr``, keyed by the content of its stack, so
editing one frame re-decodes that measurement only.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fringecal.fringe.importer import read_stack_spec
from fringecal.fringe.measurement import decode_folder
from fringecal.rundir import RunDir
from fringecal.scancloud import CLOUD_SUFFIXES, cloud_store_from_file
from fringecal.steps.base import Settings, Step, scanner_ripple_read, store_fields, store_row, stores_of_kind
from fringecal.store import copy_store

__all__ = ["Decode", "DecodePositions"]

log = logging.getLogger(__name__)

#: the kinds of the acquisition table (fringecal.schemas.AcquisitionTable), in the order decoded;
#: spelt here, not imported from fringecal.dataset, so that an edit of the data-set
#: checks does not change this step's key
KINDS = ("artefact", "ballbar", "sphere", "dumbbell", "flat")


class Decode(Step):
    """The calibration stacks (``artefact``); :class:`DecodePositions` the others, after
    them, since a stack too small for a phase-ripple fit of its own takes its scanner's
    from these."""

    name = "decode"
    title = "decode stacks"
    settings = ("decode",)
    locations = ("dataset",)
    modules = ("fringecal.fringe.measurement",)
    kinds = KINDS[:1]
    #: whether a stack too small for a phase-ripple fit takes its scanner's
    takes_scanner_ripple = False

    def items(self, rd: RunDir, cfg: Settings) -> list[str]:
        return [m for kind in self.kinds for m in stores_of_kind(rd, kind)]

    def _source(self, rd: RunDir, cfg: Settings, item: str) -> Path:
        return Path(cfg.dataset) / store_fields(rd, item)["source"]

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        source = self._source(rd, cfg, item)
        artefact = [rd.artefact] if source.suffix.lower() in CLOUD_SUFFIXES else []
        return [store_row(rd, item), source] + artefact + self._scanner_ripple(rd, cfg, item)

    def _scanner_ripple(self, rd: RunDir, cfg: Settings, item: str) -> list:
        return []

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        return [rd.store(item)]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        row = store_fields(rd, item)
        source = self._source(rd, cfg, item)
        if source.suffix == ".zarr":
            copy_store(source, rd.store(item).path)
            return
        if source.suffix.lower() in CLOUD_SUFFIXES:
            attrs = {"measurement": item, "pose": row["pose"], "scanner": row["scanner"], "kind": row["kind"],
                     "source": row["source"]}
            min_extent = float(rd.artefact.load().radii.min())
            cloud_store_from_file(source, rd.store(item).path, min_extent, attrs)
            return
        attrs = {"measurement": item, "pose": row["pose"], "scanner": row["scanner"], "kind": row["kind"],
                 "source": row["source"]}
        fits = rd.phase_ripple_fits(row["scanner"]) if self.takes_scanner_ripple else []
        result = decode_folder(source, rd.store(item).path, cfg.decode, attrs=attrs, scanner_fits=fits)
        log.info("%s -> %s: %.1f %% valid", source, item, 100 * float(result.valid.mean()))
        for o, r in result.ripple.items():
            if r.applied:
                log.info("%s: phase ripple %s corrected, %.1f mrad RMS (Z %.3g, phase noise %.1f mrad; fitted on %s)",
                         item, o, 1000 * r.excess_rms_rad, r.z, 1000 * r.noise_rms_rad,
                         "this stack" if r.source == "stack" else "the scanner's calibration stacks")


class DecodePositions(Decode):
    """The ball-bar's and the acceptance test's stacks, after the calibration stacks: a
    stack too small for a phase-ripple fit of its own (a ball-bar's two spheres) is
    corrected with its scanner's ripple from those
    (:func:`fringecal.fringe.ripple.scanner_ripple`)."""

    name = "decode-positions"
    title = "decode positions"
    kinds = KINDS[1:]
    takes_scanner_ripple = True

    def _scanner_ripple(self, rd: RunDir, cfg: Settings, item: str) -> list:
        source = self._source(rd, cfg, item)
        if source.suffix == ".zarr" or source.suffix.lower() in CLOUD_SUFFIXES:
            return []  # decoded already, or a black box's cloud: nothing to correct
        try:
            sequence = read_stack_spec(source)[0].sequence
        except (OSError, ValueError):  # a bad folder: its decoding says what is wrong
            return []
        return [scanner_ripple_read(rd, store_fields(rd, item)["scanner"], sequence)]
