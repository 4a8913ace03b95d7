"""A row of black-box scanners: the joint adjustment against registering each scanner on
its own by its sphere centres, on the ball-bar; prints one JSON object.

    PYTHONPATH=. python -m fringecal.flows.cli simulate -c configs/run_row3_blackbox.yaml --out DS
    PYTHONPATH=. python benchmarks/black_box_row.py DS [--out benchmarks/results/black_box_row.json]

The data set (``configs/run_row3_blackbox.yaml``: the three-scanner row, every scanner a
black box that delivers its triangulated points in its own frame, 768 px, ideal
simulation profile) is calibrated by the run's own steps in-process, as ``fringecal run
--dataset DS`` calibrates it (:func:`fringecal.steps.run_pipeline` up to the bundle step,
without Prefect): each cloud's sphere candidates, labelling, poses and links, each
labelled sphere refitted in its cloud, then

* joint: every scanner's exterior and every artefact pose adjusted at once (the bundle
  step's black boxes, :func:`fringecal.calibration.blackbox.adjust_black_boxes`,
  reference scanner1: ``black_boxes.json``);
* pairwise SVD: each scanner registered on its own on the same refitted centres
  (:func:`fringecal.calibration.blackbox.pairwise_svd`: per shared measurement the SVD
  pose of the artefact in it and in the reference, averaged);
* truth: the true transforms (each scanner's camera frame in scanner1's).

Each is measured on the same ball-bar sightings as the run's verification step measures
them (:func:`fringecal.verification.black_box.verify_with_black_boxes` with the run's
settings; the joint one with the transforms' joint covariance), so the lengths differ
only by the transforms. Reported: E_max of each, the joint's U and coverage.

``--smoke`` (no data set): a synthetic data set of two black boxes written into a
temporary folder (the clouds of ``benchmarks/cloud_speed.py``: three artefact poses, 20 000
points each at 0.4 points per mm^2 on the caps, no plan; one ball-bar position, each
sphere seen by both): the figures mean nothing, every path runs.
"""

from __future__ import annotations

import argparse
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fringecal.artefact import load_artefact  # noqa: E402
from fringecal.calibration.blackbox import pairwise_svd, scanners_from_document  # noqa: E402
from fringecal.dataset import DataSet  # noqa: E402
from fringecal.frames import Frame, frames_from_rows  # noqa: E402
from fringecal.verification.black_box import verify_with_black_boxes  # noqa: E402
from _common import add_options, conditions, finish  # noqa: E402

NAMES = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad", "scale")


def doc_of(boxes: dict) -> dict:
    """A ``black_boxes.json`` document of ``boxes`` (scanner -> BlackBoxScanner)."""
    names = list(boxes)
    C = np.zeros((7 * len(names), 7 * len(names)))
    for i, b in enumerate(boxes.values()):
        C[7 * i:7 * i + 7, 7 * i:7 * i + 7] = b.covariance
    return {"scanners": [b.to_dict() for b in boxes.values()],
            "joint_covariance": {"n_sensor_parameters": 0, "black_boxes": names, "matrix": C.tolist()}}


def calibrate(dataset: Path, workdir: Path) -> dict:
    """The data set through the run's own steps up to the bundle step (what ``fringecal
    run --dataset`` does, without Prefect): the joint adjustment's black boxes, the
    labelled and refitted centres (``tables/fits_final``) for the pairwise baseline."""
    from fringecal.run.config import load_run_config
    from fringecal.rundir import RunDir
    from fringecal.steps import run_pipeline
    from fringecal.steps.base import stores_of

    t0 = time.perf_counter()
    cfg = load_run_config(dataset=dataset)
    rd = RunDir(workdir / "run").create()
    run_pipeline(rd, cfg, workers=2, until="bundle")
    finals = pd.concat([f for f in (rd.fits_final(m).load() for m in stores_of(rd, "artefact", black_box=True))
                        if len(f)], ignore_index=True)
    boxes = scanners_from_document(rd.black_boxes.load())
    doc = rd.black_boxes.load()
    artefact = rd.artefact.load()
    return {"joint": boxes, "joint_doc": doc, "config": cfg, "s0": doc["s0"], "reference": cfg.reference_scanner,
            "svd": pairwise_svd(finals, artefact, cfg.reference_scanner), "centres": finals,
            "labels": rd.label_outcomes.load(), "seconds": {"total": time.perf_counter() - t0}}


