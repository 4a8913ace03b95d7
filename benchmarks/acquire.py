"""Benchmark: one simulated measurement end to end (render + decode + store write, and
the ground truth's own store), as one ``simulate-render`` step instance does it.

Prints JSON: wall and CPU seconds (median of ``--repeats``) at each ``--widths``, split
into rendering and decoding + writing the store, the store's size on disk, and the
peak memory of the process. Thesis scanner 1 at pose 1 of table 6-1, default
configuration (configs/run_thesis.yaml), no hexapod (its moves cost no wall time
with the simulated box).

    PYTHONPATH=. python benchmarks/acquire.py [--widths 512,2048] [--repeats 3] [--out FILE]

``--smoke``: 64 px, one repeat.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import add_options, conditions, finish  # noqa: E402

from fringecal.run.config import load_run_config  # noqa: E402
from fringecal.simulate.measurement import simulate_measurement  # noqa: E402
from fringecal.simulate.scenes import artefact_scene  # noqa: E402
from fringecal.simulate.source import load_simulated_rig  # noqa: E402


def store_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--widths", default="512,2048")
    ap.add_argument("--repeats", type=int, default=3)
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        args.widths, args.repeats = "64", 1
    out = {**conditions("acquire", argv, args.smoke), "cpus": os.cpu_count(), "widths": {}}
    tmp = Path(tempfile.mkdtemp(prefix="fringecal-bench-acquire-"))
    try:
        for width in map(int, args.widths.split(",")):
            cfg = load_run_config(None, {"simulate": {"acquisition": {"camera_width_px": width,
                                                                      "hexapod": {"enabled": False}}}})
            sr = load_simulated_rig(cfg.simulate)
            pose, T = next(iter(sr.planned.items()))
            scanner = sr.truth.scanners[0]
            measurement = f"{pose}-{scanner.name}"
            scene = artefact_scene(sr.artefact, sr.rods, T, sr.hardware)

            def acquire(path):
                return simulate_measurement(measurement, scanner, scene, cfg.simulate.acquisition, cfg.decode, path,
                                            path.with_name("truth-" + path.name))

            acquire(tmp / "warm.zarr")  # compile, caches
            runs = []
            for i in range(args.repeats):
                path = tmp / f"{width}-{i}.zarr"
                w, c = time.perf_counter(), time.process_time()
                r = acquire(path)
                runs.append({"wall_s": time.perf_counter() - w, "cpu_s": time.process_time() - c,
                             "render_s": r.summary["render_s"], "decode_store_s": r.summary["decode_store_s"],
                             "store_mb": store_mb(path), "truth_store_mb": store_mb(path.with_name("truth-" + path.name))})
                shutil.rmtree(path)
                shutil.rmtree(path.with_name("truth-" + path.name))
            med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            out["widths"][width] = {"measurement": measurement, **med, "runs_wall_s": [r["wall_s"] for r in runs]}
            print(json.dumps({width: out["widths"][width]}), file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    return finish(out, args.out)


if __name__ == "__main__":
    main()
