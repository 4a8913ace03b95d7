"""The probing error size P_S at the far acceptance positions: the guideline's orthogonal
sphere fit against the fit along the camera's lines of sight (docs/acceptance.md).

    PYTHONPATH=. python benchmarks/probing_size_bias.py [--draws 40] [--out FILE.json]

``--smoke``: 192 px, the farthest position only, two draws.

The default demo (``configs/run_thesis.yaml``, ideal profile, 512 px) as it planned its
sphere positions before it stated a measuring volume: every scanner's whole calibrated
volume, 2.4-3.65 m deep. Each sphere position deeper than ``--far-mm`` (3.3 m: the
five far ones per scanner) is rendered as the demo renders it (same sensors, noise
model and seed) and measured with the **true** scanner, so that the calibration's
own error is not in the figures; P_S comes from

* the orthogonal (Gaussian) least-squares sphere with free radius, as VDI/VDE 2634
  part 2 writes it (the demo's fit before), and
* the fit along the camera rays (:func:`fringecal.acceptance.measure.sphere_along_rays`,
  the demo's fit now),

on the same points. To tell a bias from a scatter, the farthest position is rendered
``--draws`` more times with other noise seeds; the mean of each fit's P_S over them
and its standard error are reported, beside the noise-free rendering (the bias of the
rendering itself: pixel integration), the mean signed distance of the measured points
from the true sphere, the mean stated u of each fit against the draws' scatter, and how
the noise moves the points: its RMS along and across the camera rays (one draw against
the noise-free rendering, pixel by pixel).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import add_options, conditions, finish  # noqa: E402

from fringecal.acceptance import measure as M  # noqa: E402
from fringecal.acceptance.standards import load_standards  # noqa: E402
from fringecal.frames import frames_from_rows  # noqa: E402
from fringecal.rig import scaled_scanner  # noqa: E402
from fringecal.run.config import load_run_config  # noqa: E402
from fringecal.rundir import measurement_id  # noqa: E402
from fringecal.simulate.config import AcquisitionConfig  # noqa: E402
from fringecal.simulate.measurement import simulate_measurement  # noqa: E402
from fringecal.simulate.scenes import ArtefactHardware, acceptance_scene  # noqa: E402
from fringecal.simulate.source import acceptance_camera_width, load_simulated_rig  # noqa: E402


def measure(store, scanner, standard, centre_true) -> dict:
    """P_S of both fits (mm), their stated u, and the mean distance from the true sphere
    of the points within 2 mm of the fitted one (are the points biased, or the fit?)."""
    m = M.measure_sphere_store(store, scanner, standard)
    _, _, _, xyz, inner = M._points(store, scanner)
    p = xyz[inner]
    p = p[np.abs(np.linalg.norm(p - m.centre, axis=1) - m.diameter_mm / 2) <= M.SEGMENT_MM]
    return {"P_S_orthogonal_mm": m.diameter_orthogonal_mm - standard.diameter_mm,
            "P_S_along_rays_mm": m.size_mm,
            "u_diameter_orthogonal_mm": m.diameter_u_orthogonal_mm,
            "u_diameter_along_rays_mm": m.diameter_u_fit_mm,
            "mean_distance_from_true_sphere_mm": float(np.mean(np.linalg.norm(p - centre_true, axis=1))
                                                       - standard.diameter_mm / 2),
            "rms_orthogonal_mm": m.rms_mm, "n_points": m.n_points}


def noise_directions(free_store, noisy_store, scanner) -> tuple[float, float]:
    """RMS (mm) of the noise of the points along and across their camera rays: the same
    pixels of a noisy and the noise-free rendering."""
    _, _, ok0, x0, _ = M._points(free_store, scanner)
    _, _, ok1, x1, _ = M._points(noisy_store, scanner)
    both = ok0 & ok1
    d = (x1 - x0)[both]
    ray = x0[both] - scanner.camera.pinhole
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    keep = np.linalg.norm(d, axis=1) < 5.0  # a pixel decoded to another fringe is no noise
    d, ray = d[keep], ray[keep]
    a = np.sum(d * ray, axis=1)
    return float(np.sqrt(np.mean(a ** 2))), float(np.sqrt(np.mean(np.sum((d - a[:, None] * ray) ** 2, axis=1))))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=40)
    ap.add_argument("--far-mm", type=float, default=3300.0)
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        args.draws = 2
    head = conditions("probing_size_bias", argv, args.smoke)
    t0 = time.perf_counter()
    cfg = load_run_config()
    sim = cfg.simulate
    sr = load_simulated_rig(sim, None)  # the whole calibrated volume, as the demo planned before
    standards = load_standards(sim.acceptance.standards_path())
    hardware = ArtefactHardware.from_materials(sim.rig_config().materials)
    acq = sim.acquisition
    width = 192 if args.smoke else acceptance_camera_width(sim)
    plan = sr.acceptance[sr.acceptance["test"] == "sphere"]
    frames = frames_from_rows(plan)
    if args.smoke:  # the farthest position only
        depths = [float(sr.truth.scanner(r.scanner).camera.to_sensor(frames[r.measurement].t[None])[0, 2])
                  for r in plan.itertuples(index=False)]
        plan = plan.iloc[[int(np.argmax(depths))]]
    positions, farthest = [], None
    with tempfile.TemporaryDirectory() as tmp:
        def render(name, scanner, seed, render_cfg):
            store = Path(tmp) / f"{name}-{seed}.zarr"
            a = AcquisitionConfig(render=render_cfg, sequence=acq.sequence, seed=seed, backdrop_mm=acq.backdrop_mm)
            scene = acceptance_scene("sphere", standards, frames[name], hardware)
            # the store id names the noise stream, as in a run (measurements/<position>-<scanner>)
            simulate_measurement(measurement_id(name, scanner.name), scanner, scene, a, cfg.decode, store)
            return store

        for r in plan.itertuples(index=False):
            scanner = sr.truth.scanner(r.scanner)
            scanner = scaled_scanner(scanner, width) if width is not None else scanner
            centre = frames[r.measurement].t
            depth = float(scanner.camera.to_sensor(centre[None])[0, 2])
            if depth < args.far_mm:
                continue
            store = render(r.measurement, scanner, sim.acceptance.seed, acq.render)
            positions.append({"position": r.measurement, "scanner": r.scanner, "depth_mm": depth,
                              **measure(store, scanner, standards.sphere, centre)})
            if farthest is None or depth > farthest[0]:
                farthest = (depth, r.measurement, scanner, centre)
        depth, name, scanner, centre = farthest
        stores = [render(name, scanner, 5000 + k, acq.render) for k in range(args.draws)]
        draws = [measure(st, scanner, standards.sphere, centre) for st in stores]
        free_store = render(name, scanner, 0, acq.render.noise_free())
        free = measure(free_store, scanner, standards.sphere, centre)
        along, across = noise_directions(free_store, stores[0], scanner)

    def stats(rows, key):
        v = np.array([r[key] for r in rows])
        return {"mean_mm": float(v.mean()), "sd_mm": float(v.std(ddof=1)), "sem_mm": float(v.std(ddof=1) / np.sqrt(len(v)))}

    doc = {
        **head,
        "config": "configs/run_thesis.yaml (ideal profile), sphere positions over the whole calibrated volume",
        "camera_width_px": width or acq.camera_width_px,
        "far_mm": args.far_mm,
        "far_positions": len(positions),
        "far_mean_P_S_orthogonal_mm": float(np.mean([p["P_S_orthogonal_mm"] for p in positions])),
        "far_mean_P_S_along_rays_mm": float(np.mean([p["P_S_along_rays_mm"] for p in positions])),
        "repeated_position": name, "repeated_depth_mm": depth, "draws": args.draws,
        "repeated_P_S_orthogonal": stats(draws, "P_S_orthogonal_mm"),
        "repeated_P_S_along_rays": stats(draws, "P_S_along_rays_mm"),
        "repeated_mean_u_orthogonal_mm": float(np.mean([d["u_diameter_orthogonal_mm"] for d in draws])),
        "repeated_mean_u_along_rays_mm": float(np.mean([d["u_diameter_along_rays_mm"] for d in draws])),
        "repeated_points_mean_distance_from_true_sphere_mm": float(np.mean(
            [d["mean_distance_from_true_sphere_mm"] for d in draws])),
        "noise_rms_along_rays_mm": along, "noise_rms_across_rays_mm": across,
        "noise_free_P_S_orthogonal_mm": free["P_S_orthogonal_mm"],
        "noise_free_P_S_along_rays_mm": free["P_S_along_rays_mm"],
        "positions": positions,
        "wall_seconds": time.perf_counter() - t0,
    }
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