def truth_boxes(truth_dir: Path, reference: str, like: dict) -> dict:
    from fringecal.calibration.blackbox import BlackBoxScanner

    frames = frames_from_rows(pd.read_csv(truth_dir / "scanner_frames.csv"), key="scanner")
    ref = frames[reference].inverse()
    out = {}
    for s, b in like.items():
        T = ref.compose(frames[s])
        T = Frame.from_matrix(T.R, T.t, near=b.params[3:6])
        out[s] = BlackBoxScanner(s, np.r_[T.params, 1.0], np.zeros((7, 7)), 0.0, 0)
    return out


def ballbar(ds: DataSet, doc: dict, cfg) -> dict:
    """The ball-bar measured with the black boxes of ``doc`` (a ``black_boxes.json``
    document) as the run's verification step measures it (its settings)."""
    stores = {}
    for src in ds.verification:
        stores.setdefault(src.group, {})[src.scanner] = src.path
    _, failures, result, budget = verify_with_black_boxes(
        stores, None, doc, load_artefact(ds.ballbar), cfg.extraction.rejection, cfg.verification, float("nan"),
        cfg.control_points.max_incidence_deg, cfg.control_points.pixel_integration_px)
    return {"max_abs_error_mm": result["max_abs_error_mm"],
            "lengths": [{"measurement": e["measurement"], "scanners": [e["scanner_a"], e["scanner_b"]],
                         "error_mm": e["error_mm"], "U_mm": e["U_mm"], "covered": e["covered"]}
                        for e in budget["lengths"]],
            "failures": failures.to_dict("records")}


def smoke_dataset(root: Path) -> Path:
    """The tiny synthetic data set of ``--smoke`` (module notes); its truth beside it
    (``<root>-truth/scanner_frames.csv``)."""
    import yaml

    from cloud_speed import SCANNERS, cloud, poses
    from fringecal.frames import frame_rows
    from fringecal.scancloud import write_scanner_cloud

    rng = np.random.default_rng(7)
    thesis = ROOT / "configs" / "thesis"
    root.mkdir(parents=True)
    (root / "dataset.yaml").write_text(yaml.safe_dump({"name": "black-box-smoke", "reference_scanner": "bbA"}))
    shutil.copy(thesis / "artefact_cmm1.csv", root / "artefact.csv")
    for m, pose in poses(3, rng).items():
        for s, frame in SCANNERS.items():
            (root / "measurements" / m).mkdir(parents=True, exist_ok=True)
            write_scanner_cloud(root / "measurements" / m / f"{s}.ply", cloud(pose, frame, 20_000, rng, 0.4))
    bar = load_artefact(thesis / "ballbar.csv")
    (root / "verification").mkdir()
    shutil.copy(thesis / "ballbar.csv", root / "verification" / "ballbar.csv")
    for k, y in enumerate((0.0,)):
        world = bar.centres - bar.centres.mean(axis=0) + [375.0, y, 3400.0]
        for s, frame in SCANNERS.items():
            (root / "verification" / f"bb{k + 1}").mkdir(exist_ok=True)
            pts = []
            for c, r in zip(frame.to_local(world), bar.radii):
                u = rng.normal(size=(4000, 3))
                u /= np.linalg.norm(u, axis=1, keepdims=True)
                u = u[u @ (-c / np.linalg.norm(c)) > 0.2][:800]
                pts.append(c + (r + rng.normal(0, 0.05, (len(u), 1))) * u)
            write_scanner_cloud(root / "verification" / f"bb{k + 1}" / f"{s}.ply", np.concatenate(pts))
    truth = Path(f"{root}-truth")
    truth.mkdir()
    frame_rows(SCANNERS, key="scanner").to_csv(truth / "scanner_frames.csv", index=False)
    return root


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, nargs="?", help="the data set (fringecal simulate's; not with --smoke)")
    ap.add_argument("--truth", type=Path, help="the truth folder (default: DATASET-truth)")
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        with tempfile.TemporaryDirectory(prefix="bbrow-") as tmp:
            return _main(args, argv, smoke_dataset(Path(tmp) / "ds"))
    if args.dataset is None:
        ap.error("a data set is needed (or --smoke)")
    return _main(args, argv, args.dataset)


