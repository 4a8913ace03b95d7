"""Benchmark of ``fringecal measure``: 24 stores of 2048 px (the thesis's 12 artefact
poses x 2 scanners, 12 measurement folders) into one binary PLY, as a user runs it.

    PYTHONPATH=. python benchmarks/measure.py [--width 2048] [--repeats 3] [--without-regions] [--out FILE.json]

``--smoke``: 64 px stores, one repeat.

The stores are made first (not timed): every camera pixel's ray is intersected with the
artefact's 15 spheres at the pose (thesis table 6-1, the thesis's refined sensors,
table 6-8), the hit is projected into the projector and its phases written with
1 mrad of Gaussian noise, as a decoded store (``tau_x``, ``tau_y``, ``valid``,
``modulation_x``/``_y``); pixels that see no sphere are invalid, as on the
artefact's dark background. The calibration file is those sensors with a diagonal
covariance (each parameter's standard uncertainty from the default run's magnitudes:
the cost of the propagation does not depend on the values, only on how many
parameters are uncertain: all 14 of every sensor here) and each sensor's observed
region, built from the stores' own valid pixels and phases (every point is inside it,
but each is tested: ``--without-regions`` leaves the regions out, as a calibration
file written before them).

Timed: the command ``fringecal measure --calibration CAL --stores M1 ... --stores M12
--out cloud.ply --json`` in a fresh process (imports and numba's cached kernels
included), ``--repeats`` times; the JSON gives the median and every wall time, the
command's own phase times, the points and the file size, the load average before and
after, and whether the numba cache was cold for the first repeat (``numba_cache``: a
cold first run compiles the triangulation kernel, about 10 s, and is reported
separately from the median of the warm ones).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402

from fringecal.artefact import load_artefact  # noqa: E402
from fringecal.calibration.file import rig_to_dict  # noqa: E402
from fringecal.calibration.propagation import ParameterCovariances  # noqa: E402
from fringecal.frames import frames_from_rows  # noqa: E402
from fringecal.lens.observed_region import ObservedRegion  # noqa: E402
from fringecal.pointcloud import camera_ray_cache  # noqa: E402
from fringecal.rig import (
    load_rig,  # noqa: E402
    scaled_rig,  # noqa: E402
)
from fringecal.store import write_store  # noqa: E402

THESIS = ROOT / "configs" / "thesis"
# standard uncertainties per parameter, of the size the default run states (mm, rad)
_STD = np.array([0.05, 0.05, 0.2, 1e-4, 1e-4, 3e-5, 0.006, 0.005, 0.002, 1e-6, 3e-8, 2e-10, 1e-6, 1e-6])


def _sphere_hits(origin, dirs, centres, radii):
    """Nearest ray parameter t (n,) over spheres, inf where none is hit."""
    best = np.full(dirs.shape[0], np.inf)
    for c, r in zip(centres, radii):
        oc = origin - c
        b = dirs @ oc
        disc = b * b - (oc @ oc - r * r)
        hit = disc > 0
        t = np.where(hit, -b - np.sqrt(np.where(hit, disc, 0.0)), np.inf)
        best = np.minimum(best, np.where(t > 0, t, np.inf))
    return best


def make_store(scanner, centres, radii, path: Path, rng) -> tuple[float, np.ndarray, np.ndarray]:
    """The decoded store of ``scanner`` looking at spheres; returns its valid fraction and
    the valid points' camera and projector image-plane mm (n, 2) each."""
    import xarray as xr

    cam, prj = scanner.camera, scanner.projector
    ideal = camera_ray_cache(cam).ideal                          # (2, h, w) camera frame, mm
    h, w = ideal.shape[1:]
    local = np.stack([-ideal[0], -ideal[1], np.full((h, w), cam.c)], axis=-1).reshape(-1, 3)
    dirs = local @ cam.R                                         # R^T l per row
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = _sphere_hits(cam.pinhole, np.nan_to_num(dirs), centres, radii)
    valid = np.isfinite(t)
    tau = np.full((h * w, 2), np.nan)
    X = cam.pinhole + dirs[valid] * t[valid, None]
    tau[valid] = prj.measured(prj.project(X)) + rng.normal(0, 1e-3, (len(X), 2))
    valid &= np.isfinite(tau).all(axis=1)
    mod = np.where(valid, 300.0, 0.0).astype(np.float32).reshape(h, w)
    ds = xr.Dataset({"tau_x": (("v", "u"), tau[:, 0].astype(np.float32).reshape(h, w)),
                     "tau_y": (("v", "u"), tau[:, 1].astype(np.float32).reshape(h, w)),
                     "valid": (("v", "u"), valid.reshape(h, w)),
                     "modulation_x": (("v", "u"), mod), "modulation_y": (("v", "u"), mod)},
                    attrs={"source": "benchmarks/measure.py: analytic phases of the artefact's spheres"})
    write_store(path, ds)
    rows, cols = np.divmod(np.flatnonzero(valid), w)
    return float(valid.mean()), cam.image_mm(np.stack([cols, rows], axis=-1).astype(float)), prj.image_mm(tau[valid])


