"""A simulated rig written as a recorded data set (``fringecal simulate``).

The data set is exactly what a real cell would deliver (:mod:`fringecal.dataset`):
the CMM table (with the artefact corrections and temperature in ``dataset.yaml``),
rods, each scanner's prior calibration, the planned poses, one image stack per
(measurement, scanner) rendered at the pose the hexapod reached, the ball-bar's CMM
table and its image stacks, and the acceptance test's certificates
(``verification/acceptance/standards.yaml``) and image stacks
(``verification/acceptance/<test>/<position>/<scanner>/``, each position by the
scanner it was planned for; none when ``simulate.acceptance`` plans nothing), and the
objects to measure of ``simulate.objects`` (``objects/<name>/<scanner>/``, by every
scanner that sees enough of the object, at the scanners' session-start placement;
the calibration does not read them, :mod:`fringecal.simulate.objects`).
``dataset.yaml`` carries the simulation config's
processing settings, so ``fringecal run --dataset`` processes it as ``fringecal run``
processes the simulation. The truth goes to a separate folder that the data set
does not reference (true sensors, the artefact and ball-bar as built, scanner
frames, reached poses, hexapod moves, ball-bar and acceptance positions, and each object's
``objects/<name>.json``), laid out as a run directory's ``truth/`` (:class:`~fringecal.rundir.TruthDir`).

Both are written under hidden temporary names in their parent folders and renamed
when complete; a ``fringecal simulate`` killed midway leaves them behind, marked with
its process (:data:`OWNER_FILE`), and the next ``fringecal simulate`` into the same
folder removes them (:func:`remove_interrupted_exports`).

Both doors render with the same functions, the same measurement ids and noise
seeds and the same unmodelled errors (``simulate.errors``), and the frames are
integers written losslessly, so the data set decodes to the very maps the simulated
run stores.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pandas as pd
import yaml

from fringecal import dataset as layout
from fringecal.acceptance.plan import PLAN_COLUMNS
from fringecal.acceptance.standards import load_standards
from fringecal.artefact import load_rods
from fringecal.atomic import temporary_sibling
from fringecal.frames import frame_rows, frames_from_rows
from fringecal.fringe.importer import write_frames
from fringecal.lifeline import process_start
from fringecal.names import check_name, confined
from fringecal.rig import scaled_scanner
from fringecal.rundir import TruthDir, measurement_id
from fringecal.schemas import ArtefactTable, PosePlanTable, RodsTable, SensorParametersTable, read_table, write_table
from fringecal.simulate.black_box import without_black_boxes, write_black_box_ply
from fringecal.simulate.measurement import render_frames, simulate_measurement
from fringecal.simulate.moves import move_hexapod, poses_table
from fringecal.simulate.objects import object_truth
from fringecal.simulate.scenes import acceptance_scene, artefact_scene
from fringecal.simulate.source import acceptance_camera_width, load_simulated_rig, object_plans
from fringecal.simulate.world import drifted_scanner, native_formats, render_errors, session_displacement
from fringecal.verification.ballbar import ballbar_rods

__all__ = ["write_dataset", "PROCESSING_SECTIONS", "interrupted_exports", "remove_interrupted_exports", "OWNER_FILE"]

PROCESSING_SECTIONS = ("decode", "extraction", "control_points", "bundle", "verification", "acceptance")


def _dataset_yaml(cfg) -> dict:
    sim = cfg.simulate
    doc = {"name": cfg.name, "reference_scanner": cfg.reference_scanner,
           "description": f"simulated by fringecal from rig {sim.rig} (simulation profile {sim.errors.profile_name})"}
    if sim.temperature_c is not None:
        doc["temperature_c"] = sim.temperature_c
    if sim.artefact_corrections is not None:
        doc["artefact_corrections"] = sim.artefact_corrections.model_dump(mode="json", exclude_none=True)
    processing = {k: getattr(cfg, k).model_dump(mode="json", exclude_defaults=True) for k in PROCESSING_SECTIONS}
    processing = {k: v for k, v in processing.items() if v}
    if processing:
        doc["processing"] = processing
    if cfg.certificate is not None:
        doc["certificate"] = cfg.certificate.model_dump(mode="json", exclude_none=True, exclude_defaults=True)
    return doc


#: the owner of a data set being written (in its hidden temporary folder)
OWNER_FILE = ".fringecal-owner.json"
_TEMPORARY = re.compile(r"^\..+\.[0-9a-f]{12}\.tmp$")


def _own(tmp: Path) -> None:
    """Mark ``tmp`` as this process's data set in the making (pid, its start, host)."""
    (tmp / OWNER_FILE).write_text(json.dumps({"pid": os.getpid(), "start": process_start(os.getpid()),
                                              "host": socket.gethostname()}))


