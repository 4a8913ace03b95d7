"""``fringecal measure`` without the command line: folder in, cloud file and summary out."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fringecal.calibration.blackbox import point_uncertainty, scanners_from_document, transform_points
from fringecal.calibration.file import read_calibration
from fringecal.calibration.propagation import frame_free_covariance
from fringecal.measure.cloud import OUTSIDE, POINT_DTYPE, Cloud, MeasureSettings, measure_cloud
from fringecal.measure.files import CLOUD_SUFFIXES, write_cloud
from fringecal.measure.overlap import overlap_report
from fringecal.measure.sources import MeasurementSourceError, measurement_entries, open_entry
from fringecal.rundir import RunDir
from fringecal.scancloud import load_points
from fringecal.measure.spheres import measure_spheres, read_nominal_spheres, sphere_distances

__all__ = ["measure_folder", "check_output", "observed_region_summary"]


def check_output(out) -> Path:
    """``out`` is a cloud file fringecal can write there (suffix, not a folder, a parent
    that exists or can be made)."""
    out = Path(out)
    if out.suffix.lower() not in CLOUD_SUFFIXES:
        raise MeasurementSourceError(f"{out}: the cloud is written as {' or '.join(CLOUD_SUFFIXES)} "
                                     f"(by the suffix), not {out.suffix or 'no suffix'!r}")
    if out.suffix.lower() == ".ply" and out.is_dir():
        raise MeasurementSourceError(f"{out}: is a folder, not a file to write")
    if out.suffix.lower() == ".zarr" and out.exists() and not out.is_dir():
        raise MeasurementSourceError(f"{out}: is a file, not a store to write")
    parent = out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise MeasurementSourceError(f"{out}: {parent} is a file, not a folder")
    return out


DATUMS = ("rig", "calibration")


def black_box_points(box, path, index: int, measurement: int, settings: MeasureSettings) -> np.ndarray:
    """A black-box scanner's cloud file as points of the registered cloud: carried into
    the world by its transform (:func:`fringecal.calibration.blackbox.transform_points`),
    ``u_mm`` from the transform's covariance, ``eps1`` and ``modulation`` NaN (a cloud
    has neither), every ``decimate**2``-th point (as ``decimate`` thins a map's rows and
    columns)."""
    points = load_points(path)[0][::settings.decimate ** 2]
    world = transform_points(box, points)
    pts = np.zeros(len(world), POINT_DTYPE)
    pts["x"], pts["y"], pts["z"] = world[:, 0], world[:, 1], world[:, 2]
    pts["scanner"], pts["measurement"] = index, measurement
    pts["eps1"] = pts["modulation"] = np.nan
    pts["u_mm"] = point_uncertainty(box, points) if settings.uncertainty else np.nan
    return pts


def _ripple_fits(cal, path) -> dict[str, list[dict]]:
    """Per scanner, what its small stacks are corrected with: the fits of the calibration
    stacks of the run directory the calibration file lies in, else the ripple the file
    carries (``phase_ripple``; none in an XML file or on a cell without one)."""
    run = RunDir(Path(path).parent)
    out = {}
    for s in cal.rig.scanners:
        out[s.name] = run.phase_ripple_fits(s.name) or list((cal.phase_ripple.get(s.name) or {}).values())
    return out


def _outside_per_store(part: Cloud, group: dict, measurement: str) -> list[dict]:
    """Per store of one measurement's cloud (modelled scanners only): its points and
    how many of them the observed region flags."""
    out = []
    for i, name in enumerate(part.scanners):
        if name not in group:
            continue
        flags = part.points[OUTSIDE][part.points["scanner"] == i]
        n, k = int(len(flags)), int(flags.sum())
        out.append({"store": str(group[name]), "scanner": name, "measurement": measurement, "points": n,
                    "outside": k, "fraction": k / n if n else 0.0})
    return out


def observed_region_summary(cal, per_store: list[dict]) -> dict:
    """The summary's ``observed_region``: the sensors whose region the calibration
    records (``known``) and those it does not (``unknown``: their points cannot be
    flagged), each known sensor's covered fraction of its format, and per store the
    points outside (``stores``) with their total and fraction over every store."""
    regions = cal.observed_regions
    sensors = [s.name for s in cal.rig.sensors]
    n = sum(r["points"] for r in per_store)
    k = sum(r["outside"] for r in per_store)
    return {"known": [s for s in sensors if s in regions], "unknown": [s for s in sensors if s not in regions],
            "fraction_of_format": {s: regions[s].fraction for s in sensors if s in regions},
            "points_outside": k, "fraction_outside": k / n if n else 0.0, "stores": per_store}


def measure_folder(calibration, folders, kind: str, out, settings: MeasureSettings = MeasureSettings(),
                   decode_settings=None, datum: str = "rig", spheres=None) -> dict:
    """Measure ``folders`` (a measurement folder or a list of them; one entry per
    scanner, ``kind`` "frames" or "stores") with the calibration file ``calibration``
    and write one cloud to ``out``.

    ``datum`` says relative to what ``u_mm`` is stated: ``"rig"``, the frame the sensors
    realise (:func:`~fringecal.calibration.propagation.frame_free_covariance`), or
    ``"calibration"``, the adjustment's own world frame (the reference camera's
    exterior orientation as given), which is the frame to compare with coordinates
    known in it (a simulation's truth).

    Frames are decoded as a run decodes them; a stack too small for a phase-ripple fit of
    its own takes its scanner's ripple from the calibration stacks of the run directory
    ``calibration`` lies in (:meth:`~fringecal.rundir.RunDir.phase_ripple_fits`), or
    else from the calibration file's ``phase_ripple``.

    ``spheres``: a CSV file of nominal spheres (:func:`~fringecal.measure.spheres.read_nominal_spheres`)
    to fit in every measurement (:func:`~fringecal.measure.spheres.measure_spheres`):
    each centre with the u of its position (in the frame of ``datum``), every distance
    between two of them with its own u (:func:`~fringecal.measure.spheres.sphere_distances`).

    Every point whose camera pixel or projector phases lie outside the region of that
    sensor's image plane the calibration observed (the file's ``observed_region``,
    :class:`~fringecal.lens.observed_region.ObservedRegion`) is flagged in the cloud's
    ``outside_observed_region`` field and counted per store (``observed_region`` of the
    summary); each sphere states how many of its points are.

    Returns the summary: points per scanner, their median ``u_mm``, RMS ``eps1`` and
    how many lie outside the observed region,
    the overlap between scanners (:func:`~fringecal.measure.overlap.overlap_report`),
    the spheres and their distances, wall times, and what the cloud's header records. Every folder is checked before
    any is read; the cloud file appears whole or not at all.
    """
    t0 = time.perf_counter()
    if datum not in DATUMS:
        raise MeasurementSourceError(f"datum must be one of {', '.join(DATUMS)}, got {datum!r}")
    folders = [Path(folders)] if isinstance(folders, (str, Path)) else [Path(f) for f in folders]
    if len({f.resolve() for f in folders}) != len(folders):
        raise MeasurementSourceError(f"a measurement folder is given twice: {', '.join(map(str, folders))}")
    cal = read_calibration(calibration)
    out = check_output(out)
    nominal = None
    if spheres is not None:
        try:
            nominal = read_nominal_spheres(spheres)
        except ValueError as err:
            raise MeasurementSourceError(str(err)) from None
    boxes = scanners_from_document(cal.black_boxes) if cal.black_boxes else {}
    entries = [measurement_entries(f, cal.rig, kind, tuple(boxes)) for f in folders]
    ripple_fits = _ripple_fits(cal, calibration) if kind == "frames" else {}
    cov = placed = field = None
    if settings.uncertainty and cal.covariances is not None:
        cov = cal.covariances.total
        if cal.covariances.field is not None:  # with correction fields: distances take the extended one
            f = cal.covariances.field
            field = (cal.covariances.field_total, f.n_terms, f.calibration)
        # points and sphere positions: with the fields' coefficients where there are fields
        placed = cov if field is None else field[0]
        if datum == "rig":
            cov, placed = frame_free_covariance(cal.rig, cov), frame_free_covariance(cal.rig, placed)
    adjustment = None if cov is None else cal.covariances.calibration  # a distance's jackknife is compared with it
    factors = {s: max(1.0, float(d["kappa"])) for s, d in (cal.metadata.get("sighting_dispersion") or {}).items()}
    t_read = t_cloud = 0.0
    regions = cal.observed_regions
    parts, fitted, distances, per_store = [], [], [], []
    for g, group in enumerate(entries):   # one measurement in memory at a time
        t = time.perf_counter()
        stores = {name: open_entry(path, kind, decode_settings, ripple_fits.get(name, ()))
                  for name, path in group.items() if name not in boxes}
        t_read += time.perf_counter() - t
        t = time.perf_counter()
        try:
            part = measure_cloud(cal.rig, stores, settings, placed, measurement=g, regions=regions)
            per_store += _outside_per_store(part, group, folders[g].name)
            if nominal is not None:
                found = measure_spheres(part, stores, cal.rig, placed, nominal, measurement=g, fit_factors=factors,
                                        regions=regions)
                name = folders[g].name
                fitted += [{"measurement": name, **m.as_dict()} for m in found]
                table = sphere_distances(found, cov, adjustment, cal.replicas, field)
                distances += [{"measurement": name, **r} for r in table.to_dict("records")]
            parts.append(part.points)
            for k, (name, box) in enumerate(boxes.items()):
                if name in group:
                    parts.append(black_box_points(box, group[name], len(cal.rig.scanners) + k, g, settings))
        finally:
            for ds in stores.values():
                ds.close()
        t_cloud += time.perf_counter() - t
    t = time.perf_counter()
    rig = cal.rig
    cloud = Cloud(np.concatenate(parts), tuple(s.name for s in rig.scanners) + tuple(boxes),
                  tuple(f.name for f in folders))
    viewpoints = {s.name: s.camera.pinhole for s in rig.scanners} | {n: b.params[:3] for n, b in boxes.items()}
    overlap = [] if len(folders) > 1 else overlap_report(cloud, viewpoints)
    comments = {"calibration": str(Path(calibration).resolve()),
                "measurement_folders": [str(f.resolve()) for f in folders],
                "calibration_inputs": cal.provenance.get("inputs", {}),
                "decimate": settings.decimate, "max_eps1_mm": settings.max_eps1_mm, "u_mm_datum": datum}
    write_cloud(cloud, out, comments)
    t_write = time.perf_counter() - t
    per = {}
    for i, name in enumerate(cloud.scanners):
        p = cloud.points[cloud.points["scanner"] == i]
        if len(p) == 0:
            continue
        eps1 = float(np.sqrt(np.mean(p["eps1"].astype(float) ** 2)))
        per[name] = {"sources": [str(g[name]) for g in entries if name in g], "points": int(len(p)),
                     "eps1_rms_mm": eps1 if np.isfinite(eps1) else None,
                     "u_mm_median": float(np.median(p["u_mm"])) if cov is not None else None,
                     "outside_observed_region": int(p[OUTSIDE].sum())}
    return {"out": str(out), "points": len(cloud), "measurements": [str(f) for f in folders], "scanners": per,
            "datum": datum,
            "uncertainty": "from the calibration's covariance" if cov is not None else
            ("not requested" if not settings.uncertainty else "none: the calibration file carries no covariance"),
            "overlap": [o.as_dict() for o in overlap],
            "observed_region": observed_region_summary(cal, per_store),
            "spheres": None if nominal is None else {"nominal": str(spheres), "fitted": fitted, "distances": distances},
            "seconds": {"read": t_read, "triangulate": t_cloud, "overlap_and_write": t_write,
                        "total": time.perf_counter() - t0}}
