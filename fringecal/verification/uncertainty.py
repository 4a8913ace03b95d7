"""Every ball-bar length with its own uncertainty budget and the ISO 14253-1 verdict.

For each measured length (one per position and pair of scanners) the budget of
:mod:`fringecal.verification.budget` (calibration, artefact CMM, artefact temperature,
sphere fits, bar certificate, bar temperature), its expanded uncertainty U = k u_c, the
Monte Carlo check of the linear propagation, and two judgements:

* **ISO 14253-1** (the decision rule for conformity with a specification): conformance
  is proven only when ``|error| + U <= MPE``, non-conformance only when ``|error| - U >
  MPE``; in between the length lies in the uncertainty zone and neither is proven.
* **Covered by the budget**: ``|error| <= U``. A length error beyond its expanded
  uncertainty means an error source the budget does not hold (an artefact whose scale
  differs from its table, an unmodelled lens term, ...). For k = 2 about one length in
  twenty may exceed U by chance; the summary says how many did.

Model error. Every length is measured again with the sensors of each replica of the
delete-one-measurement jackknife (:mod:`fringecal.calibration.jackknife`, in
``calibration_covariance.npz``) and of the same jackknife in worlds of noise alone; the
jackknife variance holds what differs between the calibration's measurements, the
observation noise the linear ``calibration`` term states and what that term cannot see
(a smooth phase error of one measurement, drift), and the noise worlds' variance what
it holds when the noise is all there is, so ``u_calibration sqrt(max(0, var_J /
var_J,noise - 1))`` is the length's ``model error (cross-validation)``: one figure per
length, as large as the calibration's geometry makes it there. With the
cross-validation's half-calibrations every length is also measured with each half and
the difference compared with its predicted uncertainty (RMS of the normalised differences against
``CROSSVAL_RMS_Z_MAX``): a check reported beside, no longer a budget term, since a half
of few poses errs along its weak directions far beyond what the full calibration does
(:mod:`fringecal.calibration.jackknife` has the case).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd

from fringecal.calibration.keyed import value_key
from fringecal.calibration.propagation import parameter_covariances
from fringecal.rig import Rig
from fringecal.spheres.pixel_integration import phase_integration_bias
from fringecal.store import open_store
from fringecal.verification.ballbar import SightingConfig
from fringecal.verification.budget import (
    BUDGET_TERMS,
    SightingModel,
    SightingPoints,
    block_params,
    bootstrap_bias,
    jackknife_model_error,
    length_budget,
    length_gradient,
    monte_carlo_lengths,
    refitted_length,
    sighting_model,
    validate_linear,
)
from fringecal.verification.measure import store_scanner

__all__ = ["sighting_points", "ballbar_uncertainty", "iso14253_verdict", "monte_carlo_disagreement", "scaled_fit"]


def sighting_points(store, rig: Rig, scanner: str, pixels, centre, radius_mm: float, rms_mm: float,
                    pixel_integration_px: float = SightingConfig().pixel_integration_px) -> SightingPoints:
    """The kept pixels of one sphere fit in image-plane mm, read from its store, their
    phases corrected for pixel integration against the fitted sphere as the fit's
    points were (:func:`fringecal.verification.ballbar.refit_sighting`), so that the
    Monte Carlo and the bootstrap re-triangulate the points the length was measured
    from."""
    rows, cols = (np.asarray(a, int) for a in pixels)
    with open_store(store) as ds:
        sc = store_scanner(ds, rig.scanner(scanner))
        tau = np.stack([ds["tau_x"].values[rows, cols], ds["tau_y"].values[rows, cols]], axis=-1).astype(float)
    block = [s.name for s in rig.scanners].index(scanner)
    uv = np.stack([cols, rows], axis=-1).astype(float)
    centre = np.asarray(centre, float)
    bias = phase_integration_bias(sc.camera, sc.projector, uv, np.broadcast_to(centre, (len(uv), 3)),
                                  np.full(len(uv), float(radius_mm)), pixel_integration_px)
    tau = tau - np.nan_to_num(bias)
    return SightingPoints(sc, block, sc.camera.image_mm(uv), sc.projector.image_mm(tau), centre, float(radius_mm),
                          float(rms_mm))


def iso14253_verdict(error_mm: float, U_mm: float, mpe_mm: float | None) -> str:
    """``conformance``, ``non-conformance`` or ``uncertainty zone`` (ISO 14253-1)."""
    if mpe_mm is None or not np.isfinite(error_mm):
        return "uncertainty zone"
    if abs(error_mm) + U_mm <= mpe_mm:
        return "conformance"
    if abs(error_mm) - U_mm > mpe_mm:
        return "non-conformance"
    return "uncertainty zone"


def ballbar_uncertainty(centres: pd.DataFrame, pixels: dict, stores: dict, rig: Rig, lengths: pd.DataFrame,
                        reference_length_mm: float, arrays: dict, config, mpe_mm: float | None,
                        certificate_u_mm: float, ids=("A", "B"), workers: int = 2,
                        halves: dict | None = None, points_verdict: str | None = None,
                        fit_factors: dict | None = None) -> dict:
    """Budget, expanded uncertainty, Monte Carlo check and verdicts of every length.

    Parameters
    ----------
    centres : the ball-bar centres table (``position, scanner, sphere_id, x_mm, ...``)
    pixels : (position, scanner, sphere_id) -> (rows, cols) of each fit's kept pixels
    stores : position -> scanner -> store path
    rig : the calibrated rig; lengths : :func:`fringecal.verification.lengths.ballbar_lengths`
    arrays : the run's ``calibration_covariance.npz`` (with ``jackknife_params`` each
        length gets its model-error term from the jackknife replicas)
    config : :class:`~fringecal.verification.settings.LengthUncertaintyConfig`
    certificate_u_mm : standard uncertainty of the certified length
    workers : threads for the lengths' Monte Carlo runs
    halves : the run's ``crossval_halves.npz`` arrays (the lengths are then also
        cross-validated: measured with each half-calibration and compared)
    points_verdict : the cross-validation's verdict on the points (``crossval.json``)
    fit_factors : scanner -> factor (>= 1) on its sphere fits' standard uncertainty: the
        scatter of its centres between spheres in the calibration's views
        (:mod:`fringecal.spheres.dispersion`, ``max(1, kappa)``), which a fit's own
        residuals do not hold; it scales each fit's covariance (the ``sphere fits`` term),
        and the Monte Carlo moves each refitted centre by a draw of the difference

    Returns a JSON-ready dict: ``lengths`` (one entry per length, in ``lengths`` order),
    ``budget`` (per contribution the RMS over the lengths and the value at the length
    of largest error), ``coverage_factor``, ``not_covered``, the ``monte_carlo`` summary
    and the ``cross_validation`` summary (None without ``halves``).
    """
    cov = parameter_covariances(arrays, abs(config.artefact_cte_per_c) * config.artefact_temperature_u_c,
                                config.artefact_u_factor)
    std_all = np.sqrt(np.clip(np.diag(cov.total), 0, None))
    u_bar_rel = abs(config.ballbar_cte_per_c) * config.ballbar_temperature_u_c
    k = config.coverage_factor
    models = {}
    for r in centres.itertuples():
        key = (str(r.position), str(r.scanner), str(r.sphere_id))
        pts = sighting_points(stores[key[0]][key[1]], rig, key[1], pixels[key], (r.x_mm, r.y_mm, r.z_mm),
                              r.radius_mm, r.rms_mm)
        models[key] = scaled_fit(sighting_model(pts, std_all[28 * pts.block:28 * pts.block + 28]),
                                 (fit_factors or {}).get(key[1], 1.0))

    cross = None if halves is None else _cross_validated(models, lengths, halves, len(cov.scale), ids,
                                                         points_verdict)
    replicas, noise = arrays.get("jackknife_params"), arrays.get("jackknife_noise_params")
    jackknifed = replicas is not None and noise is not None and len(replicas) >= 2 and len(noise) > 0
    boot = arrays["bootstrap_params"] if "bootstrap_params" in arrays else None
    if boot is not None and len(boot) < 2:
        boot = None

    def one(i_row):
        i, r = i_row
        a = models[(str(r.position), str(r.scanner_a), ids[0])]
        b = models[(str(r.position), str(r.scanner_b), ids[1])]
        bias = u_bias = spread = 0.0
        if boot is not None:
            bias, u_bias, spread = bootstrap_bias(a.points, b.points, boot)
        jack = None
        if jackknifed:
            extended = cov.field is not None and replicas.shape[-1] > 14
            jack = jackknife_model_error(a, b, replicas, noise, cov.field.calibration if extended else cov.calibration,
                                         cov.field.n_terms if extended else 0)
        u_model = 0.0 if jack is None else jack["model_error_mm"]
        budget = length_budget(a, b, cov, certificate_u_mm, u_bar_rel, u_model, u_bias)
        u = budget.combined_mm
        length = float(r.length_mm) - bias
        error = length - reference_length_mm
        entry = {"measurement": str(r.measurement), "length_mm": length, "error_mm": error,
                 "u_mm": u, "U_mm": k * u, "budget_mm": budget.u_mm,
                 "iso14253": iso14253_verdict(error, k * u, mpe_mm), "covered": bool(abs(error) <= k * u)}
        if jack is not None:
            entry["jackknife"] = jack
        if boot is not None:
            entry["calibration_bias"] = {"length_uncorrected_mm": float(r.length_mm), "bias_mm": bias,
                                         "u_bias_mm": u_bias, "bootstrap_spread_mm": spread, "draws": int(len(boot))}
        if config.monte_carlo_draws > 0:
            # per length, keyed by its measured value: the same draws in any thread, order or naming
            rng = np.random.default_rng([config.seed, value_key(float(r.length_mm))])
            f = fit_factors or {}
            samples = monte_carlo_lengths(a.points, b.points, cov, certificate_u_mm, u_bar_rel,
                                          config.monte_carlo_draws, rng, u_model,
                                          (_shift(a, f.get(str(r.scanner_a), 1.0)),
                                           _shift(b, f.get(str(r.scanner_b), 1.0))))
            samples = samples - bias + u_bias * rng.standard_normal(len(samples))
            entry["monte_carlo"] = validate_linear(length, u, k, samples)
        return entry

    with ThreadPoolExecutor(max_workers=workers) as pool:
        out = list(pool.map(one, enumerate(lengths.itertuples())))
    if cross is not None:
        for entry, c in zip(out, cross["lengths"]):
            entry["cross_validation"] = c
    return {"coverage_factor": k, "lengths": out, "budget": _budget(out), "fit_factors": dict(fit_factors or {}),
            "not_covered": [e["measurement"] for e in out if not e["covered"]],
            "monte_carlo": _mc_summary(out),
            "cross_validation": None if cross is None else {k_: v for k_, v in cross.items() if k_ != "lengths"},
            "jackknife": None if not jackknifed else {
                "replicas": int(len(replicas)), "model_error_rms_mm": _rms([e["jackknife"]["model_error_mm"] for e in out])}}


#: RMS of the halves' normalised length differences above which they disagree: with
#: the stated uncertainty right it is 1; its scatter over 9 lengths is about 0.25
CROSSVAL_RMS_Z_MAX = 2.0


def scaled_fit(model: SightingModel, factor: float) -> SightingModel:
    """``model`` with its fit's standard uncertainty times ``factor`` (its covariance
    times ``factor**2``)."""
    if factor == 1.0:
        return model
    return SightingModel(model.points, model.J, model.C_fit * factor**2, model.J_field)


def _shift(model: SightingModel, factor: float) -> np.ndarray:
    """The part of a scaled fit's covariance beyond its points' own noise (what the Monte
    Carlo draws as a shift of the whole sighting): ``(1 - 1 / factor^2) C_fit``."""
    return model.C_fit * (1.0 - 1.0 / factor**2)


def _rms(values) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else 0.0


def _cross_validated(models: dict, lengths: pd.DataFrame, halves: dict, n_params: int, ids,
                     points_verdict: str | None = None) -> dict:
    """Every length measured with each half-calibration (``crossval_halves.npz``), the
    difference against its predicted standard uncertainty sqrt(g^T (C_a + C_b) g): the
    fits' own noise is common to both and cancels, the calibrations' errors do not.

    A check, not a budget term (the jackknife gives that). ``halves_excess_mm`` is the
    halves' excess per half-calibration when both the lengths and the points call it
    model error. Lengths that disagree while the points agree are ``inconclusive``:
    seen with half calibrations of few poses each (4 and 3 at 320 px), whose weak
    directions make the linear prediction of their difference far too small."""
    C = halves["covariance_a"] + halves["covariance_b"]

    def params(which: str, block: int) -> np.ndarray:
        return block_params(halves[f"params_{which}"], block)

    rows = []
    for r in lengths.itertuples():
        a = models[(str(r.position), str(r.scanner_a), ids[0])]
        b = models[(str(r.position), str(r.scanner_b), ids[1])]
        g, _, _ = length_gradient(a, b, n_params)
        la = refitted_length(a.points, b.points, params("a", a.points.block), params("a", b.points.block))
        lb = refitted_length(a.points, b.points, params("b", a.points.block), params("b", b.points.block))
        u = float(np.sqrt(max(g @ C @ g, 0.0)))
        rows.append({"length_a_mm": la, "length_b_mm": lb, "difference_mm": la - lb, "u_predicted_mm": u,
                     "z": (la - lb) / u if u > 0 else None})
    d = np.array([x["difference_mm"] for x in rows])
    u = np.array([x["u_predicted_mm"] for x in rows])
    rms_z = float(np.sqrt(np.mean((d / u) ** 2))) if len(d) and np.all(u > 0) else None
    excess = float(np.sqrt(max(0.0, np.mean(d**2) - np.mean(u**2)) / 2)) if len(d) else 0.0
    if rms_z is not None and rms_z <= CROSSVAL_RMS_Z_MAX:
        verdict = "consistent"
    elif points_verdict is not None and points_verdict != "model error":
        verdict = "inconclusive"
    else:
        verdict = "model error"
    return {"lengths": rows, "rms_z": rms_z, "rms_z_max": CROSSVAL_RMS_Z_MAX, "verdict": verdict,
            "points_verdict": points_verdict, "halves_excess_mm": excess if verdict == "model error" else 0.0}


def _budget(entries: list) -> dict:
    if not entries:
        return {}
    worst = max(entries, key=lambda e: abs(e["error_mm"]))
    rms = {t: float(np.sqrt(np.mean([e["budget_mm"][t] ** 2 for e in entries]))) for t in BUDGET_TERMS}
    return {"terms": list(BUDGET_TERMS), "rms_mm": rms, "largest_error": {
        "measurement": worst["measurement"], "error_mm": worst["error_mm"], "u_mm": worst["u_mm"],
        "U_mm": worst["U_mm"], "budget_mm": worst["budget_mm"], "iso14253": worst["iso14253"]}}


def monte_carlo_disagreement(measurement: str, mc: dict) -> str:
    """One line saying how a length's Monte Carlo check (:func:`validate_linear`'s
    dict) disagrees with its linear propagation, with the numbers that show it: both
    95 % intervals, how far their ends lie apart, the tolerance and where it comes
    from, and both standard uncertainties (um)."""
    lin, mcs = mc["linear_interval_mm"], mc["mc_interval_mm"]
    return (f"{measurement}: linear interval [{lin[0]:.4f}, {lin[1]:.4f}] mm, Monte Carlo [{mcs[0]:.4f}, "
            f"{mcs[1]:.4f}] mm ({mc['draws']} draws): ends {1000 * mc['d_low_mm']:.1f} / "
            f"{1000 * mc['d_high_mm']:.1f} um apart, tolerance {1000 * mc['tolerance_mm']:.1f} um "
            f"({mc['tolerance_source']}); u {1000 * mc['u_linear_mm']:.1f} um linear, "
            f"{1000 * mc['u_mc_mm']:.1f} um Monte Carlo")


def _mc_summary(entries: list) -> dict | None:
    mc = [e["monte_carlo"] for e in entries if "monte_carlo" in e]
    if not mc:
        return None
    ratios = np.array([m["ratio"] for m in mc], float)
    off = [e for e in entries if "monte_carlo" in e and not e["monte_carlo"]["agree"]]
    return {"draws": mc[0]["draws"], "ratio_min": float(ratios.min()), "ratio_max": float(ratios.max()),
            "all_agree": bool(all(m["agree"] for m in mc)),
            "disagree": [e["measurement"] for e in off],
            "disagreements": [monte_carlo_disagreement(e["measurement"], e["monte_carlo"]) for e in off]}
