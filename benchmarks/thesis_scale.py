"""Processing time of the thesis-scale data set: 24 measurements at 2048 x 2048 px and
the 18 ball-bar measurements, frames already acquired, to a verified calibration.

Needs a run directory of the full-resolution profile (``fringecal run --config
configs/run_thesis_full.yaml --out runs/thesis-full``) for its stores. The run's
inputs (tables, artefact, acquisition stores as hard links) are copied to a scratch
run directory, and every processing step is timed there with the step objects the
flow runs (:mod:`fringecal.steps`, ``--workers`` instances at a time, forced to
recompute), without Prefect, whose overhead is reported apart (about 7 s to start
plus ~0.1 s per task). Decoding and storing is timed on one measurement's frames
rendered in memory (the renderer is not timed), median of ``--repeat``. Prints JSON.

    PYTHONPATH=. python benchmarks/thesis_scale.py runs/thesis-full [--steps NAME,...] [--out FILE]

``--steps``: time only these processing steps, on a copy of the whole run (the earlier
steps' outputs are their inputs). ``--smoke``: one decode, ``--steps initialise,bundle``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402

from fringecal.frames import frames_from_rows  # noqa: E402
from fringecal.fringe.measurement import decode_to_store  # noqa: E402
from fringecal.run.config import RunConfig  # noqa: E402
from fringecal.rundir import RunDir  # noqa: E402
from fringecal.simulate.measurement import render_frames  # noqa: E402
from fringecal.simulate.scenes import artefact_scene  # noqa: E402
from fringecal.steps import COMMON, run_step  # noqa: E402
from fringecal.store import copy_store  # noqa: E402


def scratch_copy(src: RunDir, dst: RunDir) -> None:
    """The inputs of the processing steps: what a data source leaves in a run directory."""
    for f in (src.artefact, src.rods, src.ballbar, src.sensors_prior, src.poses_planned, src.acquisition):
        if f.exists():
            (dst.root / f.rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f.path, dst.root / f.rel)
    for m in src.acquisition.load()["measurement"]:
        copy_store(src.store(m).path, dst.store(m).path)


def decode_seconds(rd: RunDir, cfg: RunConfig, repeat: int) -> float:
    """Median wall time to decode and store one measurement's frames (in memory)."""
    row = rd.acquisition.load().iloc[0]
    T = frames_from_rows(rd.truth.poses.load())[row["pose"]]
    scene = artefact_scene(rd.truth.artefact.load(), rd.rods.load() if rd.rods.exists() else None, T)
    acq = cfg.simulate.acquisition
    m = render_frames(row["measurement"], rd.truth.sensors.load().scanner(row["scanner"]), scene, acq)
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeat):
            t0 = time.perf_counter()
            decode_to_store(m.frames, m.sequence, Path(tmp) / f"m{i}.zarr", {"measurement": "bench"},
                            settings=cfg.decode, full_scale=acq.render.max_dn)
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", nargs="?", default="runs/thesis-full")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2, help="step instances at a time (the flow: 2)")
    ap.add_argument("--steps", help="comma-separated processing steps to time (default: all)")
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        args.repeat, args.steps = 1, args.steps or "initialise,bundle"
    src = RunDir(args.run_dir)
    cfg = RunConfig.model_validate(src.read_manifest()["config"])
    policy = cfg.thread_policy(args.workers)
    names = [s.name for s in COMMON]
    chosen = names if not args.steps else [n for n in args.steps.split(",") if n]
    unknown = sorted(set(chosen) - set(names))
    if unknown:
        ap.error(f"--steps: {unknown} are not processing steps ({', '.join(names)})")
    table = src.acquisition.load()
    out = {**conditions("thesis_scale", argv, args.smoke), "run_dir": str(src.root),
           "n_measurements": int((table.kind == "artefact").sum()),
           "n_ballbar_measurements": int((table.kind == "ballbar").sum()), "workers": policy.workers,
           "threads": policy.to_dict()}
    if cfg.simulate is not None:
        out["camera_width_px"] = cfg.simulate.acquisition.camera_width_px
        out["decode_and_store_s_per_measurement"] = decode_seconds(src, cfg, args.repeat)
        out["decode_and_store_all_s"] = len(table) * out["decode_and_store_s_per_measurement"]
    with tempfile.TemporaryDirectory(dir=src.root.parent) as tmp:
        rd = RunDir(Path(tmp) / "run")
        if chosen == names:
            rd.create()
            scratch_copy(src, rd)
        else:  # the earlier steps' outputs are the chosen steps' inputs
            shutil.copytree(src.root, rd.root, ignore=shutil.ignore_patterns(".prefect", "report.html"))
        steps = {}
        with ThreadPoolExecutor(max_workers=policy.workers) as pool:
            for step in COMMON:
                if step.name not in chosen:
                    continue
                items = step.items(rd, step.view(cfg))
                threads = policy.instance_threads(len(items))
                t0 = time.perf_counter()
                list(pool.map(lambda item: run_step(step, rd, cfg, item, force=True, threads=threads), items))
                steps[step.name] = time.perf_counter() - t0
        if rd.bundle_summary.exists():
            out["n_control_points"] = int(rd.bundle_summary.load()["n_control_points"])
    out["steps_s"] = steps
    out["total_from_frames_s"] = out.get("decode_and_store_all_s", 0.0) + sum(steps.values())
    out["note"] = ("decode+store timed on one measurement and multiplied by the number of stores (the decoder "
                   "already uses every core); the steps run --workers instances at a time like the flow, each "
                   "with its share of the cores (fringecal.threads); Prefect adds ~7 s start-up and ~0.1 s per "
                   "task")
    return finish(out, args.out)


if __name__ == "__main__":
    main()
