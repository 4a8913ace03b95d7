"""The simulated data source: what the simulator knows before it renders.

:func:`load_simulated_rig` turns a :class:`~fringecal.simulate.settings.SimulationConfig`
into a :class:`SimulatedRig`: the true sensors (cameras at the simulated
resolution), each scanner's prior calibration in its own frame, the artefact (CMM
table with the configured corrections: what the run fits against) and the artefact
as built (what is rendered; the same unless ``simulate.errors`` switches artefact
errors on, :mod:`fringecal.simulate.world`), its rods and hardware, the planned
artefact poses, the verification ball-bar (certificate and as built) and its
positions. The simulated pipeline steps
(:mod:`fringecal.steps.simulate_prepare` and friends) and ``fringecal simulate``
(which writes the same measurements as a recorded data set) both start from it, so
both doors see the same rig.

Ball-bar positions are thesis table 6-9's, VDI/VDE 2634's seven, or planned for the
rig (``verification.scheme``). Which scanners record a planned position is the plan's
choice; for the others it is decided by visibility, as an operator would: a scanner
records the position when the centre of at least one bar sphere lies in front of its
camera and inside its image. On the thesis rig this gives
thesis table 6-9's arrangement (sphere A seen by scanner one, B by scanner two).

The acceptance test's positions (sphere, dumbbell, flat; ``simulate.acceptance``) are
planned in each scanner's measurement volume from the true rig and the planned poses,
within the specified measuring volume (``acceptance.specification``), as an operator
would place them (:func:`fringecal.acceptance.plan.plan_acceptance`, seeded by
``simulate.acceptance.seed``); each is recorded by the scanner it was planned for. A
position asked for that does not fit is refused with a message, never dropped.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from fringecal.acceptance.plan import TESTS, plan_acceptance
from fringecal.acceptance.standards import load_standards
from fringecal.artefact import Artefact, load_artefact, load_rods
from fringecal.config import ConfigError
from fringecal.frames import frames_from_rows
from fringecal.lens.observed_region import ObservedRegion
from fringecal.names import check_name
from fringecal.rig import Rig, load_rig, scaled_rig
from fringecal.rundir import measurement_id
from fringecal.schemas import PosePlanTable, TableError, read_table
from fringecal.simulate.objects import plan_object
from fringecal.simulate.prior import simulate_prior_rig
from fringecal.simulate.scenes import ArtefactHardware
from fringecal.simulate.unmodelled import emitted_harmonics
from fringecal.simulate.world import as_built_artefact, as_built_ballbar
from fringecal.verification.ballbar import BallBarPosition, thesis_positions, vdi7_positions
from fringecal.verification.plan import plan_positions, volumes_from_observations

if TYPE_CHECKING:
    from fringecal.acceptance.standards import AcceptanceStandards

log = logging.getLogger(__name__)

__all__ = ["acceptance_camera_width", "SimulatedRig", "load_simulated_rig", "input_files", "scanners_seeing",
           "sphere_sightings", "acquisition_table", "true_volumes", "predicted_regions", "positions_outside",
           "specified_volumes",
           "acceptance_plan",
           "object_plans"]


@dataclass(frozen=True)
class SimulatedRig:
    """Everything a simulated acquisition starts from.

    Attributes
    ----------
    truth : Rig
        True sensors in the world frame, cameras resampled to the acquisition width.
    prior : Rig
        Each scanner's prior calibration in its own frame (with errors).
    scanner_frames : dict scanner -> Frame
        ``T_world_scanner`` of each scanner's own frame (truth, for evaluation).
    planned : dict measurement -> Frame
        Planned ``T_world_artefact`` of every measurement, in table order.
    positions : list of BallBarPosition
        Verification positions; ``scanner_of`` maps each visible sphere to the first
        scanner that sees it.
    recorders : dict position -> list of scanner names
        The scanners that record each position.
    built, ballbar_built : Artefact
        The artefact and ball-bar as built (rendered); ``artefact`` and ``ballbar``
        are the CMM table and the certificate the run uses.
    acceptance_standards : AcceptanceStandards or None
        The acceptance objects' certificates (None: no acceptance test simulated).
    acceptance : DataFrame or None
        The acceptance positions (:data:`fringecal.acceptance.plan.PLAN_COLUMNS`:
        measurement = position, test, scanner, ``T_world_<object>``); each is recorded
        by its ``scanner`` only.
    """

    truth: Rig
    prior: Rig
    scanner_frames: dict
    artefact: Artefact
    rods: pd.DataFrame | None
    hardware: ArtefactHardware
    planned: dict
    ballbar: Artefact
    positions: list
    recorders: dict
    built: Artefact | None = None
    ballbar_built: Artefact | None = None
    acceptance_standards: AcceptanceStandards | None = None
    acceptance: pd.DataFrame | None = None


def acceptance_camera_width(simulate) -> int | None:
    """The camera width (px) the acceptance stores are recorded at:
    ``simulate.acceptance.camera_width_px``, else the verification's; None: as the
    acquisition (both doors: the ``simulate-sphere/-dumbbell/-flat`` steps and
    :mod:`fringecal.simulate.export`)."""
    a, v = simulate.acceptance.camera_width_px, simulate.verification.camera_width_px
    return a if a is not None else v


def input_files(sim) -> list[Path]:
    """Every file a simulated rig is built from (rig YAML, the tables it names, the
    verification positions, the acceptance standards, files named by the artefact
    corrections)."""
    rc = sim.rig_config()
    files = [sim.rig, sim.ballbar_path()] + ([] if sim.verification.scheme == "planned" else [sim.positions_path()])
    if sim.acceptance.enabled:
        files.append(sim.acceptance.standards_path())
    files += [p for p in (rc.sensors, rc.artefact, rc.rods, rc.artefact_poses, rc.materials) if p is not None]
    sag = sim.artefact_corrections.sag if sim.artefact_corrections is not None else None
    if sag is not None:
        files += [p for p in (sag.rods, sag.materials) if p is not None]
    return sorted(set(Path(p).resolve() for p in files))


def scanners_seeing(rig: Rig, points_world: np.ndarray) -> list[list[str]]:
    """For each point (n, 3), the scanners whose camera sees it (in front, inside the image)."""
    out = [[] for _ in range(len(points_world))]
    for s in rig.scanners:
        for i in np.flatnonzero(s.camera.in_view(points_world)):
            out[i].append(s.name)
    return out


def sphere_sightings(rig: Rig, artefact: Artefact, poses: dict) -> pd.DataFrame:
    """measurement, scanner, sphere_id: every artefact sphere whose centre a scanner's
    camera sees at the poses (``measurement -> T_world_artefact``)."""
    rows = [(m, name, sid) for m, T in poses.items()
            for sid, names in zip(artefact.ids, scanners_seeing(rig, T.to_world(artefact.centres))) for name in names]
    return pd.DataFrame(rows, columns=["measurement", "scanner", "sphere_id"])


def true_volumes(truth: Rig, artefact: Artefact, planned: dict, regions: dict | None = None) -> dict:
    """Each scanner's measurement volume (:class:`~fringecal.verification.plan.MeasurementVolume`)
    from the true rig: the artefact spheres it sees in the planned poses; with
    ``regions`` (sensor name -> ObservedRegion, :func:`predicted_regions`) only where a
    sphere's whole image lies inside them."""

    return volumes_from_observations(truth, sphere_sightings(truth, artefact, planned), planned, artefact,
                                     regions=regions)


