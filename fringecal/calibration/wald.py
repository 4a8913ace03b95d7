"""Is a thin-prism lens term there at all? A Wald test of the terms against zero.

The 14 parameters absorb about 95 % of a thin-prism term (:mod:`.models`): what remains
is spread over every image bin, below what the residual pattern (:mod:`.adequacy`) or
held-out prediction can resolve. The test asks directly: the ``thin_prism`` model is
adjusted from the 14-parameter solution and

    W = a^T C^-1 a

over its terms ``a`` (s1, s3 of every camera and projector) with their stated covariance
``C`` is chi-square with one degree of freedom per term (8 on a two-scanner rig) when
the 14 parameters describe the images.

``C`` takes every control point's error as independent. Errors shared by one
measurement's points (a smooth phase error over its image) move the terms from
measurement to measurement far more than ``C`` says, and W grows with them. So the terms
are also jackknifed, each measurement left out in turn, in the data and in worlds that
hold only the noise ``C`` assumes (:func:`.jackknife.noise_worlds`), and

    kappa = tr(C^-1 C_J) / tr(C^-1 C_J,noise)

is how much more the measurements scatter the terms than the noise does: the mean
inflation of W (``E[W] = tr(C^-1 Sigma)`` for terms of covariance ``Sigma``; the noise
worlds' jackknife stands for ``C`` with the same over-statement a jackknife of few
unequal measurements has, so the ratio removes it), and ``W / max(1, kappa)`` is the
test that holds then (a first-moment, Satterthwaite-type correction). Taken as a ratio
of traces it needs no inverse of a covariance estimated from one replica per
measurement (12 replicas of 8 terms on the thesis rig; a 4-measurement rig's are of
rank 3). Kappa still scatters with few measurements: with fewer than ``MIN_REPLICAS``
the check is not made (``verdict`` "undecided"), since it could never call the terms
present there.

Verdict (:func:`prism_check`, run by every bundle step that chooses its model): the
terms are "present" when ``p(W_c / max(1, kappa)) < PRISM_ALPHA``, ``W_c`` the test of the
terms less their noise bias (below). Kappa costs a
re-adjustment per measurement in the data and in each noise world (10-24 s on the
thesis rig at 512-1024 px), and ``W / max(1, kappa) <= W``, so it is computed only when
``W`` alone reaches the threshold. A flagged 14-parameter model is "too simple" (the
warning ``lens_model_too_simple``), as the residual pattern's verdict says it.

The terms' estimate is also biased by the noise itself, at second order: the adjustment
is non-linear in the phase noise (:mod:`.bootstrap`), and the terms couple to the
near-singular directions of the rig (a rotation of the world against the reference
camera's principal point). A mirrored pair of noise worlds (:func:`.jackknife.noise_worlds`,
``mirrored``) cancels what is linear in the noise, so the mean of its two estimates less
the calibration's is that bias; ``BIAS_PAIRS`` pairs give it, and the test is made on the
terms less it. Its share of W grows with the points (the squares of the bias over u
summed to 0.85 at 512 px and 3.1 at 1024 px on the thesis rig): on the clean rig at 1024 px
(rendered, ideal profile, seed 4; 162,000 control points) it was 0.0-1.25 u per term,
and in worlds of that run's own noise without a term W averaged 12.4, 9.1 less the bias
(chi-square: 8; ``benchmarks/prism_detectability.py --null``). Measured there, and not
an error of the renderer: the phases of the same run rendered without noise move the
terms by 0.09 u at most, and the noise of its control points is independent between
pixels, measurements and the two phases (|corr| <= 0.024; ``--noise-free``). Like the
factor, the bias is taken only when ``W`` alone reaches the threshold (8 re-adjustments
of the whole problem).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.stats import chi2

from fringecal.calibration.bundle import BundleOptions, BundleResult
from fringecal.calibration.candidates import SPANS_THIN_PRISM, fit_model
from fringecal.calibration.diagnostics import Diagnosis
from fringecal.calibration.jackknife import adjust_each, leave_one_out, noise_worlds, readjusted_solution
from fringecal.calibration.model import BundleProblem

__all__ = ["PRISM_ALPHA", "MIN_REPLICAS", "prism_wald", "prism_check", "prism_diagnosis"]

#: significance below which the thin-prism terms are "present" (after the dispersion
#: factor): the chi-square tail a model without the terms reaches once in a thousand runs
PRISM_ALPHA = 1e-3
#: fewest jackknife replicas (measurements) from which the dispersion factor is taken:
#: with fewer, a jackknife variance scatters by more than half its value (sqrt(2 / (n - 1)))
MIN_REPLICAS = 6
#: mirrored pairs of noise worlds the terms' second-order noise bias is taken from (in 8
#: null worlds of the 1024 px thesis run the bias so taken agreed within 0.25 u per term)
BIAS_PAIRS = 4
#: sign seed of those worlds (the dispersion factor's noise worlds use seed 0)
_BIAS_SEED = 1


def _prism_terms(problem: BundleProblem, options: BundleOptions) -> np.ndarray:
    """The thin-prism terms (n_free,) of ``problem`` adjusted from its start values."""
    layout, x = readjusted_solution(problem, options)
    return x[layout.prism_index[layout.prism_index >= 0]]


def _prism_replicas(problems: list[BundleProblem], names: list[str], options: BundleOptions,
                    workers: int = 1) -> list[dict[str, np.ndarray]]:
    """Per problem, measurement -> its thin-prism terms re-adjusted without that
    measurement (:func:`.jackknife.leave_one_out`); a measurement whose removal leaves a
    problem that cannot be calibrated gets none, as in the jackknife of the sensors."""
    done = leave_one_out(problems, names, options, _prism_terms, workers)
    tasks = [(k, m) for k in range(len(problems)) for m in names]
    out = [{} for _ in problems]
    for (k, m), (terms, _) in zip(tasks, done):
        if terms is not None:
            out[k][m] = terms
    return out


def _jackknife_covariance(replicas: np.ndarray) -> np.ndarray:
    n = len(replicas)
    d = replicas - replicas.mean(axis=0)
    return (n - 1) / n * d.T @ d


def _thin_prism_fit(first: BundleResult, options: BundleOptions):
    """The ``thin_prism`` adjustment from ``first``'s solution, the indices of its free
    terms in x and the options it was adjusted with; raises ValueError when no term can
    be adjusted or their covariance is not positive definite."""
    given = options.model_copy(update={"start": "given"})
    fit = fit_model(first.problem.with_start(first.rig, first.poses), given, "thin_prism")
    lay = fit.layout
    idx = lay.prism_index[lay.prism_index >= 0]
    if not len(idx):
        raise ValueError("no thin-prism term can be adjusted")
    np.linalg.cholesky(fit.uncertainty.covariance[np.ix_(idx, idx)])
    return fit, idx, given


def _statistic(fit: BundleResult, idx: np.ndarray, a: np.ndarray | None = None) -> float:
    """``a^T C^-1 a`` of the terms ``a`` at ``idx`` in x (default: the fitted ones) with
    their stated covariance ``C``."""
    a = fit.x[idx] if a is None else a
    return float(a @ np.linalg.solve(fit.uncertainty.covariance[np.ix_(idx, idx)], a))


def _wald(fit: BundleResult, idx: np.ndarray, options: BundleOptions) -> dict:
    W = _statistic(fit, idx)
    lay = fit.layout
    per = {}
    for i, sensor in enumerate(fit.rig.sensors):
        mine = lay.prism_index[i][lay.prism_index[i] >= 0]
        if len(mine):
            w = _statistic(fit, mine)
            per[sensor.name] = {"W": w, "p": float(chi2.sf(w, len(mine)))}
    return {"model": "thin_prism", "W": W, "dof": int(len(idx)), "p": float(chi2.sf(W, len(idx))),
            "covariance": options.covariance, "per_sensor": per}


def _dispersion(fit: BundleResult, idx: np.ndarray, given: BundleOptions, W: float, noise_draws: int,
                seed: int, workers: int) -> dict:
    if noise_draws <= 0:
        return {}
    names = [str(m) for m in fit.problem.measurements]
    if len(names) < MIN_REPLICAS:
        return {"kappa": None, "n_replicas": 0, "noise_draws": noise_draws}
    problems = [fit.problem.with_start(fit.rig, fit.poses), *noise_worlds(fit, noise_draws, seed)]
    data, *noise = _prism_replicas(problems, names, given, workers)
    kept = [m for m in data if all(m in n for n in noise)]
    if len(kept) < MIN_REPLICAS:
        return {"kappa": None, "n_replicas": len(kept), "noise_draws": noise_draws}
    C = fit.uncertainty.covariance[np.ix_(idx, idx)]
    CJ = _jackknife_covariance(np.array([data[m] for m in kept]))
    CN = np.mean([_jackknife_covariance(np.array([n[m] for m in kept])) for n in noise], axis=0)
    kappa = float(np.trace(np.linalg.solve(C, CJ)) / np.trace(np.linalg.solve(C, CN)))
    Wd = W / max(1.0, kappa)
    return {"kappa": kappa, "W_dispersed": Wd, "p_dispersed": float(chi2.sf(Wd, len(idx))),
            "noise_draws": noise_draws, "n_replicas": len(kept)}


def _noise_bias(fit: BundleResult, idx: np.ndarray, given: BundleOptions, pairs: int, workers: int) -> dict:
    """The terms' second-order noise bias from ``pairs`` mirrored noise worlds of ``fit``
    (module notes): ``bias`` (n_terms,) and ``bias_over_u`` (the bias over each term's
    stated u); ``bias_pairs`` 0 and no bias where a world cannot be adjusted."""
    worlds = noise_worlds(fit, pairs, _BIAS_SEED, mirrored=True)
    done = adjust_each([lambda w=w: w for w in worlds], given, _prism_terms, workers)
    if any(terms is None for terms, _ in done):
        return {"bias_pairs": 0}
    terms = np.array([terms for terms, _ in done])
    bias = (terms[0::2] + terms[1::2]).mean(axis=0) / 2 - fit.x[idx]
    u = np.sqrt(np.diag(fit.uncertainty.covariance[np.ix_(idx, idx)]))
    return {"bias": bias, "bias_over_u": [float(b) for b in bias / u], "bias_pairs": pairs}


def _corrected(fit: BundleResult, idx: np.ndarray, given: BundleOptions, noise_draws: int, seed: int,
               workers: int) -> dict:
    """The test of the terms less their noise bias (``W_corrected``, :func:`_noise_bias`;
    the terms themselves where the bias cannot be taken) and the dispersion factor on it
    (:func:`_dispersion`)."""
    out = _noise_bias(fit, idx, given, BIAS_PAIRS, workers)
    a = fit.x[idx] - out.pop("bias", 0.0)
    out["W_corrected"] = _statistic(fit, idx, a)
    out.update(_dispersion(fit, idx, given, out["W_corrected"], noise_draws, seed, workers))
    return out


def prism_wald(first: BundleResult, options: BundleOptions, dispersion: bool = False,
               noise_draws: int = 4, seed: int = 0, workers: int = 1, corrected: bool = False) -> dict:
    """The Wald test of the first-order thin-prism terms (s1, s3 of every sensor) against
    zero, from the 14-parameter solution ``first`` (module notes).

    Returns ``W``, ``dof``, ``p`` (the chi-square tail), per sensor its own ``W`` and ``p``
    (two degrees of freedom) and, with ``dispersion``, ``W_corrected`` of the terms less
    their second-order noise bias (``bias_over_u``, from ``BIAS_PAIRS`` mirrored noise
    worlds), ``kappa`` from the jackknife of the data and of ``noise_draws`` noise-only
    worlds, ``W_dispersed = W_corrected / max(1, kappa)`` and its ``p_dispersed``
    (``workers`` re-adjustments at once); ``corrected`` alone: ``W_corrected`` without
    the factor; ``skipped`` with the reason when no term can be adjusted.
    """
    t0 = time.perf_counter()
    try:
        fit, idx, given = _thin_prism_fit(first, options)
    except (ValueError, np.linalg.LinAlgError) as err:  # DegenerateCalibrationError is a ValueError
        return {"model": "thin_prism", "skipped": str(err), "seconds": time.perf_counter() - t0}
    out = _wald(fit, idx, options)
    if dispersion:
        out.update(_corrected(fit, idx, given, noise_draws, seed, workers))
    elif corrected:
        out.update(_corrected(fit, idx, given, 0, seed, workers))
    out["seconds"] = time.perf_counter() - t0
    return out


def prism_check(first: BundleResult, options: BundleOptions, alpha: float = PRISM_ALPHA,
                workers: int = 1) -> dict:
    """The verdict on the thin-prism terms of ``first`` (module notes): :func:`prism_wald`,
    with the noise bias and the dispersion factor only when ``W`` alone is below
    ``alpha``. Adds ``alpha``, ``present`` (the terms are there), ``verdict`` ("present",
    "absent", or "undecided": fewer than ``MIN_REPLICAS`` measurements, where the factor
    cannot be taken and the check could only ever say "absent", so it is not made; or W
    alone is significant but too few measurements leave a replica) and a ``message``."""
    t0 = time.perf_counter()
    n = len(first.problem.measurements)
    if n < MIN_REPLICAS:
        why = (f"{n} measurement(s) are too few (at least {MIN_REPLICAS}) to tell a thin-prism term from errors "
               "each measurement has of its own")
        return {"model": "thin_prism", "skipped": why, "alpha": alpha, "present": False, "verdict": "undecided",
                "message": f"thin-prism terms not tested: {why}", "seconds": time.perf_counter() - t0}
    try:
        fit, idx, given = _thin_prism_fit(first, options)
    except (ValueError, np.linalg.LinAlgError) as err:
        return {"model": "thin_prism", "skipped": str(err), "alpha": alpha, "present": False, "verdict": "undecided",
                "message": f"thin-prism terms not tested: {err}", "seconds": time.perf_counter() - t0}
    out = _wald(fit, idx, options)
    out["alpha"] = alpha
    if out["p"] < alpha:
        out.update(_corrected(fit, idx, given, 4, 0, workers))
    # W alone cannot tell a lens term from errors each measurement has of its own: with
    # too few measurements for the factor, the terms are not called present
    out["present"] = bool(out.get("p_dispersed", out["p"]) < alpha and out.get("kappa", 0.0) is not None)
    out["verdict"] = "present" if out["present"] else "undecided" if out.get("kappa", 0.0) is None else "absent"
    out["message"] = _message(out)
    out["seconds"] = time.perf_counter() - t0
    return out


def _message(w: dict) -> str:
    head = f"Wald test of the thin-prism terms: W = {w['W']:.1f} ({w['dof']} terms), p = {w['p']:.2g}"
    if "kappa" not in w:
        return f"{head} >= {w['alpha']:g}: no thin-prism term the 14 parameters leave"
    if w["kappa"] is None:
        return (f"{head} < {w['alpha']:g}, but {w['n_replicas']} measurement(s) are too few (at least "
                f"{MIN_REPLICAS}) to tell a thin-prism term from errors each measurement has of its own: "
                "not decided")
    dispersed = (f"{head}; less the noise's own bias of the terms W = {w['W_corrected']:.1f}; the measurements "
                 f"scatter the terms {w['kappa']:.2g} times as much as their noise (kappa), W / max(1, kappa) = "
                 f"{w['W_dispersed']:.1f}, p = {w['p_dispersed']:.2g}")
    if w["present"]:
        return (f"{dispersed} < {w['alpha']:g}: the images carry a thin-prism-shaped error common to the "
                "measurements that the 14 parameters leave (a lens term is the usual cause; see the residuals)")
    return (f"{dispersed} >= {w['alpha']:g}: no thin-prism term beyond what errors shared by a measurement's "
            "points give")


def prism_diagnosis(w: dict, model: str) -> Diagnosis | None:
    """The warning ``lens_model_too_simple`` when the terms are present and ``model``
    (the run's) does not adjust them (the correction field spans them), else None."""
    if not w.get("present") or model in SPANS_THIN_PRISM:
        return None
    return Diagnosis("lens_model_too_simple", "warning", "thin_prism",
                     f"the lens model is too simple ({model}): {w['message']}")
