"""Speed of the black-box path: 24 clouds of 2 million points each from PLY files to
the black boxes' calibration, and the PLY reading rate against the file system's;
prints one JSON object.

    PYTHONPATH=. python benchmarks/cloud_speed.py [--clouds 24] [--points 2000000] \\
        [--out benchmarks/results/cloud_speed.json]

The clouds are synthetic (written once into a temporary folder, not timed): two
black-box scanners 750 mm apart looking along +z at the thesis artefact (CMM set 1)
3.6 m away in twelve poses, each cloud the visible caps of the spheres in a 1.2 m field
(1.5 points per mm^2, 0.05 mm noise) and a backdrop plane filling it up to the point
count, written as binary little-endian float32 PLY (24 MB each), as a 2048 px
fringe scanner's export would be. What is timed runs the functions of the run's steps
on two threads, as `fringecal run` schedules them on 2 cores:

* read: each PLY read and checked (:func:`fringecal.scancloud.read_scanner_cloud`,
  the decode step) and written as the run's cloud store;
* spheres: the first pass (:func:`fringecal.spheres.cloud_spheres.cloud_sphere_fits`
  on the store's points);
* label: labelling, poses and links with the planned poses
  (:func:`fringecal.spheres.poses_and_links.label_pose_link`);
* refit: each labelled sphere's second pass in its cloud;
* adjust: the joint adjustment (:func:`fringecal.calibration.blackbox.adjust_black_boxes`).

The file-system rate is reading the same files' bytes (``Path.read_bytes``), the PLY
rate reading them with plyfile into float64 points; both with the files in the page
cache (they were just written; dropping the cache needs root on a shared machine).
Median of ``--repeats`` whole runs; the conditions (load average before and after,
commit, numba's cache) as every benchmark records them (``benchmarks/_common.py``).

``--smoke``: 6 clouds of 20 000 points (0.4 points per mm^2 on the caps), one repeat: the figures mean nothing, every
path runs (``tests/test_benchmarks.py``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fringecal.artefact import load_artefact  # noqa: E402
from fringecal.calibration.blackbox import adjust_black_boxes  # noqa: E402
from fringecal.frames import Frame  # noqa: E402
from fringecal.scancloud import (read_cloud_store, read_scanner_cloud, write_cloud_store,  # noqa: E402
                                 write_scanner_cloud)
from fringecal.spheres.cloud_spheres import cloud_sphere_fits, refit_cloud_sphere  # noqa: E402
from fringecal.spheres.fit import FitError  # noqa: E402
from fringecal.spheres.poses_and_links import label_pose_link, sphere_fit_row  # noqa: E402
from _common import add_options, conditions, finish  # noqa: E402

ARTEFACT = load_artefact(ROOT / "configs" / "thesis" / "artefact_cmm1.csv")
SCANNERS = {"bbA": Frame.from_params([0, 0, 0, 0, 0, 0]), "bbB": Frame.from_params([750, 0, 0, 0, -0.1, 0])}
FIELD_MM = 1200.0
DENSITY = 1.5  # points per mm^2


def poses(n: int, rng) -> dict:
    c0 = ARTEFACT.centres.mean(axis=0)
    out = {}
    for m in range(n):
        R = Frame.from_params([0, 0, 0, *rng.normal(0, 0.15, 3)]).R
        t = np.array([375 + rng.normal(0, 80), rng.normal(0, 80), 3600 + rng.normal(0, 80)])
        out[str(m + 1)] = Frame.from_matrix(R, t - R.T @ c0)
    return out


def cloud(pose: Frame, scanner: Frame, n_points: int, rng, density: float = DENSITY) -> np.ndarray:
    """The scanner's cloud of the artefact at ``pose``: visible caps in its field and a backdrop."""
    centres = scanner.to_local(pose.to_world(ARTEFACT.centres))
    inside = (np.abs(centres[:, 0]) < FIELD_MM / 2) & (np.abs(centres[:, 1]) < FIELD_MM / 2)
    parts = []
    for c, r in zip(centres[inside], ARTEFACT.radii[inside]):
        n = int(density * np.pi * r**2)
        u = rng.normal(size=(4 * n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u = u[u @ (-c / np.linalg.norm(c)) > 0.1][:n]
        parts.append(c + (r + rng.normal(0, 0.05, (len(u), 1))) * u)
    rest = n_points - sum(len(p) for p in parts)
    xy = rng.uniform(-FIELD_MM / 2, FIELD_MM / 2, (rest, 2))
    parts.append(np.column_stack([xy, 4300 + rng.normal(0, 0.05, rest)]))
    return np.concatenate(parts)


def one_run(files: dict, planned: dict, workdir: Path) -> dict:
    t = {}
    t0 = time.perf_counter()
    radius = float(np.median(ARTEFACT.radii))

    def read(item):
        (m, s), path = item
        c = read_scanner_cloud(path, radius / 2)
        write_cloud_store(workdir / f"{m}-{s}.zarr", c.points)

    def first(item):
        (m, s), _ = item
        points, _ = read_cloud_store(workdir / f"{m}-{s}.zarr")
        return cloud_sphere_fits(points, m, s, radius)[0]

    with ThreadPoolExecutor(max_workers=2) as pool:
        list(pool.map(read, files.items()))
        t["read_s"] = time.perf_counter() - t0
        fits = list(pool.map(first, files.items()))
        t["spheres_s"] = time.perf_counter() - t0 - t["read_s"]
        t1 = time.perf_counter()
        res = label_pose_link(pd.concat(fits, ignore_index=True), ARTEFACT, "bbA", planned=planned)
        t["label_s"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        labelled = res.fits[res.fits["sphere_id"] != ""]

        def second(key):
            m, s = key
            points, _ = read_cloud_store(workdir / f"{m}-{s}.zarr")
            rows = []
            for r in labelled[(labelled["measurement"] == m) & (labelled["scanner"] == s)].itertuples():
                try:
                    fit = refit_cloud_sphere(points, np.array([r.x_mm, r.y_mm, r.z_mm]), radius)
                except (FitError, ValueError):
                    continue
                rows.append(sphere_fit_row(m, s, r.candidate, fit, sphere_id=r.sphere_id))
            return rows

        finals = pd.DataFrame([r for rows in pool.map(second, files) for r in rows])
        t["refit_s"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    links = {str(r.scanner): Frame.from_params([r.tx_mm, r.ty_mm, r.tz_mm, r.omega_rad, r.phi_rad, r.kappa_rad])
             for r in res.links_table().itertuples()}
    identity = Frame.from_params(np.zeros(6))
    joint = adjust_black_boxes(finals, ARTEFACT, "bbA", {s: (links.get(s, identity), 1.0) for s in SCANNERS})
    t["adjust_s"] = time.perf_counter() - t1
    t["total_s"] = time.perf_counter() - t0
    err = joint.scanners["bbB"].params[:6] - SCANNERS["bbB"].params
    t["views_labelled"] = int((res.labels["status"] == "labelled").sum())
    t["bbB_error_mm"] = float(np.linalg.norm(err[:3]))
    return t


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clouds", type=int, default=24)
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        args.clouds, args.points, args.repeats = 6, 20_000, 1
    doc = conditions("cloud_speed", argv, args.smoke)
    density = 0.4 if args.smoke else DENSITY
    rng = np.random.default_rng(2026)
    planned = poses(args.clouds // len(SCANNERS), rng)
    with tempfile.TemporaryDirectory(prefix="cloudspeed-") as tmp:
        tmp = Path(tmp)
        files = {}
        for m, pose in planned.items():
            for s, frame in SCANNERS.items():
                files[(m, s)] = write_scanner_cloud(tmp / f"{m}-{s}.ply", cloud(pose, frame, args.points, rng, density))
        size = sum(p.stat().st_size for p in files.values())
        t0 = time.perf_counter()
        for p in files.values():
            p.read_bytes()
        fs_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for p in files.values():
            read_scanner_cloud(p)
        ply_s = time.perf_counter() - t0
        runs = []
        for i in range(args.repeats):
            work = tmp / f"run{i}"
            work.mkdir()
            runs.append(one_run(files, planned, work))
    median = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
    doc.update({
        "what": f"{len(files)} synthetic black-box clouds of {args.points:,} points (binary float32 PLY) through "
                "reading, the store, sphere candidates, labelling, the second pass and the joint adjustment, "
                "on two threads",
        "cache": "warm (files just written, in the page cache)",
        "median": median, "runs": runs,
        "bytes": size, "filesystem_read_mb_s": size / fs_s / 1e6, "ply_read_mb_s": size / ply_s / 1e6,
        "ply_read_points_per_s": len(files) * args.points / ply_s,
    })
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
