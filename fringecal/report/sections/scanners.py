"""One part per scanner: its 14 + 14 parameters with their uncertainties (and the
thin-prism terms, and the correction field's RMS and largest displacement, of a model
that has them), the residuals
and the coverage by control points over its camera's and projector's images, the region of
each image the calibration observed (``calibration.json``'s ``observed_region``), the
uncertainty a measured point inherits from the calibration at three depths of its
measuring volume, and its acceptance values; one part per black-box scanner: its
transform and scale with their uncertainties (``black_boxes.json``), its 4x4 matrix
and its acceptance values; then the strongest correlations of the adjustment."""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
from markupsafe import Markup

from fringecal.lens.field import format_grid
from fringecal.report import figures
from fringecal.report.figures import Image
from fringecal.report.formatting import PARAM_LABELS, PARAM_UNITS, finite, length, num, plus_minus, um
from fringecal.report.rundata import Missing, RunData, Shown, guard
from fringecal.report.sections.certificate import VERDICT_CLASSES
from fringecal.report.tables import table
from fringecal.sensor import PARAM_NAMES, PRISM_NAMES

__all__ = ["build", "correlations", "residual_maps", "uncertainty_maps", "depths", "acceptance_values",
           "black_box_parts", "field_displacement", "observed_region"]

#: Cells across the camera image of an uncertainty map.
MAP_CELLS = 24
#: Maps drawn in this process, by the digests of what they are drawn from: a page rewritten
#: from the same files (``fringecal serve``, a test's run directory) does not draw them again.
_DRAWN: OrderedDict = OrderedDict()
_DRAWN_MAX = 32


def _drawn(key: tuple, draw):
    """``draw()``, or what it gave for the same ``key`` before."""
    if key in _DRAWN:
        _DRAWN.move_to_end(key)
        return _DRAWN[key]
    value = draw()
    _DRAWN[key] = value
    while len(_DRAWN) > _DRAWN_MAX:
        _DRAWN.popitem(last=False)
    return value


def _sha(f) -> str:
    return hashlib.sha256(f.path.read_bytes()).hexdigest()


def _value(rig, i: int, j: int):
    value = float(rig.sensors[i].params[j])
    if not rig.free[i, j]:
        return Markup('<span class="fixed">{} (fixed)</span>').format(f"{value:.7g}")
    return plus_minus(value, None if rig.uncertainty is None else float(rig.uncertainty[i, j]))


def _prism_value(rig, i: int, j: int):
    value = float(rig.sensors[i].prism[j])
    if not rig.prism_free[i, j]:
        return Markup('<span class="fixed">{} (fixed)</span>').format(f"{value:.7g}")
    u = None if rig.prism_uncertainty is None else float(rig.prism_uncertainty[i, j])
    return plus_minus(value, u)


def field_displacement(rig, i: int) -> dict | None:
    """Sensor ``i``'s correction field over its format, or None without one.

    ``rms_mm`` and ``largest_mm``: RMS and largest length of ``field.value`` on
    :func:`fringecal.lens.field.format_grid` (the grid the basis is orthonormal on, so
    ``rms_mm`` is ``sqrt(sum a_j^2)`` to rounding).
    ``u_rms_mm``: first-order standard uncertainty of that RMS from the coefficients'
    standard uncertainties ``u_j`` (``rig.field_uncertainty``, taken as uncorrelated:
    the file holds no covariance between them), ``sqrt(sum (a_j u_j)^2) / RMS``; None
    without them. ``noise_mm``: ``sqrt(sum u_j^2)``, the RMS a field of zero would show
    from the coefficients' noise alone (the estimated RMS is biased up by about it).
    """
    sensor = rig.sensors[i]
    if sensor.field is None or (sensor.field.is_zero and not rig.field_free[i]):
        return None
    field = sensor.field
    length = np.linalg.norm(field.value(format_grid(field.width_mm, field.height_mm)), axis=-1)
    out = {"rms_mm": float(np.sqrt(np.mean(length ** 2))), "largest_mm": float(length.max()), "u_rms_mm": None,
           "noise_mm": None}
    u = None if rig.field_uncertainty is None else np.asarray(rig.field_uncertainty[i], float)
    a = sensor.field.coefficients
    if u is not None and u.shape == a.shape and np.all(np.isfinite(u)):
        norm = float(np.sqrt(np.sum(a ** 2)))
        out["u_rms_mm"] = float(np.sqrt(np.sum((a * u) ** 2)) / norm) if norm > 0 else float(np.sqrt(np.max(u ** 2)))
        out["noise_mm"] = float(np.sqrt(np.sum(u ** 2)))
    return out


