"""Is the stated uncertainty of the sensor parameters right? Error / u over many seeds.

The default run's world (``configs/run_thesis.yaml``: the thesis rig, twelve poses,
ideal profile, control points every pixel) at ``--width`` px is simulated ``--seeds``
times without Prefect (:func:`fringecal.steps.run_pipeline`, one worker, up to the
``bundle`` step), the seed index ``i`` changing the camera noise
(``simulate.acquisition.seed = 1000 + i``) and the scanners' prior calibration
(``simulate.prior.seed = 3000 + i``). Per seed, every free sensor parameter's error
against the truth (moved into the calibration's world, the reference scanner's own
frame, as the ``evaluate`` step does) divided by its stated standard uncertainty. If
the uncertainty is right these ratios have an RMS of 1.

Two statements of u on the same calibration: ``sandwich``, the run's own
(``calibration.json``; ``bundle.covariance: sandwich``, each point's own residuals), and
``per-term`` (one variance factor per residual term, what fringecal stated before),
re-estimated from the run's control points and calibrated poses
(:func:`fringecal.calibration.bundle.bundle_adjust` from the solution, ``covariance:
per-term``); and the sandwich's u against the parameters corrected by the bootstrap's
estimate of the adjustment's bias (the mean of its replicas minus the estimate,
:mod:`fringecal.calibration.bootstrap`), which the lengths already get.

    PYTHONPATH=. python benchmarks/parameter_coverage.py --seeds 20 --width 512 \\
        --out benchmarks/results/parameter_coverage_512.json

``RUN_DIR`` (a finished simulated run, given as the first argument) gives that run's
ratios alone, no new run (the smoke test, on ``tests/test_run_flow.py``'s run).

The JSON holds the command, the load average at start and end, the wall time, and per
statement the RMS of the ratios over every parameter of every seed, the RMS per seed,
the worst ratio and the RMS per parameter name.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")

import numpy as np  # noqa: E402  (after the thread settings)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(_HERE))
from _common import add_options, conditions, finish  # noqa: E402

from fringecal.sensor import PARAM_NAMES  # noqa: E402


def ratios(rd) -> dict:
    """Error / stated u of every free sensor parameter of a run's calibration: ``sandwich``
    (the run's) and ``per-term`` (re-estimated)."""
    from fringecal.calibration.bundle import BundleOptions, bundle_adjust
    from fringecal.calibration.model import BundleProblem
    from fringecal.frames import frames_from_rows
    from fringecal.steps.evaluate import truth_in_reference_frame

    cal = rd.calibration.load()
    reference = cal.scanners[0].name
    T = frames_from_rows(rd.truth.scanner_frames.load(), key="scanner")[reference]
    truth = truth_in_reference_frame(rd.truth.sensors.load(reference), T, cal)
    cps = rd.control_points.load()
    poses = rd.poses_calibrated.load()
    problem = BundleProblem.from_tables(cal, rd.artefact.load(), cps, poses[poses.measurement.isin(set(cps.measurement))])
    boot = rd.covariance.load().get("bootstrap_params")
    out = {}
    for how in ("sandwich", "per-term"):
        r = bundle_adjust(problem, BundleOptions(start="given", covariance=how))
        u = r.rig.uncertainty
        params = {"": np.array([s.params for s in r.rig.sensors])}
        if how == "sandwich" and boot is not None and len(boot) > 1:
            params[", bootstrap bias subtracted"] = params[""] - (boot.mean(axis=0) - params[""])
        for suffix, P in params.items():
            out[how + suffix] = {f"{est.name}.{name}": float((P[k][j] - true.params[j]) / u[k][j])
                                 for k, (est, true) in enumerate(zip(r.rig.sensors, truth.sensors))
                                 for j, name in enumerate(PARAM_NAMES) if u[k][j] > 0}
    return out


def _entry(r: dict, seconds: float = 0.0) -> dict:
    v = np.array(list(r.values()))
    return {"seconds": seconds, "rms": float(np.sqrt(np.mean(v**2))), "max_abs": float(np.max(np.abs(v))),
            "ratios": r}


def run_seed(i: int, width: int, workdir: Path) -> dict:
    from fringecal.config import configs_dir
    from fringecal.run.config import load_run_config
    from fringecal.run.summary import manifest
    from fringecal.rundir import RunDir
    from fringecal.steps import run_pipeline

    d = Path(tempfile.mkdtemp(dir=workdir, prefix=f"seed{i}-"))
    out = {"seed_index": i}
    try:
        overrides = {"simulate": {"acquisition": {"seed": 1000 + i, "camera_width_px": width},
                                  "prior": {"seed": 3000 + i}}}
        cfg = load_run_config(configs_dir() / "run_thesis.yaml", overrides=overrides)
        rd = RunDir(d / "run").create()
        rd.manifest.save(manifest(cfg))
        t0 = time.perf_counter()
        run_pipeline(rd, cfg, workers=1, until="bundle")
        seconds = time.perf_counter() - t0
        out.update({how: _entry(r, seconds) for how, r in ratios(rd).items()})
    finally:
        shutil.rmtree(d, ignore_errors=True)
    return out


#: the statements of u compared (the third: the parameters corrected by the bootstrap's
#: bias estimate, ``bootstrap_params`` of ``calibration_covariance.npz``, with the sandwich u)
HOW = ("sandwich", "per-term", "sandwich, bootstrap bias subtracted")


def summarise(seeds: list, statements) -> dict:
    out = {}
    for how in statements:
        per = [s[how] for s in seeds if how in s]
        allr = np.array([v for p in per for v in p["ratios"].values()])
        names = sorted({n.split(".", 1)[1] for p in per for n in p["ratios"]})
        by_name = {n: float(np.sqrt(np.mean([v**2 for p in per for k, v in p["ratios"].items()
                                              if k.split(".", 1)[1] == n]))) for n in names}
        out[how] = {"seeds": len(per), "ratios": int(allr.size), "rms": float(np.sqrt(np.mean(allr**2))),
                        "max_abs": float(np.max(np.abs(allr))), "rms_per_seed": [p["rms"] for p in per],
                        "rms_per_parameter": by_name}
    return out


def main(argv=None) -> dict:
    ap = add_options(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("run", nargs="?", type=Path, help="a finished simulated run: its ratios alone")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=512)
    args = ap.parse_args(argv)
    doc = conditions("parameter_coverage", argv, args.smoke)
    if args.run is not None:
        from fringecal.rundir import RunDir

        doc.update({"run": str(args.run), "complete": True, "per_seed": [
            {"seed_index": None, **{how: _entry(r) for how, r in ratios(RunDir(args.run)).items()}}]})
        doc["summary"] = summarise(doc["per_seed"], HOW)
        return finish(doc, args.out)
    doc.update({"width_px": args.width, "complete": False, "per_seed": []})
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fringecal-paramcov-") as work:
        for i in range(args.first_seed, args.first_seed + args.seeds):
            doc["per_seed"].append(run_seed(i, args.width, Path(work)))
            doc["summary"] = summarise(doc["per_seed"], HOW)
            doc["wall_seconds"] = time.perf_counter() - t0
            print(f"seed {i}: " + ", ".join(f"{h}: RMS {doc['per_seed'][-1][h]['rms']:.2f}" for h in HOW), flush=True)
            if args.out:
                with open(os.devnull, "w") as quiet:
                    finish(dict(doc), args.out, stream=quiet)
    doc["complete"] = True
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
