"""Sensor models richer than the thesis's 14 parameters, chosen per run by held-out data.

Candidates (``SENSOR_MODELS``; ``bundle.sensor_model`` of a run)
-----------------------------------------------------------------
``brown14``
    The thesis's model (:mod:`fringecal.sensor`): radial k1..k3, tangential p1, p2.
``thin_prism``
    Plus the first-order thin-prism terms s1 (x) and s3 (y), ``dx += s1 r^2``,
    ``dy += s3 r^2``, of every camera and projector (OpenCV's s1, s3; Weng et al. 1992).
``thin_prism4``
    Plus OpenCV's fourth-order thin-prism terms s2, s4 as well (``+ s2 r^4``, ``+ s4 r^4``).
``field``
    The 14 parameters plus a smooth correction field over each camera's and projector's
    image plane (:mod:`fringecal.lens.field`: 19 orthonormal vector polynomials of degree
    2..4 per sensor, orthogonal to what the 14 parameters absorb; they span the thin-prism
    terms too, so this model does not free those). Regularised twice: by its basis (a
    fixed low degree), and by a prior that each coefficient is of order ``FIELD_PRIOR_MM``
    (F gains ``lambda |a|^2``, ``lambda = s0^2 / FIELD_PRIOR_MM^2`` with ``s0^2`` the
    variance per residual of the start values, the 14-parameter solution): the
    observations only cover parts of each image, where the basis is no longer orthogonal
    to a tilt, so without the prior a tilt traded against a principal-point shift and the
    field drifts along a direction the data hardly see. The held-out error below decides
    whether the data carry the field at all.
``auto`` (default)
    The candidate held-out measurements choose (below).

What the thin-prism terms can add
---------------------------------
To first order the r^2 thin-prism terms are *not* new: a small rotation phi of a sensor
about its y axis maps the ideal image by ``x -> x + phi (c + x^2/c)``, ``y -> y + phi x y/c``,
so the field ``(x^2, x y)`` is a tilt plus a principal-point shift, and
``s1 (r^2, 0) = s1 [(3x^2 + y^2, 2xy) - 2 (x^2, xy)]`` is tangential p1 minus that tilt
(likewise s3 with p2 and a rotation about x). Where the distortion is zero (start values
computed from the control points) the terms are exactly degenerate with p1, p2, the
angles and the principal point, so richer models are always adjusted from the
14-parameter solution; there they are determined only by the second-order remainder.
On noise-free simulated control points of the thesis rig with a thin-prism term of
0.2 px at the corner (2 px), the 14-parameter adjustment leaves 2.0 / 2.3 um RMS of
epsilon-1 / epsilon-2 (27 / 25 um) of the 45 / 54 um (227 / 639 um) the term causes
with the true 14 parameters: it absorbs about 95 % of the term.

Choice by cross-validation (``auto``)
-------------------------------------
The measurements are split into two halves (:func:`.crossval.split_measurements`,
alternating). For each candidate and each half, the sensors are adjusted on that half
alone (from the full 14-parameter solution, ``start="given"``) and then *predict* the
other half: with those sensors fixed only the other half's artefact poses are adjusted,
and the residuals left (epsilon-1, the rays' miss distance, does not depend on a pose at
all; epsilon-2 only through the six pose parameters of each measurement) are the
candidate's held-out error on data it never saw. Its figure is the held-out RMS of F
over both directions, in mm like the rest of the calibration; the truth is never used.

A richer candidate is eligible only if it predicts better than the 14 parameters by a
margin held-out noise cannot give: its held-out sum of squares must be lower than
brown14's by at least ``MIN_GAIN`` (0.5 %) *and* consistently over the measurements --
the per-measurement differences (brown14 minus candidate) must have a mean ``T_MIN`` (3)
standard errors above zero (a one-sided t statistic over the measurements; 12
measurements: 11 degrees of freedom, p ~ 0.006). Terms that only fit noise raise the
held-out error, so where the 14 parameters describe the images (the ideal profile) the
thesis's model stays and its figures are unchanged. Among brown14 and the eligible
candidates, the one with the lowest held-out error is the best, and the smallest one
(in the order of ``CANDIDATES``) whose held-out error is within ``ONE_SE`` (1) standard
error of the best's (the same paired t, candidate minus best) is chosen: the
one-standard-error rule of cross-validation (Hastie, Tibshirani and Friedman, section
7.10). A sequential rule (each candidate against the best so far, at ``T_MIN``) kept
``thin_prism4`` on a simulated 3 um lens error where the field predicted better at
t = 1.7 and measured the ball-bar to 410 against 522 um.

Screening (``bundle.model_selection``). Cross-validation costs four half-adjustments and
four pose-only fits per candidate (the bundle step of the demo run: about 1.7 s alone,
10-13 s with it on the loaded 2-core machine). With ``screened`` (default) it runs only
when the 14-parameter residuals keep a pattern over the images, residual-pattern
``Z > SCREEN_Z`` (3; :mod:`.adequacy`, whose verdict threshold is 5), or when the Wald
test of the thin-prism terms finds them (:func:`.wald.prism_check`, run on every
14-parameter solution the run may keep: about 1 s, 10-24 s more when W alone is
significant): without either there is nothing fixed to the image for a richer image
model to absorb, and the 14 parameters stay (the record says so, with Z and W).
``always`` cross-validates every run. The record's ``prism_wald`` holds the test; a
chosen model without thin-prism terms (or a field, which spans them) gets the warning
``lens_model_too_simple`` when they are present.

The result carries the choice and its evidence (``record``): every candidate's held-out
RMS, per-measurement sums, the gain and t statistic, how much the richer model inflates
the stated u of the 14 parameters in the half-adjustments (``u_inflation_max``,
``u_inflation_median``: the thin-prism terms trade against p1, p2, the angles and the
principal point, see above), and the residual-pattern statistic
of :mod:`.adequacy` of the 14-parameter fit and of the chosen one. The cost is four
half-adjustments and four pose-only fits per richer candidate, each from a solution
close to its minimum.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from fringecal.calibration.adequacy import residual_pattern
from fringecal.calibration.bundle import BundleOptions, BundleResult, bundle_adjust, minimise
from fringecal.calibration.candidates import CANDIDATES, fit_model, with_model
from fringecal.calibration.crossval import split_measurements, subproblem
from fringecal.calibration.model import BundleProblem, Evaluator
from fringecal.calibration.wald import prism_check, prism_diagnosis

__all__ = ["MIN_GAIN", "T_MIN", "ONE_SE", "SCREEN_Z", "held_out_error", "choose_by_held_out", "choose_sensor_model"]

#: smallest relative drop of the held-out sum of squares that chooses a richer model
MIN_GAIN = 0.005
#: smallest t statistic of the per-measurement held-out differences that chooses it
T_MIN = 3.0
#: a smaller eligible model within this many standard errors of the best is chosen
ONE_SE = 1.0
#: residual-pattern Z of the 14-parameter fit below which ``model_selection: screened``
#: keeps the 14 parameters without cross-validation
SCREEN_Z = 3.0
def _predict(fit: BundleResult, problem: BundleProblem, options: BundleOptions) -> np.ndarray:
    """Residuals (n, 2) of ``problem`` (other measurements) predicted by the sensors of
    ``fit``: only the poses adjusted, from ``problem``'s start values."""
    rig = replace(fit.rig, free=np.zeros_like(fit.rig.free), prism_free=np.zeros_like(fit.rig.prism_free),
                  field_free=np.zeros_like(fit.rig.field_free))
    test = problem.with_start(rig=rig)
    ev = Evaluator(test, chunk_size=options.chunk_size)
    x0 = ev.layout.pack_rig(rig, test.poses)
    e0 = ev.evaluate(x0, True)
    plain = options.model_copy(update={"robust_loss": "none", "coarse_points": 0})
    report, _, _ = minimise(ev, x0, e0, plain)
    return ev.evaluate(report.x, False).res


