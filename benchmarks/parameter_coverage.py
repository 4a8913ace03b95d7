"""Is the stated uncertainty of the sensor parameters right? Error / u over many seeds.

The default run's world (``configs/run_thesis.yaml``: the thesis rig, twelve poses,
ideal profile, control points every pixel) at ``--width`` px is simulated ``--seeds``
times without Prefect (:func:`fringecal.steps.run_pipeline`, one worker, up to the
``bundle`` step), the seed index ``i`` changing the camera noise
(``simulate.acquisition.seed = 1000 + i``) and the scanners' prior calibration
(``simulate.prior.seed = 3000 + i``). Per seed, every free sensor parameter's error
against the truth (moved into the calibration's world, the reference scanner's own
frame, as the ``evaluate`` step does) divided by its stated standard uncertainty
(``calibration.json``). If the uncertainty is right these ratios have an RMS of 1.

``--spacings 1 3``: after the run with the first control-point spacing, the same
rendered stores are calibrated again with each further spacing (only the control
points and the bundle step rerun): if neighbouring pixels' errors are correlated, the
ratio's RMS falls as the spacing grows (fewer, more nearly independent points).

    PYTHONPATH=. python benchmarks/parameter_coverage.py --seeds 20 --width 512 \\
        --out benchmarks/results/parameter_coverage_512.json

``RUN_DIR`` (a finished simulated run, given as the first argument) gives that run's
ratios alone, no new run (the smoke test, on ``tests/test_run_flow.py``'s run).

The JSON holds the command, the load average at start and end, the wall time, and per
spacing the RMS of the ratios over every parameter of every seed, the RMS per seed,
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


def ratios(rd) -> dict:
    """Error / stated u of every free sensor parameter of a run's calibration."""
    from fringecal.frames import frames_from_rows
    from fringecal.sensor import PARAM_NAMES
    from fringecal.steps.evaluate import truth_in_reference_frame

    cal = rd.calibration.load()
    reference = cal.scanners[0].name
    T = frames_from_rows(rd.truth.scanner_frames.load(), key="scanner")[reference]
    truth = truth_in_reference_frame(rd.truth.sensors.load(reference), T, cal)
    out = {}
    for k, (est, true) in enumerate(zip(cal.sensors, truth.sensors)):
        u = cal.uncertainty[k]
        for j, name in enumerate(PARAM_NAMES):
            if u[j] > 0:
                out[f"{est.name}.{name}"] = float((est.params[j] - true.params[j]) / u[j])
    return out


def _entry(r: dict, seconds: float = 0.0) -> dict:
    v = np.array(list(r.values()))
    return {"seconds": seconds, "rms": float(np.sqrt(np.mean(v**2))), "max_abs": float(np.max(np.abs(v))),
            "ratios": r}


def run_seed(i: int, width: int, spacings, workdir: Path) -> dict:
    from fringecal.config import configs_dir
    from fringecal.run.config import load_run_config
    from fringecal.run.summary import manifest
    from fringecal.rundir import RunDir
    from fringecal.steps import run_pipeline

    d = Path(tempfile.mkdtemp(dir=workdir, prefix=f"seed{i}-"))
    out = {"seed_index": i}
    try:
        for spacing in spacings:
            overrides = {"simulate": {"acquisition": {"seed": 1000 + i, "camera_width_px": width},
                                      "prior": {"seed": 3000 + i}},
                         "control_points": {"spacing_px": int(spacing)}}
            cfg = load_run_config(configs_dir() / "run_thesis.yaml", overrides=overrides)
            rd = RunDir(d / "run")
            if not rd.root.exists():
                rd.create()
            rd.manifest.save(manifest(cfg))
            t0 = time.perf_counter()
            run_pipeline(rd, cfg, workers=1, until="bundle")
            out[str(spacing)] = _entry(ratios(rd), time.perf_counter() - t0)
    finally:
        shutil.rmtree(d, ignore_errors=True)
    return out


def summarise(seeds: list, spacings) -> dict:
    out = {}
    for spacing in map(str, spacings):
        per = [s[spacing] for s in seeds if spacing in s]
        allr = np.array([v for p in per for v in p["ratios"].values()])
        names = sorted({n.split(".", 1)[1] for p in per for n in p["ratios"]})
        by_name = {n: float(np.sqrt(np.mean([v**2 for p in per for k, v in p["ratios"].items()
                                              if k.split(".", 1)[1] == n]))) for n in names}
        out[spacing] = {"seeds": len(per), "ratios": int(allr.size), "rms": float(np.sqrt(np.mean(allr**2))),
                        "max_abs": float(np.max(np.abs(allr))), "rms_per_seed": [p["rms"] for p in per],
                        "rms_per_parameter": by_name}
    return out


def main(argv=None) -> dict:
    ap = add_options(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("run", nargs="?", type=Path, help="a finished simulated run: its ratios alone")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--spacings", type=int, nargs="+", default=[1])
    args = ap.parse_args(argv)
    doc = conditions("parameter_coverage", argv, args.smoke)
    if args.run is not None:
        from fringecal.rundir import RunDir

        doc.update({"run": str(args.run), "per_seed": [{"seed_index": None, "given": _entry(ratios(RunDir(args.run)))}],
                    "complete": True})
        doc["summary"] = summarise(doc["per_seed"], ["given"])
        return finish(doc, args.out)
    doc.update({"width_px": args.width, "spacings": args.spacings, "complete": False, "per_seed": []})
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fringecal-paramcov-") as work:
        for i in range(args.first_seed, args.first_seed + args.seeds):
            doc["per_seed"].append(run_seed(i, args.width, args.spacings, Path(work)))
            doc["summary"] = summarise(doc["per_seed"], args.spacings)
            doc["wall_seconds"] = time.perf_counter() - t0
            print(f"seed {i}: " + ", ".join(f"spacing {s}: RMS {doc['per_seed'][-1][str(s)]['rms']:.2f}"
                                            for s in args.spacings), flush=True)
            if args.out:
                with open(os.devnull, "w") as quiet:
                    finish(dict(doc), args.out, stream=quiet)
    doc["complete"] = True
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
