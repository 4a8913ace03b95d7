"""Labelling and linking of three rigs through prior calibrations with the documented
errors, with and without planned poses; prints one JSON object.

    PYTHONPATH=. python benchmarks/labelling_rigs.py [--seeds 0 1 2] [--out FILE]

``--smoke``: the thesis rig, one seed.

Rigs (``fringecal.simulate.sphere_centres``): the thesis's two scanners (six
spheres per view), the three-scanner row (scanner1 sees only the triangle 1-2-3), a
six-scanner ring with a narrow field (3-14 spheres per view). Each scanner's centres
are 0.4-0.6 % off in scale about its own origin, warped by ~1 mm and noisy by 0.1 mm,
in an arbitrary frame; the planned poses are good to 1 mm / 1 mrad.

Per rig and seed, with and without the plan: views labelled, wrong labels, methods,
largest scale error, largest link error where each scanner measures (mm) and in angle
(mrad), time. Per view of the first seed: whether the spheres it sees, at their exact
CMM positions, are ambiguous (:func:`fringecal.spheres.labelling.ambiguous_subsets`)
with the stated tolerances and with the scanner's own estimated ones, how many
labellings fit and what they are (permutations of the same spheres: a symmetry of
the set seen; other spheres: another part of the artefact looks the same), and what
the labelling did without the plan. That is the report of which measurements need
the plan and why (docs/spheres.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from dataclasses import asdict, replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402

from fringecal.simulate.sphere_centres import RIGS, PriorErrors, link_errors, observe_rig  # noqa: E402
from fringecal.spheres.labelling import LabellingConfig, ambiguous_subsets  # noqa: E402
from fringecal.spheres.poses_and_links import label_pose_link  # noqa: E402


def run(obs, planned) -> tuple[dict, object]:
    t0 = time.perf_counter()
    res = label_pose_link(obs.fits, obs.artefact, obs.reference, planned=planned)
    dt = time.perf_counter() - t0
    merged = res.fits.merge(obs.fits[["measurement", "scanner", "candidate", "truth"]])
    labelled = merged[merged["sphere_id"] != ""]
    out = res.labels
    mm, rad = link_errors(obs, res)
    return {
        "views_labelled": int((out["status"] == "labelled").sum()), "views": len(out),
        "wrong_labels": int((labelled["sphere_id"] != labelled["truth"]).sum()),
        "methods": dict(Counter(out.loc[out["status"] == "labelled", "method"])),
        "refused": dict(Counter(out.loc[out["status"] == "refused", "reason"])),
        "scale_error_max": float(max(abs(e.scale - obs.scales[s]) for s, e in res.estimates.items())),
        "link_error_mm": round(mm, 2), "link_error_mrad": round(rad * 1e3, 2),
        "unlinked": sorted(res.links.unlinked) if res.links is not None else res.links_error,
        "seconds": round(dt, 2),
    }, res


def why(sub, alternatives) -> str:
    seen = set(sub)
    same = [a for a in alternatives if {x for x in a if x} == seen]
    other = {frozenset(x for x in a if x) for a in alternatives} - {frozenset(seen)}
    parts = []
    if len(same) > 1:
        parts.append(f"{len(same)} orderings of the same spheres (a symmetry of the set seen)")
    if other:
        parts.append(f"{len(other)} other sets of spheres that look the same")
    return "; ".join(parts)


def view_report(obs, res, cfg) -> list[dict]:
    rows = []
    out = res.labels.set_index(["measurement", "scanner"])
    for (m, s), g in obs.fits.groupby(["measurement", "scanner"], sort=False):
        sub = tuple(sorted((x for x in g["truth"] if x), key=int))
        est = res.estimates[s]
        own = replace(cfg, centre_u_mm=est.centre_u_mm, scale_tol=est.scale_tol)
        stated = list(ambiguous_subsets(obs.artefact, len(sub), sub, cfg))
        refined = list(ambiguous_subsets(obs.artefact, len(sub), sub, own))
        rows.append({"measurement": m, "scanner": s, "spheres": ",".join(sub),
                     "ambiguous_stated": bool(stated), "ambiguous_own": bool(refined),
                     "alternatives_own": len(refined[0][1]) if refined else 0,
                     "why": why(sub, refined[0][1]) if refined else "",
                     "without_plan": out.loc[(m, s), "method"] if out.loc[(m, s), "status"] == "labelled"
                     else f"refused ({out.loc[(m, s), 'reason']})"})
    return rows


def summarise(views: list[dict]) -> dict:
    """Per scanner: which sets of spheres need help and why."""
    by = {}
    for v in views:
        d = by.setdefault(v["scanner"], {"views": 0, "unambiguous_alone": 0, "need_plan": {}, "without_plan": Counter()})
        d["views"] += 1
        d["without_plan"][v["without_plan"]] += 1
        if not v["ambiguous_own"]:
            d["unambiguous_alone"] += 1
        else:
            d["need_plan"].setdefault(v["spheres"], {"views": 0, "why": v["why"]})["views"] += 1
    for d in by.values():
        d["without_plan"] = dict(d["without_plan"])
    return by


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = add_options(ap).parse_args(argv)
    rigs = list(RIGS)[:1] if args.smoke else list(RIGS)
    if args.smoke:
        args.seeds = args.seeds[:1]
    cfg = LabellingConfig()
    report = {**conditions("labelling_rigs", argv, args.smoke), "prior_errors": asdict(PriorErrors()),
              "config": asdict(cfg), "rigs": {}}
    for name in rigs:
        r = report["rigs"][name] = {"seeds": {}}
        for seed in args.seeds:
            obs = observe_rig(name, seed=seed)
            with_plan, _ = run(obs, obs.planned)
            without, res = run(obs, None)
            sizes = obs.fits.groupby(["measurement", "scanner"]).size()
            r["seeds"][seed] = {"prior_rms_mm": round(obs.rms_mm, 2),
                                "spheres_per_view": {int(k): int(v) for k, v in sizes.value_counts().items()},
                                "with_plan": with_plan, "without_plan": without}
            if seed == args.seeds[0]:
                views = view_report(obs, res, cfg)
                r["need_plan"] = summarise(views)
                r["views"] = views
            print(f"{name} seed {seed}: with plan {with_plan['views_labelled']}/{with_plan['views']} "
                  f"(wrong {with_plan['wrong_labels']}), without {without['views_labelled']}/{without['views']} "
                  f"(wrong {without['wrong_labels']})", file=sys.stderr)
    return finish(report, args.out)


if __name__ == "__main__":
    main()