def make_inputs(root: Path, width: int, regions: bool = True) -> tuple[Path, list[Path], dict]:
    rig = scaled_rig(load_rig(THESIS / "sensors_refined_table6-8.csv"), width)
    art = load_artefact(THESIS / "artefact_cmm2.csv")
    poses = frames_from_rows(pd.read_csv(THESIS / "poses_scanner1_table6-1.csv"))
    rng = np.random.default_rng(24)
    folders, fractions, seen = [], {}, {s.name: [] for s in rig.sensors}
    for m, T in poses.items():
        folder = root / f"pose{int(m):02d}"
        folder.mkdir()
        centres = T.to_world(art.centres)
        for scanner in rig.scanners:
            fraction, cam_mm, prj_mm = make_store(scanner, centres, art.diameters / 2,
                                                  folder / f"{scanner.name}.zarr", rng)
            fractions[f"{m}-{scanner.name}"] = fraction
            seen[scanner.camera.name].append(cam_mm)
            seen[scanner.projector.name].append(prj_mm)
        folders.append(folder)
    n = 14 * len(rig.sensors)
    cov = np.diag(np.tile(_STD, len(rig.sensors)) ** 2)
    covariances = ParameterCovariances(cov, np.zeros((n, n)), np.zeros(n), 0.0)
    observed = {s.name: ObservedRegion.from_observations(np.concatenate(seen[s.name]), s.format.width_mm,
                                                         s.format.height_mm) for s in rig.sensors} if regions else None
    doc = rig_to_dict(rig, {"source": "benchmarks/measure.py"}, covariances, observed_regions=observed)
    cal = root / "calibration.json"
    cal.write_text(json.dumps(doc))
    return cal, folders, fractions


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--without-regions", action="store_true",
                    help="a calibration file without observed regions (no point is tested)")
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        args.width, args.repeats = 64, 1
    head = conditions("measure", argv, args.smoke)
    import numba

    cache_dir = Path(numba.config.CACHE_DIR or ROOT / "fringecal" / "__pycache__")
    cold = not any(cache_dir.glob("pointcloud._triangulate_kernel*.nbi"))
    root = Path(tempfile.mkdtemp(prefix="fringecal-bench-measure-"))
    try:
        t = time.perf_counter()
        cal, folders, fractions = make_inputs(root, args.width, not args.without_regions)
        setup = time.perf_counter() - t
        cmd = [sys.executable, "-m", "fringecal.flows.cli", "measure", "--calibration", str(cal),
               *[a for f in folders for a in ("--stores", str(f))], "--out", str(root / "cloud.ply"), "--json"]
        load_start = os.getloadavg()
        runs = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
            wall = time.perf_counter() - t
            if p.returncode != 0:
                raise SystemExit(f"fringecal measure failed ({p.returncode}):\n{p.stderr[-3000:]}")
            summary = json.loads(p.stdout)
            runs.append({"wall_s": wall, "phases_s": summary["seconds"], "points": summary["points"]})
        walls = [r["wall_s"] for r in runs]
        doc = {**head,
               "timed_command": "fringecal measure --calibration CAL " + " ".join(f"--stores {f.name}" for f in folders)
               + " --out cloud.ply --json",
               "width_px": args.width, "stores": 2 * len(folders), "observed_regions": not args.without_regions,
               "points_outside_observed_region": summary["observed_region"]["points_outside"], "valid_fraction_mean": float(np.mean(list(fractions.values()))),
               "points": runs[-1]["points"], "ply_bytes": (root / "cloud.ply").stat().st_size,
               "numba_cache": "cold for the first repeat" if cold else "warm",
               "median_wall_s": float(np.median(walls if not cold or len(walls) < 2 else walls[1:])),
               "walls_s": walls, "runs": runs, "setup_s": setup, "cpu_count": os.cpu_count(),
               "load_average_before_the_command": load_start}
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
