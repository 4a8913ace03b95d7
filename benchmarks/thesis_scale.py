"""Processing time of the thesis-scale data set: 24 measurements at 2048 x 2048 px,
frames already acquired, to a verified calibration (issue 6).

Needs a run directory of the full-resolution profile (``fringecal run --config
configs/run_thesis_full.yaml --out runs/thesis-full``) for its stores. The frames of
a measurement are rendered (not timed) and then decoded and stored (timed, median of
``--repeat``); every later step is timed on the run's stores by calling the same
functions the flow's tasks call, without Prefect (whose overhead is reported apart:
about 7 s to start plus ~0.1 s per task). Prints JSON.

    PYTHONPATH=. python benchmarks/thesis_scale.py runs/thesis-full
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fringecal.artefact import load_artefact, load_rods  # noqa: E402
from fringecal.ballbar import BallBarPosition, frame_along  # noqa: E402
from fringecal.calibration import calibrate_run  # noqa: E402
from fringecal.calibration_file import read_calibration_json  # noqa: E402
from fringecal.frames import Frame  # noqa: E402
from fringecal.pipeline.extract import first_pass, second_pass  # noqa: E402
from fringecal.pipeline.initialise import initial_calibration, poses_from_table  # noqa: E402
from fringecal.pipeline.verify import ballbar_centres  # noqa: E402
from fringecal.rig import load_rig  # noqa: E402
from fringecal.runconfig import RunConfig  # noqa: E402
from fringecal.simulate import artefact_scene, render_measurement  # noqa: E402
from fringecal.simulate.resolution import scaled_rig  # noqa: E402
from fringecal.spheres.steps import label_pose_link  # noqa: E402
from fringecal.fringe.measurement import decode_to_store  # noqa: E402
from schemas import AcquiredPosesTable, AcquisitionTable, read_table  # noqa: E402

POSE = ["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", nargs="?", default="runs/thesis-full")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workers", type=int, default=2, help="measurements processed at a time (the flow: 2)")
    args = ap.parse_args()
    root = Path(args.run_dir)
    manifest = json.loads((root / "manifest.json").read_text())
    cfg = RunConfig.model_validate(manifest["config"])
    rc = cfg.rig_config()
    width = cfg.acquisition.camera_width_px
    art = load_artefact(root / "artefact.csv")
    rods = load_rods(rc.rods, art)
    acq = read_table(root / "tables" / "acquisition.csv", AcquisitionTable)
    out = {"run_dir": str(root), "camera_width_px": width, "n_measurements": len(acq)}

    # decode + store of one measurement from frames in memory (the renderer is not timed)
    truth = scaled_rig(load_rig(rc.sensors, reference=rc.reference_scanner), width)
    poses = read_table(root / "tables" / "acquisition_poses.csv", AcquiredPosesTable)
    p0 = poses.iloc[0]
    T0 = Frame.from_params([p0[c] for c in POSE])
    m = render_measurement(truth.scanners[0], artefact_scene(art, rods, T0), cfg.acquisition.render,
                           np.random.default_rng(1), cfg.acquisition.sequence.build())
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeat):
            t0 = time.perf_counter()
            decode_to_store(m.frames, m.sequence, Path(tmp) / f"m{i}.zarr", {"measurement": "bench"},
                            settings=cfg.decode, full_scale=cfg.acquisition.render.max_dn)
            times.append(time.perf_counter() - t0)
    del m
    out["decode_and_store_s_per_measurement"] = float(np.median(times))

    prior = load_rig(root / "tables" / "sensors_prior.csv")
    radius = float(np.median(art.radii))
    pool = ThreadPoolExecutor(max_workers=args.workers)  # as the flow's task runner
    t0 = time.perf_counter()
    fits = [rows for rows, _ in pool.map(
        lambda r: first_pass(root / r.store, prior.scanner(r.scanner), radius, cfg.extraction, r.pose),
        acq.itertuples())]
    out["spheres_first_pass_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    planned = {str(r.measurement): Frame.from_params([getattr(r, f"planned_{c}") for c in POSE])
               for r in poses.itertuples()}
    lpl = label_pose_link(pd.concat(fits, ignore_index=True), art, rc.reference_scanner,
                          cfg.extraction.labelling_config(), planned=planned)
    out["label_pose_link_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    local = poses_from_table(lpl.poses.poses)

    def second(r):
        g = lpl.fits[(lpl.fits.measurement == r.pose) & (lpl.fits.scanner == r.scanner)]
        return second_pass(root / r.store, prior.scanner(r.scanner), art, rods, g, local.get((r.pose, r.scanner)),
                           cfg.extraction, cfg.control_points, r.pose)

    list(pool.map(second, acq.itertuples()))
    out["spheres_second_pass_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    initial_calibration(prior, lpl.centres, lpl.poses.poses, lpl.links_table(), art)
    out["start_values_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    result, _ = calibrate_run(root)  # the run's own inputs (identical to the above)
    out["bundle_adjustment_s"] = time.perf_counter() - t0
    out["n_control_points"] = int(result.problem.n_points)

    ver = json.loads((root / "verification.json").read_text())
    bb = load_artefact(cfg.verification.ballbar or rc.ballbar)
    names = [p["measurement"] for p in ver["calibrated"]["positions"]]
    table = pd.read_csv(root / "tables" / "ballbar_centres_calibrated.csv", dtype={"measurement": str})
    positions, stores = [], {}
    for name in names:
        g = table[table.measurement == name]
        a = g[g.sphere_id == "A"].iloc[0]
        b = g[g.sphere_id == "B"].iloc[0]
        pos = BallBarPosition(name, frame_along(a[["x_mm", "y_mm", "z_mm"]].to_numpy(float),
                                                b[["x_mm", "y_mm", "z_mm"]].to_numpy(float)),
                              {"A": a.scanner, "B": b.scanner})
        positions.append(pos)
        for sid, sc in pos.scanner_of.items():
            stores[(name, sid)] = root / "measurements" / f"{name}-{sc}.zarr"
    cal = scaled_rig(read_calibration_json(root / "calibration.json"), cfg.verification.camera_width_px or width)
    t0 = time.perf_counter()
    ballbar_centres(stores, positions, bb, {"calibrated": cal}, cfg.extraction.rejection_config())
    out["verification_measuring_s"] = time.perf_counter() - t0
    out["n_ballbar_measurements"] = len(stores)
    decode_total = (len(acq) + len(stores)) * out["decode_and_store_s_per_measurement"]
    steps = ["spheres_first_pass_s", "label_pose_link_s", "spheres_second_pass_s", "start_values_s",
             "bundle_adjustment_s", "verification_measuring_s"]
    out["decode_and_store_all_s"] = decode_total
    out["total_from_frames_s"] = decode_total + sum(out[k] for k in steps)
    out["workers"] = args.workers
    out["note"] = ("decode+store timed on one measurement and multiplied by the number of calibration and "
                   "ball-bar measurements (the decoder already uses every core); the sphere passes run "
                   "--workers measurements at a time like the flow; Prefect adds ~7 s start-up and ~0.1 s per task")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
