"""Can a calibration's own data correct the artefact's CMM table?

The adjustment holds the artefact's sphere centres at their CMM values (10 um per
coordinate in the thesis's table). Photogrammetry's usual alternative adjusts them too,
each held by its table value with the table's u as a prior. Whether that helps depends on
how well the scanners' data alone determine the centres, and on whether what the data hold
besides noise (a lens term outside the model, smooth phase errors, drift) moves them.

For a run directory whose ``truth/artefact.csv`` holds the artefact as built (a simulated
run; a recorded data set has no truth), the script adjusts the run's control points with
the 14-parameter model, then linearises the adjustment at its solution in the artefact's
centres (``da``, 3 per sphere, radii held; spheres without control points are left at
their table values and out of every figure) and reports:

* ``directions``: along each combination of centres the data determine (the
  eigen-directions of ``I = J_a^T W J_a - B^T N^-1 B``, the information the data hold on
  ``da`` once the sensors and poses are adjusted with it; W the inverse variance of a
  residual), its standard uncertainty ``u_um``, what the data alone say the table's error
  is there (``data_um``, ``-g / lambda``, g the gradient) and what it truly is
  (``table_error_um``), and their difference over u (``z``). ``I`` has six null
  directions, a rigid motion of all the centres (the poses take it), and a seventh,
  their common scale (the sensors take it), where the poses do not tell it;
* ``finer_than_table``: those combinations the data determine better than the table's
  u: how many, the RMS of their ``z`` (about 1 if the data were limited by their noise)
  and the correlation of what the data say with the table's true error;
* ``with_prior``: the centres adjusted with the table as a prior (``I + Sigma^-1``):
  their error against the truth (RMS after a best-fit similarity transform) next to the
  table's own (``table_error_rms_um``).

Prints one JSON object::

    PYTHONPATH=. python benchmarks/artefact_refinement.py RUN_DIR [RUN_DIR ...] \\
        --out benchmarks/results/artefact_refinement.json

Each RUN_DIR comes from ``fringecal run -c CONFIG --out RUN_DIR --until bundle`` of a
simulated config; the JSON names each run's simulation profile (its manifest).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import add_options, conditions, finish  # noqa: E402

#: eigenvalues of the data's information below this fraction of the largest are its null space
NULL = 1e-9


def _similarity_rms(reference: np.ndarray, other: np.ndarray) -> float:
    """RMS 3-D distance (mm) between ``other`` and ``reference`` (n, 3) after the
    best-fit similarity transform of ``other`` onto ``reference`` (Umeyama)."""
    a = reference - reference.mean(0)
    b = other - other.mean(0)
    U, S, Vt = np.linalg.svd(a.T @ b)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    scale = np.trace(np.diag(S) @ D) / np.sum(b**2)
    return float(np.sqrt(np.mean(np.sum((a - scale * b @ R.T) ** 2, axis=1))))


def _correlation(a: np.ndarray, b: np.ndarray) -> float | None:
    """Pearson correlation; None with fewer than 3 values or a constant one (an ideal
    profile's table has no error to correlate with)."""
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) < 1e-12:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def _linearised(result):
    """Information I (3 n_s, 3 n_s) and gradient g (3 n_s) of the data on the centres at
    the solution, the sensors and poses adjusted with them (Schur complement), in
    inverse-variance units; and the residual variance used."""
    from fringecal.calibration.artefact_sensitivity import artefact_blocks

    pr = result.problem
    n_s = len(pr.artefact.ids)
    blocks = artefact_blocks(result)
    w = blocks.w
    Ja = blocks.Ja[:, :, :3]  # the centres; the radii stay at the table
    r = np.where(w > 0, blocks.residuals, 0.0)
    variance = float(np.sum(w * r**2) / (2 * np.count_nonzero(w[:, 0]) - result.layout.n))
    w = w / variance
    Iaa = np.zeros((n_s, 3, 3))
    g = np.zeros((n_s, 3))
    np.add.at(Iaa, pr.sphere_idx, np.einsum("nt,nti,ntj->nij", w, Ja, Ja))
    np.add.at(g, pr.sphere_idx, np.einsum("nt,nt,ntj->nj", w, r, Ja))
    # the sensors and poses adjusted with the centres: I = Iaa - B^T N^-1 B (N^-1 B does not
    # depend on the residual variance, B^T does)
    B = blocks.B[:, :, :3].reshape(result.layout.n, 3 * n_s) / variance
    NinvB = blocks.solved()[:, :, :3].reshape(result.layout.n, 3 * n_s)
    I = np.zeros((3 * n_s, 3 * n_s))
    for k in range(n_s):
        I[3 * k:3 * k + 3, 3 * k:3 * k + 3] = Iaa[k]
    I -= B.T @ NinvB
    return 0.5 * (I + I.T), g.reshape(-1), variance


