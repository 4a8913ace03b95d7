"""From sphere fits to linked scanner frames: the table-level steps of issue 4.

The image-space step fits one :class:`~fringecal.spheres.robust.RobustSphereFit`
per candidate region and turns each into a row with :func:`sphere_fit_row`;
:func:`label_pose_link` then labels every (measurement, scanner)
(:func:`fringecal.spheres.label_scanners.label_sphere_fits`), estimates one artefact
pose each by SVD (:func:`fringecal.spheres.pose.estimate_poses`) and links the scanners into
the reference frame (:func:`fringecal.spheres.linking.link_scanners`), then refuses every
labelling that the other scanners' poses of the same measurement contradict and links
again. Every table it returns satisfies its schema in :mod:`schemas`.

Poses and links are those of the *scale-corrected* scanner frames: each scanner's
centres are divided, about its origin, by the scale its labelling estimated (column
``scale`` of the label outcomes), so that a prior calibration 0.6 % off in scale does
not shift its poses by 0.6 % of its distance to the artefact. The labelled centres
table keeps the centres as measured.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.frames import Frame
from fringecal.registration import kabsch
from fringecal.schemas import LabelOutcomesTable, ScannerLinksTable, SphereCentresTable, SphereFitsTable, validate_table
from fringecal.spheres.fit import SphereModel
from fringecal.spheres.label_consensus import frame_uncertainty, scanner_frame_from_plan
from fringecal.spheres.label_joint import joint_placements
from fringecal.spheres.label_links import links_from_hypotheses
from fringecal.spheres.label_scanners import estimate_scale, label_sphere_fits, label_with_prior
from fringecal.spheres.labelling import Labelling, LabellingConfig
from fringecal.spheres.linking import LinkResult, link_scanners, mean_frame, pose_contradictions
from fringecal.spheres.pose import PoseResult, estimate_poses
from fringecal.spheres.robust import RobustSphereFit

__all__ = ["sphere_fit_row", "centres_from_fits", "label_pose_link", "LabelPoseLink"]


def sphere_fit_row(measurement, scanner, candidate, fit: RobustSphereFit | SphereModel, bbox=None,
                   sphere_id: str = "") -> dict:
    """One :class:`fringecal.schemas.SphereFitsTable` row.

    ``bbox`` is the candidate's image region ``(u_min, v_min, u_max, v_max)`` in
    camera pixels. Rejection counts come from a :class:`RobustSphereFit`.
    """
    model = fit.model if isinstance(fit, RobustSphereFit) else fit
    d = model.to_dict()
    row = {"measurement": str(measurement), "scanner": str(scanner), "candidate": str(candidate),
           "sphere_id": sphere_id, "x_mm": d["x_mm"], "y_mm": d["y_mm"], "z_mm": d["z_mm"],
           "radius_mm": d["radius_mm"], "radius_fixed": d["radius_fixed"], "rms_mm": d["rms_mm"],
           "n_points": d["n_points"], "u_x_mm": d["u_x_mm"], "u_y_mm": d["u_y_mm"], "u_z_mm": d["u_z_mm"],
           "cap_angle_deg": d["cap_angle_deg"], "coverage": d["coverage"]}
    if bbox is not None:
        row.update(zip(("u_min_px", "v_min_px", "u_max_px", "v_max_px"), map(float, bbox)))
    if isinstance(fit, RobustSphereFit):
        row["n_rejected"] = fit.n_rejected
        row.update({f"rejected_{k}": int(v) for k, v in fit.rejected.items()})
    else:
        row["n_rejected"] = 0
    return row


def centres_from_fits(fits: pd.DataFrame) -> pd.DataFrame:
    """The labelled rows of a sphere-fits table as a :class:`fringecal.schemas.SphereCentresTable`."""
    labelled = fits[fits["sphere_id"].astype(str) != ""].reset_index(drop=True)
    return validate_table(labelled, SphereCentresTable, "labelled sphere fits")


@dataclass(frozen=True)
class LabelPoseLink:
    """Tables of :func:`label_pose_link`.

    ``fits``: the sphere-fits table with ``sphere_id`` filled; ``labels``: one
    outcome per (measurement, scanner); ``centres``: labelled centres;
    ``poses``: poses and the groups skipped with their reasons; ``links``:
    ``T_reference_scanner`` per scanner (``links.table()``) and the unlinked ones;
    ``estimates``: scanner -> :class:`~fringecal.spheres.label_scanners.ScannerEstimate`;
    ``contradictions``: the labellings refused because other scanners' poses of the
    same measurement contradict them (:func:`fringecal.spheres.linking.pose_contradictions`).
    """

    fits: pd.DataFrame
    labels: pd.DataFrame
    centres: pd.DataFrame
    poses: PoseResult
    links: LinkResult | None
    links_error: str = ""
    estimates: dict = field(default_factory=dict)
    contradictions: pd.DataFrame | None = None

    def links_table(self) -> pd.DataFrame:
        if self.links is None:
            return pd.DataFrame(columns=list(ScannerLinksTable.to_schema().columns))
        return validate_table(self.links.table(), ScannerLinksTable, "scanner links")


def _poses(centres: pd.DataFrame, scales: dict, artefact: Artefact, source: str) -> PoseResult:
    if not len(centres):
        return PoseResult(pd.DataFrame(columns=["measurement", "scanner"]),
                          pd.DataFrame(columns=["measurement", "scanner", "reason"]))
    f = centres["scanner"].map(scales).fillna(1.0).to_numpy(float)[:, None]
    corrected = centres.copy()
    corrected[["x_mm", "y_mm", "z_mm"]] = centres[["x_mm", "y_mm", "z_mm"]].to_numpy(float) / f
    return estimate_poses(corrected, artefact, source)


def label_pose_link(fits: pd.DataFrame, artefact: Artefact, reference: str,
                    config: LabellingConfig | None = None, allowed_ids: dict | None = None,
                    planned: dict | None = None, source: str = "<sphere fits>") -> LabelPoseLink:
    """Label, pose and link in one go; bad groups are reported, the others go on.

    Parameters
    ----------
    fits : DataFrame
        :class:`fringecal.schemas.SphereFitsTable` rows (``sphere_id`` may be empty; a filled
        group is a given labelling, checked like the others).
    artefact : Artefact
    reference : str
        Reference scanner of the global frame.
    config, allowed_ids, planned
        See :func:`fringecal.spheres.label_scanners.label_sphere_fits`.

    After linking, a labelling whose pose, carried into the reference frame, puts the
    artefact more than half the artefact's smallest sphere spacing from where the
    other scanners of that measurement put it is refused (``inconsistent``, the
    message says which scanners disagree and by how much), its pose dropped, and the
    scanners linked again; then the groups still ambiguous are labelled from the
    poses the linked scanners measured (:func:`_label_from_poses`, method ``linked
    pose``), and so on until nothing changes. With planned poses, a link that disagrees
    by as much with the link the plan implies (each scanner's consensus frame) is
    refused too. Without planned poses, a scanner that no labelled pose links is linked
    by the transform its and another scanner's possible labellings agree on in their
    shared measurements, and a measurement no scanner labelled alone is placed by all
    linked scanners' views at once (:mod:`fringecal.spheres.label_links`,
    :mod:`fringecal.spheres.label_joint`); a view left
    ambiguous says what the other scanners' views gave and what would decide it, and
    ``links.unlinked`` says why a scanner has no link. Poses and links are those of the
    scale-corrected scanner frames (see the module doc); ``estimates`` and the outcomes'
    ``scale`` hold each scanner's scale.
    """
    fits = validate_table(fits, SphereFitsTable, source)
    estimates: dict = {}
    labelled, outcomes = label_sphere_fits(fits, artefact, config, allowed_ids, planned, estimates)
    scales = {s: e.scale for s, e in estimates.items()}
    D = artefact.distance_matrix()
    tol = 0.5 * float(D[np.triu_indices(len(D), 1)].min()) if len(D) > 1 else np.inf
    found = []
    # without a plan: links from the hypotheses alone (where no labelled pose links a scanner),
    # and measurements placed by all linked scanners' views at once
    joint = None if planned else {}
    guess = None
    for attempt in range(12):  # refuse contradicted labellings, label from the links, link again
        centres = centres_from_fits(validate_table(labelled, SphereFitsTable, source))
        if attempt:
            scales = _rescale(centres, estimates, outcomes, artefact, config or LabellingConfig())
        poses = _poses(centres, scales, artefact, source)
        links, links_error = _link(poses, reference, source)
        if attempt == 11:
            break
        anchor = _anchor_links(poses, links, source)
        if joint is not None and guess is None and _lacks_links(anchor, estimates, reference):
            guess = links_from_hypotheses(labelled, estimates, artefact, reference, config or LabellingConfig())
        anchor = _with_guess(anchor, guess)
        if anchor is None:
            break
        bad = pose_contradictions(poses.poses, anchor, artefact.centres, tol, source) if len(poses.poses) else []
        if len(bad):
            found.append(bad)
            for r in bad.itertuples(index=False):
                rows = (labelled["measurement"] == r.measurement) & (labelled["scanner"] == r.scanner)
                seen = ", ".join(f"{c}={sid}" for c, sid in zip(labelled.loc[rows, "candidate"],
                                                              labelled.loc[rows, "sphere_id"]) if sid)
                _refuse(labelled, outcomes, r.measurement, r.scanner,
                        f"inconsistent: {r.message} (it had labelled candidates {seen})")
            continue
        if not _label_from_poses(labelled, outcomes, poses.poses, anchor, estimates, artefact,
                                 config or LabellingConfig(), allowed_ids, tol, joint):
            break
    if links is not None and planned:
        links = _check_links_against_plan(links, estimates, artefact, planned, tol)
    if joint is not None:
        links = _say_what_decides(outcomes, links, guess, joint, reference)
    labelled = validate_table(labelled, SphereFitsTable, source)
    outcomes = validate_table(outcomes, LabelOutcomesTable, "label outcomes")
    # groups refused by labelling never reach the pose step: say so in its skip list
    refused = outcomes[outcomes["status"] == "refused"]
    if len(refused):
        extra = pd.DataFrame({"measurement": refused["measurement"], "scanner": refused["scanner"],
                              "reason": "labelling refused: " + refused["message"]})
        poses = PoseResult(poses.poses, pd.concat([poses.skipped, extra], ignore_index=True))
    contradictions = pd.concat(found, ignore_index=True) if found else None
    return LabelPoseLink(labelled, outcomes, centres, poses, links, links_error, estimates, contradictions)


def _link(poses: PoseResult, reference: str, source: str) -> tuple[LinkResult | None, str]:
    if not len(poses.poses):
        return None, "no poses to link"
    try:
        return link_scanners(poses.poses, reference, source=source), ""
    except ValueError as err:
        return None, str(err)


def _rescale(centres: pd.DataFrame, estimates: dict, outcomes: pd.DataFrame, artefact: Artefact,
             config: LabellingConfig) -> dict:
    """Each scanner's scale again from all its labelled groups (the link step may have
    labelled more); updates ``estimates`` and the ``scale`` column of ``outcomes``."""
    for s, g in centres.groupby("scanner"):
        est = estimates.get(s)
        if est is None or not config.refine:
            continue
        sets = [(h[["x_mm", "y_mm", "z_mm"]].to_numpy(float), [tuple(h["sphere_id"])])
                for _, h in g.groupby("measurement") if len(h) >= 3]
        if not sets:
            continue
        scale, u_scale, n = estimate_scale(sets, artefact, replace(config, centre_u_mm=est.centre_u_mm))
        estimates[s] = replace(est, scale=scale, u_scale=u_scale, n_measurements=n)
        outcomes.loc[outcomes["scanner"] == s, "scale"] = scale
    return {s: e.scale for s, e in estimates.items()}


def _anchor_links(poses: PoseResult, links: LinkResult | None, source: str) -> LinkResult | None:
    """The links that place the most poses in one frame: the reference's, or, while the
    reference shares too few labelled measurements, another scanner's."""
    if not len(poses.poses):
        return None
    counts = poses.poses["scanner"].value_counts()
    best, n_best = links, sum(counts.get(s, 0) for s in links.links) if links is not None else -1
    for s in counts.index:
        if links is not None and s in links.links:
            continue
        cand, _ = _link(poses, s, source)
        n = sum(counts.get(t, 0) for t in cand.links) if cand is not None else -1
        if n > n_best:
            best, n_best = cand, n
    return best