def held_out_error(problem: BundleProblem, options: BundleOptions, model: str, halves) -> dict:
    """Held-out error of ``model``: sensors adjusted on each half predict the other.

    ``problem`` holds the start values (the full 14-parameter solution). Returns the
    per-measurement held-out sums of squares (gamma-weighted, mm^2) and point counts,
    and the held-out RMS of F and of epsilon-1 and epsilon-2 (mm).
    """
    opts = options.model_copy(update={"start": "given", "bootstrap_draws": 0})
    full = with_model(problem, model)
    g1, g2 = problem.gamma1, problem.gamma2
    ss = {}
    count = {}
    sums = np.zeros(2)
    n = 0
    u = []
    for fit_half, test_half in ((halves[0], halves[1]), (halves[1], halves[0])):
        fit = bundle_adjust(subproblem(full, fit_half), opts)
        u.append(fit.rig.uncertainty)
        test = subproblem(problem, test_half)
        res = _predict(fit, test, opts)
        ok = np.all(np.isfinite(res), axis=1)
        for i, m in enumerate(test.measurements):
            sel = ok & (test.meas_idx == i)
            ss[m] = float(g1 * np.sum(res[sel, 0] ** 2) + g2 * np.sum(res[sel, 1] ** 2))
            count[m] = int(sel.sum())
        sums += np.sum(res[ok] ** 2, axis=0)
        n += int(ok.sum())
    return {"model": model, "sum_squares_mm2": ss, "n_points": count, "u_sensors": np.mean(u, axis=0).tolist(),
            "rms_f_mm": float(np.sqrt((g1 * sums[0] + g2 * sums[1]) / max(n, 1))),
            "rms_eps1_mm": float(np.sqrt(sums[0] / max(n, 1))), "rms_eps2_mm": float(np.sqrt(sums[1] / max(n, 1)))}