def _main(args, argv, dataset: Path) -> dict:
    doc = conditions("black_box_row", argv, args.smoke)
    ds = DataSet.open(dataset)
    with tempfile.TemporaryDirectory(prefix="bbrow-run-") as work:
        cal = calibrate(dataset, Path(work))
    reference = cal["reference"]
    truth = truth_boxes(args.truth or Path(f"{dataset}-truth"), reference, cal["joint"])
    out = {
        **doc,
        "what": "three black-box scanners in a row (configs/run_row3_blackbox.yaml, 768 px, simulation profile "
                "ideal): ball-bar lengths with the joint adjustment, with each scanner registered on its own "
                "(pairwise SVD) and with the true transforms, on the same sightings",
        "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
        "views_labelled": int((cal["labels"]["status"] == "labelled").sum()), "views": len(cal["labels"]),
        "centres": len(cal["centres"]), "s0": cal["s0"], "seconds": cal["seconds"],
        "joint": ballbar(ds, cal["joint_doc"], cal["config"]),
        "pairwise_svd": ballbar(ds, doc_of(cal["svd"]), cal["config"]),
        "true_transforms": ballbar(ds, doc_of(truth), cal["config"]),
        "transform_errors": {},
    }
    for s, b in cal["joint"].items():
        d = b.params - truth[s].params
        e = cal["svd"][s].params - truth[s].params
        out["transform_errors"][s] = {"joint_mm": float(np.linalg.norm(d[:3])), "joint_mrad": float(1e3 * np.abs(
            d[3:6]).max()), "svd_mm": float(np.linalg.norm(e[:3])), "svd_mrad": float(1e3 * np.abs(e[3:6]).max())}
    j, p, t = (out[k]["max_abs_error_mm"] for k in ("joint", "pairwise_svd", "true_transforms"))
    # the lengths between two scanners test the transforms; a scanner's own lengths do not
    true = {e["measurement"]: e["error_mm"] for e in out["true_transforms"]["lengths"]}
    cross = {}
    for k in ("joint", "pairwise_svd", "true_transforms"):
        es = [e for e in out[k]["lengths"] if e["scanners"][0] != e["scanners"][1]]
        cross[k] = {"n": len(es), "max_abs_error_um": 1e3 * max(abs(e["error_mm"]) for e in es),
                    "rms_error_um": 1e3 * float(np.sqrt(np.mean([e["error_mm"] ** 2 for e in es]))),
                    "rms_from_true_transforms_um": 1e3 * float(np.sqrt(np.mean(
                        [(e["error_mm"] - true[e["measurement"]]) ** 2 for e in es])))}
    out["lengths_across_scanners"] = cross
    out["summary"] = {"E_max_joint_um": 1e3 * j, "E_max_pairwise_svd_um": 1e3 * p, "E_max_true_um": 1e3 * t,
                      "joint_over_true": j / t, "svd_over_joint": p / j,
                      "coverage_joint": float(np.mean([e["covered"] for e in out["joint"]["lengths"]]))}
    return finish(out, args.out)


if __name__ == "__main__":
    main()