def _say_what_decides(outcomes: pd.DataFrame, links: LinkResult | None, guess: LinkResult | None, joint: dict,
                      reference: str) -> LinkResult | None:
    """Without a plan: each view still ambiguous says what the other scanners' views gave
    and what would decide it; each scanner left unlinked, why the hypotheses gave no link
    (the reference is never unlinked)."""
    rows = (outcomes["status"] == "refused") & (outcomes["reason"] == "ambiguous")
    for i in np.flatnonzero(rows.to_numpy()):
        m = outcomes.at[i, "measurement"]
        others = joint.get(m, "no scanner linked to it sees this measurement")
        outcomes.at[i, "message"] = (f"{outcomes.at[i, 'message']}; with the other scanners' views: {others}; "
                                     "the planned poses (poses_planned.csv) or more spheres in the view would "
                                     "decide it")
    if guess is None:
        return links
    linked = links.links if links is not None else {}
    unlinked = dict(links.unlinked) if links is not None else {}
    for s, why in guess.unlinked.items():
        if s not in linked and s != reference:
            unlinked[s] = f"{unlinked[s]}; " if s in unlinked else ""
            unlinked[s] += f"from its possible labellings: {why}"
    return LinkResult(reference, dict(linked), unlinked) if links is not None or unlinked else links


