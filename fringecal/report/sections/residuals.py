"""Residuals: the histograms of the run, the residuals per measurement and per sphere
image, and the sensor model the data chose with the residual-pattern statistic
(``bundle_summary.json``'s ``sensor_model``; :mod:`fringecal.calibration.models`,
:mod:`fringecal.calibration.adequacy`)."""

from __future__ import annotations

from fringecal.fringe.measurement import decoding_summary
from fringecal.report.figures import Image
from fringecal.report.formatting import length, natural, um
from fringecal.report.rundata import Missing, RunData, guard
from fringecal.report.tables import table

__all__ = ["build", "decoding", "per_measurement", "per_sphere", "sensor_model", "sphere_scatter"]

SPHERE_HEADS = ["Measurement", "Scanner", "Sphere", "Points", "RMS ε1", "RMS ε2", "Mean ε2", "Max |ε2|"]


def build(run: RunData) -> dict:
    """The two histograms (``figures/eps{1,2}_hist.png``; a note for one that is missing) and the tables."""
    histograms = []
    for term, alt in (("eps1", "ε1 histogram"), ("eps2", "ε2 histogram")):
        try:
            histograms.append({"image": Image(run.load(run.rd.histogram(term)), alt), "missing": None})
        except Missing as why:
            histograms.append({"image": None, "missing": f"Not available: {why}."})
    return {"histograms": histograms, "decoding": guard(decoding, run), "sensor_model": guard(sensor_model, run),
            "sphere_scatter": guard(sphere_scatter, run),
            "per_measurement": guard(per_measurement, run), "per_sphere": guard(per_sphere, run)}


def decoding(run: RunData) -> dict:
    """Per scanner, what the decoder found in its stacks (each store's summary:
    :func:`fringecal.fringe.measurement.decoding_summary`): valid pixels, phase noise and
    the phase ripple it corrected."""
    rec = decoding_summary(run.rd.store_summaries())
    if not rec:
        raise Missing("the run has no decoded image stack (black-box clouds only)")
    rows = []
    for d in rec:
        r = d["phase_ripple"]
        noise = d["phase_noise_median_rad"]
        fixed = r["corrected"]
        rows.append([d["scanner"], d["stacks"], f"{100 * d['valid_fraction_median']:.1f} %",
                     " / ".join(f"{1000 * noise[o]:.1f}" for o in sorted(noise)), r["fits"],
                     "-" if r["largest_z"] is None else f"{r['largest_z']:.1f}",
                     f"{len(fixed)}: largest {1000 * r['largest_corrected_rms_rad']:.1f} mrad RMS"
                     if fixed else "none"])
    corrected = [c for d in rec for c in d["phase_ripple"]["corrected"]]
    return {"table": table(["Scanner", "Stacks", "Valid pixels (median)", "Phase noise x / y (mrad, median)",
                            "Ripple fits", "Largest Z", "Corrected"], rows, left=1),
            "corrected": ", ".join(corrected)}


