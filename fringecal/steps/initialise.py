"""Start values: every scanner's prior calibration moved into the reference frame by
its link, a DLT per sensor in the global frame from the CMM centres at the linked
poses (thesis 6.3), one start pose per measurement; and the control points of all
measurements in one table. These are the bundle adjustment's inputs.
"""

from __future__ import annotations

import pandas as pd

from fringecal.calibration.initial import UnlinkedScanners, initial_calibration
from fringecal.rundir import RunDir
from fringecal.steps.base import DataProblem, Settings, Step, black_boxes_only
from fringecal.steps.spheres_first import modelled_items

__all__ = ["Initialise"]


class Initialise(Step):
    name = "initialise"
    title = "start values"
    settings = ("reference_scanner",)
    modules = ("fringecal.calibration.initial",)

    def reads(self, rd: RunDir, cfg: Settings, item: str):
        if black_boxes_only(rd):  # black boxes only: nothing to start (docs/blackbox.md)
            return [rd.sensors_prior]
        return [rd.sensors_prior, rd.sphere_centres, rd.poses, rd.scanner_links, rd.artefact] + \
            [rd.control_points_of(m) for m in modelled_items(rd)]

    def writes(self, rd: RunDir, cfg: Settings, item: str):
        if black_boxes_only(rd):
            return []
        return [rd.control_points, rd.poses_initial, rd.sensors_initial, rd.dlt]

    def run(self, rd: RunDir, cfg: Settings, item: str, **context) -> None:
        if black_boxes_only(rd):  # black boxes only: the bundle step adjusts their transforms alone
            return
        centres = rd.sphere_centres.load()
        try:
            init = initial_calibration(rd.sensors_prior.load(cfg.reference_scanner), centres,
                                       rd.poses.load(), rd.scanner_links.load(), rd.artefact.load())
        except UnlinkedScanners as err:
            raise DataProblem(unlinked_message(rd, err.scanners, cfg.reference_scanner, centres)) from None
        cps = [rd.control_points_of(m).load() for m in modelled_items(rd)]
        rd.control_points.save(pd.concat([c for c in cps if len(c)], ignore_index=True))
        rd.poses_initial.save(init.poses)
        rd.sensors_initial.save(init.rig)
        rd.dlt.save(init.dlt)


def unlinked_message(rd: RunDir, scanners: list[str], reference: str, centres: pd.DataFrame) -> str:
    """One sentence for the scanners without a link (each named once, the reference never):
    per scanner why its views were not labelled (from ``label_outcomes``: ambiguous, too
    few spheres, inconsistent, by measurement) and its labelled spheres per measurement (a
    pose needs three, and a link one pose shared with a linked scanner); then what would
    decide them: the planned poses for ambiguous views, more spheres per view for the others."""
    scanners = list(dict.fromkeys(s for s in scanners if s != reference))
    per = centres.groupby(["scanner", "measurement"]).size() if len(centres) else pd.Series(dtype=int)
    outcomes = rd.label_outcomes.load() if rd.label_outcomes.exists() else None
    parts, reasons = [], set()
    for s in scanners:
        seen = per[s] if s in per.index.get_level_values(0) else pd.Series(dtype=int)
        best = ", ".join(f"{m}: {n}" for m, n in seen.sort_values(ascending=False).head(4).items()) or "none"
        why = []
        if outcomes is not None:
            mine = outcomes[outcomes["scanner"] == s]
            for reason, g in mine[mine["status"] == "refused"].groupby("reason", sort=False):
                reasons.add(reason)
                most = int(g["n_candidates"].max())
                why.append(f"{_REASON.get(reason, reason)} in measurement(s) {_listed(g['measurement'])}"
                           + (f" (at most {most} candidate(s) in a view)" if reason == "too_few_candidates" else ""))
        parts.append(f"scanner {s}: {'; '.join(why + [f'labelled spheres per measurement, most first: {best}'])}")
    ref_seen = per[reference] if reference in per.index.get_level_values(0) else pd.Series(dtype=int)
    if not (ref_seen >= 3).any() and outcomes is not None:
        mine = outcomes[(outcomes["scanner"] == reference) & (outcomes["status"] == "refused")]
        reasons |= set(mine["reason"])
        why = [f"{_REASON.get(r, r)} in measurement(s) {_listed(g['measurement'])}"
               for r, g in mine.groupby("reason", sort=False)]
        parts.insert(0, f"the reference scanner {reference} itself has no labelled view"
                        + (f" ({'; '.join(why)})" if why else "") + ", so nothing can be linked to it")
    decide = []
    if "ambiguous" in reasons:
        decide.append("the planned poses (poses_planned.csv in the data set) or views with more spheres, not all "
                      "of one symmetric part of the artefact, would decide the ambiguous views")
    if reasons - {"ambiguous"} or not reasons:
        decide.append("a view needs three or more of the artefact's spheres, in a measurement a linked scanner "
                      "shares, to link its scanner")
    return (f"{rd.root}: {len(scanners)} scanner(s) cannot be placed in the frame of the reference scanner "
            f"({reference}): {'. '.join(parts)}. {_first_upper('; '.join(decide))}; why each view was refused: "
            f"{rd.label_outcomes.path}")


_REASON = {"ambiguous": "ambiguous (its spheres fit several labellings, and the other scanners' views do not "
                        "single one out)",
           "too_few_candidates": "fewer than three spheres", "inconsistent": "contradicted by its other views or "
           "the other scanners", "search_limit": "too many candidates to search"}


def _listed(measurements) -> str:
    ms = sorted(map(str, measurements), key=lambda m: (len(m), m))
    return ", ".join(ms) if len(ms) <= 8 else f"{', '.join(ms[:6])}, ... ({len(ms)} in all)"


def _first_upper(text: str) -> str:
    return text[:1].upper() + text[1:]