def interrupted_exports(folder) -> list[Path]:
    """The hidden temporary folders in ``folder`` that a ``fringecal simulate`` killed
    midway left behind: marked by :data:`OWNER_FILE` with a process of this host that no
    longer runs (a running export's folder, or any folder not marked, is not listed)."""
    folder = Path(folder)
    found = []
    if not folder.is_dir():
        return found
    for p in folder.iterdir():
        if not (_TEMPORARY.match(p.name) and p.is_dir() and not p.is_symlink()):
            continue
        try:
            owner = json.loads((p / OWNER_FILE).read_text())
        except (OSError, ValueError):
            continue
        if owner.get("host") == socket.gethostname() and process_start(int(owner.get("pid", -1))) != owner.get("start"):
            found.append(p)
    return sorted(found)


def remove_interrupted_exports(*folders) -> list[tuple[Path, int]]:
    """Remove :func:`interrupted_exports` of ``folders``; (folder removed, its bytes)."""
    gone = []
    for folder in dict.fromkeys(Path(f) for f in folders):
        for p in interrupted_exports(folder):
            size = sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
            shutil.rmtree(p, ignore_errors=True)
            gone.append((p, size))
    return gone


def _folder(root: Path, *names: str) -> Path:
    """``root/<names>``: each name one safe path component, the result inside ``root``."""
    return confined(root, *(check_name(n, "folder name") for n in names))