#: Points drawn on each artefact sphere for :func:`predicted_regions`, and the largest
#: angle between a point's normal and its line of sight to the camera that gives a
#: control point (the default run's ``control_points.max_incidence_deg``).
PREDICTION_POINTS, PREDICTION_INCIDENCE_DEG = 400, 60.0


def predicted_regions(truth: Rig, artefact: Artefact, planned: dict, seed: int = 0) -> dict:
    """The region of each sensor's image the calibration will observe, predicted before
    anything is rendered: the :class:`~fringecal.lens.observed_region.ObservedRegion` of
    points drawn on every artefact sphere its camera sees at the planned poses
    (``measurement -> T_world_artefact``) with its whole image (1.5 image radii) inside
    both formats, as the measurement volumes take them, on the cap facing the camera within
    :data:`PREDICTION_INCIDENCE_DEG` and facing the projector, imaged in camera and
    projector (occlusion by rods and other spheres ignored: the hull of the points).

    Returns
    -------
    dict sensor name -> ObservedRegion
    """
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(PREDICTION_POINTS, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)                          # unit normals (k, 3)
    radii = np.asarray(artefact.diameters, float) / 2
    cos_max = np.cos(np.radians(PREDICTION_INCIDENCE_DEG))
    seen = {s.name: [] for s in truth.sensors}
    for T in planned.values():
        centres = T.to_world(artefact.centres)
        for sc in truth.scanners:
            mine = np.ones(len(centres), bool)
            for sensor in sc.sensors:  # a sphere whose image the format cuts gives no control points
                z = np.maximum(sensor.to_sensor(centres)[:, 2], radii)
                mine &= sensor.in_view(centres, 1.5 * sensor.c * radii / z)
            P = centres[mine, None, :] + radii[mine, None, None] * d          # (n, k, 3)
            to_cam, to_prj = sc.camera.pinhole - P, sc.projector.pinhole - P
            facing = (np.sum(d * to_cam, -1) >= cos_max * np.linalg.norm(to_cam, axis=-1)) \
                & (np.sum(d * to_prj, -1) > 0)
            for sensor in sc.sensors:
                seen[sensor.name].append(sensor.project(P[facing]))
    return {s.name: ObservedRegion.from_observations(np.concatenate(seen[s.name] or [np.zeros((0, 2))]),
                                                     *s.format.size_mm) for s in truth.sensors}


