"""The mixed thesis rig (scanner1 modelled, scanner2 a black box) over many seeds: how
often does each ball-bar length's ``+- U`` hold the true length, and how does E_max
compare with the ball-bar measured with the true parameters? Prints one JSON object.

    PYTHONPATH=. python benchmarks/black_box_coverage.py --seeds 20 \\
        --out benchmarks/results/black_box_coverage.json

Simulation profile: ideal (``configs/run_thesis_blackbox.yaml``: the thesis rig at
512 px, scanner2 ``output: cloud``, the nine ball-bar positions of table 6-9), so the
true length is the certified one. Seed index ``i`` changes::

    simulate.acquisition.seed  = 1000 + i    (camera noise of the artefact measurements)
    simulate.verification.seed = 2000 + i    (camera noise of the ball-bar measurements)
    simulate.prior.seed        = 3000 + i    (scanner1's prior calibration)

Each seed runs without Prefect (:func:`fringecal.steps.run_pipeline`, two workers, up to
the ``evaluate`` step) in a fresh run directory deleted after its results are read.
Coverage = mean over every length of every seed of ``|error| <= U``; credible within
0.9-0.98 for k = 2. E_max ratio per seed: the run's ball-bar E_max over the E_max of
the same sightings measured with the true sensors and the true black-box transform
(``evaluation.json``).

``--smoke``: one seed of the tests' small rig (poses 1, 5, 9, 12, ball-bar positions 1
and 4, 320 px, 4 bootstrap draws) with scanner2 a black box: the figures mean nothing,
every path runs.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import add_options, conditions, finish  # noqa: E402

CONFIG = ROOT / "configs" / "run_thesis_blackbox.yaml"


def smoke_config(d: Path) -> Path:
    """The tests' small thesis rig with scanner2 a black box."""
    import yaml

    from fringecal.simulate.small_thesis import write_small_thesis_config

    path = write_small_thesis_config(d, 320, (1, 5, 9, 12), (1, 4), name="black-box-smoke")
    cfg = yaml.safe_load(path.read_text())
    cfg["simulate"]["outputs"] = {"scanner2": "cloud"}
    cfg["bundle"] = {"bootstrap_draws": 4}
    path.write_text(yaml.safe_dump(cfg))
    return path


def run_seed(i: int, workdir: Path, config: Path = CONFIG) -> dict:
    from fringecal.run.config import load_run_config
    from fringecal.run.summary import manifest
    from fringecal.rundir import RunDir
    from fringecal.steps import run_pipeline

    # the acceptance objects are left out: the coverage is the ball-bar's (and its recorded runs had none)
    overrides = {"simulate": {"acquisition": {"seed": 1000 + i}, "verification": {"seed": 2000 + i},
                              "prior": {"seed": 3000 + i}, "acceptance": {"enabled": False}}}
    out = {"seed_index": i}
    t0 = time.perf_counter()
    rd = RunDir(workdir / f"seed{i:03d}").create()
    try:
        cfg = load_run_config(config, overrides=overrides)
        rd.manifest.save(manifest(cfg))
        run_pipeline(rd, cfg, workers=2, until="evaluate")
        v = rd.verification.load()
        ev = rd.evaluation.load()
        lengths = [{"measurement": e["measurement"], "error_mm": e["error_mm"], "U_mm": e["U_mm"],
                    "covered": e["covered"]} for e in v["uncertainty"]["lengths"]]
        e_max = v["calibrated"]["max_abs_error_mm"]
        e_true = ev["verification_true_params"]["max_abs_error_mm"]
        out.update(ok=True, lengths=lengths, e_max_mm=e_max, e_max_true_mm=e_true, ratio=e_max / e_true,
                   black_box=ev["black_boxes"], s0=rd.black_boxes.load()["s0"])
    except Exception as err:  # noqa: BLE001  (a failed seed is reported, not fatal)
        out.update(ok=False, error=f"{type(err).__name__}: {err}", traceback=traceback.format_exc(limit=8))
    finally:
        out["wall_seconds"] = time.perf_counter() - t0
        shutil.rmtree(rd.root, ignore_errors=True)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    args = add_options(ap).parse_args(argv)
    if args.smoke:
        args.seeds = 1
    doc = conditions("black_box_coverage", argv, args.smoke)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bbcov-") as tmp:
        config = smoke_config(Path(tmp)) if args.smoke else CONFIG
        seeds = []
        for i in range(args.seeds):
            seeds.append(run_seed(i, Path(tmp), config))
            s = seeds[-1]
            print(f"seed {i}: {'ok' if s['ok'] else s['error']}, ratio {s.get('ratio', float('nan')):.2f}, "
                  f"{s['wall_seconds']:.0f} s", file=sys.stderr)
    ok = [s for s in seeds if s["ok"]]
    entries = [e for s in ok for e in s["lengths"]]
    ratios = np.array([s["ratio"] for s in ok])
    doc.update({
        "what": "mixed thesis rig (configs/run_thesis_blackbox.yaml: scanner1 modelled, scanner2 a black box, "
                "512 px, simulation profile ideal): coverage of each ball-bar length's U (k = 2) over seeds, "
                "and E_max against E_max with the true parameters",
        "seeds_run": len(seeds), "seeds_ok": len(ok), "n_lengths": len(entries),
        "coverage": float(np.mean([e["covered"] for e in entries])) if entries else None,
        "mean_U_um": 1e3 * float(np.mean([e["U_mm"] for e in entries])) if entries else None,
        "rms_z": float(np.sqrt(np.mean([(2 * e["error_mm"] / e["U_mm"]) ** 2 for e in entries]))) if entries
        else None,
        "e_max_um": {"median": 1e3 * float(np.median([s["e_max_mm"] for s in ok])),
                     "median_true_parameters": 1e3 * float(np.median([s["e_max_true_mm"] for s in ok]))}
        if ok else None,
        "e_max_ratio": {"median": float(np.median(ratios)), "min": float(ratios.min()), "max": float(ratios.max()),
                        "within_1p2": int(np.sum(ratios <= 1.2))} if len(ratios) else None,
        "wall_seconds": time.perf_counter() - t0,
        "seeds": seeds,
    })
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
