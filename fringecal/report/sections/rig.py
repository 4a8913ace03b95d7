"""Rig and artefact: the scanners and sensors, the artefact and ball-bar, the
acquisition and hexapod moves, the labelling, scanner links and DLT start values."""

from __future__ import annotations

import numpy as np
import pandas as pd

from fringecal.report.formatting import finite, length, num, truthy, um, urad
from fringecal.report.rundata import Missing, RunData, failure, guard, numeric
from fringecal.report.tables import table

__all__ = ["build"]


def build(run: RunData) -> dict:
    """The section's four parts, each shown on its own (one missing file spoils none other)."""
    return {"scanners": guard(scanners, run), "artefact": guard(artefact, run),
            "acquisition": guard(acquisition, run), "processing": guard(processing, run)}


def scanners(run: RunData) -> dict:
    """The scanners and their sensors' formats (``calibration.json``)."""
    rig = run.load(run.rd.calibration)
    rows = []
    for sc in rig.scanners:
        for s in sc.sensors:
            f = s.format
            rows.append([sc.name + (" (reference)" if sc.name == rig.reference else ""), s.name, s.role,
                         f"{f.width_px} × {f.height_px} px", f"{f.width_mm:g} × {f.height_mm:g} mm",
                         um(f.width_mm / f.width_px, 2)])
    return {"n_scanners": len(rig.scanners), "n_sensors": len(rig.sensors), "reference": rig.reference,
            "table": table(["Scanner", "Sensor", "Role", "Format", "Image size", "Pixel pitch"], rows, left=3)}


def _rods(run: RunData, art) -> str:
    try:
        return f"{len(run.load(run.rd.rods, art))}"
    except Missing:
        return "none recorded for this run"
    except ValueError as err:
        return f"could not be read: {run.clean(str(err))}"


def _ballbar(run: RunData) -> str:
    rd = run.rd
    try:
        bar = run.load(rd.ballbar)
    except Missing as why:
        return str(why) if rd.verification.exists() else "none in this run (the calibration is not verified)"
    except ValueError as err:
        return f"could not be read: {run.clean(str(err))}"
    distance = float(np.linalg.norm(bar.centres[1] - bar.centres[0])) if len(bar) >= 2 else float("nan")
    return (f"spheres {', '.join(bar.ids)}, diameters {', '.join(f'{x:.3f}' for x in bar.diameters)} mm, "
            f"centre distance {num(distance, '.4f', 'mm')} (CMM)")


def artefact(run: RunData) -> dict:
    """The artefact (``artefact.csv``, ``rods.csv``), the volume diagonal and the ball-bar."""
    art = run.load(run.rd.artefact)
    bs = run.maybe_json(run.rd.bundle_summary) or {}
    diagonal = bs.get("volume_diagonal_mm")
    return {"spheres": f"{len(art)} (diameters {art.diameters.min():.3f} to {art.diameters.max():.3f} mm)",
            "rods": _rods(run, art),
            "largest_distance": num(float(art.distance_matrix().max()), ".1f", "mm"),
            "centre_diagonal": num(art.diagonal_mm, ".1f", "mm"),
            "centre_u": um(float(art.u.max())) if art.u.max() > 0 else "not given",
            "volume_diagonal": (f"{num(diagonal, '.1f', 'mm')} "
                                f"({bs.get('volume_diagonal_source', 'source not recorded')})"
                                if finite(diagonal) else None),
            "ballbar": _ballbar(run)}


def _acquisition_counts(acq: pd.DataFrame) -> dict:
    art = acq[acq["kind"] == "artefact"]
    bar = acq[acq["kind"] == "ballbar"]
    external = acq[acq["source"].astype(str) != "simulated"]
    return {"artefact": f"{len(art)} from {art['pose'].nunique()} artefact poses and {art['scanner'].nunique()} "
                        f"scanner(s)",
            "ballbar": f"{len(bar)} from {bar['pose'].nunique()} positions" if len(bar) else
                       "none (the calibration is not verified)",
            "external": f"{len(external)} image stacks or stores" if len(external) else None,
            "rendered": f"{len(acq)} stores" if not len(external) and len(acq) else None}