def positions_outside(truth: Rig, positions: list, ballbar: Artefact, regions: dict) -> list[str]:
    """Each ball-bar sphere of ``positions`` whose image does not lie wholly inside the
    ``regions`` (sensor name -> ObservedRegion, :func:`predicted_regions`) of the
    scanner that measures it, with the numbers: where its image centre is, how far
    inside (negative: beyond) the region's edge, and its image radius it needs there."""
    radius = float(np.min(ballbar.diameters)) / 2
    out = []
    for p in positions:
        X = p.T_world_ballbar.to_world(ballbar.centres[:2])
        for sid, x in zip(ballbar.ids[:2], X):
            if sid not in p.scanner_of:
                continue
            for sensor in truth.scanner(p.scanner_of[sid]).sensors:
                m = sensor.project(x[None])
                need = sensor.c * radius / sensor.to_sensor(x[None])[0, 2]
                depth = float(regions[sensor.name].depth_inside(m)[0]) if sensor.name in regions else np.inf
                if not depth >= need:
                    out.append(f"{p.name} sphere {sid} in {sensor.name} (image at {m[0, 0]:.2f}, {m[0, 1]:.2f} mm: "
                               f"{depth:.2f} mm inside the edge, its image radius {need:.2f} mm)")
    return out


def _planned_positions(sim, truth: Rig, artefact: Artefact, planned: dict, ballbar: Artefact):
    """Positions planned from the true rig's measurement volumes: the spheres each
    scanner sees in the planned poses, each sphere's image inside the region of the
    images the calibration will observe (:func:`predicted_regions`)."""

    volumes = true_volumes(truth, artefact, planned, predicted_regions(truth, artefact, planned))
    v = sim.verification
    plan = plan_positions(truth, volumes, float(np.linalg.norm(ballbar.centres[1] - ballbar.centres[0])),
                          v.per_pair, v.per_scanner, seed=v.seed)
    if plan.uncovered:
        raise ConfigError(f"{sim.rig}: no ball-bar position covers {', '.join(plan.uncovered)} "
                          "(the bar does not fit the measurement volumes there)")
    if plan.beyond_region:
        log.warning("ball-bar positions planned partly beyond the region of the images the calibration will observe "
                    "(predicted from the planned poses): %s", "; ".join(plan.beyond_region))
    return plan.positions, {p.name: list(dict.fromkeys(p.scanner_of.values())) for p in plan.positions}