def _lacks_links(anchor: LinkResult | None, estimates: dict, reference: str) -> bool:
    """Does some scanner with hypotheses lack a link in the reference's frame?"""
    if anchor is None or anchor.reference != reference:
        return True
    return any(s not in anchor.links and e.hypotheses and any(e.hypotheses.values()) for s, e in estimates.items())


def _with_guess(anchor: LinkResult | None, guess: LinkResult | None) -> LinkResult | None:
    """The anchor's links, and for the scanners it lacks the links the hypotheses
    alone gave (:func:`~fringecal.spheres.label_links.links_from_hypotheses`), when both
    are in the reference's frame."""
    if guess is None or (anchor is not None and anchor.reference != guess.reference):
        return anchor
    if anchor is None:
        return guess if len(guess.links) > 1 else None
    extra = {s: lk for s, lk in guess.links.items() if s not in anchor.links}
    if not extra:
        return anchor
    return LinkResult(anchor.reference, {**anchor.links, **extra},
                      {s: w for s, w in anchor.unlinked.items() if s not in extra})


def _refuse(labelled: pd.DataFrame, outcomes: pd.DataFrame, measurement, scanner, message: str) -> None:
    key = (outcomes["measurement"] == measurement) & (outcomes["scanner"] == scanner)
    outcomes.loc[key, ["status", "reason", "n_labelled", "rms_mm"]] = ["refused", "inconsistent", 0, np.nan]
    outcomes.loc[key, "message"] = message
    rows = (labelled["measurement"] == measurement) & (labelled["scanner"] == scanner)
    labelled.loc[rows, "sphere_id"] = ""
    labelled.loc[rows, "label_residual_mm"] = np.nan


