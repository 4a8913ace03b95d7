"""What a run records about itself: the manifest (what it was asked to compute, from
what) and the summary (what came out), plus the check that a run directory is
already up to date with a configuration.

The manifest is deterministic -- resolved configuration, its digest, the digest of
fringecal's source, package versions, the digests of the source's input files -- so
writing it again for the same run changes nothing. What describes one execution
(when, which command, step timings, which steps ran) goes to the summary, with the
run's verdict over its ball-bar verification and acceptance test
(:func:`fringecal.acceptance.verdict.run_verdict`: ``verdict``), the acceptance test's
result (``acceptance``) and the ball-bar's lengths, each with the one U of its budget
(``verification.lengths``; the GUM U of the mean length is ``verification.mean_length``)
and the sensor model the data chose (``sensor_model``: an outcome of the run, so in the
summary, while the manifest holds the setting ``bundle.sensor_model`` that asked for it),
and per scanner what the decoder found in its stacks (``decoding``: valid pixels, phase
noise, the phase ripple it corrected; :func:`fringecal.fringe.measurement.decoding_summary`).
The acceptance block counts, per test, the object positions measured partly and wholly
outside the region of the images the calibration observed
(``acceptance.outside_observed_region``, :func:`fringecal.acceptance.observed.outside_counts`;
``known: false`` and None counts when the calibration carries no regions).
"""

from __future__ import annotations

from fringecal.acceptance.observed import outside_counts
from fringecal.acceptance.verdict import run_verdict
from fringecal.calibration.candidates import SPANS_THIN_PRISM
from fringecal.dataset import DataSet
from fringecal.digests import code_digest, digest_path
from fringecal.fringe.measurement import decoding_summary
from fringecal.rundir import RunDir, package_versions
from fringecal.simulate.source import input_files
from fringecal.steps import current_record, pipeline, step_key

__all__ = ["manifest", "run_summary", "ballbar_summary", "pipeline_status", "source_files", "simulation_profile"]


def source_files(cfg) -> list:
    """The files the run's data source is described by (not its image stacks)."""
    if cfg.source == "simulated":
        return input_files(cfg.simulate)

    ds = DataSet.open(cfg.dataset)
    return [p for p in (ds.root / "dataset.yaml", ds.artefact, ds.rods, ds.sensors_prior, ds.poses_planned,
                        ds.ballbar, ds.acceptance_standards) if p is not None]


def manifest(cfg) -> dict:
    """The manifest of a run of ``cfg`` (a resolved :class:`~fringecal.run.config.RunConfig`)."""
    doc = cfg.model_dump(mode="json")
    return {"config": doc, "config_digest": RunDir.config_digest(doc), "source": cfg.source,
            "code_digest": code_digest(), "versions": package_versions(),
            "inputs": {str(p): digest_path(p) for p in source_files(cfg)}}


def pipeline_status(rd: RunDir, cfg) -> str | None:
    """None if every step of a run of ``cfg`` in ``rd`` is current (its record has
    today's key and its outputs are unchanged), else the first step instance that is
    not (or why the run directory cannot be checked)."""
    try:
        if rd.read_manifest() != manifest(cfg):
            return "manifest.json (configuration, inputs or code changed)"
        for step in pipeline(cfg):
            view = step.view(cfg)
            for item in step.items(rd, view):
                if current_record(step, rd, view, item, step_key(step, rd, view, item)) is None:
                    return f"{step.name}:{item}" if item else step.name
    except (FileNotFoundError, ValueError, KeyError) as err:
        return f"{type(err).__name__}: {err}"
    return None


def _maybe(f) -> dict | None:
    return f.load() if f.exists() else None


def simulation_profile(cfg) -> str | None:
    """Which simulated world a run's figures come from (``ideal``, ``realistic``, or
    ``custom`` / ``realistic+custom`` for edited switches); None for recorded data."""
    if cfg.source != "simulated":
        return None
    return cfg.simulate.errors.profile_name


def ballbar_summary(v: dict) -> dict:
    """The ball-bar figures of ``verification.json``: each length with its one U (its
    budget's, None without a budget) and ISO 14253-1 verdict, and the GUM statement of
    the mean length under ``mean_length`` (the mean's U, not a length's)."""
    cal = v["calibrated"]
    budget = v.get("uncertainty") or {}
    by_name = {str(e["measurement"]): e for e in budget.get("lengths") or []}
    gum = cal["uncertainty"]
    mean = cal["mean_length_mm"]
    return {
        "reference_length_mm": cal["reference_length_mm"], "max_abs_error_mm": cal["max_abs_error_mm"],
        "volume_diagonal_mm": cal["volume_diagonal_mm"], "one_part_in": cal["one_part_in"], "mpe_mm": cal["mpe_mm"],
        "within_mpe": cal["pass"], "n_lengths": len(cal["positions"]), "n_failures": len(v["failures"]),
        "lengths": [{"measurement": str(p["measurement"]), "error_mm": p["error_mm"],
                     "U_mm": by_name.get(str(p["measurement"]), {}).get("U_mm"),
                     "iso14253": by_name.get(str(p["measurement"]), {}).get("iso14253"),
                     "covered": by_name.get(str(p["measurement"]), {}).get("covered")} for p in cal["positions"]],
        "length_coverage_factor": budget.get("coverage_factor"),
        "not_covered": budget.get("not_covered", []),
        "budget_rms_mm": (budget.get("budget") or {}).get("rms_mm"),
        "monte_carlo_agrees": None if budget.get("monte_carlo") is None else budget["monte_carlo"]["all_agree"],
        # each with its numbers (a verification.json from before they were written: the names)
        "monte_carlo_disagreements": [] if budget.get("monte_carlo") is None else
        budget["monte_carlo"].get("disagreements", budget["monte_carlo"]["disagree"]),
        # position -> share of its sphere fits' pixels outside the calibration's observed
        # region (None: a calibration without regions)
        "outside_observed_region": None if cal.get("observed_region") is None else
        {p: e["fraction"] for p, e in cal["observed_region"].items()},
        "mean_length": {"what": "GUM statement of the mean of the lengths (type A over the positions, type B "
                                "from the certificate): the U of the mean, not of any one length",
                        "length_mm": mean, "error_mm": mean - cal["reference_length_mm"],
                        "U_mm": gum["expanded_mm"], "coverage_factor": gum["coverage_factor"]},
    }


