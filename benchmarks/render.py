"""Benchmark: rendering one 98-frame measurement with the virtual scanner.

Prints JSON: seconds (median of ``--repeats``, wall and CPU) for a 2048 x 2048 and
a 512 x 512 measurement of the thesis rig (scanner 1, artefact pose 1 of table 6-1,
a backdrop 3.5 m from the camera so every pixel sees a surface: the worst case),
default render configuration (3 x 3 sub-samples, defocus, noise); peak memory; where
the time goes (at 1024 x 1024); and, as a reference in the same run, numpy
evaluating the bare sequence contract with Gaussian noise for the same frame count
(no geometry, no pixel integration).

    PYTHONPATH=. python benchmarks/render.py [--size 2048] [--small 512] [--repeats 3] [--no-backdrop] [--out FILE]

``--smoke``: 64 and 32 px, 48 px for where the time goes, one repeat.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numba
import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402

from fringecal.artefact import load_artefact, load_rods  # noqa: E402
from fringecal.config import thesis_dir  # noqa: E402
from fringecal.frames import Frame  # noqa: E402
from fringecal.fringe.sequence import FringeSequence  # noqa: E402
from fringecal.rig import load_rig  # noqa: E402
from fringecal.simulate import RenderConfig, artefact_scene, backdrop, render_measurement, scaled_scanner  # noqa: E402

SEQ = FringeSequence()


def thesis_setup(with_backdrop: bool):
    d = thesis_dir()
    rig = load_rig(d / "sensors_refined_table6-8.csv")
    art = load_artefact(d / "artefact_cmm2.csv")
    rods = load_rods(d / "rods.csv", art)
    row = pd.read_csv(d / "poses_scanner1_table6-1.csv").iloc[0]
    pose = Frame.from_params(row[["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]].to_numpy(float))
    scanner = rig.scanner("scanner1")
    scene = artefact_scene(art, rods, pose, background=backdrop(scanner, 3500.0) if with_backdrop else None)
    return scanner, scene


def timed(fn, repeats: int) -> dict:
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
        del out
    return {"wall_s": statistics.median(walls), "cpu_s": statistics.median(cpus), "runs_wall_s": walls}


def numpy_reference(size: int, seed: int = 0) -> np.ndarray:
    """The contract I = A + B cos(t w + 2 pi k/N) plus Gaussian noise, 12 bit, in numpy."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:size, 0:size].astype(np.float32) / np.float32(size - 1) - np.float32(0.5)
    w = {"x": 5.6 * u, "y": 5.6 * v}
    frames = np.empty((SEQ.n_frames, size, size), np.uint16)
    for i, (o, t, k) in enumerate(SEQ.frames()):
        img = np.float32(1500) + np.float32(1000) * np.cos(t * w[o] + np.float32(2 * np.pi * k / SEQ.n_steps))
        img += rng.standard_normal((size, size), dtype=np.float32) * np.float32(8)
        np.clip(np.rint(img), 0, 4095, out=img)
        frames[i] = img
    return frames


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--small", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-backdrop", action="store_true")
    args = add_options(ap).parse_args(argv)
    mid = 1024
    if args.smoke:
        args.size, args.small, args.repeats, mid = 64, 32, 1, 48
    head = conditions("render", argv, args.smoke)

    scanner, scene = thesis_setup(not args.no_backdrop)
    cfg = RenderConfig()
    rng = np.random.default_rng(1)
    t0 = time.perf_counter()
    render_measurement(scaled_scanner(scanner, 32), scene, cfg, rng)  # compile or load the numba cache
    warmup = time.perf_counter() - t0

    def render(size, config=cfg):
        return render_measurement(scaled_scanner(scanner, size), scene, config, rng)

    result = {
        **head,
        "scene": "thesis scanner1, table 6-1 pose 1" + ("" if args.no_backdrop else ", backdrop at 3500 mm"),
        "frames": SEQ.n_frames,
        "supersampling": cfg.supersampling,
        "threads": numba.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "warmup_s": warmup,
    }
    result[f"render_{args.small}"] = timed(lambda: render(args.small), args.repeats)

    breakdown = {
        "1x1_noise_free": timed(lambda: render(mid, cfg.noise_free().model_copy(update={"supersampling": 1})), 1),
        "3x3_noise_free": timed(lambda: render(mid, cfg.noise_free()), 1),
        "3x3_noisy": timed(lambda: render(mid, cfg), 1),
    }
    b = {k: v["cpu_s"] for k, v in breakdown.items()}
    result[f"where_the_time_goes_{mid}_cpu_s"] = {
        "frames_and_one_ray_per_pixel": b["1x1_noise_free"],
        "extra_sub_samples_3x3": b["3x3_noise_free"] - b["1x1_noise_free"],
        "camera_noise": b["3x3_noisy"] - b["3x3_noise_free"],
    }

    tracemalloc.start()
    result[f"render_{args.size}"] = timed(lambda: render(args.size), args.repeats)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    result[f"render_{args.size}"]["peak_numpy_bytes"] = peak
    result["peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    result["frames_bytes"] = SEQ.n_frames * args.size * args.size * 2

    ref = timed(lambda: numpy_reference(args.size), 1)
    result["reference_numpy_contract_plus_noise"] = ref
    result["ratio_render_to_reference_wall"] = result[f"render_{args.size}"]["wall_s"] / ref["wall_s"]
    return finish(result, args.out)


if __name__ == "__main__":
    main()