def write_dataset(cfg, out, truth_out, fmt: str = "png", workers: int = 2, on_stack=None) -> Path:
    """Render the simulated rig of ``cfg`` (a resolved RunConfig with ``simulate``) into
    the data set folder ``out`` and its truth into ``truth_out``.

    Both are written under temporary names and renamed when complete, so an
    interrupted export leaves no half data set. ``on_stack(id)`` is called after each
    image stack is written. Refuses to overwrite an existing ``out`` or ``truth_out``.
    """

    out, truth_out = Path(out), Path(truth_out)
    for p in (out, truth_out):
        if p.exists():
            raise FileExistsError(f"{p}: already exists; choose a new folder (nothing is overwritten)")
    sim = cfg.simulate
    sr = load_simulated_rig(sim, cfg.acceptance.specification.depth_range_mm)
    rc = sim.rig_config()
    tmp, tmp_truth = temporary_sibling(out), temporary_sibling(truth_out)
    try:
        for t in (tmp, tmp_truth):
            t.mkdir(parents=True)
            _own(t)
        (tmp / layout.DATASET_FILE).write_text(yaml.safe_dump(_dataset_yaml(cfg), sort_keys=False))
        write_table(read_table(rc.artefact, ArtefactTable), tmp / layout.ARTEFACT_FILE)
        if rc.rods is not None:
            write_table(read_table(rc.rods, RodsTable), tmp / layout.RODS_FILE)
        boxes = sim.black_boxes()
        modelled = without_black_boxes(sr.prior, sim.outputs)
        if modelled is not None:  # black boxes only: no prior calibration at all
            write_table(modelled.to_frame(), tmp / layout.SENSORS_PRIOR_FILE, SensorParametersTable)
        write_table(frame_rows(sr.planned), tmp / layout.POSES_PLANNED_FILE)
        verification = tmp / layout.VERIFICATION_DIR
        write_table(sr.ballbar.to_frame(), verification / layout.BALLBAR_FILE, ArtefactTable)
        # the truth as a simulated run keeps it; everything is rendered from these tables
        # as read back, as the simulated run's steps do, so both doors render alike
        planned = frames_from_rows(read_table(tmp / layout.POSES_PLANNED_FILE, PosePlanTable))
        moves = move_hexapod(planned, sim.acquisition.hexapod)
        known = TruthDir(tmp_truth, prefix="")
        known.sensors.save(sr.truth)
        known.artefact.save(sr.built)
        known.ballbar.save(sr.ballbar_built)
        known.scanner_frames.save(frame_rows(sr.scanner_frames, key="scanner"))
        known.poses.save(frame_rows({m.pose: m.reached for m in moves}))
        known.hexapod_moves.save(poses_table(moves))
        known.ballbar_positions.save(frame_rows({p.name: p.T_world_ballbar for p in sr.positions}))
        planned_acceptance = sr.acceptance if sr.acceptance is not None else pd.DataFrame(columns=list(PLAN_COLUMNS))
        known.acceptance_positions.save(planned_acceptance)
        acceptance_dir = verification / layout.ACCEPTANCE_DIR
        if not planned_acceptance.empty:
            acceptance_dir.mkdir(parents=True)
            (acceptance_dir / layout.STANDARDS_FILE).write_text(yaml.safe_dump(
                sr.acceptance_standards.model_dump(mode="json", exclude_none=True), sort_keys=False))
        truth = known.sensors.load()
        built = known.artefact.load()
        rods = load_rods(tmp / layout.RODS_FILE, built) if rc.rods is not None else None
        bar = known.ballbar.load()
        reached = frames_from_rows(known.poses.load())
        positions = frames_from_rows(known.ballbar_positions.load())
        acceptance = known.acceptance_positions.load()
        standards = load_standards(acceptance_dir / layout.STANDARDS_FILE) if not acceptance.empty else None

        acq = sim.acquisition
        v_acq = acq.model_copy(update={"seed": sim.verification.seed})
        errors = sim.errors
        native = native_formats(rc.sensors) if errors.thin_prism_corner_px else None
        jobs = []
        for i, (m, T) in enumerate(reached.items()):
            scene = artefact_scene(built, rods, T, sr.hardware)
            for s in truth.scanners:
                s = drifted_scanner(s, session_displacement(errors, s.name, list(reached)[:i + 1]))
                jobs.append((measurement_id(m, s.name), s, scene, acq, _folder(tmp, layout.MEASUREMENTS_DIR, m, s.name),
                             render_errors(errors, s, T, "artefact", scene.sphere_ids, native)))
        for name, T in positions.items():
            scene = artefact_scene(bar, ballbar_rods(bar), T, sr.hardware)
            for scanner in sr.recorders[name]:
                s = truth.scanner(scanner)
                if sim.verification.camera_width_px is not None:
                    s = scaled_scanner(s, sim.verification.camera_width_px)
                jobs.append((measurement_id(name, scanner), s, scene, v_acq, _folder(verification, name, scanner),
                             render_errors(errors, s, T, "ballbar", scene.sphere_ids, native)))
        # the acceptance objects as simulate-sphere/-dumbbell/-flat render them: the
        # acceptance's camera width (else the verification's) and noise seed
        a_acq = acq.model_copy(update={"seed": sim.acceptance.seed})
        a_width = acceptance_camera_width(sim)
        for (name, T), row in zip(frames_from_rows(acceptance).items(), acceptance.itertuples(index=False)):
            scene = acceptance_scene(row.test, standards, T, sr.hardware)
            s = truth.scanner(row.scanner)
            if a_width is not None:
                s = scaled_scanner(s, a_width)
            jobs.append((measurement_id(name, row.scanner), s, scene, a_acq,
                         _folder(acceptance_dir, row.test, name, row.scanner),
                         render_errors(errors, s, T, row.test, scene.sphere_ids, native)))

        # the objects to measure: the acquisition's cameras and noise, each object's own
        # seed, the scanners at their session-start placement (no session drift)
        for plan in object_plans(sim, truth, built, rods, sr.hardware):
            spec = plan.spec
            known.object(spec.name).save(object_truth(plan, built if spec.kind == "artefact" else None,
                                                      acq.camera_width_px))
            o_acq = acq.model_copy(update={"seed": spec.seed})
            label = "artefact" if spec.kind == "artefact" else spec.kind
            for scanner in plan.recorders:
                s = truth.scanner(scanner)
                jobs.append((measurement_id(spec.name, scanner), s, plan.scene, o_acq,
                             _folder(tmp, layout.OBJECTS_DIR, spec.name, scanner),
                             render_errors(errors, s, plan.T_world_object, label, plan.scene.sphere_ids, native)))

        def render(job):
            mid, scanner, scene, settings, folder, errs = job
            if scanner.name in boxes:  # a black box: its cloud, from the maps the simulated run stores
                store = folder.parent / f".{folder.name}.decoded.zarr"
                folder.parent.mkdir(parents=True, exist_ok=True)
                try:
                    simulate_measurement(mid, scanner, scene, settings, cfg.decode, store, errors=errs)
                    write_black_box_ply(store, scanner, folder.parent / f"{folder.name}.ply")
                finally:
                    shutil.rmtree(store, ignore_errors=True)
                if on_stack is not None:
                    on_stack(mid)
                return
            m = render_frames(mid, scanner, scene, settings, errs)
            write_frames(folder, m.frames, m.sequence, acq.render.bit_depth, fmt, scanner=scanner.name)
            if on_stack is not None:
                on_stack(mid)

        with ThreadPoolExecutor(max_workers=workers) as pool:
            list(pool.map(render, jobs))
        for t in (tmp, tmp_truth):
            (t / OWNER_FILE).unlink()
        os.rename(tmp, out)
        os.rename(tmp_truth, truth_out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(tmp_truth, ignore_errors=True)
    return out