def _field_rows(rig, sensors) -> list:
    """Rows of the correction field's RMS and largest displacement (µm) of each sensor."""
    stats = [field_displacement(rig, i) for i in sensors]

    def rms(d):
        if d is None:
            return "none"
        if d["u_rms_mm"] is None:
            return num(d["rms_mm"] * 1e3, ".3g")
        return Markup("{} <span class=\"meta\">(noise alone {})</span>").format(
            plus_minus(d["rms_mm"] * 1e3, d["u_rms_mm"] * 1e3), num(d["noise_mm"] * 1e3, ".2g"))

    return [["correction field, RMS over the format", "µm", *(rms(d) for d in stats)],
            ["correction field, largest over the format", "µm",
             *("none" if d is None else num(d["largest_mm"] * 1e3, ".3g") for d in stats)]]


def _parameters(rig, k: int):
    """The parameter table of scanner ``k`` (camera and projector columns)."""
    sc = rig.scanners[k]
    first = 2 * k
    sensors = range(first, first + len(sc.sensors))
    rows = [[PARAM_LABELS[p], PARAM_UNITS[p], *(_value(rig, i, j) for i in sensors)] for j, p in enumerate(PARAM_NAMES)]
    if rig.has_prism:  # the thin-prism terms of a model that has them
        rows += [[f"thin prism {p}", unit, *(_prism_value(rig, i, j) for i in sensors)]
                 for j, (p, unit) in enumerate(zip(PRISM_NAMES, ("1/mm", "1/mm³", "1/mm", "1/mm³")))]
    if rig.has_field:  # the correction field's size, of a model that has one
        rows += _field_rows(rig, sensors)
    return table(["Parameter", "Unit"] + [f"{s.name} ({s.role})" for s in sc.sensors], rows, left=2)


def residual_maps(run: RunData, scanner: str) -> dict:
    """The residual and coverage maps of one scanner (``tables/residuals_binned.csv``)."""
    t = run.table(run.rd.residuals_binned)
    mine = t[t["scanner"].astype(str) == scanner]
    if mine.empty:
        raise Missing(f"{run.rd.residuals_binned.rel} holds no control point of {scanner}")
    rig = run.load(run.rd.calibration)
    formats = {s.name: s.format for s in rig.scanner(scanner).sensors}
    key = ("residuals", _sha(run.rd.residuals_binned), _sha(run.rd.calibration), scanner)
    png = _drawn(key, lambda: figures.residual_maps_png(mine, formats))
    n = int(mine[mine["role"] == "camera"]["n_points"].sum())
    cells = {role: (int((g["n_points"] > 0).sum()), int(g["nx"].iloc[0] * g["ny"].iloc[0]))
             for role, g in mine.groupby("role")}
    return {"image": Image(png, f"residuals and control points over the images of {scanner}"), "n": n,
            "covered": ", ".join(f"{role} {k} of {total} cells" for role, (k, total) in sorted(cells.items()))}


def observed_region(run: RunData, scanner: str) -> dict:
    """Where on its camera's and projector's image planes the calibration saw control
    points (:class:`~fringecal.lens.observed_region.ObservedRegion` of each sensor,
    ``calibration.json``): the figure of the grids and each sensor's covered fraction."""
    cal = run.calibration_file()
    sensors = cal.rig.scanner(scanner).sensors
    regions = [(s.name, s.role, cal.observed_regions[s.name]) for s in sensors if s.name in cal.observed_regions]
    if not regions:
        raise Missing(f"{run.rd.calibration.rel} records no observed region of {scanner} (a calibration written "
                      "before fringecal recorded it)")
    png = _drawn(("observed", _sha(run.rd.calibration), scanner), lambda: figures.observed_regions_png(regions))
    first = regions[0][2]
    return {"image": Image(png, f"regions of the image planes of {scanner} the calibration observed"),
            "fractions": ", ".join(f"{name} ({role}) {100 * r.fraction:.0f} %" for name, role, r in regions),
            "cells": f"{first.shape[1]} × {first.shape[0]}", "min_points": first.min_points}