def refine(run_dir: Path) -> dict:
    from fringecal.artefact import load_artefact
    from fringecal.calibration.bundle import BundleOptions, bundle_adjust
    from fringecal.rundir import RunDir
    from fringecal.steps.bundle import load_problem

    rd = RunDir(run_dir)
    truth_path = rd.root / "truth" / "artefact.csv"
    if not truth_path.exists():
        raise FileNotFoundError(f"{truth_path}: no artefact as built (a simulated run's truth folder is needed)")
    manifest = json.loads(rd.manifest.path.read_text()) if rd.manifest.exists() else {}
    t0 = time.perf_counter()
    problem = load_problem(rd, None)
    result = bundle_adjust(problem, BundleOptions())
    art = problem.artefact
    truth = load_artefact(truth_path)
    if truth.ids != art.ids:
        raise ValueError(f"{truth_path}: sphere ids differ from {rd.artefact.path}")
    I, g, variance = _linearised(result)
    seen = np.bincount(problem.sphere_idx, minlength=len(art.ids)) > 0
    rows = np.repeat(seen, 3)
    # spheres without control points are neither moved nor compared: their posterior is the table
    art = type(art)(tuple(np.asarray(art.ids)[seen]), art.centres[seen], art.diameters[seen], art.u[seen])
    truth = type(truth)(tuple(np.asarray(truth.ids)[seen]), truth.centres[seen], truth.diameters[seen])
    I, g = I[np.ix_(rows, rows)], g[rows]
    lam, V = np.linalg.eigh(I)
    keep = lam > NULL * lam[-1]
    lam, V = lam[keep], V[:, keep]
    true_da = (truth.centres - art.centres).reshape(-1)
    # along each determined combination v of the centres: what the data say the table's error
    # is (v . da, da = -I^+ g), its u, and what the table's error truly is; rigid motions of
    # the whole artefact are null directions, so v sees the table's error without them
    u_dir = 1.0 / np.sqrt(lam)
    said = -(V.T @ g) / lam
    true_dir = V.T @ true_da
    z = (said - true_dir) / u_dir
    finer = u_dir < np.median(art.u)
    prior = 1.0 / np.repeat(art.u, 3) ** 2
    post = np.linalg.inv(I + np.diag(prior))
    post_da = -(post @ g).reshape(-1, 3)
    order = np.argsort(u_dir)
    return {
        "run": str(run_dir), "profile": ((manifest.get("config") or {}).get("simulate") or {}).get("errors"),
        "n_spheres": int(len(seen)), "n_spheres_seen": int(seen.sum()), "n_control_points": int(problem.n_points),
        "residual_sd_mm": float(np.sqrt(variance)), "null_directions": int(len(keep) - keep.sum()),
        "table_u_um": float(np.median(art.u) * 1e3),
        "table_error_rms_um": _similarity_rms(truth.centres, art.centres) * 1e3,
        "directions": [{"u_um": u_dir[k] * 1e3, "data_um": said[k] * 1e3, "table_error_um": true_dir[k] * 1e3,
                        "z": z[k]} for k in order],
        "finer_than_table": {"n": int(finer.sum()), "rms_z": float(np.sqrt(np.mean(z[finer] ** 2)))
                             if finer.any() else None,
                             "corr_data_with_table_error": _correlation(said[finer], true_dir[finer])},
        "with_prior": {
            "u_median_um": float(np.median(np.sqrt(np.diag(post))) * 1e3),
            "error_rms_um": _similarity_rms(truth.centres, art.centres + post_da) * 1e3,
            "move_max_um": float(np.abs(post_da).max() * 1e3),
            "corr_with_table_error": _correlation(post_da.ravel(), true_da),
        },
        "seconds": time.perf_counter() - t0,
    }


def main(argv=None) -> dict:
    ap = add_options(argparse.ArgumentParser(description=__doc__.split("\n\n")[0]))
    ap.add_argument("runs", nargs="+", type=Path, help="run directories (to the bundle step at least)")
    args = ap.parse_args(argv)
    doc = conditions("artefact_refinement", argv, args.smoke)
    doc["runs"] = [refine(r) for r in args.runs]
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