def _label_from_poses(labelled: pd.DataFrame, outcomes: pd.DataFrame, poses: pd.DataFrame, links: LinkResult,
                      estimates: dict, artefact: Artefact, config: LabellingConfig, allowed_ids: dict | None,
                      tol: float, joint: dict | None = None) -> int:
    """Label the groups refused as ambiguous from the poses other scanners measured.

    The linked scanners' poses of a measurement, carried into the reference frame,
    stand in for its planned pose (with the standard uncertainty of the registration
    that gave each): a scanner's frame is found by the same consensus as with a plan
    (:func:`~fringecal.spheres.label_scanners.scanner_frame_from_plan`, over all its
    possible labellings), and its ambiguous measurements are labelled with the
    predicted pose (method ``linked pose``) if the labelling's own pose puts every
    sphere within ``tol`` of it. Returns how many groups were labelled.

    ``joint`` (without a plan): a measurement no linked scanner has posed is placed by
    all linked scanners' views together
    (:func:`~fringecal.spheres.label_joint.joint_placement`), and each scanner's frame
    is its link rather than a consensus; the dict is filled with measurement -> why
    it stays refused.
    """
    placed: dict[str, list] = {}
    for r in poses.itertuples(index=False):
        if r.scanner not in links.links or r.scanner not in estimates:
            continue
        T = Frame([r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad])
        rows = (labelled["measurement"] == r.measurement) & (labelled["scanner"] == r.scanner) & \
            (labelled["sphere_id"] != "")
        est = estimates[r.scanner]
        X = labelled.loc[rows, ["x_mm", "y_mm", "z_mm"]].to_numpy(float) / est.scale
        sigma = frame_uncertainty(X, T.to_world(artefact.centres), max(est.centre_u_mm, config.centre_u_mm))
        placed.setdefault(str(r.measurement), []).append((r.scanner, links.links[r.scanner].frame.compose(T), sigma))
    world = {m: mean_frame([T for _, T, _ in v])[0] for m, v in placed.items()}
    sigma = {m: min(sg for _, _, sg in v) for m, v in placed.items()}
    if joint is None:
        for m, (W, sg, names) in _poses_from_alternatives(labelled, outcomes, links, estimates, artefact, config,
                                                          set(world)).items():
            world[m], sigma[m] = W, sg
            placed[m] = [(f"{', '.join(names)} (the only labelling on which they agree)", W, sg)]
    else:
        for m, jp in joint_placements(labelled, outcomes, links, estimates, artefact, config, set(world),
                                      tol).items():
            if jp.frame is None:
                joint[m] = jp.note
                continue
            joint.pop(m, None)
            world[m], sigma[m] = jp.frame, jp.sigma
            placed[m] = [(f"{', '.join(jp.scanners)} together ({jp.note})", jp.frame, jp.sigma)]
    todo = outcomes[(outcomes["status"] == "refused") & (outcomes["reason"] == "ambiguous")
                    & outcomes["measurement"].isin(list(world))]
    n_new = 0
    for s, mine in todo.groupby("scanner", sort=False):
        est = estimates.get(s)
        if est is None:
            continue
        results = {}
        for m, alts in est.hypotheses.items():
            rows = (labelled["measurement"] == m) & (labelled["scanner"] == s)
            if m in world and alts:
                results[m] = (labelled.loc[rows, ["x_mm", "y_mm", "z_mm"]].to_numpy(float), alts)
        if joint is not None and s in links.links:  # no plan: the link is the scanner's frame
            frame = links.links[s].frame.inverse()
        else:
            frame, _, _ = scanner_frame_from_plan(results, world, artefact, config, est.scale, sigma)
        if frame is None:
            continue
        for i, r in mine.iterrows():
            m = r["measurement"]
            prior = frame.compose(world[m])
            rows = (labelled["measurement"] == m) & (labelled["scanner"] == s)
            res = label_with_prior(labelled[rows], artefact, config, est, prior, (allowed_ids or {}).get(s))
            if not isinstance(res, Labelling):
                continue
            d = float(np.linalg.norm(res.T_scanner_artefact.to_world(artefact.centres)
                                     - prior.to_world(artefact.centres), axis=1).max())
            if d > tol:
                continue
            labelled.loc[rows, "sphere_id"] = [sid or "" for sid in res.sphere_ids]
            labelled.loc[rows, "label_residual_mm"] = res.residuals_mm
            cands = list(labelled.loc[rows, "candidate"])
            notes = [f"candidate {cands[j]}: {w}" for j, w in res.unlabelled.items()]
            notes.append(f"distances alone: ambiguous; labelled with the pose of scanner(s) "
                         f"{', '.join(sc for sc, _, _ in placed[m])} carried by their links, {s}'s frame from "
                         + ("its link" if joint is not None else "the consensus of its measurements"))
            outcomes.loc[i, ["status", "reason", "method", "n_labelled", "rms_mm", "message"]] = [
                "labelled", "", "linked pose", res.n_labelled, res.rms_mm, "; ".join(notes)]
            n_new += 1
    return n_new


