"""Measure what the virtual scanner's noise does after decoding: tau against truth,
epsilon-1 with the true sensor parameters, unwrapping errors. Not a speed benchmark:
the numbers behind RenderConfig's default ``excess_noise`` (docs/acquisition.md).

For each camera width and measurement (table 6-1 pose, scanner), the same scene is
rendered with the configuration under test and noise-free, both are decoded, and on
valid pixels wholly on a lit sphere (``fringecal.simulate.evaluation.pure_mask``):

* ``tau_*_vs_truth``: RMS of decoded tau - true tau (noise and pixel-integration bias);
* ``tau_*_noise`` and ``tau_*_theory``: RMS of tau - tau(noise-free) against
  ``config.phase_noise`` per pixel (true level, decoded modulation);
* ``eps1_total_um``: epsilon-1 RMS (``pointcloud.triangulate_maps``, true sensors);
  ``eps1_noise_um`` of eps1 - eps1(noise-free), ``eps1_bias_um`` of the noise-free render.

``--unwrap N`` also counts unwrapping errors (|tau - truth| > pi / max count) over every
valid pure pixel (spheres, end caps, rods and a backdrop 3.5 m away) of all 24
measurements at width N.

    PYTHONPATH=. python benchmarks/noise_calibration.py [--widths 512,2048] [--measurements 1-scanner1]
        [--excess 0.0062] [--unwrap 512] [--all-poses 384] [--out FILE]

``--smoke``: one measurement at 64 px; the unwrapping count over two poses at 48 px.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402

from fringecal.artefact import load_artefact, load_rods  # noqa: E402
from fringecal.config import thesis_dir  # noqa: E402
from fringecal.frames import Frame  # noqa: E402
from fringecal.fringe.decode import decode  # noqa: E402
from fringecal.fringe.sequence import FringeSequence  # noqa: E402
from fringecal.pointcloud import triangulate_maps  # noqa: E402
from fringecal.rig import load_rig  # noqa: E402
from fringecal.simulate import RenderConfig, artefact_scene, backdrop, phase_noise, render_measurement, scaled_scanner  # noqa: E402
from fringecal.simulate.evaluation import pure_mask, tau_error_summary, tau_residuals  # noqa: E402

SEQ = FringeSequence()
COLS = ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]


def setup():
    d = thesis_dir()
    rig = load_rig(d / "sensors_refined_table6-8.csv")
    art = load_artefact(d / "artefact_cmm2.csv")
    poses = pd.read_csv(d / "poses_scanner1_table6-1.csv", dtype={"measurement": str})
    return rig, art, load_rods(d / "rods.csv", art), {r.measurement: Frame.from_params([getattr(r, c) for c in COLS])
                                                       for r in poses.itertuples()}


def render_decode(scanner, scene, cfg, seed):
    m = render_measurement(scanner, scene, cfg, np.random.default_rng(seed), SEQ)
    return m.truth, decode(m.frames, SEQ, None, cfg.max_dn)


def rms(a) -> float:
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def measure(rig, art, rods, T, scanner_name, width, cfg, seed=1) -> dict:
    s = scaled_scanner(rig.scanner(scanner_name), width)
    scene = artefact_scene(art, rods, T)
    t0 = time.perf_counter()
    truth, noisy = render_decode(s, scene, cfg, seed)
    _, clean = render_decode(s, scene, cfg.noise_free(), seed)
    mask = pure_mask(truth, ("sphere",), noisy.valid & clean.valid)
    eps = [triangulate_maps(s.camera, s.projector, r.tau["x"], r.tau["y"], r.valid).eps1[mask] for r in (noisy, clean)]
    out = {"width": width, "scanner": scanner_name, "n_pixels": int(mask.sum()),
           "eps1_total_um": 1e3 * rms(eps[0]), "eps1_noise_um": 1e3 * rms(eps[0] - eps[1]),
           "eps1_bias_um": 1e3 * rms(eps[1])}
    level = (truth.ambient_level + cfg.offset * truth.irradiance)[mask]
    for o in SEQ.orientations:
        modulation = noisy.modulation[o][mask] / cfg.max_dn
        theory = np.array([phase_noise(cfg, a, b, SEQ)["sigma_tau"] for a, b in zip(level, modulation)])
        out[f"tau_{o}_vs_truth_rad"] = rms(tau_residuals(noisy.tau[o][mask], getattr(truth, f"tau_{o}")[mask]))
        out[f"tau_{o}_noise_rad"] = rms(tau_residuals(noisy.tau[o][mask], clean.tau[o][mask]))
        out[f"tau_{o}_theory_rad"] = rms(theory)
        out[f"tau_{o}_bias_noise_free_projector_px"] = tau_error_summary(
            clean.tau, truth, mask, SEQ, s.projector)[o]["rms_projector_px"]
    out["seconds"] = time.perf_counter() - t0
    return out


def unwrap_count(rig, art, rods, poses, width, cfg) -> dict:
    n = 0
    errors = {"x": 0, "y": 0}
    per_kind: dict[str, int] = {}
    for scanner in rig.scanners:
        s = scaled_scanner(scanner, width)
        for i, (pose, T) in enumerate(poses.items()):
            truth, res = render_decode(s, artefact_scene(art, rods, T, background=backdrop(s, 3500.0)), cfg, 100 + i)
            mask = pure_mask(truth, None, res.valid)
            summary = tau_error_summary(res.tau, truth, mask, SEQ, s.projector)
            n += summary["n_pixels"]
            kinds = np.asarray(truth.object_kinds + ("",))[truth.object_index][mask]
            for k in np.unique(kinds):
                per_kind[str(k)] = per_kind.get(str(k), 0) + int(np.sum(kinds == k))
            for o in SEQ.orientations:
                errors[o] += summary[o]["unwrap_errors"]
    return {"width": width, "measurements": len(rig.scanners) * len(poses), "valid_pure_pixels": n,
            "pixels_per_kind": per_kind, "unwrap_errors": errors,
            "rate_upper_95": (3.0 if sum(errors.values()) == 0 else float("nan")) / n}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--widths", default="512,2048")
    ap.add_argument("--measurements", default="1-scanner1", help="comma-separated <pose>-<scanner>")
    ap.add_argument("--excess", type=float, default=None, help="excess_noise (default: RenderConfig's)")
    ap.add_argument("--unwrap", type=int, default=0, help="count unwrapping errors at this width (0: skip)")
    ap.add_argument("--all-poses", type=int, default=0,
                    help="pooled epsilon-1 over all 24 measurements at this width (0: skip)")
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        args.widths, args.unwrap, args.all_poses = "64", 48, 0
    cfg = RenderConfig() if args.excess is None else RenderConfig(excess_noise=args.excess)
    rig, art, rods, poses = setup()
    if args.smoke:
        poses = dict(list(poses.items())[:2])
    report = {**conditions("noise_calibration", argv, args.smoke), "excess_noise": cfg.excess_noise,
              "measurements": []}
    for width in map(int, args.widths.split(",")):
        for mid in args.measurements.split(","):
            pose, scanner = mid.split("-", 1)
            row = measure(rig, art, rods, poses[pose], scanner, width, cfg)
            report["measurements"].append({"measurement": mid, **row})
            print(json.dumps(report["measurements"][-1]), file=sys.stderr, flush=True)
    if args.all_poses:
        rows = [measure(rig, art, rods, T, s.name, args.all_poses, cfg, seed=7)
                for s in rig.scanners for T in poses.values()]
        w = np.array([r["n_pixels"] for r in rows], float)
        report["all_poses"] = {"width": args.all_poses, "measurements": len(rows), "n_pixels": int(w.sum()), **{
            k: float(np.sqrt(np.sum(w * np.array([r[k] for r in rows]) ** 2) / w.sum()))
            for k in ("eps1_total_um", "eps1_noise_um", "eps1_bias_um")},
            "eps1_noise_um_per_measurement": [round(r["eps1_noise_um"], 1) for r in rows]}
        print(json.dumps(report["all_poses"]), file=sys.stderr, flush=True)
    if args.unwrap:
        report["unwrap"] = unwrap_count(rig, art, rods, poses, args.unwrap, cfg)
        print(json.dumps(report["unwrap"]), file=sys.stderr, flush=True)
    return finish(report, args.out)


if __name__ == "__main__":
    main()
