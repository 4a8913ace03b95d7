"""Benchmarks of issue 4's hot paths; prints one JSON object.

    PYTHONPATH=. python benchmarks/pointcloud.py [--quick] [--out FILE]

``--smoke``: a 128 px camera, 2,000 sphere points, one repeat of each.

* triangulation of a full 2048 x 2048 thesis measurement (every pixel valid), float32
  and float64 outputs, against a memory-bandwidth reference (numpy streaming the same
  bytes) and the numpy reference implementation (fringecal.triangulation) in the same run;
* sphere fit of 10,000 points (70-degree cap), free and fixed radius, against scipy's
  least_squares on the same points; the robust fit of a node with rods;
* labelling of a thesis-size problem (12 measurements x 2 scanners, 6 candidates and a
  false one each) and the thesis's own centres resolved with the pose plan.

Medians of repeated runs; wall and process CPU time; the machine's load average is
reported because the numbers are only comparable at similar load.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numba
import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402

from fringecal.artefact import load_artefact  # noqa: E402
from fringecal.frames import Frame  # noqa: E402
from fringecal.pointcloud import camera_ray_cache, triangulate_maps  # noqa: E402
from fringecal.rig import load_rig  # noqa: E402
from fringecal.schemas import PosePlanTable, SphereCentresTable, read_table  # noqa: E402
from fringecal.spheres.fit import SphereModel  # noqa: E402
from fringecal.spheres.label_scanners import label_sphere_fits  # noqa: E402
from fringecal.spheres.labelling import LabellingConfig  # noqa: E402
from fringecal.spheres.reference_data import sphere_reference_data  # noqa: E402
from fringecal.spheres.robust import fit_sphere_robust  # noqa: E402
from fringecal.spheres.synthetic import sphere_node_cloud  # noqa: E402
from fringecal.triangulation import triangulate  # noqa: E402

THESIS = ROOT / "configs" / "thesis"


def timed(fn, repeats: int) -> dict:
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return {"median_s": float(np.median(wall)), "min_s": float(np.min(wall)), "cpu_median_s": float(np.median(cpu)),
            "repeats": repeats}


def bench_triangulation(quick: bool, width: int | None = None) -> dict:
    s = load_rig(THESIS / "sensors_refined_table6-8.csv").scanners[0]
    if width is not None:
        from fringecal.simulate import scaled_scanner

        s = scaled_scanner(s, width)
    cam, prj = s.camera, s.projector
    t0 = time.perf_counter()
    cache = camera_ray_cache(cam)
    cache_s = time.perf_counter() - t0
    h, w = cam.format.shape
    # a plane 2.5 m away seen by every pixel: realistic, smooth phase maps
    ideal = np.moveaxis(cache.ideal, 0, -1)
    d = np.concatenate([-ideal, np.full((h, w, 1), cam.c)], axis=-1) @ cam.R
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    depth = (-50.0 - cam.pinhole[2]) / d[..., 2]
    X = cam.pinhole + depth[..., None] * d
    tau = prj.measured(prj.project(X))
    tx = np.clip(tau[..., 0], -np.pi, np.pi).astype(np.float32)
    ty = np.clip(tau[..., 1], -np.pi, np.pi).astype(np.float32)
    valid = np.ones((h, w), bool)
    n = h * w
    t0 = time.perf_counter()
    triangulate_maps(cam, prj, tx, ty, valid, cache=cache)  # compiles or loads the kernel
    first_s = time.perf_counter() - t0
    reps = 1 if width is not None else 5 if quick else 15
    out = {"pixels": n, "camera_cache_build_s": cache_s, "first_call_s": first_s,
           "numba_threads": numba.get_num_threads()}
    for dtype in (np.float32, np.float64):
        r = timed(lambda: triangulate_maps(cam, prj, tx, ty, valid, cache=cache, dtype=dtype), reps)
        r["points_per_s"] = n / r["median_s"]
        out[np.dtype(dtype).name] = r
    # memory reference: stream the kernel's bytes (read tau x2, ideal x2, mask; write 4 float32 + status)
    a = np.ones(n * 7, np.float32)  # 28 bytes/pixel read
    b = np.empty(n * 4, np.float32)  # 16 bytes/pixel written
    ref = timed(lambda: np.add(a[: n * 4], a[n * 3:], out=b), reps)
    out["memory_reference_median_s"] = ref["median_s"]
    out["ratio_float32_to_memory_reference"] = out["float32"]["median_s"] / ref["median_s"]
    # numpy reference implementation on a quarter of the rows, scaled
    rows = slice(0, h // 8)
    vv, uu = np.mgrid[rows, 0:w]
    uv = np.stack([uu.ravel(), vv.ravel()], axis=-1).astype(float)
    tau_sub = np.stack([tx[rows].ravel(), ty[rows].ravel()], axis=-1).astype(float)
    r = timed(lambda: triangulate(cam, prj, uv, tau_sub), 1 if quick else 3)
    out["numpy_reference_full_image_s"] = r["median_s"] * 8
    out["speedup_vs_numpy_reference"] = out["numpy_reference_full_image_s"] / out["float32"]["median_s"]
    out["aim"] = "4e6 points in < 0.1 s on 2 cores"
    return out


def bench_sphere_fit(quick: bool, smoke: bool = False) -> dict:
    from scipy.optimize import least_squares

    ds = sphere_reference_data([300.0, -200.0, 2400.0], 25.0, 2_000 if smoke else 10_000, 70.0, (0.1, -0.2, 1.0),
                               0.0, seed=1)
    pts = ds.points + np.random.default_rng(0).normal(0, 0.02, ds.points.shape)
    reps = 1 if smoke else 50 if quick else 300
    free = timed(lambda: SphereModel.from_estimate(pts), reps)
    fixed = timed(lambda: SphereModel.from_estimate(pts, radius=25.0), reps)

    def scipy_fit():
        least_squares(lambda x: np.linalg.norm(pts - x[:3], axis=1) - x[3], np.r_[ds.centre + 0.5, 24.5],
                      method="lm", xtol=1e-12, ftol=1e-12)

    sp = timed(scipy_fit, 1 if smoke else 5 if quick else 20)
    cloud = sphere_node_cloud([0.0, 0.0, 0.0], 25.0, [[1, 0, 0.3], [-0.3, 1, 0.8]], n_glints=40, seed=2)
    robust = timed(lambda: fit_sphere_robust(cloud.points, expected_radius=25.0,
                                             viewpoints=[cloud.camera, cloud.projector]), 1 if smoke else 3 if quick else 10)
    return {"points": len(pts), "free_radius": free, "fixed_radius": fixed, "scipy_least_squares": sp,
            "ratio_free_to_scipy": free["median_s"] / sp["median_s"],
            "robust_node_fit": {**robust, "points": len(cloud.points), "rods": 2},
            "aim": "< 5 ms for 10,000 points"}


def bench_labelling(quick: bool, smoke: bool = False) -> dict:
    art = load_artefact(THESIS / "artefact_cmm2.csv")
    plan = read_table(THESIS / "poses_scanner1_table6-1.csv", PosePlanTable)
    rng = np.random.default_rng(3)
    T_s1_s2 = Frame.from_params([-1428.7, 4.4, 138.4, -0.026, 0.089, 0.0006])
    rows = []
    for r in plan.itertuples():
        T1 = Frame([r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad])
        for scanner, T, ids in (("scanner1", T1, range(4, 10)), ("scanner2", T_s1_s2.inverse().compose(T1), range(10, 16))):
            X = T.to_world(art.centres_of([str(i) for i in ids])) + rng.normal(0, 0.005, (6, 3))
            X = np.vstack([X, T.to_world(rng.uniform(-600, 600, (1, 3)))])
            for k, x in enumerate(X[rng.permutation(7)]):
                rows.append({"measurement": r.measurement, "scanner": scanner, "candidate": str(k),
                             "x_mm": x[0], "y_mm": x[1], "z_mm": x[2], "radius_mm": 25.0})
    fits = pd.DataFrame(rows)
    cfg = LabellingConfig(centre_u_mm=0.01)
    res = timed(lambda: label_sphere_fits(fits, art, cfg), 1 if smoke else 2 if quick else 5)
    labelled, outcomes = label_sphere_fits(fits, art, cfg)
    thesis = []
    for name in ("centres_scanner1_table6-3.csv", "centres_scanner2_table6-6.csv"):
        c = read_table(THESIS / name, SphereCentresTable).drop(columns="sphere_id")
        c["candidate"] = c.groupby(["measurement", "scanner"]).cumcount().astype(str)
        thesis.append(c)
    thesis = pd.concat(thesis, ignore_index=True)
    planned = {r.measurement: Frame([r.tx_mm, r.ty_mm, r.tz_mm], [r.omega_rad, r.phi_rad, r.kappa_rad])
               for r in plan.itertuples()}
    with_plan = timed(lambda: label_sphere_fits(thesis, art, LabellingConfig(centre_u_mm=0.15), planned=planned),
                      1 if quick or smoke else 3)
    return {"groups": int(outcomes.shape[0]), "candidates": len(fits), "labelled_groups":
            int((outcomes.status == "labelled").sum()), "all_groups": res, "per_group_s": res["median_s"] / 24,
            "thesis_centres_with_plan": with_plan}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    args = add_options(ap).parse_args(argv)
    out = conditions("pointcloud", argv, args.smoke)
    out["machine"] = {"cpus": os.cpu_count(),
                      "note": "shared 2-core machine; a load average above the core count means the numbers "
                              "are slower than on an idle machine (compare the cpu_median_s)"}
    out["triangulation_2048x2048" if not args.smoke else "triangulation_128x128"] = bench_triangulation(
        args.quick, 128 if args.smoke else None)
    out["sphere_fit"] = bench_sphere_fit(args.quick, args.smoke)
    out["labelling"] = bench_labelling(args.quick, args.smoke)
    return finish(out, args.out)


if __name__ == "__main__":
    main()