def depths(run: RunData, scanner: str) -> tuple[list[float], str]:
    """Near, middle and far depth (mm) of the scanner's measuring volume, and where the
    volume comes from: the specification's (``acceptance.json``, else the run
    configuration), else the depths of the artefact spheres that gave control points."""
    spec = ((run.maybe_json(run.rd.acceptance) or {}).get("specification")
            or (run.config().get("acceptance") or {}).get("specification") or {})
    rng = spec.get("depth_range_mm") if isinstance(spec, dict) else None
    source = "the specified measuring volume"
    if not (isinstance(rng, (list, tuple)) and len(rng) == 2):
        from fringecal.verification.plan import volumes_from_run  # lazy: reads the control points

        try:
            rng = volumes_from_run(run.rd)[scanner].depth_range_mm
        except (KeyError, FileNotFoundError, OSError) as err:
            raise Missing(f"no measuring volume of {scanner}: no specification and no control points ({err})")
        source = "the depths of the artefact spheres that gave control points"
    lo, hi = float(rng[0]), float(rng[1])
    return [lo, (lo + hi) / 2, hi], source


def uncertainty_maps(run: RunData, scanner: str) -> dict:
    """The calibration's uncertainty of a measured point over the camera image at three
    depths (:func:`fringecal.calibration.propagation.uncertainty_at_depth`, the
    adjustment's and the artefact's covariance), relative to the frame the rig's sensors
    realise (:func:`~fringecal.calibration.propagation.frame_free_covariance`: how the
    world frame is fixed is no uncertainty of what is measured), as ``fringecal measure``
    states it."""
    from fringecal.calibration.propagation import (  # lazy: numba kernels
        frame_free_covariance,
        scanner_block,
        uncertainty_at_depth,
    )

    cal = run.calibration_file()
    if cal.covariances is None:
        raise Missing(f"{run.rd.calibration.rel} holds no covariance of the sensor parameters")
    rig = cal.rig
    at, source = depths(run, scanner)

    def draw():
        cov = scanner_block(frame_free_covariance(rig, cal.covariances.total), rig, scanner)
        maps = [uncertainty_at_depth(rig.scanner(scanner), cov, d, MAP_CELLS) for d in at]
        return maps, figures.uncertainty_maps_png(maps, rig.scanner(scanner).camera.format)

    maps, png = _drawn(("uncertainty", _sha(run.rd.calibration), scanner, tuple(at)), draw)
    medians = [float(np.nanmedian(m.u_mm)) if np.isfinite(m.u_mm).any() else float("nan") for m in maps]
    return {"image": Image(png, f"uncertainty of a measured point over the camera image of {scanner}"),
            "source": source, "depths": ", ".join(num(d, ".0f", "mm") for d in at),
            "medians": ", ".join(um(u, 1) for u in medians),
            "largest": um(max((float(np.nanmax(m.u_mm)) for m in maps if np.isfinite(m.u_mm).any()),
                              default=float("nan")))}


def acceptance_values(run: RunData, scanner: str, depths_title: str = "Camera depths"):
    """The scanner's acceptance parameters (``acceptance.json``) with the depths of their positions."""
    doc = run.json(run.rd.acceptance)
    depth = {}
    for v in doc.get("values") or []:
        if v.get("scanner") == scanner and finite(v.get("depth_mm")):
            lo = v.get("depth_near_mm") if finite(v.get("depth_near_mm")) else v["depth_mm"]
            a, b = depth.get(v.get("parameter"), (lo, v["depth_mm"]))
            depth[v.get("parameter")] = (min(a, lo), max(b, v["depth_mm"]))
    rows = []
    for p in doc.get("parameters") or []:
        if p.get("scanner") != scanner:
            continue
        d = depth.get(p.get("name"))
        verdict = str(p.get("verdict"))
        rows.append([f"{p.get('name')} {p.get('title') or ''}".strip(), p.get("positions"),
                     f"{num(d[0], '.0f')}-{num(d[1], '.0f')} mm" if d else "n/a", um(p.get("measured_mm")),
                     um(p.get("U_mm")), length(p.get("mpe_mm")) if p.get("mpe_mm") is not None else "not limited",
                     (verdict, VERDICT_CLASSES[verdict]) if verdict in VERDICT_CLASSES else verdict])
    if not rows:
        raise Missing(f"{run.rd.acceptance.rel} has no parameter of {scanner}")
    return table(["Parameter", "Positions", depths_title, "Measured", "U (k = 2)", "MPE", "Verdict"], rows, left=1)