def _sensor_model(record: dict | None) -> dict | None:
    """The sensor model a run used, how it was chosen and the residual-pattern verdict
    (``bundle_summary.json``'s ``sensor_model``; None for runs before it existed)."""
    if record is None:
        return None
    pattern = record.get("residual_pattern") or {}
    prism = record.get("prism_wald") or {}
    # the chosen model is too simple when its residual pattern says so, or when the
    # thin-prism terms are present and it adjusts none
    prism_unmodelled = bool(prism.get("present")) and record["model"] not in SPANS_THIN_PRISM
    return {"model": record["model"], "chosen_by": record["chosen_by"],
            "held_out_rms_f_mm": {m: e["rms_f_mm"] for m, e in (record.get("held_out") or {}).items()},
            "residual_pattern_z": pattern.get("z_max"), "residual_pattern_threshold": pattern.get("threshold"),
            "prism_wald_p": prism.get("p_dispersed", prism.get("p")), "prism_wald_kappa": prism.get("kappa"),
            # W less the terms' second-order noise bias, taken only where W alone is significant
            "prism_wald_W": prism.get("W"), "prism_wald_W_corrected": prism.get("W_corrected"),
            "prism_wald_alpha": prism.get("alpha"), "prism_present": prism.get("present"),
            "prism_verdict": prism.get("verdict"),
            "lens_model_too_simple": None if not pattern else bool(pattern.get("too_simple")) or prism_unmodelled,
            "message": pattern.get("message"), "prism_message": prism.get("message")}


def run_summary(rd: RunDir, cfg) -> dict:
    """The figures of a finished run, from its files (missing parts are None), with the
    run's verdict (:func:`fringecal.acceptance.verdict.run_verdict`) over its
    ball-bar verification and acceptance test."""
    b = rd.bundle_summary.load()
    before, after = b.get("before", {}), b.get("after", {})
    v = _maybe(rd.verification)
    a = _maybe(rd.acceptance)
    t = _maybe(rd.evaluation)
    n_measurements = int((rd.acquisition.load()["kind"] == "artefact").sum())
    out = {
        "name": cfg.name, "source": cfg.source, "dataset": None if cfg.dataset is None else str(cfg.dataset),
        "n_measurements": n_measurements,
        # measurements the adjustment left out, each with why (bundle_summary.json)
        "measurements_left_out": [str(d.get("measurement")) for d in b.get("dropped_measurements", [])],
        "n_control_points": b["n_control_points"],
        # a rig of black boxes only has no sensor model: no F, eps1, eps2 (its centres' RMS instead)
        "rms_F_mm_before": before.get("rms_f_mm"), "rms_F_mm_after": after.get("rms_f_mm"),
        "rms_eps1_mm_before": before.get("rms_eps1_mm"), "rms_eps2_mm_before": before.get("rms_eps2_mm"),
        "rms_eps1_mm_after": after.get("rms_eps1_mm"), "rms_eps2_mm_after": after.get("rms_eps2_mm"),
        "black_boxes_only": bool(b.get("black_boxes_only", False)), "rms_centre_mm": b.get("rms_centre_mm"),
        "one_part_in": b.get("one_part_in_1p96_sigma"), "volume_diagonal_mm": b["volume_diagonal_mm"],
        "bundle_seconds": b.get("bundle_seconds", b.get("elapsed_s")),
        "bundle_compile_seconds": b.get("bundle_compile_seconds", 0.0),
        "simulation_profile": simulation_profile(cfg),
        "sensor_model": _sensor_model(b.get("sensor_model")),
        "decoding": decoding_summary(rd.store_summaries()),
        "verification": None, "acceptance": None, "verdict": None, "truth": None,
    }
    if v is not None:
        out["verification"] = ballbar_summary(v)
    if a is not None:
        out["acceptance"] = {"accepted": a["accepted"], "within_mpe": a["within_mpe"],
                             "coverage_factor": a["coverage_factor"], "n_parameters": len(a["parameters"]),
                             "n_failures": len(a["failures"]),
                             # per test, the positions partly and wholly outside the calibration's
                             # observed region (None: not known, never 0)
                             "outside_observed_region": outside_counts(a.get("observed_region"))}
    out["verdict"] = run_verdict(v, a)
    if t is not None:
        out["truth"] = {
            "max_position_error_mm": t["max_position_error_mm"], "max_angle_error_rad": t["max_angle_error_rad"],
            "rms_eps1_mm_true_params": t["rms_eps1_mm_true_params"],
            "rms_eps2_mm_true_params": t["rms_eps2_mm_true_params"],
            "verification_max_abs_error_true_params_mm": (t.get("verification_true_params") or {}).get(
                "max_abs_error_mm")}
    return out