def _positions(sim, truth: Rig, ballbar: Artefact, artefact: Artefact, planned: dict
               ) -> tuple[list[BallBarPosition], dict]:
    if sim.verification.scheme == "planned":
        return _planned_positions(sim, truth, artefact, planned, ballbar)
    table = pd.read_csv(sim.positions_path(), dtype={"measurement": str})
    positions = thesis_positions(table, scanners=("", ""))
    for p in positions:  # a position's name becomes folders and store names
        check_name(p.name, "ball-bar position", str(sim.positions_path()))
    if sim.verification.scheme == "vdi7":
        positions = vdi7_positions(positions, float(np.linalg.norm(ballbar.centres[1] - ballbar.centres[0])))
    placed, recorders = [], {}
    for p in positions:
        seen = scanners_seeing(truth, p.T_world_ballbar.to_world(ballbar.centres[:2]))
        scanner_of = {sid: names[0] for sid, names in zip(ballbar.ids[:2], seen) if names}
        placed.append(BallBarPosition(p.name, p.T_world_ballbar, scanner_of))
        recorders[p.name] = [s.name for s in truth.scanners if any(s.name in names for names in seen)]
    return placed, recorders


def specified_volumes(volumes: dict, depth_range_mm) -> tuple[dict, list[str]]:
    """The measurement volumes cut to a specified measuring volume's depth range (along
    each camera's axis; None: unchanged), and the scanners whose volume it misses."""
    if depth_range_mm is None:
        return volumes, []
    near, far = depth_range_mm
    out, missed = {}, []
    for name, v in volumes.items():
        lo, hi = max(v.depth_range_mm[0], near), min(v.depth_range_mm[1], far)
        if lo < hi:
            out[name] = replace(v, depth_range_mm=(lo, hi))
        else:
            missed.append(f"{name}: the specified measuring volume (depths {near:g}-{far:g} mm) misses the volume "
                          f"the artefact calibrates ({v.depth_range_mm[0]:.0f}-{v.depth_range_mm[1]:.0f} mm)")
    return out, missed


def acceptance_plan(sim, truth: Rig, artefact: Artefact, planned: dict, depth_range_mm=None):
    """(standards, positions) of the simulated acceptance test; (None, None) when
    ``simulate.acceptance`` is disabled. The positions lie in each scanner's
    measurement volume within the specified measuring volume's depths
    ``depth_range_mm`` (``acceptance.specification``; None: the whole volume), as an
    operator following the specification places them. Raises ConfigError, naming
    every position that does not fit, when the plan falls short of the counts asked for."""

    a = sim.acceptance
    if not a.enabled:
        return None, None
    standards = load_standards(a.standards_path())
    counts = {t: getattr(a, t) for t in TESTS}
    volumes, missed = specified_volumes(true_volumes(truth, artefact, planned), depth_range_mm)
    plan = plan_acceptance(truth, volumes, standards, counts, seed=a.seed)
    if missed:
        plan = plan._replace(uncovered=missed + [u for u in plan.uncovered if "no measurement volume" not in u])
    if plan.uncovered:
        raise ConfigError(f"{a.standards_path()}: the acceptance positions asked for do not fit the rig "
                          f"{sim.rig}: {'; '.join(plan.uncovered)} (lower simulate.acceptance.<test>, or set "
                          "simulate.acceptance.enabled: false)")
    return standards, plan.positions