def sensor_model(run: RunData) -> dict:
    """The model used, how it was chosen, every candidate's held-out error, the
    residual-pattern statistic per sensor image (its value and threshold) and the Wald
    test of the thin-prism terms (``prism_wald``; absent in runs before it)."""
    rec = run.json(run.rd.bundle_summary).get("sensor_model")
    if rec is None:
        raise Missing("this run's bundle_summary.json has no sensor_model (a run before issue 29)")
    pattern = rec["residual_pattern"]
    held = rec.get("held_out") or {}
    cmp = {c["richer"]: c for c in rec.get("comparisons") or []}
    against = rec.get("t_against_lowest") or {}
    candidates = None
    if held:
        rows = []
        for name, e in held.items():
            c = cmp.get(name)
            rows.append([name, um(e["rms_f_mm"]), um(e["rms_eps1_mm"]), um(e["rms_eps2_mm"]),
                         "" if c is None else f"{100 * c['gain']:+.2f} % vs {c['simpler']}",
                         "" if c is None else f"{c['t']:.1f}",
                         "" if name not in against else f"{against[name]:.1f}",
                         "chosen" if name == rec["model"] else ""])
        candidates = table(["Model", "Held-out RMS F", "RMS ε1", "RMS ε2", "Gain", "t", "t vs lowest", ""], rows,
                           left=1)
    stats = table(["Scanner", "Sensor", "Residual", "Z", "Pattern RMS", "Bins"],
                  [[s["scanner"], s["sensor"], s["residual"], f"{s['z']:.1f}", f"{s['systematic_um']:.1f} um",
                    s["n_bins"]] for s in pattern["statistics"]], left=3)
    prism = rec.get("prism_wald")
    wald = None
    if prism is not None and "W" in prism:
        wald = table(["Sensor", "W (2 terms)", "p"], [[name, f"{w['W']:.1f}", f"{w['p']:.2g}"]
                                                      for name, w in prism["per_sensor"].items()], left=1)
    return {"prism": prism, "prism_table": wald, "model": rec["model"], "chosen_by": rec["chosen_by"],
            "min_gain": rec.get("min_gain"),
            "t_min": rec.get("t_min"), "one_se": rec.get("one_se", "-"), "candidates": candidates, "message": pattern["message"],
            "too_simple": pattern["too_simple"], "z_max": pattern["z_max"], "threshold": pattern["threshold"],
            "statistics": stats}


def sphere_scatter(run: RunData):
    """Per scanner, the scatter of its sphere centres between spheres in the calibration's
    views against their fits' stated u (``bundle_summary.json``'s ``sighting_dispersion``,
    :mod:`fringecal.spheres.dispersion`) and the factor the length budgets apply."""
    rec = run.json(run.rd.bundle_summary).get("sighting_dispersion")
    if not rec:
        raise Missing("this run's bundle_summary.json has no sighting_dispersion (a run before it was measured)")
    return table(["Scanner", "kappa", "Factor on the sphere fits' u", "Views", "Sightings", "Degrees of freedom"],
                 [[s, f"{d['kappa']:.2f}", f"{max(1.0, d['kappa']):.2f}", d["views"], d["sightings"], d["dof"]]
                  for s, d in rec.items()], left=1)


def per_measurement(run: RunData):
    """RMS residuals per measurement (``tables/residuals_per_measurement.csv``), in natural order."""
    t = run.table(run.rd.residuals_per_measurement)
    t = t.iloc[sorted(range(len(t)), key=lambda i: natural(t["measurement"].iloc[i]))]
    return table(["Measurement", "Scanners", "Points", "Spheres", "RMS ε1", "RMS ε2", "Mean ε2", "RMS ε2 at start"],
                 [[r.measurement, r.scanners, r.n_points, r.n_spheres, um(r.rms_eps1_mm), um(r.rms_eps2_mm),
                   um(r.mean_eps2_mm), length(r.rms_eps2_start_mm)] for r in t.itertuples()], left=2)


def per_sphere(run: RunData, show: int = 10, most: int = 300) -> dict:
    """Sphere images worst first (``tables/residuals_per_sphere.csv``): ``show`` on the
    page, up to ``most`` in a fold-out."""
    f = run.rd.residuals_per_sphere
    t = run.table(f).sort_values("rms_eps2_mm", ascending=False)
    rows = [[r.measurement, r.scanner, r.sphere_id, r.n_points, um(r.rms_eps1_mm), um(r.rms_eps2_mm),
             um(r.mean_eps2_mm), um(r.max_abs_eps2_mm)] for r in t.itertuples()]
    more = None
    if len(rows) > show:
        title = (f"All {len(rows)} sphere images" if len(rows) <= most else
                 f"The worst {most} of {len(rows)} sphere images (all in {f.rel})")
        more = {"title": title, "table": table(SPHERE_HEADS, rows[:most], left=3)}
    return {"n": len(rows), "worst": table(SPHERE_HEADS, rows[:show], left=3), "more": more}
