"""How large must a thin-prism lens term be before the data can tell it from noise?

For each corner displacement of a thin-prism term (OpenCV's s1 and s3, the simulator's
``thin_prism_corner_px``, a random direction per sensor), simulated control points of the
thesis rig are adjusted with the 14-parameter model and with the thin-prism model, and
the script records:

* ``z_max``: the residual-pattern statistic of the 14-parameter fit
  (:mod:`fringecal.calibration.adequacy`, flagged above 5);
* ``term_over_u``: each sensor's true term ``hypot(s1, s3)`` over the larger stated u of
  its fitted s1, s3 (what a Wald test of the term could see at best; below about 3 no
  statistic can flag it without also flagging noise);
* ``error_over_u``: the fitted terms' errors over their stated u (does the richer model
  recover the term within its u?);
* ``wald_W``, ``wald_p``: the Wald test of the fitted s1, s3 against zero
  (:func:`fringecal.calibration.wald.prism_wald`, chi-square, 8 degrees of freedom).

Then (``dense``) the Wald test alone on control points every ``DENSE_SPACING_PX`` px,
``--seeds`` seeds (noise and the terms' directions) without a term and with a 0.2 px one:
how often it flags at each of ``ALPHAS``; the first ``--dispersed-seeds`` of them also
with the jackknife's dispersion factor (``kappa``, ``W_dispersed``). ``--runs
RUN_DIR=CONFIG ...``: the test, with the dispersion factor, on the control points of
rendered runs too (``fringecal run -c CONFIG --out RUN_DIR --until bundle`` first).

``--null RUN_DIR=CONFIG ...`` instead: the test in ``--null-worlds`` worlds without a term
that hold each run's own noise (:func:`null_worlds`), W and W less the terms' noise bias.

``--noise-free RUN_DIR=CONFIG=QUIET_RUN_DIR ...`` instead: the error the renderer holds
beyond its noise, through the test (:func:`noise_free`).

``--sweep NAME:WIDTH:CORNER:SEED ...`` instead: rendered runs of ``configs/run_thesis.yaml``
at WIDTH px and seed SEED with a thin-prism term of CORNER px (``R``: the realistic
profile), made to the bundle step in ``--sweep-dir`` (or reused from there), with the
run's own check of the terms (how often it flags, with and without a term) and the test
with the dispersion factor always.

Prints one JSON object::

    PYTHONPATH=. python benchmarks/prism_detectability.py \\
        --out benchmarks/results/prism_detectability.json

Simulation profile: ideal otherwise (thesis rig, 12 poses, control points every 20 px at
2048 px with the thesis's epsilon-1 noise, ``simulate_control_points``), as in
``tests/test_sensor_models.py``. ``--smoke``: the 3 px term on control points every 60 px,
one seed at that spacing for the dense section, and the dispersion factor on its clean
world.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import add_options, conditions, finish  # noqa: E402

CORNERS_PX = (0.2, 0.5, 1.0, 2.0, 3.0)
#: control-point spacing of the Wald test over seeds (about 78,600 points, half the
#: 1024 px rendered run's)
DENSE_SPACING_PX = 4
#: significance levels at which the dense section counts flags
ALPHAS = (1e-3, 1e-4, 1e-5)


def prism_world(corner_px: float, spacing_px: int, seed: int = 1):
    """The thesis rig's control points with a thin-prism term of ``corner_px`` at every
    sensor's corner, and the true terms (n_sensors, 4) in OpenCV's order (``seed``: the
    control points' noise; the terms' directions from ``seed - 1``)."""
    from fringecal.calibration.model import BundleProblem
    from fringecal.simulate.control_points import simulate_control_points, thesis_truth
    from fringecal.simulate.unmodelled import thin_prism

    rig, art, poses = thesis_truth()
    angles = np.random.default_rng(seed - 1).uniform(0, 2 * np.pi, len(rig.sensors))
    truth = np.zeros((len(rig.sensors), 4))
    truth[:, [0, 2]] = [[*thin_prism(s.format, corner_px, a)] for s, a in zip(rig.sensors, angles)]
    sim = simulate_control_points(rig.with_params(rig.params, prism=truth), art, poses, spacing_px=spacing_px, rng=seed)
    return BundleProblem.from_tables(rig, art, sim.control_points, poses), truth


def measure(corner_px: float, spacing_px: int) -> dict:
    from fringecal.calibration.adequacy import residual_pattern
    from fringecal.calibration.bundle import BundleOptions
    from fringecal.calibration.candidates import fit_model
    from fringecal.calibration.wald import prism_wald

    options = BundleOptions(bootstrap_draws=0, start="given")
    problem, truth = prism_world(corner_px, spacing_px)
    first = fit_model(problem, options, "brown14")
    richer = fit_model(problem.with_start(first.rig, first.poses), options, "thin_prism")
    u = richer.rig.prism_uncertainty[:, [0, 2]]
    wald = prism_wald(first, options)
    return {"corner_px": corner_px, "n_control_points": int(problem.n_points),
            "z_max": float(residual_pattern(first.problem, first.residuals).z_max),
            "wald_W": wald["W"], "wald_dof": wald["dof"], "wald_p": wald["p"],
            "term_over_u": (np.hypot(truth[:, 0], truth[:, 2]) / u.max(axis=1)).tolist(),
            "error_over_u": ((richer.rig.prism[:, [0, 2]] - truth[:, [0, 2]]) / u).ravel().tolist()}


def _wald_record(w: dict) -> dict:
    keys = ("W", "dof", "p", "W_corrected", "bias_over_u", "kappa", "W_dispersed", "p_dispersed", "n_replicas",
            "seconds")
    return {k: w[k] for k in keys if k in w}


def wald_over_seeds(corner_px: float, spacing_px: int, seeds, dispersion: bool = False) -> list[dict]:
    """The Wald test of the thin-prism terms (:func:`fringecal.calibration.wald.prism_wald`)
    on control points of ``seeds`` (their noise and the terms' directions)."""
    from fringecal.calibration.bundle import BundleOptions
    from fringecal.calibration.candidates import fit_model
    from fringecal.calibration.wald import prism_wald

    options = BundleOptions(bootstrap_draws=0, start="given")
    out = []
    for seed in seeds:
        problem, _ = prism_world(corner_px, spacing_px, seed)
        w = prism_wald(fit_model(problem, options, "brown14"), options, dispersion=dispersion)
        out.append({"seed": seed, "n_control_points": int(problem.n_points), **_wald_record(w)})
    return out


def wald_of_run(run_dir: str, config: str) -> dict:
    """The Wald test on a finished run's control points (its bundle step's inputs), as
    the run's bundle options adjust them: ``fringecal run -c CONFIG --out RUN_DIR
    --until bundle`` first."""
    from fringecal.calibration.candidates import fit_model
    from fringecal.calibration.wald import prism_wald
    from fringecal.run.config import load_run_config
    from fringecal.rundir import RunDir
    from fringecal.steps.bundle import load_problem

    cfg = load_run_config(config)
    b = cfg.bundle
    problem = load_problem(RunDir(run_dir), cfg.reference_scanner, b.gamma1, b.gamma2)
    w = prism_wald(fit_model(problem, b, "brown14"), b, dispersion=True)
    errors = cfg.simulate.errors if cfg.simulate is not None else None
    return {"run": run_dir, "config": config, "n_control_points": int(problem.n_points),
            "camera_width_px": cfg.simulate.acquisition.camera_width_px if cfg.simulate is not None else None,
            "profile": errors.profile_name if errors is not None else None,
            "thin_prism_corner_px": errors.thin_prism_corner_px if errors is not None else None,
            **_wald_record(w), "per_sensor": w["per_sensor"]}


def null_worlds(problem, options, worlds: int, label: str) -> dict:
    """The test in ``worlds`` worlds without any thin-prism term but with ``problem``'s
    own noise: its 14-parameter solution plus each control point's residual times a
    random sign (:func:`fringecal.calibration.jackknife.noise_worlds`, signs of seed 7),
    each adjusted with the 14 parameters from that solution and tested, W and W less the
    terms' second-order noise bias (``W_corrected``). Both should be chi-square(8) there."""
    from scipy.stats import chi2

    from fringecal.calibration.candidates import fit_model
    from fringecal.calibration.jackknife import noise_worlds
    from fringecal.calibration.wald import PRISM_ALPHA, prism_wald

    given = options.model_copy(update={"start": "given"})
    first = fit_model(problem, options, "brown14")
    rows = []
    for k, world in enumerate(noise_worlds(first, worlds, seed=7)):
        w = prism_wald(fit_model(world, given, "brown14"), options, corrected=True, workers=2)
        rows.append({"world": k, "W": w["W"], "dof": w["dof"], "W_corrected": w.get("W_corrected"),
                     "bias_over_u": w.get("bias_over_u")})
    W = np.array([r["W"] for r in rows]); Wc = np.array([r["W_corrected"] for r in rows], float)
    crit = float(chi2.isf(PRISM_ALPHA, rows[0]["dof"]))
    return {"problem": label, "n_control_points": int(problem.n_points), "worlds": rows, "mean_W": float(W.mean()),
            "mean_W_corrected": float(np.nanmean(Wc)), "flagged": int((W > crit).sum()),
            "flagged_corrected": int((Wc > crit).sum())}


def _control_point_errors(run: str):
    """A simulated run's control points with each one's phase error against the
    renderer's truth at the pixel centre (``ex``, ``ey``, rad; the decoded phases less
    the pixel-integration correction's bias, as the adjustment takes them)."""
    import pandas as pd
    import zarr

    from fringecal.rundir import RunDir

    rd = RunDir(run)
    cp = rd.control_points.load().reset_index(drop=True)
    ex = np.full(len(cp), np.nan)
    ey = np.full(len(cp), np.nan)
    for (m, sc), rows in cp.groupby(["measurement", "scanner"]).groups.items():
        z = zarr.open_group(str(rd.truth.store(f"{m}-{sc}").path), mode="r")
        u, v = cp.u_px.to_numpy(int)[rows], cp.v_px.to_numpy(int)[rows]
        ex[rows] = cp.tau_x_rad.to_numpy()[rows] - z["truth_tau_x_centre"][:][v, u]
        ey[rows] = cp.tau_y_rad.to_numpy()[rows] - z["truth_tau_y_centre"][:][v, u]
    return cp, pd.DataFrame({"ex": ex, "ey": ey})


def noise_free(run: str, config: str, quiet_run: str) -> dict:
    """Does the renderer hold an error the 14 parameters leave? ``run``'s control points
    with their phases replaced by the renderer's truth plus the error of the same
    control points in ``quiet_run`` (the same configuration rendered without noise:
    ``render: {shot_noise: false, read_noise_e: 0, excess_noise: 0}``), adjusted and
    tested with ``run``'s covariance of the terms: W and the terms over their u of that
    error alone. And the noise (``run``'s error less it): its correlation between
    neighbouring pixels, between measurements at the same pixel and between the phases."""
    import pandas as pd

    from fringecal.calibration.candidates import fit_model
    from fringecal.calibration.model import BundleProblem
    from fringecal.calibration.wald import _thin_prism_fit
    from fringecal.run.config import load_run_config
    from fringecal.rundir import RunDir

    cfg = load_run_config(config)
    b = cfg.bundle
    rd = RunDir(run)
    cp, err = _control_point_errors(run)
    qcp, qerr = _control_point_errors(quiet_run)
    key = ["measurement", "scanner", "u_px", "v_px"]
    quiet = cp[key].merge(pd.concat([qcp[key], qerr], axis=1), on=key, how="left")
    matched = quiet.ex.notna().to_numpy()
    systematic = quiet[["ex", "ey"]].fillna(0.0).to_numpy()
    truth = cp[["tau_x_rad", "tau_y_rad"]].to_numpy() - err.to_numpy()
    rig = rd.sensors_initial.load(cfg.reference_scanner)

    def terms(tau):
        t = cp.copy()
        t["tau_x_rad"], t["tau_y_rad"] = tau[:, 0], tau[:, 1]
        problem = BundleProblem.from_tables(rig, rd.artefact.load(), t, rd.poses_initial.load(), b.gamma1, b.gamma2)
        fit, idx, _ = _thin_prism_fit(fit_model(problem, b, "brown14"), b)
        return fit.x[idx], fit.uncertainty.covariance[np.ix_(idx, idx)]

    a_run, C = terms(truth + err.to_numpy())
    a_sys, _ = terms(truth + systematic)
    noise = (err.to_numpy() - systematic)[matched]
    on = cp[matched].assign(nx=noise[:, 0], ny=noise[:, 1])
    lag = on.assign(u_px=on.u_px + 1).merge(on, on=key, suffixes=("", "_next"))
    same = on.merge(on, on=["scanner", "u_px", "v_px"], suffixes=("", "_other"))
    same = same[same.measurement.astype(str) < same.measurement_other.astype(str)]
    corr = lambda a, b: float(np.corrcoef(a, b)[0, 1])  # noqa: E731
    return {"run": run, "quiet_run": quiet_run, "n_control_points": int(len(cp)), "matched": int(matched.sum()),
            "W_run": float(a_run @ np.linalg.solve(C, a_run)),
            "W_systematic": float(a_sys @ np.linalg.solve(C, a_sys)),
            "systematic_terms_over_u": (a_sys / np.sqrt(np.diag(C))).tolist(),
            "systematic_rms_rad": np.sqrt(np.mean(systematic[matched] ** 2, axis=0)).tolist(),
            "noise_rms_rad": np.sqrt(np.mean(noise ** 2, axis=0)).tolist(),
            "noise_corr_next_pixel": [corr(lag.nx, lag.nx_next), corr(lag.ny, lag.ny_next)],
            "noise_corr_same_pixel_other_measurement": [corr(same.nx, same.nx_other), corr(same.ny, same.ny_other)],
            "noise_corr_x_y": corr(on.nx, on.ny)}


def _smoke_null() -> dict:
    from fringecal.calibration.bundle import BundleOptions

    return null_worlds(prism_world(0.0, 60)[0], BundleOptions(bootstrap_draws=0), 1, "smoke")


def sweep_config(base: dict, width: int, corner: str, seed: int) -> dict:
    """``base`` (configs/run_thesis.yaml) at ``width`` px, seed ``seed`` (acquisition and
    errors), with a thin-prism term of ``corner`` px at the corner (``R``: the realistic
    profile instead), no bootstrap or jackknife, the rig by its absolute path."""
    import copy

    cfg = copy.deepcopy(base)
    sim = cfg["simulate"]
    sim["rig"] = str(ROOT / "configs" / sim["rig"])
    sim["acquisition"].update({"camera_width_px": width, "seed": seed})
    sim["errors"] = ({"profile": "realistic", "seed": seed} if corner == "R"
                     else {"thin_prism_corner_px": float(corner), "seed": seed})
    cfg["bundle"].update({"bootstrap_draws": 0, "jackknife": False})
    return cfg


def sweep_run(spec: str, folder: Path) -> dict:
    """One rendered run of the sweep, ``NAME:WIDTH:CORNER:SEED`` (:func:`sweep_config`),
    made by ``fringecal run -c CONFIG --out RUN --until bundle`` unless ``folder`` holds
    it already: the run's own check of the thin-prism terms (its bundle_summary.json's
    ``prism_wald``: the dispersion factor only where W alone was significant) and the
    test with the factor always (:func:`wald_of_run`)."""
    import json
    import subprocess

    import yaml

    name, width, corner, seed = spec.split(":")
    base = yaml.safe_load((ROOT / "configs" / "run_thesis.yaml").read_text())
    run = folder / f"{name}_{seed}"
    config = folder / f"{name}_{seed}.yaml"
    config.write_text(yaml.safe_dump(sweep_config(base, int(width), corner, int(seed))))
    t0 = time.perf_counter()
    if not (run / "bundle_summary.json").exists():
        subprocess.run([str(Path(sys.executable).parent / "fringecal"), "run", "-c", str(config), "--out", str(run),
                        "--until", "bundle"], cwd=ROOT, check=True, capture_output=True, text=True)
    made = time.perf_counter() - t0
    check = json.loads((run / "bundle_summary.json").read_text())["sensor_model"]["prism_wald"]
    return {"name": name, "seed": int(seed), "run_seconds": made,
            "check": {k: check.get(k) for k in ("W", "p", "kappa", "p_dispersed", "verdict", "seconds")},
            **wald_of_run(str(run), str(config))}


def _sweep_summary(rows: list[dict]) -> dict:
    out = {}
    for name in dict.fromkeys(r["name"] for r in rows):
        mine = [r for r in rows if r["name"] == name]
        kappa = [r["kappa"] for r in mine if r.get("kappa") is not None]
        out[name] = {"runs": len(mine), "flagged": sum(r["check"]["verdict"] == "present" for r in mine),
                     "W": [min(r["W"] for r in mine), max(r["W"] for r in mine)],
                     "p_dispersed": [min(r["p_dispersed"] for r in mine if "p_dispersed" in r),
                                     max(r["p_dispersed"] for r in mine if "p_dispersed" in r)] if kappa else None,
                     "kappa": [min(kappa), max(kappa)] if kappa else None}
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="seeds of the dense Wald section")
    ap.add_argument("--dispersed-seeds", type=int, default=5,
                    help="of them, the first seeds with the jackknife's dispersion factor too")
    ap.add_argument("--runs", nargs="*", default=[], metavar="RUN_DIR=CONFIG",
                    help="finished runs (to the bundle step) whose control points get the Wald test too")
    ap.add_argument("--sweep", nargs="*", default=[], metavar="NAME:WIDTH:CORNER:SEED",
                    help="rendered runs to make (or reuse) in --sweep-dir and test: thin-prism CORNER px (R: the "
                         "realistic profile) at WIDTH px, seed SEED; only these when given")
    ap.add_argument("--sweep-dir", type=Path, default=Path("prism-sweep"), help="where the sweep's runs live")
    ap.add_argument("--null", nargs="*", default=[], metavar="RUN_DIR=CONFIG",
                    help="finished runs (to the bundle step) whose noise fills --null-worlds worlds without a "
                         "thin-prism term (null_worlds); only these when given")
    ap.add_argument("--null-worlds", type=int, default=10, help="worlds per run of --null")
    ap.add_argument("--noise-free", nargs="*", default=[], metavar="RUN_DIR=CONFIG=QUIET_RUN_DIR",
                    help="simulated runs and the same runs rendered without noise: the error the renderer "
                         "holds beyond the noise, through the test (noise_free); only these when given")
    args = add_options(ap).parse_args(argv)
    doc = conditions("prism_detectability", argv, args.smoke)
    t0 = time.perf_counter()
    if args.sweep:
        from fringecal.calibration.wald import PRISM_ALPHA

        args.sweep_dir.mkdir(parents=True, exist_ok=True)
        rows = [sweep_run(spec, args.sweep_dir) for spec in args.sweep]
        doc.update({"what": "the run's check of the thin-prism terms (the Wald test, the dispersion factor where W "
                            "alone is significant) over rendered runs of the thesis rig (configs/run_thesis.yaml "
                            "at the size and seed named, ideal profile with the term named or the realistic "
                            "profile, to the bundle step), and the test with the factor always",
                    "alpha": PRISM_ALPHA, "sweep": rows, "by_variant": _sweep_summary(rows),
                    "wall_seconds": time.perf_counter() - t0})
        return finish(doc, args.out)
    if args.noise_free:
        doc.update({"what": "the phase error of rendered runs' control points against the renderer's truth: what "
                            "of it the same runs rendered without noise hold, through the Wald test with the "
                            "run's covariance, and how independent the rest (the noise) is",
                    "noise_free": [noise_free(*spec.split("=", 2)) for spec in args.noise_free],
                    "wall_seconds": time.perf_counter() - t0})
        return finish(doc, args.out)
    if args.null:
        from fringecal.run.config import load_run_config
        from fringecal.rundir import RunDir
        from fringecal.steps.bundle import load_problem

        rows = []
        for spec in args.null:
            run, config = spec.split("=", 1)
            cfg = load_run_config(config)
            problem = load_problem(RunDir(run), cfg.reference_scanner, cfg.bundle.gamma1, cfg.bundle.gamma2)
            rows.append({"run": run, "config": config, **null_worlds(problem, cfg.bundle, args.null_worlds, run)})
        doc.update({"what": "the Wald test of the thin-prism terms, W and W less the terms' second-order noise "
                            "bias, in worlds without a term that hold each run's own noise (its 14-parameter "
                            "solution plus its residuals with random signs): chi-square(8) expected",
                    "null": rows, "wall_seconds": time.perf_counter() - t0})
        return finish(doc, args.out)
    corners, spacing = ((3.0,), 60) if args.smoke else (CORNERS_PX, 20)
    rows = [measure(c, spacing) for c in corners]
    dense_spacing, seeds = (60, range(1, 2)) if args.smoke else (DENSE_SPACING_PX, range(1, args.seeds + 1))
    dense = {str(c): wald_over_seeds(c, dense_spacing, seeds) for c in (0.0, 0.2)}
    few = range(1, args.dispersed_seeds + 1)
    # the smoke: the factor on the clean world only
    dispersed = {str(c): wald_over_seeds(c, dense_spacing, range(1, 2) if args.smoke else few, dispersion=True)
                 for c in ((0.0,) if args.smoke else (0.0, 0.2))}
    flagged = {c: {str(a): int(sum(r["p"] < a for r in rows_)) for a in ALPHAS} for c, rows_ in dense.items()}
    doc.update({"what": "thin-prism terms of growing size on the thesis rig's simulated control points (ideal "
                        "profile otherwise): the 14-parameter fit's residual-pattern Z (flag above 5), the Wald "
                        "test of the thin-prism terms against zero, each sensor's true term over its stated u, "
                        "and the thin-prism fit's errors over their u; then the Wald test on denser control "
                        "points over seeds, without a term and with a 0.2 px one",
                "spacing_px": spacing, "sizes": rows,
                "dense": {"spacing_px": dense_spacing, "seeds": len(seeds), "wald": dense,
                          "flagged_at_alpha": flagged, "with_dispersion": dispersed},
                "rendered_runs": [wald_of_run(*r.split("=", 1)) for r in args.runs],
                # the smoke runs the null worlds' code on its clean world
                "null": [_smoke_null()] if args.smoke else [],
                "wall_seconds": time.perf_counter() - t0})
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
