"""Labelling a whole run: each scanner's errors estimated from all its measurements.

:func:`fringecal.spheres.labelling.label_spheres` labels one (measurement, scanner)
with given tolerances. A scanner's prior calibration is wrong in the same way in every
measurement, so its errors are estimated from all of them, and a labelling that the
scanner's other measurements contradict is refused, never passed on. Per scanner:

1. **Stated tolerances.** Every measurement is labelled with the configured
   tolerances (:class:`LabellingConfig`: the prior calibration's stated uncertainty,
   scale free within ``scale_tol``). Accepted labellings and every alternative of an
   ambiguous one are the scanner's *hypotheses*.
2. **Scale.** Each hypothesis's similarity registration gives a scale; the scanner's
   scale is the median over its measurements of the median over each measurement's
   hypotheses (symmetric alternatives share the scale of the true labelling, so
   ambiguity does not bias it), with its standard uncertainty from the scatter and
   the geometry. The scanner's centres are divided by it about the scanner's origin.
3. **Centre uncertainty.** The pooled residuals of the rigid registrations of the
   rescaled centres (per measurement the best of its hypotheses, measurements with
   more than 9 times the median variance dropped) give the scanner's centre
   uncertainty, raised to its one-sided 95 % upper confidence limit. Step 4 uses it
   (at most twice the stated value); labelling with a prior pose (step 6) and checking
   given labels use the larger of it and the stated value.
4. **Distances alone, refined.** Every measurement is labelled again with the scale
   known to within ``k`` of its uncertainty and the refined centre uncertainty. A
   labelling accepted here needed no plan (method ``distances``).
5. **Consensus of the scanner's frame** (with planned poses ``T_world_artefact``).
   Every hypothesis of measurement m implies ``T_scanner_world = T_scanner_artefact o
   T_world_artefact(m)^-1``. Frames are compared by where they put the artefact's
   spheres (at the first planned pose): RMS distance, normalised by the standard
   uncertainty of each implied frame -- from the registration of the spheres seen
   (centre uncertainty as stated) and the plan's ``plan_u_mm`` / ``plan_u_rad``.
   A candidate frame's misfit is the sum over measurements of the squared normalised
   distance of its nearest hypothesis, capped at ``k**2`` (a measurement that
   contradicts it costs ``k**2``, however far off it is). The best candidate is refined
   by the mean of its members (one hypothesis per measurement within ``k``). It is
   accepted when at least two measurements and half of those with hypotheses are
   members, and every far rival (more than ``2 k`` away) has a misfit larger by
   ``consensus_margin``: a wrong alternative repeats the visible spheres' symmetry,
   but the hexapod's moves between measurements make its frames disagree; where they
   do not (moves along a symmetry axis), the scanner is refused as ambiguous
   (:mod:`fringecal.spheres.label_consensus`).
6. **Each measurement against the consensus.** The spheres predicted by the
   consensus frame and the planned pose label the measurement (method ``planned
   pose`` where distances alone were refused), and the frame the labelling implies
   must lie within ``k`` of the consensus. A distance labelling or a given labelling
   (``sphere_id`` already filled in the fits table, e.g. by hand) that contradicts the
   consensus is refused as ``inconsistent``, with the measurement, the spheres seen
   and how far off it is in the message.

Without planned poses only steps 1-4 run. The link step
(:func:`fringecal.spheres.poses_and_links.label_pose_link`) then checks every labelling against
the other scanners' poses of the same measurement, and labels the measurements still
ambiguous from those poses; a scanner no labelled pose links is linked by the transform
its and another scanner's hypotheses agree on in their shared measurements, and a
measurement no scanner labelled alone by all linked scanners' views together
(:mod:`fringecal.spheres.label_links`, :mod:`fringecal.spheres.label_joint`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.registration import kabsch, umeyama
from fringecal.spheres.label_consensus import _hypothesis, _rms, _split, alternatives, scanner_frame_from_plan
from fringecal.spheres.labelling import Labelling, LabellingConfig, LabellingRefused, label_spheres

__all__ = ["ScannerEstimate", "label_sphere_fits", "label_with_prior", "estimate_scale", "estimate_centre_u",
           "scanner_frame_from_plan"]


@dataclass(frozen=True)
class ScannerEstimate:
    """What the labelling estimated for one scanner from all its measurements.

    ``scale`` (with standard uncertainty ``u_scale``): its prior's scale factor
    (centres are divided by it), from its accepted labellings where there are any;
    ``centre_u_mm``, ``scale_tol``: the refined tolerances of step 4; ``u_hat``: the
    centre uncertainty the data show (upper 95 % limit); ``frame``:
    ``T_scanner_world`` of the planned poses' frame (scale-corrected scanner frame),
    None without a consensus; ``members``: the measurements that agreed on it;
    ``note``: all this in words, or why there is no frame; ``hypotheses``:
    measurement -> the labellings steps 1 and 4 found possible (for the link step).
    """

    scanner: str
    scale: float
    u_scale: float
    centre_u_mm: float
    scale_tol: float
    n_measurements: int
    frame: Frame | None = None
    note: str = ""
    members: tuple = field(default=(), repr=False)
    u_hat: float | None = None
    hypotheses: dict = field(default_factory=dict, repr=False)


def estimate_scale(hypotheses: list[tuple[np.ndarray, list[tuple]]], artefact: Artefact,
                   config: LabellingConfig) -> tuple[float, float, int]:
    """A scanner's scale from its measurements' hypotheses (step 2 of the module doc).

    ``hypotheses``: per measurement (centres (n, 3), alternative labellings). Returns
    (scale, standard uncertainty, number of measurements used); (1, scale_tol / k, 0)
    without hypotheses.
    """
    bounds = (1 - config.scale_tol, 1 + config.scale_tol)
    s_m, spread = [], []
    for X, alts in hypotheses:
        if not alts:
            continue
        scales = []
        for alt in alts:
            idx, Y = _split(alt, artefact)
            scales.append(umeyama(Y, X[idx], bounds)[0])
            spread.append(float(np.sum((Y - Y.mean(axis=0)) ** 2)))
        s_m.append(float(np.median(scales)))
    if not s_m:
        return 1.0, config.scale_tol / config.k, 0
    s = np.array(s_m)
    scale = float(np.median(s))
    # the geometric limit of one measurement: u / sqrt(sum |y - mean|^2)
    geometric = config.centre_u_mm / np.sqrt(np.median(spread) * len(s))
    scatter = 1.4826 * float(np.median(np.abs(s - scale))) / np.sqrt(len(s)) if len(s) >= 3 else 0.0
    return scale, float(max(geometric, scatter)), len(s)


def estimate_centre_u(hypotheses: list[tuple[np.ndarray, list[tuple]]], artefact: Artefact,
                      scale: float) -> tuple[float | None, int]:
    """A scanner's centre uncertainty per coordinate, one-sided 95 % upper limit
    (step 3 of the module doc), from the rigid residuals of its rescaled centres.
    Returns (u or None, degrees of freedom)."""
    var, dof = [], []
    for X, alts in hypotheses:
        v, n = [], 0
        for alt in alts:
            idx, Y = _split(alt, artefact)
            if len(idx) < 3:
                continue
            Xs = X[idx] / scale
            M, t = kabsch(Y, Xs)
            v.append(float(np.sum((Y @ M.T + t - Xs) ** 2)) / (3 * len(idx) - 6))
            n = max(n, len(idx))
        if v:
            var.append(min(v))
            dof.append(3 * n - 6)
    if not var:
        return None, 0
    var, dof = np.array(var), np.array(dof)
    keep = var <= 9 * np.median(var)
    nu = int(dof[keep].sum())
    pooled = float(np.sum(var[keep] * dof[keep]) / nu)
    # one-sided 95 % upper limit: nu s^2 / chi2_0.05(nu), Wilson-Hilferty for the quantile
    q05 = nu * (1 - 2 / (9 * nu) - 1.6449 * np.sqrt(2 / (9 * nu))) ** 3
    return float(np.sqrt(pooled * nu / max(q05, 1e-3 * nu))), nu


# -- one scanner -------------------------------------------------------------------

@dataclass
class _Group:
    measurement: str
    scanner: str
    index: pd.Index
    X: np.ndarray
    kwargs: dict
    candidates: list
    given: tuple | None
    first: object = None  # stated tolerances
    result: object = None
    method: str = "distances"
    notes: list = field(default_factory=list)


def _seen(g: _Group, ids=None) -> str:
    if ids is None:
        return f"{len(g.X)} candidate(s)"
    lab = [s for s in ids if s is not None]
    return f"spheres {','.join(lab)}"


def _given_labelling(g: _Group, artefact: Artefact, cfg: LabellingConfig, scale: float):
    """A labelling given in the fits table, checked against the artefact's shape: the
    similarity registration of the given spheres (scale within ``scale_tol`` of the
    scanner's) must put every one within ``k`` of its candidate. Symmetric subsets pass
    whichever way they are given; the consensus and the link check judge those."""
    ids = g.given
    unknown = sorted({s for s in ids if s is not None and s not in set(artefact.ids)})
    repeated = sorted({s for s in ids if s is not None and ids.count(s) > 1})
    idx = [i for i, s in enumerate(ids) if s is not None]
    if unknown or repeated or len(idx) < cfg.min_spheres:
        why = (f"sphere ids {unknown} are not in the artefact" if unknown else
               f"sphere ids {repeated} are given to more than one candidate" if repeated else
               f"{len(idx)} labelled candidate(s); at least {cfg.min_spheres} are needed")
        return LabellingRefused("inconsistent", f"the given labels {list(ids)}: {why}")
    X = g.X / scale
    Y = artefact.centres_of([ids[i] for i in idx])
    s_fit, M, t = umeyama(Y, X[idx], (1 - cfg.scale_tol, 1 + cfg.scale_tol))
    res = np.linalg.norm(s_fit * Y @ M.T + t - X[idx], axis=1)
    u = g.kwargs.get("uncertainties")
    u = np.full(len(g.X), cfg.centre_u_mm) if u is None else np.asarray(u, float)
    u = np.sqrt(np.mean(u**2, axis=1)) if u.ndim == 2 else u
    u = np.maximum(np.nan_to_num(u[idx], nan=cfg.centre_u_mm), cfg.centre_u_mm)
    tol = cfg.k * np.sqrt(u**2 + np.asarray(artefact.u, float)[artefact.index([ids[i] for i in idx])] ** 2)
    if np.any(res > tol):
        worst = int(np.argmax(res / tol))
        return LabellingRefused("inconsistent", f"the given labels {list(ids)} do not fit the artefact's shape: "
                                f"candidate {g.candidates[idx[worst]]} ({ids[idx[worst]]}) is {res[worst]:.2f} mm "
                                f"from its sphere, more than {tol[worst]:.2f} mm")
    residuals = np.full(len(ids), np.nan)
    residuals[idx] = res
    M2, t2 = kabsch(Y, X[idx] / s_fit)
    return Labelling(tuple(ids), residuals, Frame.from_matrix(M2.T, t2), float(np.sqrt(np.mean(res**2))),
                     {i: "not labelled in the given labels" for i in range(len(ids)) if ids[i] is None}, 0,
                     float(scale * s_fit))


def _frame_check(g, lab, est: ScannerEstimate, planned, probe_world, artefact, cfg):
    """(normalised distance, mm) of the frame a labelling implies from the consensus."""
    h = _hypothesis(g.measurement, g.X, lab.sphere_ids, planned[g.measurement], probe_world, artefact, cfg,
                    est.scale)
    pts = est.frame.to_world(probe_world)
    dist = float(_rms(h.points, pts))
    return dist / h.sigma, dist


def _label_scanner(groups: list[_Group], artefact: Artefact, cfg: LabellingConfig,
                   planned: dict | None) -> ScannerEstimate:
    """Steps 1-6 for one scanner; the final scale and centre uncertainty are estimated
    again from its accepted labellings (no alternatives left to blur them)."""
    est = _label_scanner_groups(groups, artefact, cfg, planned)
    accepted = [(g.X, [g.result.sphere_ids]) for g in groups if isinstance(g.result, Labelling)]
    if accepted and cfg.refine:
        scale, u_scale, _ = estimate_scale(accepted, artefact, replace(cfg, centre_u_mm=est.centre_u_mm))
        u_hat, _ = estimate_centre_u(accepted, artefact, scale)
        est = replace(est, scale=scale, u_scale=u_scale, u_hat=u_hat)
    parts = [f"scale {est.scale:.5f} +- {est.u_scale:.5f} from {est.n_measurements} measurement(s)"]
    if est.n_measurements and abs(est.scale - 1) >= 0.999 * cfg.scale_tol:
        parts.append(f"the scale sits at the bound of extraction.labelling.scale_tol = {cfg.scale_tol:g}: the prior "
                     "may be further off in scale than stated")
    if est.u_hat is not None:
        parts.append(f"centre u {est.u_hat:.2f} mm (stated {cfg.centre_u_mm:g})")
        if est.u_hat > cfg.centre_u_mm:
            parts.append(f"the centres scatter more than extraction.labelling.centre_u_mm = {cfg.centre_u_mm:g} "
                         "states: raise it if measurements are refused as inconsistent")
    return replace(est, note="; ".join(parts + [est.note] if est.note else parts))


def _common_labelling(err: LabellingRefused, g: _Group, artefact, prior, cfg, scale):
    """With a prior pose each candidate can be one sphere only, so alternatives differ
    only in which doubtful candidates they leave out: label the spheres they all share."""
    alts = err.alternatives
    if err.reason != "ambiguous" or len(alts) < 2:
        return err
    common = [s for i, s in enumerate(alts[0]) if s is not None and all(a[i] == s for a in alts)]
    if any(_conflict_ids(a, b) for a in alts for b in alts) or len(common) < cfg.min_spheres:
        return err
    allowed = g.kwargs.get("allowed_ids")
    kwargs = dict(g.kwargs, allowed_ids=[s for s in common if allowed is None or s in set(map(str, allowed))])
    try:
        lab = label_spheres(g.X, artefact, prior=prior, config=cfg, scale=scale, **kwargs)
    except LabellingRefused:
        return err
    left = [g.candidates[i] for i, s in enumerate(lab.sphere_ids) if s is None and any(a[i] for a in alts)]
    why = dict(lab.unlabelled)
    for i, s in enumerate(lab.sphere_ids):
        if s is None and any(a[i] for a in alts):
            why[i] = "fits the plan's sphere only without another doubtful candidate; left out"
    g.notes.append(f"candidates {left} left out: the labellings keeping one or the other fit equally well")
    return replace(lab, unlabelled=why)


def _conflict_ids(a: tuple, b: tuple) -> bool:
    inv = {s: i for i, s in enumerate(b) if s is not None}
    return any((s is not None and b[i] is not None and b[i] != s) or (s is not None and inv.get(s, i) != i)
               for i, s in enumerate(a))


def _label_scanner_groups(groups: list[_Group], artefact: Artefact, cfg: LabellingConfig,
                          planned: dict | None) -> ScannerEstimate:
    scanner = groups[0].scanner
    for g in groups:  # step 1
        try:
            g.first = label_spheres(g.X, artefact, config=cfg, **g.kwargs)
        except LabellingRefused as err:
            g.first = err
        g.result = g.first
    hyp_sets = [(g.X, alternatives(g.first, cfg.min_spheres)) for g in groups]
    scale, u_scale, n_used = estimate_scale(hyp_sets, artefact, cfg)  # step 2
    if not cfg.refine:
        scale, u_scale = 1.0, cfg.scale_tol / cfg.k
    u_hat, _ = estimate_centre_u(hyp_sets, artefact, scale)  # step 3
    refined = loose = cfg
    note = ""
    if n_used == 0:
        note = (f"no measurement of scanner {scanner} matches the artefact within the stated tolerances "
                f"(centre_u_mm {cfg.centre_u_mm:g}, scale_tol {cfg.scale_tol:g}): the prior may be worse than stated")
    elif cfg.refine:
        # the data may tighten the tolerance, or widen it up to twice the stated one
        u_new = cfg.centre_u_mm if u_hat is None else float(np.clip(u_hat, 1e-3, 2 * cfg.centre_u_mm))
        refined = replace(cfg, centre_u_mm=u_new, scale_tol=float(min(cfg.scale_tol, cfg.k * u_scale)))
        loose = replace(refined, centre_u_mm=max(u_new, cfg.centre_u_mm))
        for g in groups:  # step 4
            try:
                g.result = label_spheres(g.X, artefact, config=refined, scale=scale, **g.kwargs)
            except LabellingRefused as err:
                if isinstance(g.first, Labelling):
                    err = LabellingRefused(err.reason, f"{err.args[0]} with the scanner's estimated scale "
                                           f"{scale:.5f} (labelled {list(g.first.sphere_ids)} with the scale free)",
                                           err.alternatives)
                g.result = err
    hypotheses = {g.measurement: list(dict.fromkeys(alternatives(g.first, cfg.min_spheres)
                                                    + alternatives(g.result, cfg.min_spheres))) for g in groups}
    est = ScannerEstimate(scanner, scale, u_scale, refined.centre_u_mm, refined.scale_tol, n_used, note=note,
                          u_hat=u_hat, hypotheses=hypotheses)
    for g in groups:
        if g.given is not None:
            g.result, g.method = _given_labelling(g, artefact, loose, scale), "given"
    if not planned:
        return est
    mine = {g.measurement: (g.X, hypotheses[g.measurement]) for g in groups if g.measurement in planned}
    frame, why, members = scanner_frame_from_plan(mine, planned, artefact, cfg, scale)  # step 5
    est = replace(est, frame=frame, note="; ".join(x for x in (note, why) if x), members=members)
    if frame is None:
        for g in groups:
            if isinstance(g.result, LabellingRefused):
                g.result = LabellingRefused(g.result.reason, f"{g.result.args[0]}; plan: {why}",
                                            g.result.alternatives)
        return est
    probe_world = planned[next(m for m in mine)].to_world(artefact.centres)
    for g in groups:  # step 6
        if g.measurement not in planned:
            continue
        before = g.result
        prior = frame.compose(planned[g.measurement])
        try:
            res = label_spheres(g.X, artefact, prior=prior, config=loose, scale=scale, **g.kwargs)
        except LabellingRefused as err:
            res = _common_labelling(err, g, artefact, prior, loose, scale)
        where = f"measurement {g.measurement}, scanner {scanner}"
        others = len([m for m in members if m != g.measurement])
        if isinstance(before, Labelling):
            z, dist = _frame_check(g, before, est, planned, probe_world, artefact, cfg)
            if z > cfg.k:
                planned_ids = list(res.sphere_ids) if isinstance(res, Labelling) else f"nothing ({res})"
                g.result = LabellingRefused(
                    "inconsistent",
                    f"{where}: {'the given labels' if g.method == 'given' else 'distances alone give'} "
                    f"{list(before.sphere_ids)} for the {len(g.X)} candidate(s) ({_seen(g, before.sphere_ids)}), "
                    f"but that puts the scanner frame {dist:.0f} mm ({z:.0f} sigma) from the consensus of "
                    f"{others} other measurement(s) with the planned poses, which label it {planned_ids}",
                    [before.sphere_ids] + ([res.sphere_ids] if isinstance(res, Labelling) else []))
                continue
            # (no numbers of the plan in a labelled group's message: a plan a millimetre off
            # gives the same labels and the same tables)
            g.notes.append(f"agrees with the scanner frame {others} other measurement(s) and the plan give")
            continue
        if isinstance(res, Labelling):
            z, dist = _frame_check(g, res, est, planned, probe_world, artefact, cfg)
            if z > cfg.k:
                g.result = LabellingRefused(
                    "inconsistent",
                    f"{where}: the spheres the plan predicts ({_seen(g, res.sphere_ids)}) put the scanner frame "
                    f"{dist:.0f} mm ({z:.0f} sigma) from the consensus of {others} other measurement(s): "
                    f"its planned pose or its candidates are wrong; distances alone: {before}",
                    [res.sphere_ids])
                continue
            g.result, g.method = res, "planned pose"
            g.notes.append(f"distances alone: {before.reason}; labelled with the scanner frame {others} other "
                           "measurement(s) and the plan give")
        else:
            g.result = LabellingRefused(before.reason, f"{before.args[0]}; with the planned pose: {res}",
                                        before.alternatives)
    return est


def _inputs(g: pd.DataFrame, allowed=None) -> tuple[np.ndarray, dict]:
    X = g[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    u = g[["u_x_mm", "u_y_mm", "u_z_mm"]].to_numpy(float) if {"u_x_mm", "u_y_mm", "u_z_mm"} <= set(g) else None
    radii = g["radius_mm"].to_numpy(float) if "radius_mm" in g else None
    return X, {"uncertainties": u, "radii": radii, "allowed_ids": allowed}


def label_with_prior(group: pd.DataFrame, artefact: Artefact, config: LabellingConfig, estimate: ScannerEstimate,
                     prior: Frame, allowed=None):
    """Label one group's candidates (rows of a sphere-fits table) with a prior pose in
    the scanner's scale-corrected frame, with that scanner's estimated scale and the
    larger of its estimated and the stated centre uncertainty (as step 6). Returns a
    Labelling or the LabellingRefused."""
    X, kwargs = _inputs(group, allowed)
    cfg = replace(config, centre_u_mm=max(estimate.centre_u_mm, config.centre_u_mm), scale_tol=estimate.scale_tol)
    try:
        return label_spheres(X, artefact, prior=prior, config=cfg, scale=estimate.scale, **kwargs)
    except LabellingRefused as err:
        g = _Group("", "", group.index, X, kwargs, list(group.get("candidate", range(len(group)))), None)
        return _common_labelling(err, g, artefact, prior, cfg, estimate.scale)


def label_sphere_fits(fits: pd.DataFrame, artefact: Artefact, config: LabellingConfig | None = None,
                      allowed_ids: dict | None = None, planned: dict | None = None,
                      estimates: dict | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Label every (measurement, scanner) group of a sphere-fits table.

    Parameters
    ----------
    fits : DataFrame
        Rows of :class:`fringecal.schemas.SphereFitsTable` (``measurement, scanner, candidate,
        x_mm, y_mm, z_mm`` and optionally ``radius_mm``, ``u_x_mm, u_y_mm, u_z_mm``).
        A group whose ``sphere_id`` is already filled (by hand, say) is a *given*
        labelling: checked against the artefact and the scanner's other
        measurements like any other, never trusted.
    artefact : Artefact
    config : LabellingConfig
        The prior calibration's stated uncertainty.
    allowed_ids : dict, optional
        scanner -> sphere ids that scanner can see.
    planned : dict, optional
        measurement -> planned ``T_world_artefact`` (Frame) from the pose plan, in
        any fixed frame (see the module doc, steps 5-6).
    estimates : dict, optional
        Filled with scanner -> :class:`ScannerEstimate`.

    Returns
    -------
    labelled : DataFrame
        ``fits`` with ``sphere_id`` filled ("" where unlabelled) and ``label_residual_mm``.
    outcomes : DataFrame
        :class:`fringecal.schemas.LabelOutcomesTable`: one row per group with ``status``
        (labelled / refused), ``reason``, ``method`` (distances / planned pose /
        given), ``n_candidates, n_labelled, rms_mm, message``, and ``scale``: the
        scanner's estimated scale (its centres are divided by it for poses).
    """
    cfg = config or LabellingConfig()
    out = fits.copy().reset_index(drop=True)
    if "sphere_id" not in out:
        out["sphere_id"] = ""
    given_col = out["sphere_id"].fillna("").astype(str)
    out["sphere_id"] = ""
    out["label_residual_mm"] = np.nan
    by_scanner: dict[str, list[_Group]] = {}
    first_seen = {}
    for (meas, scanner), g in out.groupby(["measurement", "scanner"], sort=False):
        first_seen[str(meas), str(scanner)] = len(first_seen)
        X, kwargs = _inputs(g, (allowed_ids or {}).get(scanner))
        given = tuple(s or None for s in given_col[g.index]) if (given_col[g.index] != "").any() else None
        by_scanner.setdefault(scanner, []).append(_Group(
            str(meas), str(scanner), g.index, X, kwargs,
            list(g["candidate"]) if "candidate" in g else list(range(len(g))), given))
    rows = {}
    for scanner, groups in by_scanner.items():
        est = _label_scanner(groups, artefact, cfg, planned)
        if estimates is not None:
            estimates[scanner] = est
        for g in groups:
            res, n = g.result, len(g.X)
            if isinstance(res, LabellingRefused):
                msg = str(res)
                detail = msg[len(res.reason) + 2:] if msg.startswith(f"{res.reason}: ") else msg
                if not detail.startswith("measurement "):
                    msg = f"{res.reason}: measurement {g.measurement}, scanner {scanner}, {n} candidate(s): {detail}"
                rows[g.measurement, scanner] = (g.measurement, scanner, "refused", res.reason, g.method, n, 0,
                                                np.nan, msg, est.scale)
                continue
            out.loc[g.index, "sphere_id"] = [sid or "" for sid in res.sphere_ids]
            out.loc[g.index, "label_residual_mm"] = res.residuals_mm
            notes = [f"candidate {g.candidates[i]}: {w}" for i, w in res.unlabelled.items()] + g.notes
            rows[g.measurement, scanner] = (g.measurement, scanner, "labelled", "", g.method, n, res.n_labelled,
                                            res.rms_mm, "; ".join(notes), est.scale)
    order = [(g.measurement, g.scanner) for gs in by_scanner.values() for g in gs]
    order = sorted(order, key=lambda key: first_seen[key])
    outcomes = pd.DataFrame([rows[key] for key in order], columns=["measurement", "scanner", "status", "reason", "method", "n_candidates",
                                           "n_labelled", "rms_mm", "message", "scale"])
    return out, outcomes