#: a black box's transform parameters: (key of black_boxes.json, label, unit, factor from the file's unit)
_TRANSFORM = (("tx_mm", "t<sub>x</sub>", "mm", 1.0), ("ty_mm", "t<sub>y</sub>", "mm", 1.0),
              ("tz_mm", "t<sub>z</sub>", "mm", 1.0), ("omega_rad", "&omega;", "mrad", 1e3),
              ("phi_rad", "&phi;", "mrad", 1e3), ("kappa_rad", "&kappa;", "mrad", 1e3),
              ("scale", "scale k", "1", 1.0))


def _transform(run: RunData, d: dict):
    """A black box's origin, angles and scale with their standard uncertainties (a
    parameter held fixed, with zero uncertainty, is marked)."""
    rows = []
    for key, label, unit, f in _TRANSFORM:
        value, u = f * float(d[key]), f * float(d["std"][key])
        shown = plus_minus(value, u) if u > 0 else Markup('<span class="fixed">{} (fixed)</span>').format(
            f"{value:.7g}")
        rows.append([Markup(label), unit, shown])
    return table(["Parameter", "Unit", "Value ± u (k = 1)"], rows, left=2)


def _matrix(run: RunData, d: dict):
    """The 4x4 ``T_world_scanner`` (scale inside its 3x3), row by row."""
    return table(["", "1", "2", "3", "4"], [[f"row {i + 1}", *(f"{v:.9g}" for v in row)]
                                           for i, row in enumerate(d["matrix"])], left=1)


def black_box_parts(run: RunData) -> list[dict]:
    """One part per black-box scanner of ``black_boxes.json`` (none without it)."""
    doc = run.maybe_json(run.rd.black_boxes)
    if not doc:
        return []
    serials = (run.config().get("certificate") or {}).get("scanners") or {}
    return [{"name": d["scanner"], "serial": serials.get(d["scanner"]), "transform": guard(_transform, run, d),
             "matrix": guard(_matrix, run, d), "rms": um(d.get("rms_mm")), "n_centres": d.get("n_centres"),
             "reference": d["scanner"] == doc.get("reference"), "scale_free": bool(doc.get("scale")),
             "acceptance": guard(acceptance_values, run, d["scanner"], "Depths (its frame's z)")}
            for d in doc.get("scanners") or []]


def build(run: RunData) -> dict:
    """One part per scanner of the calibration, one per black box, and the correlations."""
    boxes = black_box_parts(run)
    if boxes and not run.rd.calibration.exists():  # black boxes only: no sensor model, no correlations to show
        return {"scanners": [], "black_boxes": boxes, "correlations": Shown(note="Not available: a rig of "
                                                                               "black-box scanners has no sensor "
                                                                               "parameters.")}
    rig = run.load(run.rd.calibration)
    serials = (run.config().get("certificate") or {}).get("scanners") or {}
    scanners = [{"name": sc.name, "serial": serials.get(sc.name), "parameters": _parameters(rig, k),
                 "field": rig.has_field,
                 "residuals": guard(residual_maps, run, sc.name), "observed": guard(observed_region, run, sc.name),
                 "uncertainty": guard(uncertainty_maps, run, sc.name),
                 "acceptance": guard(acceptance_values, run, sc.name)}
                for k, sc in enumerate(rig.scanners)]
    return {"scanners": scanners, "black_boxes": boxes, "correlations": guard(correlations, run)}


def correlations(run: RunData, k: int = 10) -> dict:
    """The ``k`` strongest correlations between sensor parameters, and how many pairs of
    adjusted parameters (artefact poses included) correlate by more than 0.99."""
    corr = run.json(run.rd.bundle_summary)["correlation"]
    names = list(corr["names"])
    m = np.asarray(corr["matrix"], float)
    iu = np.triu_indices(len(names), 1)
    r = m[iu]
    sensor = np.array([not n.startswith("pose[") for n in names])
    both = sensor[iu[0]] & sensor[iu[1]]
    top = np.flatnonzero(both)[np.argsort(-np.abs(r[both]), kind="stable")[:k]]
    rows = [[names[iu[0][t]], names[iu[1][t]], f"{r[t]:+.4f}"] for t in top]
    return {"table": table(["Parameter", "Parameter", "Correlation"], rows, left=2),
            "n_high": int((np.abs(r) > 0.99).sum())}
