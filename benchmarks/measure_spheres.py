"""Are the uncertainties ``fringecal measure --spheres`` states honest? A finished
simulated run's ball-bar, measured as a user measures objects, against the truth.

For every ball-bar position of the run ``RUN_DIR`` (stores ``<position>-<scanner>``),
one cloud is measured with the run's calibration (:func:`fringecal.measure.measure_cloud`)
and the bar's two spheres are fitted in it (:func:`fringecal.measure.spheres.measure_spheres`,
nominal centres: the true ones, radii: the certificate's) with the covariance moved to
the rig's frame (:func:`fringecal.calibration.propagation.frame_free_covariance`),
either the whole budget (``total``: adjustment, artefact CMM, artefact scale) or the
adjustment's part alone (``adjustment``; the one that describes an ideal world, whose
artefact is exactly its table). Against the truth (the run's ``truth/``, moved into the
calibration's world as the ``evaluate`` step does):

* each centre's **position in the rig's frame**: the calibrated centre moved back by
  the rigid motion of the whole rig that the sensors' errors amount to
  (:func:`~fringecal.calibration.propagation.frame_motion_operator`, the motion the
  frame-free covariance projects out), minus the true centre; 3-D |error| / u;
* each **distance** between the two centres: |error| / u.

As the command does, each scanner's fits are scaled by its scatter factor between
spheres (``sighting_dispersion`` of the calibration's metadata), and the distances carry
the calibration's replicas (``replicas`` of ``calibration.json``): the bootstrap's bias
subtracted, the jackknife's model error added.

Median ratios between 0.5 and 2 say the stated uncertainty is honest (about 0.9 for a
3-D error against sqrt(trace), about 0.7 for a 1-D one, when u is right).

    PYTHONPATH=. python benchmarks/measure_spheres.py runs/thesis --out benchmarks/results/measure_spheres.json

Several runs (e.g. the seeds ``benchmarks/length_coverage.py --keep`` leaves) are pooled:
each run is one draw of its calibration's errors, shared by all its centres, so the
median over many runs is the figure that tells whether u is right; the JSON keeps each
run's own median too.

``--smoke``: the same (the run decides the size).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402


def measure(run_dir: Path) -> dict:
    import pandas as pd

    from fringecal.calibration.file import read_calibration
    from fringecal.calibration.propagation import frame_free_covariance, frame_motion_operator, to_rig_frame
    from fringecal.frames import frames_from_rows
    from fringecal.measure import MeasureSettings, measure_cloud
    from fringecal.measure.spheres import measure_spheres, sphere_distances
    from fringecal.rundir import RunDir
    from fringecal.steps.evaluate import truth_in_reference_frame
    from fringecal.steps.verify import ballbar_stores
    from fringecal.store import open_store

    rd = RunDir(run_dir)
    cal = read_calibration(rd.calibration.path)
    rig = cal.rig
    reference = rig.scanners[0].name
    T = frames_from_rows(rd.truth.scanner_frames.load(), key="scanner")[reference]
    truth = truth_in_reference_frame(rd.truth.sensors.load(reference), T, rig)
    delta = np.concatenate([s.params - t.params for s, t in zip(rig.sensors, truth.sensors)])
    bar = rd.truth.ballbar.load()
    poses = frames_from_rows(rd.truth.ballbar_positions.load())
    budgets = {"total": cal.covariances.total, "adjustment": cal.covariances.calibration}
    # as `fringecal measure` states them: each scanner's scatter factor, the calibration's replicas
    factors = {s: max(1.0, float(d["kappa"])) for s, d in (cal.metadata.get("sighting_dispersion") or {}).items()}
    out = {}
    for name, C in budgets.items():
        cov = frame_free_covariance(rig, C)
        xi = frame_motion_operator(rig, np.sqrt(np.clip(np.diag(C), 0, None))) @ delta
        rows = []
        for position, by_scanner in ballbar_stores(rd).items():
            centres = T.inverse().to_world(poses[position].to_world(bar.centres))
            true = dict(zip(bar.ids, centres))
            nominal = pd.DataFrame({"sphere_id": list(bar.ids), "x_mm": centres[:, 0], "y_mm": centres[:, 1],
                                    "z_mm": centres[:, 2], "radius_mm": bar.radii})
            stores = {s: open_store(p) for s, p in by_scanner.items()}
            try:
                cloud = measure_cloud(rig, stores, MeasureSettings(uncertainty=False))
                found = measure_spheres(cloud, stores, rig, cov, nominal, fit_factors=factors)
            finally:
                for ds in stores.values():
                    ds.close()
            for m in found:
                e = float(np.linalg.norm(to_rig_frame(rig, xi, m.centre) - true[m.sphere]))
                rows.append({"position": position, "what": f"{m.sphere} ({m.scanner})", "error_mm": e,
                             "u_mm": m.u_position_mm, "kind": "position"})
            for r in sphere_distances(found, cov, cal.covariances.calibration, cal.replicas).itertuples():
                e = float(r.distance_mm - np.linalg.norm(true[r.sphere_a] - true[r.sphere_b]))
                rows.append({"position": position, "what": f"{r.sphere_a}-{r.sphere_b}", "error_mm": e,
                             "u_mm": float(r.u_mm), "kind": "distance"})
        summary = {}
        for kind in ("position", "distance"):
            k = [r for r in rows if r["kind"] == kind]
            ratio = np.array([abs(r["error_mm"]) / r["u_mm"] for r in k])
            summary[kind] = {"n": len(k), "median_ratio": float(np.median(ratio)) if len(k) else None,
                             "error_mm": [min(abs(r["error_mm"]) for r in k), max(abs(r["error_mm"]) for r in k)]
                             if k else None,
                             "u_mm": [min(r["u_mm"] for r in k), max(r["u_mm"] for r in k)] if k else None}
        out[name] = {"summary": summary, "rows": rows}
    return out


def pooled(per_run: list) -> dict:
    """Every run's rows together: for each budget and kind the median ratio over all
    rows, and the runs' own medians (each run is one draw of its calibration's errors,
    which all its centres share, so a single run's median scatters widely)."""
    out = {}
    for name in per_run[0]:
        rows = [dict(r, run=i) for i, run in enumerate(per_run) for r in run[name]["rows"]]
        summary = {}
        for kind in ("position", "distance"):
            k = [r for r in rows if r["kind"] == kind]
            ratio = np.array([abs(r["error_mm"]) / r["u_mm"] for r in k])
            summary[kind] = {"n": len(k), "median_ratio": float(np.median(ratio)) if len(k) else None,
                             "rms_ratio": float(np.sqrt(np.mean(ratio**2))) if len(k) else None,
                             "per_run_median": [run[name]["summary"][kind]["median_ratio"] for run in per_run]}
        out[name] = {"summary": summary, "rows": rows}
    return out


def main(argv=None) -> dict:
    ap = add_options(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("run", type=Path, nargs="+", help="finished simulated runs with ball-bar measurements")
    args = ap.parse_args(argv)
    doc = conditions("measure_spheres", argv, args.smoke)
    doc["runs"] = [str(r) for r in args.run]
    per_run = [measure(r) for r in args.run]
    doc["budgets"] = per_run[0] if len(per_run) == 1 else pooled(per_run)
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