def _poses_from_alternatives(labelled: pd.DataFrame, outcomes: pd.DataFrame, links: LinkResult, estimates: dict,
                             artefact: Artefact, config: LabellingConfig, skip: set) -> dict:
    """The artefact's pose in a measurement that no scanner could label alone.

    Each linked scanner's possible labellings of the measurement, carried into the
    reference frame by its link, put the artefact somewhere; the true ones of
    different scanners agree (within ``k`` of their combined registration
    uncertainty), wrong ones repeat each view's own symmetry and scatter. A placement
    is taken when two or more scanners agree on it and no placement far from it has
    as much support. Returns measurement -> (T_reference_artefact, sigma, scanners).
    """
    cfg = config
    todo = outcomes[(outcomes["status"] == "refused") & (outcomes["reason"] == "ambiguous")
                    & outcomes["scanner"].isin(list(links.links)) & ~outcomes["measurement"].isin(list(skip))]
    out = {}
    for m, g in todo.groupby("measurement", sort=False):
        hyps = []  # (scanner, points, sigma, frame)
        for s in g["scanner"]:
            est = estimates.get(s)
            if est is None:
                continue
            rows = (labelled["measurement"] == m) & (labelled["scanner"] == s)
            X = labelled.loc[rows, ["x_mm", "y_mm", "z_mm"]].to_numpy(float) / est.scale
            u = max(est.centre_u_mm, cfg.centre_u_mm)
            for alt in est.hypotheses.get(m, []):
                idx = [i for i, sid in enumerate(alt) if sid is not None]
                M, t = kabsch(artefact.centres_of([alt[i] for i in idx]), X[idx])
                T = links.links[s].frame.compose(Frame.from_matrix(M.T, t))
                sg = frame_uncertainty(X[idx], artefact.centres @ M.T + t, u)
                hyps.append((s, T.to_world(artefact.centres), sg, T))
        if len({h[0] for h in hyps}) < 2:
            continue
        P = np.stack([h[1] for h in hyps])
        sg = np.array([h[2] for h in hyps])
        rms = np.sqrt(np.mean(np.sum((P[:, None] - P[None]) ** 2, axis=3), axis=2))
        close = rms <= cfg.k * np.sqrt(sg[:, None] ** 2 + sg[None] ** 2)
        names = np.array([h[0] for h in hyps])
        support = np.array([len(set(names[close[i]])) for i in range(len(hyps))])
        best = int(np.argmax(support))
        if support[best] < 2:
            continue
        far = rms[best] > 2 * cfg.k * np.sqrt(sg[best] ** 2 + sg ** 2)
        if far.any() and support[far].max() >= support[best]:
            continue
        members = {}
        for j in np.flatnonzero(close[best]):
            if names[j] not in members or rms[best, j] < rms[best, members[names[j]]]:
                members[names[j]] = j
        W = mean_frame([hyps[j][3] for j in members.values()])[0]
        out[m] = (W, float(np.sqrt(1 / np.sum(1 / sg[list(members.values())] ** 2))), sorted(members))
    return out