def _compare(simple: dict, rich: dict) -> dict:
    """Gain and t statistic of ``rich`` over ``simple`` (per-measurement held-out sums)."""
    ms = [m for m in simple["sum_squares_mm2"] if m in rich["sum_squares_mm2"]]
    d = np.array([simple["sum_squares_mm2"][m] - rich["sum_squares_mm2"][m] for m in ms])
    total = sum(simple["sum_squares_mm2"][m] for m in ms)
    gain = float(d.sum() / total) if total > 0 else 0.0
    t = float(d.mean() / (d.std(ddof=1) / np.sqrt(len(d)))) if len(d) > 1 and d.std(ddof=1) > 0 else 0.0
    better = gain >= MIN_GAIN and t >= T_MIN
    us, ur = np.asarray(simple["u_sensors"]), np.asarray(rich["u_sensors"])
    inflation = ur[us > 0] / us[us > 0]
    return {"simpler": simple["model"], "richer": rich["model"], "gain": gain, "t": t, "n_measurements": len(d),
            "richer_chosen": bool(better), "u_inflation_max": float(inflation.max()) if inflation.size else None,
            "u_inflation_median": float(np.median(inflation)) if inflation.size else None}


def choose_by_held_out(errors: dict) -> dict:
    """The model the held-out errors choose (the module notes): ``errors`` maps each model,
    ``brown14`` first and the others in order of size, to its :func:`held_out_error`
    (its ``model``, ``sum_squares_mm2``: measurement -> held-out sum of squares, and
    ``u_sensors`` are read). A richer model that predicts about as well as a smaller one
    is not chosen; one that predicts clearly better is:

    >>> def e(model, *ss):
    ...     return {"model": model, "sum_squares_mm2": dict(enumerate(ss)), "u_sensors": [1.0]}
    >>> base, prism = e("brown14", 10, 11, 12, 10), e("thin_prism", 8, 9, 10, 8.2)
    >>> choose_by_held_out({"brown14": base, "thin_prism": prism,
    ...                     "field": e("field", 7.7, 9.2, 9.75, 8.35)})["model"]
    'thin_prism'
    >>> choose_by_held_out({"brown14": base, "thin_prism": prism,
    ...                     "field": e("field", 6, 7.1, 8, 6.3)})["model"]
    'field'
    """
    models = list(errors)
    comparisons = [_compare(errors[models[0]], errors[m]) for m in models[1:]]
    eligible = [models[0]] + [c["richer"] for c in comparisons if c["richer_chosen"]]
    lowest = min(eligible, key=lambda m: sum(errors[m]["sum_squares_mm2"].values()))
    against = {m: 0.0 if m == lowest else _compare(errors[m], errors[lowest])["t"] for m in eligible}
    return {"model": next(m for m in eligible if against[m] < ONE_SE), "comparisons": comparisons,
            "eligible": eligible, "lowest_held_out": lowest, "t_against_lowest": against}


