"""Coverage of the stated ball-bar length uncertainty: how often does the expanded
interval ``length_mm +- U_mm`` of ``verification.json`` hold the TRUE length?

The simulated experiment (the small rig of ``tests/conftest.py``'s
``write_small_config`` with eight of the twelve thesis poses, 1, 2, 3, 5, 7, 9, 11, 12:
the cross-validation on halves needs at least three measurements of every scanner in
each half, which four poses do not give; the lengths' model error comes from the
calibration's delete-one-measurement jackknife; ball-bar positions 1, 4, 9 of
thesis table 6-9, 320 px cameras by default, fringe counts 32/31/30/28/24/16
with 5 steps, control points every pixel) is run ``--seeds`` times without Prefect
(:func:`fringecal.steps.run_pipeline`, one worker, up to the ``verify`` step; the
evaluation and the report are not needed), each seed index ``i`` in a fresh run
directory that is deleted after its results are read. Per seed the draws change::

    simulate.acquisition.seed  = 1000 + i    (camera noise of the artefact stores)
    simulate.verification.seed = 2000 + i    (camera noise of the ball-bar stores)
    simulate.prior.seed        = 3000 + i    (each scanner's prior calibration)
    simulate.errors.seed       = 4000 + i    (the as-built artefact and bar, other errors)

``verification.uncertainty.monte_carlo_draws`` is 0 (the Monte Carlo check of the
linear propagation is not what is tested here and costs time).

The budget describes the simulated world it is stated for (``--profile``):

* ``ideal`` (``simulate.errors.profile: ideal``): the rendered artefact is exactly its
  CMM table at 20 C and the rendered bar is exactly its certificate, so the budget's
  terms for them are zero: ``verification.uncertainty.artefact_u_factor: 0``,
  ``artefact_temperature_u_c: 0``, ``ballbar_temperature_u_c: 0`` and
  ``verification.certificate_u_mm: 0``. The TRUE length is the certified one (centres
  A and B of the run's ``ballbar.csv``).
* ``realistic`` (``simulate.errors.profile: realistic``, :mod:`fringecal.simulate.errors`):
  the budget keeps its defaults (the artefact table's ``u_mm``, 0.5 K on artefact and
  bar, the certificate's 0.4 um at k = 2). The TRUE length is the bar as built, read
  from the run's truth folder (``truth/ballbar.csv``, :class:`fringecal.rundir.TruthDir`);
  a seed whose run has no such file fails with that message rather than falling back
  to the certificate.

Coverage = mean over every length of every seed of ``|length_mm - true| <= U_mm``;
credible when within 0.93-0.97 (k = 2 of a normal distribution: 95.45 %). Reported
with it: the number of lengths, the binomial standard error ``sqrt(p (1 - p) / n)``
(which treats the lengths as independent; the lengths of one seed share one
calibration, so the standard error over seeds -- of the per-seed covered counts,
``seed_cluster_se`` -- is given too), the mean U, the RMS of
``z = (length_mm - true) / u_mm`` (about 1 when u is right) and per seed every length.

BLAS and numba run on one thread unless the environment says otherwise (two profiles
run side by side on the shared 2-core machine).

    PYTHONPATH=. python benchmarks/length_coverage.py --profile ideal --seeds 50 --width 320 \\
        --out benchmarks/results/coverage_ideal.json

``--smoke``: one seed of the tests' small rig (poses 1, 5, 9, 12, ball-bar position 1,
320 px, 4 bootstrap draws): the figures mean nothing, every path runs.

The JSON (``--out``, rewritten after every seed with ``"complete": false`` until the
last; a run stopped by SIGTERM or Ctrl-C says so in ``"stopped"``) holds the exact
command, the load average at start and end, the wall time, the digest of fringecal's
source at start and end (``code_changed_during_run``: the modules are imported during the
first seed, so later edits do not reach a running benchmark, but say the JSON may not
describe today's code), the configuration overrides and the per-seed results; stdout gets a short table (and the
JSON when there is no ``--out``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path

_HERE = Path(__file__).resolve().parent

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")  # steps run without a flow

import numpy as np  # after the thread settings

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(_HERE))
from _common import add_options, conditions  # noqa: E402

#: The budget of each profile (see the module notes).
BUDGETS = {
    "ideal": {"verification": {"certificate_u_mm": 0.0,
                               "uncertainty": {"artefact_u_factor": 0.0, "artefact_temperature_u_c": 0.0,
                                               "ballbar_temperature_u_c": 0.0}}},
    "realistic": {},
}
NOMINAL_COVERAGE = math.erf(2 / math.sqrt(2))  # k = 2, normal: 0.9545
CREDIBLE = (0.93, 0.97)
#: what its result files called this benchmark before (benchmarks/results/coverage_*.json)
FORMER_NAMES = ("coverage",)


def write_small_config(d: Path, width: int, poses=(1, 2, 3, 5, 7, 9, 11, 12), positions=(1, 4, 9)) -> Path:
    """The small simulated thesis rig (:mod:`fringecal.simulate.small_thesis`), eight poses."""
    from fringecal.simulate.small_thesis import write_small_thesis_config

    return write_small_thesis_config(d, width, poses, positions, name="coverage")


def errors_wired() -> bool:
    """Whether ``simulate.errors`` exists in the run config (fringecal.simulate.errors)."""
    from pydantic import ValidationError

    from fringecal.simulate.settings import SimulationConfig

    try:
        return SimulationConfig(errors={"profile": "realistic"}).errors.profile_name == "realistic"
    except (ValidationError, AttributeError):
        return False


def seed_overrides(profile: str, i: int, with_errors: bool, smoke: bool = False) -> dict:
    sim = {"acquisition": {"seed": 1000 + i}, "verification": {"seed": 2000 + i}, "prior": {"seed": 3000 + i}}
    if with_errors:
        sim["errors"] = {"profile": profile, "seed": 4000 + i}
    out = {"simulate": sim, "verification": {"uncertainty": {"monte_carlo_draws": 0}}}
    if smoke:
        out["bundle"] = {"bootstrap_draws": 4}
    from fringecal.config import deep_update

    return deep_update(out, BUDGETS[profile])


def _bar_length(bar, ids) -> float:
    a, b = bar.centres_of(list(ids))
    return float(np.linalg.norm(b - a))


def true_length(rd, profile: str, ids) -> tuple[float, str]:
    """The TRUE bar length of the run and where it came from."""
    if profile == "ideal":
        return _bar_length(rd.ballbar.load(), ids), rd.ballbar.rel
    from fringecal.rundir import ArtefactFile

    f = getattr(rd.truth, "ballbar", None)
    if f is None:
        f = ArtefactFile(rd.root, "truth/ballbar.csv")
    if not f.exists():
        raise FileNotFoundError(f"realistic profile: no as-built ball-bar in the run's truth folder ({f.rel} missing; "
                                f"truth/ holds {sorted(p.name for p in (rd.root / 'truth').iterdir())})")
    return _bar_length(f.load(), ids), f.rel


def run_seed(profile: str, i: int, config_path: Path, workdir: Path, with_errors: bool, keep: bool,
             smoke: bool = False) -> dict:
    from fringecal.run.config import load_run_config
    from fringecal.run.summary import manifest
    from fringecal.rundir import RunDir
    from fringecal.steps import run_pipeline

    overrides = seed_overrides(profile, i, with_errors, smoke)
    out = {"seed_index": i, "seeds": {"acquisition": 1000 + i, "verification": 2000 + i, "prior": 3000 + i,
                                      "errors": 4000 + i if with_errors else None}}
    t0 = time.perf_counter()
    rd = RunDir(workdir / f"{profile}-seed{i:03d}").create()
    try:
        cfg = load_run_config(config_path, overrides=overrides)
        if with_errors:
            out["profile_name"] = cfg.simulate.errors.profile_name
        rd.manifest.save(manifest(cfg))  # as the flow does
        run_pipeline(rd, cfg, workers=1, until="verify")
        v = rd.verification.load()
        bar = rd.ballbar.load()
        ids = bar.ids[:2]
        true, source = true_length(rd, profile, ids)
        cert = _bar_length(bar, ids)
        budget = v["uncertainty"] or {"lengths": [], "coverage_factor": None}
        lengths = []
        for e in budget["lengths"]:
            dev = e["length_mm"] - true
            lengths.append({"measurement": e["measurement"], "length_mm": e["length_mm"],
                            "error_vs_true_mm": dev, "error_vs_certificate_mm": e["error_mm"],
                            "u_mm": e["u_mm"], "U_mm": e["U_mm"], "z": dev / e["u_mm"] if e["u_mm"] > 0 else None,
                            "covered": bool(abs(dev) <= e["U_mm"]), "budget_mm": e["budget_mm"]})
        summary = rd.bundle_summary.load()
        model = summary.get("sensor_model") or {}
        out["sensor_model"] = model.get("model")  # the model the run's data chose (issue 29)
        out["sighting_dispersion"] = {s: d["kappa"] for s, d in (summary.get("sighting_dispersion") or {}).items()}
        out["jackknife"] = summary.get("jackknife")
        positions = sorted({str(p) for p in v.get("recorded_by", {})})
        measured = sorted({e["measurement"].split(":")[0] for e in budget["lengths"]})
        out.update(ok=True, true_length_mm=true, true_source=source, certified_length_mm=cert,
                   coverage_factor=budget["coverage_factor"], n_lengths=len(lengths),
                   n_covered=sum(e["covered"] for e in lengths), lengths=lengths,
                   positions_recorded=positions, positions_not_measured=sorted(set(positions) - set(measured)),
                   failures=v.get("failures", []),
                   not_covered_by_own_verdict=budget.get("not_covered", []))
    except Exception as err:  # noqa: BLE001  (a failed seed is reported, not fatal)
        out.update(ok=False, error=f"{type(err).__name__}: {err}",
                   traceback=traceback.format_exc(limit=8))
    finally:
        out["wall_seconds"] = time.perf_counter() - t0
        if not keep:
            shutil.rmtree(rd.root, ignore_errors=True)
    return out


def summarise(seeds: list) -> dict:
    ok = [s for s in seeds if s["ok"]]
    entries = [e for s in ok for e in s["lengths"]]
    n = len(entries)
    out = {"seeds_run": len(seeds), "seeds_ok": len(ok),
           "seeds_failed": [s["seed_index"] for s in seeds if not s["ok"]], "n_lengths": n}
    if not n:
        return out
    covered = np.array([e["covered"] for e in entries], float)
    p = float(covered.mean())
    z = np.array([e["z"] for e in entries if e["z"] is not None], float)
    dev = np.array([e["error_vs_true_mm"] for e in entries], float)
    # standard error over seeds (lengths of one seed share a calibration): ratio estimator
    counts = np.array([s["n_covered"] for s in ok], float)
    sizes = np.array([s["n_lengths"] for s in ok], float)
    m = len(ok)
    cluster_se = (float(np.sqrt(np.sum((counts - p * sizes) ** 2) / (m * (m - 1))) / sizes.mean())
                  if m > 1 and sizes.mean() > 0 else None)
    out.update(coverage=p, binomial_se=float(np.sqrt(p * (1 - p) / n)),
               binomial_se_at_nominal=float(np.sqrt(NOMINAL_COVERAGE * (1 - NOMINAL_COVERAGE) / n)),
               seed_cluster_se=cluster_se, nominal=NOMINAL_COVERAGE, credible_range=list(CREDIBLE),
               credible=bool(CREDIBLE[0] <= p <= CREDIBLE[1]),
               n_not_covered=int(n - covered.sum()),
               mean_U_mm=float(np.mean([e["U_mm"] for e in entries])),
               mean_u_mm=float(np.mean([e["u_mm"] for e in entries])),
               rms_z=float(np.sqrt(np.mean(z ** 2))) if z.size else None,
               mean_z=float(z.mean()) if z.size else None,
               max_abs_z=float(np.abs(z).max()) if z.size else None,
               rms_error_vs_true_mm=float(np.sqrt(np.mean(dev ** 2))),
               mean_error_vs_true_mm=float(dev.mean()),
               lengths_per_seed=sorted({int(s["n_lengths"]) for s in ok}),
               positions_not_measured={str(s["seed_index"]): s["positions_not_measured"]
                                       for s in ok if s["positions_not_measured"]},
               seconds_per_seed_median=float(np.median([s["wall_seconds"] for s in seeds])),
               sensor_models_chosen={m: sum(s.get("sensor_model") == m for s in ok)
                                     for m in sorted({str(s.get("sensor_model")) for s in ok})})
    return out


def table(doc: dict) -> str:
    s = doc["summary"]
    head = (f"coverage benchmark, profile {doc['profile']}, {s['seeds_ok']}/{s['seeds_run']} seeds ok, "
            f"width {doc['width_px']} px, wall {doc.get('wall_seconds', float('nan')):.0f} s")
    lines = [head]
    if s.get("n_lengths"):
        se = s["seed_cluster_se"]
        cov = f"{s['coverage']:.4f} +- {s['binomial_se']:.4f} (binomial)"
        if se is not None:
            cov += f", +- {se:.4f} (over seeds)"
        verdict = "yes" if s["credible"] else "NO"
        lo, hi = s["credible_range"]
        rms_d = s["rms_error_vs_true_mm"] * 1000
        lines += [f"  lengths              {s['n_lengths']} ({s['n_not_covered']} not covered)",
                  f"  coverage (|d| <= U)  {cov}; nominal {s['nominal']:.4f}, credible {lo}-{hi}: {verdict}",
                  f"  mean U               {s['mean_U_mm'] * 1000:.2f} um (mean u {s['mean_u_mm'] * 1000:.2f} um)",
                  f"  RMS z = d/u          {s['rms_z']:.3f} (mean {s['mean_z']:+.3f}, max |z| {s['max_abs_z']:.2f})",
                  f"  RMS d                {rms_d:.2f} um (mean {s['mean_error_vs_true_mm'] * 1000:+.2f} um)",
                  f"  s per seed (median)  {s['seconds_per_seed_median']:.1f}"]
    if s["seeds_failed"]:
        lines.append(f"  failed seeds         {s['seeds_failed']}")
    if s.get("positions_not_measured"):
        lines.append(f"  positions not measured: {s['positions_not_measured']}")
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", choices=sorted(BUDGETS), default="ideal", help="simulation profile (default ideal)")
    ap.add_argument("--seeds", type=int, default=50, help="number of seeds (default 50)")
    ap.add_argument("--first-seed", type=int, default=0, help="first seed index (default 0)")
    ap.add_argument("--width", type=int, default=320, help="camera width in px, artefact and ball-bar (default 320)")
    ap.add_argument("--poses", default="1,2,3,5,7,9,11,12",
                    help="thesis table 6-1 poses (default 1,2,3,5,7,9,11,12)")
    ap.add_argument("--positions", default="1,4,9", help="thesis table 6-9 ball-bar positions (default 1,4,9)")
    ap.add_argument("--workdir", type=Path, help="where the run directories go (default: a temporary folder)")
    ap.add_argument("--keep", action="store_true", help="keep each run directory")
    args = add_options(ap, "also write the JSON here (rewritten after every seed)").parse_args(argv)
    if args.smoke:
        args.seeds, args.width, args.poses, args.positions = 1, 320, "1,5,9,12", "1"

    with_errors = errors_wired()
    if args.profile != "ideal" and not with_errors:
        ap.error("profile realistic: simulate.errors is not wired into fringecal.simulate.settings.SimulationConfig yet")
    cmd = "PYTHONPATH=. python benchmarks/length_coverage.py " + " ".join(argv if argv is not None else sys.argv[1:])
    poses = [int(x) for x in args.poses.split(",") if x]
    positions = [int(x) for x in args.positions.split(",") if x]
    doc = {**conditions("length_coverage", argv, args.smoke), "command": cmd,
           "complete": False, "profile": args.profile,
           "width_px": args.width, "poses": poses, "ballbar_positions": positions,
           "simulate_errors_wired": with_errors,
           "budget_overrides": BUDGETS[args.profile] or "defaults",
           "seed_overrides_example": seed_overrides(args.profile, args.first_seed, with_errors),
           "cpu_count": os.cpu_count(), "python": platform.python_version(),
           "threads": {v: os.environ.get(v) for v in ("OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")},
           "seeds": []}
    from fringecal.digests import code_digest

    doc["code_digest_start"] = code_digest()  # other engineers edit the tree: the code the run used
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)

    def save():
        if args.out:
            tmp = args.out.with_suffix(args.out.suffix + ".tmp")
            tmp.write_text(json.dumps(doc, indent=1) + "\n")
            tmp.replace(args.out)

    def stop(signum, frame):  # SIGTERM: leave the results so far (marked) and no temporary folders
        raise SystemExit(f"stopped by signal {signum}")

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        return _run_seeds(args, doc, save, poses, positions, with_errors)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_seeds(args, doc, save, poses, positions, with_errors) -> dict:
    from fringecal.digests import code_digest

    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fringecal-coverage-") as tmp:
        tmp = Path(tmp)
        config_path = write_small_config(tmp, args.width, poses, positions)
        workdir = args.workdir or tmp
        workdir.mkdir(parents=True, exist_ok=True)
        for i in range(args.first_seed, args.first_seed + args.seeds):
            try:
                s = run_seed(args.profile, i, config_path, workdir, with_errors, args.keep, args.smoke)
            except (SystemExit, KeyboardInterrupt) as err:
                doc.update(stopped=f"{type(err).__name__}: {err} during seed {i}",
                           wall_seconds=time.perf_counter() - t_start)
                doc["conditions"]["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
                save()
                raise
            doc["seeds"].append(s)
            msg = (f"{s['n_covered']}/{s['n_lengths']} covered, max |z| "
                   f"{max((abs(e['z']) for e in s['lengths'] if e['z'] is not None), default=float('nan')):.2f}"
                   if s["ok"] else f"FAILED {s['error']}")
            print(f"[{args.profile}] seed {i}: {msg} ({s['wall_seconds']:.1f} s, load {os.getloadavg()[0]:.2f})",
                  file=sys.stderr, flush=True)
            doc["summary"] = summarise(doc["seeds"])
            doc["wall_seconds"] = time.perf_counter() - t_start
            save()
    doc["wall_seconds"] = time.perf_counter() - t_start
    doc["conditions"]["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
    doc["code_digest_end"] = code_digest()
    doc["code_changed_during_run"] = doc["code_digest_end"] != doc["code_digest_start"]
    doc["summary"] = summarise(doc["seeds"])
    doc["complete"] = True
    save()
    print(table(doc))
    if not args.out:
        print(json.dumps(doc, indent=1))
    return doc


if __name__ == "__main__":
    main()
