"""Where a ball-bar length's error comes from, over the kept run directories of
``benchmarks/length_coverage.py --keep --workdir W``: per position, the error with the
calibrated rig (``verification.json``), the error with the TRUE rig (the evaluate step's
``verification_true_params``: the sphere fits alone) and their difference (the
calibration's part), each against the budget's stated term (``sphere fits``,
``calibration``). A mean beyond its standard error (sd / sqrt(n)) is a bias the budget
does not hold. Per run also each scanner's scatter of sphere centres between spheres in
the calibration's views against their fits' u (``kappa``,
:mod:`fringecal.spheres.dispersion`; from ``bundle_summary.json``, or computed from the
run's control points and calibration when the run predates it), and over all positions
the RMS of the true-rig error over the sphere fits' u (1 when that u holds the fits'
whole error), of the calibration's part over its linear term alone and with the
jackknife's model error (:mod:`fringecal.calibration.jackknife`), and the lengths'
jackknife spread over their linear calibration term (min, median, max).

    PYTHONPATH=. python benchmarks/coverage_split.py W [W2 ...] [--out FILE]

Each argument is a folder of ``*-seed*`` run directories, or a simulated run directory
itself. A run without ``evaluation.json`` gets its ``evaluate`` step run first. Prints
one line per position and the JSON (``--out``: also written there). ``--smoke``: as
given (point it at one small run).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402


def run_dirs(folders) -> list[Path]:
    out = []
    for a in map(Path, folders):
        out += [a] if (a / "verification.json").exists() else sorted(a.glob("*-seed*"))
    return [d for d in out if (d / "verification.json").exists()]


def rows_of(d: Path) -> list[tuple]:
    """(run, position, error, true-rig error, u, u of the sphere fits, u of the calibration,
    its model-error term, the length's jackknife spread (NaN: none))."""
    import json

    from fringecal.run.config import RunConfig
    from fringecal.rundir import RunDir
    from fringecal.steps import get_step, run_step

    rd = RunDir(d)
    if not rd.evaluation.exists():
        run_step(get_step("evaluate"), rd, RunConfig.model_validate(rd.read_manifest()["config"]))
    ev = json.loads(rd.evaluation.path.read_text())["verification_true_params"]
    true_rig = {p["measurement"]: p["error_mm"] for p in ev["positions"]}
    ver = json.loads(rd.verification.path.read_text())["uncertainty"]
    return [(d.name, length["measurement"], length["error_mm"], true_rig.get(length["measurement"], np.nan),
             length["u_mm"], length["budget_mm"].get("sphere fits", 0), length["budget_mm"].get("calibration", 0),
             length["budget_mm"].get("model error (cross-validation)", 0),
             (length.get("jackknife") or {}).get("spread_mm", np.nan))
            for length in ver["lengths"]]


def kappa_of(d: Path) -> dict:
    """scanner -> kappa of the run ``d`` (see the module)."""
    import json

    from fringecal.calibration.file import read_calibration
    from fringecal.rundir import RunDir
    from fringecal.spheres.dispersion import sighting_dispersion
    from fringecal.steps.bundle import load_problem

    rd = RunDir(d)
    rec = json.loads(rd.bundle_summary.path.read_text()).get("sighting_dispersion")
    if rec:
        return {s: v["kappa"] for s, v in rec.items()}
    rig = read_calibration(rd.calibration.path).rig
    return {s: v.kappa for s, v in sighting_dispersion(load_problem(rd, rig.scanners[0].name), rig).items()}


def _range(x: np.ndarray) -> dict | None:
    """min, median, max of the finite values (None: none)."""
    x = x[np.isfinite(x)]
    return None if not x.size else {"min": float(x.min()), "median": float(np.median(x)), "max": float(x.max())}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", help="folders of kept run directories, or run directories")
    args = add_options(ap).parse_args(argv)
    doc = conditions("coverage_split", argv, args.smoke)
    dirs = run_dirs(args.folders)
    rows = [r for d in dirs for r in rows_of(d)]
    doc["runs"] = sorted({r[0] for r in rows})
    doc["kappa"] = {d.name: kappa_of(d) for d in dirs}
    kappas = [k for v in doc["kappa"].values() for k in v.values()]
    e, et, u, uf, uc, um, sj = np.array([r[2:] for r in rows], float).T
    doc["all_positions"] = {"n": len(e), "rms_z": float(np.sqrt(np.mean((e / u) ** 2))),
                            "true_rig_rms_z_of_sphere_fits": float(np.sqrt(np.nanmean((et / uf) ** 2))),
                            "calibration_part_rms_z": float(np.sqrt(np.nanmean(((e - et) / uc) ** 2))),
                            "calibration_part_rms_z_with_model_error":
                                float(np.sqrt(np.nanmean(((e - et) / np.hypot(uc, um)) ** 2))),
                            "jackknife_spread_over_u_calibration": _range(sj / uc),
                            "kappa_range": [min(kappas), max(kappas)] if kappas else None}
    a = doc["all_positions"]
    print(f"all: n={len(e)} rms z {a['rms_z']:.2f}, true-rig error / u_fits RMS "
          f"{a['true_rig_rms_z_of_sphere_fits']:.2f}, calibration's part / u_cal RMS {a['calibration_part_rms_z']:.2f} "
          f"(with the model error {a['calibration_part_rms_z_with_model_error']:.2f}), jackknife spread / u_cal "
          f"{a['jackknife_spread_over_u_calibration']}, kappa {a['kappa_range']}", file=sys.stderr)
    doc["positions"] = {}
    for m in sorted({r[1] for r in rows}):
        e, et, u, uf, uc, um, sj = np.array([r[2:] for r in rows if r[1] == m], float).T
        entry = {"n": len(e), "calibrated_error_mean_um": 1000 * e.mean(),
                 "rms_z": float(np.sqrt(np.mean((e / u) ** 2))),
                 "true_rig_error_mean_um": 1000 * np.nanmean(et), "true_rig_error_sd_um": 1000 * np.nanstd(et),
                 "u_sphere_fits_rms_um": 1000 * np.sqrt(np.mean(uf ** 2)),
                 "calibration_part_mean_um": 1000 * np.nanmean(e - et),
                 "calibration_part_sd_um": 1000 * np.nanstd(e - et),
                 "u_calibration_rms_um": 1000 * np.sqrt(np.mean(uc ** 2)),
                 "u_model_error_rms_um": 1000 * np.sqrt(np.mean(um ** 2)),
                 "jackknife_spread_over_u_calibration": _range(sj / uc)}
        doc["positions"][m] = entry
        print(f"{m}: n={entry['n']} calibrated err mean {entry['calibrated_error_mean_um']:+.1f} um rms z "
              f"{entry['rms_z']:.2f} | true-rig err mean {entry['true_rig_error_mean_um']:+.1f} sd "
              f"{entry['true_rig_error_sd_um']:.1f} vs u_fits {entry['u_sphere_fits_rms_um']:.1f} | calibration "
              f"part mean {entry['calibration_part_mean_um']:+.1f} sd {entry['calibration_part_sd_um']:.1f} vs "
              f"u_cal {entry['u_calibration_rms_um']:.1f} + model error {entry['u_model_error_rms_um']:.1f}",
              file=sys.stderr)
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
