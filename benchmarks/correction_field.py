"""What the correction-field model (``bundle.sensor_model: field``) gains, and costs, as a
lens error beyond the 14 parameters grows.

For each size of a smooth lens error (the simulator's ``lens_field_rms_um``: a degree-6
correction field of that RMS over every true camera's and projector's format, 45 terms
of equal variance, of which the model's degree-4 basis holds 19), simulated control
points of the thesis rig are adjusted with the 14 parameters and with the field, and
the script records:

* ``z_max``: the residual-pattern statistic after each fit (flagged above 5);
* ``held_out``: the cross-validated choice between the two (gain, t, the model chosen);
* ``point_error_um``: points of the measurement volume (random, within 60 mm of a
  sphere centre of the 12 poses, seen by both sensors of a scanner), projected through
  the true sensors without noise and triangulated with each calibration (and with the
  true 14 parameters, the field ignored); the errors of the distances between 20,000
  random pairs of them (across both scanners, up to 2.7 m apart): what lengths compared
  with a CMM show, RMS, median and largest;
* ``seconds``: one adjustment of each model from the 14-parameter solution (median over
  ``--repeat``; numba compiled before).

Prints one JSON object::

    PYTHONPATH=. python benchmarks/correction_field.py --out benchmarks/results/correction_field.json

Simulation profile: ideal but for the lens error (thesis rig, 12 poses, control points
every 20 px at 2048 px with the thesis's noise, ``simulate_control_points``).
``--smoke``: the 3 um size on control points every 80 px, one repeat, kernels not warmed.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _common import add_options, conditions, finish  # noqa: E402

SIZES_UM = (0.0, 0.5, 1.0, 2.0, 3.0, 5.0)


def lens_world(rms_um: float, spacing_px: int, seed: int = 5):
    """The thesis rig's control points with every true sensor given a degree-6 field of
    ``rms_um``; the problem (start: the 14-parameter truth) and the true rig."""
    from fringecal.calibration.model import BundleProblem
    from fringecal.lens.field import CorrectionField, field_terms
    from fringecal.rig import Scanner
    from fringecal.simulate.control_points import simulate_control_points, thesis_truth

    rig, art, poses = thesis_truth()
    rng = np.random.default_rng(seed)
    sensors = []
    for s in rig.sensors:
        a = rng.normal(size=field_terms(6))
        a *= rms_um * 1e-3 / np.linalg.norm(a)  # orthonormal basis: RMS over the format = |a|
        sensors.append(s.with_field(CorrectionField.zero(s.format.width_mm, s.format.height_mm, 6)
                                    .with_coefficients(a)))
    truth = replace(rig, scanners=tuple(Scanner(sc.name, sensors[2 * i], sensors[2 * i + 1])
                                        for i, sc in enumerate(rig.scanners)))
    sim = simulate_control_points(truth, art, poses, spacing_px=spacing_px, rng=1)
    return BundleProblem.from_tables(rig, art, sim.control_points, poses), truth


def volume_points(problem, truth, n: int = 4000, seed: int = 7) -> list:
    """Per scanner: random points near the artefact's sphere centres of every pose that
    both of its true sensors image inside their formats, and their noise-free images."""
    from fringecal.frames import Frame

    rng = np.random.default_rng(seed)
    centres = np.concatenate([Frame.from_params(p).to_world(problem.artefact.centres) for p in problem.poses])
    X = centres[rng.integers(len(centres), size=n)] + rng.uniform(-60, 60, (n, 3))
    out = []
    for sc in truth.scanners:
        seen = sc.camera.in_view(X, 0.2) & sc.projector.in_view(X, 0.2)
        out.append((X[seen], sc.camera.project(X[seen]), sc.projector.project(X[seen])))
    return out


def point_error_um(rig, points, pairs: int = 20000, seed: int = 11) -> dict:
    """Errors of distances between random pairs of the volume points (across both
    scanners) triangulated with ``rig``: what a length compared with a CMM shows, free of
    the frame (a calibration's frame may differ from the truth's by a rigid motion)."""
    from fringecal.pointcloud import triangulate_image_points

    X = np.concatenate([p[0] for p in points])
    Y = np.concatenate([triangulate_image_points(sc.camera, sc.projector, cam, prj)
                        for sc, (_, cam, prj) in zip(rig.scanners, points)])
    rng = np.random.default_rng(seed)
    i, j = rng.integers(len(X), size=(2, pairs))
    e = np.abs(np.linalg.norm(Y[i] - Y[j], axis=1) - np.linalg.norm(X[i] - X[j], axis=1))
    return {"rms": float(1e3 * np.sqrt(np.nanmean(e ** 2))), "median": float(1e3 * np.nanmedian(e)),
            "max": float(1e3 * np.nanmax(e))}


def _without_fields(rig):
    from fringecal.rig import Scanner

    return replace(rig, scanners=tuple(Scanner(sc.name, sc.camera.with_field(None), sc.projector.with_field(None))
                                       for sc in rig.scanners))


def measure(rms_um: float, spacing_px: int, repeat: int) -> dict:
    from fringecal.calibration.adequacy import residual_pattern
    from fringecal.calibration.bundle import BundleOptions
    from fringecal.calibration.candidates import fit_model
    from fringecal.calibration.models import choose_sensor_model

    options = BundleOptions(bootstrap_draws=0, start="given")
    problem, truth = lens_world(rms_um, spacing_px)
    points = volume_points(problem, truth)
    first = fit_model(problem, options, "brown14")
    start = problem.with_start(first.rig, first.poses)
    seconds = {"brown14": [], "field": []}
    for _ in range(repeat):
        for model in list(seconds):
            t = time.perf_counter()
            fit = fit_model(start, options, model)
            seconds[model].append(time.perf_counter() - t)
            if model == "field":
                richer = fit
    _, record = choose_sensor_model(problem, BundleOptions(bootstrap_draws=0, model_selection="always"),
                                    candidates=("brown14", "field"), first=first)
    (cmp,) = record["comparisons"]
    return {"lens_field_rms_um": rms_um, "n_control_points": int(problem.n_points),
            "z_max": {"brown14": float(residual_pattern(first.problem, first.residuals).z_max),
                      "field": float(residual_pattern(richer.problem, richer.residuals, "field").z_max)},
            "rms_f_mm": {"brown14": first.after.rms_f_mm, "field": richer.after.rms_f_mm},
            "held_out": {"chosen": record["model"], "gain": cmp["gain"], "t": cmp["t"],
                         "u_inflation_median": cmp["u_inflation_median"]},
            "point_error_um": {"true_14_parameters_without_field": point_error_um(_without_fields(truth), points),
                                   "brown14": point_error_um(first.rig, points),
                                   "field": point_error_um(richer.rig, points)},
            "n_volume_points": int(sum(len(p[0]) for p in points)),
            "seconds": {m: float(np.median(v)) for m, v in seconds.items()}}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="adjustments timed per model and size")
    args = add_options(ap).parse_args(argv)
    doc = conditions("correction_field", argv, args.smoke)
    t0 = time.perf_counter()
    sizes, spacing, repeat = ((3.0,), 80, 1) if args.smoke else (SIZES_UM, 20, args.repeat)
    if not args.smoke:
        from fringecal.calibration.bundle import BundleOptions
        from fringecal.calibration.candidates import fit_model

        warm, _ = lens_world(1.0, 80)  # compile both kernels' variants before timing
        fit_model(warm, BundleOptions(bootstrap_draws=0, start="given"), "field")
    rows = [measure(s, spacing, repeat) for s in sizes]
    doc.update({"what": "a smooth degree-6 lens error of growing RMS on every sensor of the thesis rig's simulated "
                        "control points (ideal profile otherwise): residual-pattern Z, the held-out choice between "
                        "brown14 and field, the 3-D error of noise-free volume points triangulated with each "
                        "calibration, and one adjustment's time",
                "spacing_px": spacing, "sizes": rows, "wall_seconds": time.perf_counter() - t0})
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