def choose_sensor_model(problem: BundleProblem, options: BundleOptions, candidates=tuple(CANDIDATES),
                        first: BundleResult | None = None, workers: int = 1) -> tuple[BundleResult, dict]:
    """The adjustment with the sensor model ``options.sensor_model`` (``auto``: chosen by
    held-out measurements among ``candidates``, see the module notes) and the record of
    that choice. ``first``: the 14-parameter adjustment of ``problem`` if already done;
    ``workers``: re-adjustments at once in the Wald test's jackknife."""
    t0 = time.perf_counter()
    wanted = options.sensor_model
    # the 14 parameters first, whatever the model: the thin-prism terms are degenerate with
    # p1, p2, a tilt and the principal point where the distortion is zero (the module
    # notes), so a richer model is adjusted from the 14-parameter solution
    first = fit_model(problem, options, "brown14") if first is None else first
    pattern_first = residual_pattern(first.problem, first.residuals, "brown14")
    prism = prism_check(first, options, workers=workers) if wanted in ("auto", "brown14") else None
    evidence = {} if prism is None else {"prism_wald": prism}
    if wanted != "auto":
        result, pattern = first, pattern_first
        if wanted != "brown14":
            start = problem.with_start(first.rig, first.poses)
            result = fit_model(start, options.model_copy(update={"start": "given"}), wanted)
            pattern = residual_pattern(result.problem, result.residuals, wanted)
        record = {"model": wanted, "chosen_by": "configuration (bundle.sensor_model)",
                  "residual_pattern_brown14": pattern_first.to_dict(), "residual_pattern": pattern.to_dict(),
                  **evidence, "seconds": time.perf_counter() - t0}
        return _with_verdicts(result, pattern, prism, wanted), record
    if options.model_selection == "screened" and not pattern_first.z_max > SCREEN_Z and not prism["present"]:
        record = {"model": "brown14",
                  "chosen_by": f"residual pattern (Z = {pattern_first.z_max:.1f} <= {SCREEN_Z:g}: no pattern over "
                               "the images for a richer model to absorb, and no thin-prism term; cross-validation "
                               "not run)",
                  "screen_z": SCREEN_Z, "residual_pattern": pattern_first.to_dict(), **evidence,
                  "seconds": time.perf_counter() - t0}
        return _with_verdicts(first, pattern_first, prism, "brown14"), record
    try:
        halves = split_measurements(problem)
    except ValueError as err:  # too few measurements per scanner for two halves
        record = {"model": "brown14", "chosen_by": f"default: no cross-validation possible ({err})",
                  "residual_pattern": pattern_first.to_dict(), **evidence, "seconds": time.perf_counter() - t0}
        return _with_verdicts(first, pattern_first, prism, "brown14"), record
    start = problem.with_start(first.rig, first.poses)
    errors = {"brown14": held_out_error(start, options, "brown14", halves)}
    for model in [m for m in CANDIDATES if m in candidates and m != "brown14"]:
        errors[model] = held_out_error(start, options, model, halves)
    choice = choose_by_held_out(errors)
    best = choice["model"]
    result, pattern = first, pattern_first
    if best != "brown14":
        result = fit_model(start, options.model_copy(update={"start": "given"}), best)
        pattern = residual_pattern(result.problem, result.residuals, best)
    record = {"model": best, "chosen_by": "cross-validation on held-out measurements",
              "halves": [list(h) for h in halves], "min_gain": MIN_GAIN, "t_min": T_MIN, "one_se": ONE_SE,
              "held_out": errors, "comparisons": choice["comparisons"], "eligible": choice["eligible"],
              "lowest_held_out": choice["lowest_held_out"], "t_against_lowest": choice["t_against_lowest"],
              "residual_pattern_brown14": pattern_first.to_dict(), "residual_pattern": pattern.to_dict(),
              **evidence, "seconds": time.perf_counter() - t0}
    return _with_verdicts(result, pattern, prism, best), record


def _with_verdicts(result: BundleResult, pattern, prism: dict | None, model: str) -> BundleResult:
    """``result`` with the residual pattern's and the thin-prism test's warnings among its
    diagnostics when they flag ``model``."""
    result = _with_pattern(result, pattern)
    d = None if prism is None else prism_diagnosis(prism, model)
    return result if d is None else replace(result, diagnostics=tuple(result.diagnostics) + (d,))


def _with_pattern(result: BundleResult, pattern) -> BundleResult:
    """``result`` with the residual-pattern warning among its diagnostics when it flags."""
    d = pattern.diagnosis()
    result.extra["residual_pattern"] = pattern.to_dict()
    if d is None:
        return result
    return replace(result, diagnostics=tuple(result.diagnostics) + (d,))