def acquisition(run: RunData) -> dict:
    """The data source and what was recorded (``tables/acquisition.csv``), and the hexapod."""
    width = (run.simulation().get("acquisition") or {}).get("camera_width_px")
    out = {"source": run.source_text(),
           "camera_width": f"{width} px wide" if run.source() == "simulated" and width else None,
           "counts": None, "table_missing": None, "poses_in_adjustment": None, "table_error": None,
           "hexapod": guard(hexapod, run)}
    try:
        out["counts"] = _acquisition_counts(run.table(run.rd.acquisition))
    except Missing as why:
        bs = run.maybe_json(run.rd.bundle_summary) or {}
        out["poses_in_adjustment"] = bs.get("n_measurements")
        out["table_missing"] = f"not available: {why}"
    except (ValueError, KeyError) as err:  # a malformed table: named, the hexapod part still shown
        out["table_error"] = failure(run, err)
    return out


def hexapod(run: RunData) -> dict:
    """Planned vs reached artefact poses (``tables/hexapod_moves.csv``), or why there are none."""
    try:
        poses = run.table(run.rd.hexapod_moves)
    except Missing as why:
        return {"moves": None, "dataset": run.source() == "dataset", "missing": str(why)}
    t, r = poses["translation_error_mm"].astype(float), poses["rotation_error_rad"].astype(float)
    rows = [[p.measurement, um(p.translation_error_mm), urad(p.rotation_error_rad),
             f"{p.tx_mm:.3f}, {p.ty_mm:.3f}, {p.tz_mm:.3f}"] for p in poses.itertuples()]
    return {"moves": {"used": bool(poses["hexapod"].map(truthy).any()),
                      "translation_max": um(t.max()), "translation_rms": um(float(np.sqrt(np.mean(t ** 2)))),
                      "rotation_max": urad(r.max()),
                      "table": table(["Pose", "Translation error", "Rotation error", "Reached t (mm)"], rows)}}


def processing(run: RunData) -> dict:
    """Labelling outcomes, scanner links and DLT start values."""
    out = {"labelling": None, "labelling_missing": None,
           "links": guard(links, run), "dlt": guard(dlt, run)}
    try:
        lab = run.table(run.rd.label_outcomes)
    except Missing as why:
        out["labelling_missing"] = str(why)
        return out
    bad = lab[lab["status"] != "labelled"]
    refusals = [[r.measurement, r.scanner,
                 "; ".join(str(x) for x in (r.reason, r.message) if pd.notna(x) and str(x))]
                for r in bad.itertuples()]
    out["labelling"] = {"labelled": int((lab["status"] == "labelled").sum()), "total": len(lab),
                        "refusals": table(["Measurement", "Scanner", "Reason"], refusals, left=3)
                        if refusals else None}
    return out


def links(run: RunData):
    """How each scanner was linked to the reference for the start values (None: no table)."""
    try:
        t = run.table(run.rd.scanner_links)
    except Missing:
        return None
    return table(["Scanner", "Linked to", "Via", "Measurements", "Translation spread", "Rotation spread"],
                 [[r.scanner, r.reference, r.via, r.n_measurements, length(r.translation_spread_mm),
                   urad(r.rotation_spread_rad)] for r in t.itertuples()], left=3)


def dlt(run: RunData):
    """The DLT start values' reprojection RMS per sensor (None: no table)."""
    try:
        t = numeric(run.table(run.rd.dlt))
    except Missing:
        return None
    return table(["Sensor", "Points", "Reprojection RMS", "Method"],
                 [[r.sensor, r.n_points, um(r.reprojection_rms_mm, 2), r.method] for r in t.itertuples()])