def _check_links_against_plan(links: LinkResult, estimates: dict, artefact: Artefact, planned: dict,
                              tol: float) -> LinkResult:
    """Refuse a link that the planned poses contradict: ``T_reference_scanner`` from the
    shared measurements against ``F_reference o F_scanner^-1`` from each scanner's
    consensus frame ``F`` (where both scanners have one)."""
    ref = estimates.get(links.reference)
    if ref is None or ref.frame is None:
        return links
    probe = next(iter(planned.values())).to_world(artefact.centres)
    kept, unlinked = dict(links.links), dict(links.unlinked)
    for s, lk in links.links.items():
        est = estimates.get(s)
        if s == links.reference or est is None or est.frame is None:
            continue
        pts_s = est.frame.to_world(probe)  # the planned artefact in scanner s's frame
        by_plan = ref.frame.to_world(probe)
        by_link = lk.frame.to_world(pts_s)
        d = float(np.linalg.norm(by_plan - by_link, axis=1).max())
        if d > tol:
            del kept[s]
            unlinked[s] = (f"the link from the shared measurements ({', '.join(lk.measurements)}) disagrees by "
                           f"{d:.0f} mm with the one the planned poses imply: a labelling of {s} or of a scanner "
                           f"on its path {list(lk.via)} is wrong")
    for s, lk in list(kept.items()):  # chained through a refused link
        gone = [v for v in lk.via if v not in kept]
        if gone:
            del kept[s]
            unlinked[s] = f"linked through {gone[0]}, whose link is refused: {unlinked[gone[0]]}"
    return LinkResult(links.reference, kept, unlinked)