def load_simulated_rig(sim, depth_range_mm=None) -> SimulatedRig:
    """Build the :class:`SimulatedRig` of a simulation config; errors name the file.
    ``depth_range_mm``: the specified measuring volume the acceptance positions are
    placed in (``acceptance.specification.depth_range_mm``; None: the whole volume)."""

    rc = sim.rig_config()
    if rc.artefact_poses is None:
        raise ConfigError(f"{sim.rig}: artefact_poses is not set; a simulated acquisition needs the "
                          "planned T_world_artefact of every pose (e.g. poses_scanner1_table6-1.csv)")
    try:
        true_rig = load_rig(rc.sensors, reference=rc.reference_scanner)
    except TableError:
        raise
    except ValueError as err:  # e.g. the reference scanner is not in the sensors file
        raise ConfigError(f"{sim.rig}: {rc.sensors}: {err}") from None
    truth = scaled_rig(true_rig, sim.acquisition.camera_width_px)
    prior, frames = simulate_prior_rig(truth, sim.prior)
    artefact = sim.artefact()
    if len(artefact) < 3:
        raise ConfigError(f"{rc.artefact}: an artefact needs at least three spheres for a pose")
    rods = load_rods(rc.rods, artefact) if rc.rods is not None else None
    try:
        hardware = ArtefactHardware.from_materials(rc.materials)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    table = read_table(rc.artefact_poses, PosePlanTable)
    if table.empty:
        raise ConfigError(f"{rc.artefact_poses}: no artefact poses")
    planned = frames_from_rows(table)
    ballbar = load_artefact(sim.ballbar_path())
    if len(ballbar) != 2:
        raise ConfigError(f"{sim.ballbar_path()}: a ball-bar has two spheres, found {len(ballbar)}")
    positions, recorders = _positions(sim, truth, ballbar, artefact, planned)
    render = sim.acquisition.render
    try:  # refused here, before any work, rather than at the first render
        emitted_harmonics(render.offset, render.amplitude, sim.errors.projector_gamma)
    except ValueError as err:
        raise ConfigError(f"simulate.errors.projector_gamma: {err}") from None
    built, ballbar_built = as_built_artefact(sim, sim.errors), as_built_ballbar(ballbar, sim.errors)
    standards, acceptance = acceptance_plan(sim, truth, artefact, planned, depth_range_mm)
    return SimulatedRig(truth, prior, frames, artefact, rods, hardware, planned, ballbar, positions, recorders,
                        built, ballbar_built, standards, acceptance)


def acquisition_table(sr: SimulatedRig) -> pd.DataFrame:
    """Every store the simulation records (``fringecal.schemas.AcquisitionTable``): each planned
    measurement seen by every scanner, then each ball-bar position by its recorders,
    then each acceptance position (kind ``sphere``, ``dumbbell`` or ``flat``) by the
    scanner it was planned for."""
    rows = [{"measurement": measurement_id(m, s.name), "kind": "artefact", "pose": m, "scanner": s.name}
            for m in sr.planned for s in sr.truth.scanners]
    rows += [{"measurement": measurement_id(p, s), "kind": "ballbar", "pose": p, "scanner": s}
             for p, scanners in sr.recorders.items() for s in scanners]
    if sr.acceptance is not None:
        rows += [{"measurement": measurement_id(r.measurement, r.scanner), "kind": r.test, "pose": r.measurement,
                  "scanner": r.scanner} for r in sr.acceptance.itertuples(index=False)]
    df = pd.DataFrame(rows, columns=["measurement", "kind", "pose", "scanner"])
    df["source"] = "simulated"
    return df


def object_plans(sim, truth: Rig, built: Artefact, rods: pd.DataFrame | None, hardware: ArtefactHardware) -> list:
    """The :class:`~fringecal.simulate.objects.ObjectPlan` of every ``simulate.objects``
    entry in front of the true rig (the artefact as ``built``); raises ConfigError for an
    unknown material, and, naming the object and every scanner's view fraction, for an
    object no scanner sees."""

    materials = sim.acquisition.render.materials
    for o in sim.objects:
        if getattr(o, "material", None) is not None and o.material not in materials:
            raise ConfigError(f"simulate.objects: object {o.name!r}: material {o.material!r} is not one of "
                              f"simulate.acquisition.render.materials ({', '.join(sorted(materials))})")
    try:
        return [plan_object(o, truth, built, rods, hardware) for o in sim.objects]
    except ValueError as err:
        raise ConfigError(str(err)) from None
