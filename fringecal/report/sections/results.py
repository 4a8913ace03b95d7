"""Calibration results: the RMS of the adjustment's terms, its figures and diagnoses."""

from __future__ import annotations

from markupsafe import Markup

from fringecal.report.formatting import finite, length, num, parts, secs, um
from fringecal.report.rundata import Missing, RunData
from fringecal.report.tables import column_note, table

__all__ = ["build"]

#: The terms of the objective (thesis section 6.9.2): key in bundle_summary.json, label.
TERMS = (("rms_f_mm", Markup("F (objective, eq. 2-24)")),
         ("rms_eps1_mm", Markup("ε<sub>1</sub> (ray closest approach)")),
         ("rms_eps2_mm", Markup("ε<sub>2</sub> (distance to the CMM sphere)")))


def _rms_table(run: RunData, bs: dict):
    try:
        truth = run.evaluation()
    except (Missing, ValueError):
        truth = None
    rows = []
    for key, label in TERMS:
        row = [label, length(bs["before"][key]), length(bs["after"][key])]
        if truth is not None:
            row.append(length(truth.get(key.replace("_mm", "_mm_true_params"))))
        rows.append(row)
    if truth is None:
        rows = column_note(rows, run.no_truth())
    return table(["RMS over control points", "start values", "after adjustment", "true parameters (simulation)"],
                 rows)


def _diagnoses(bs: dict):
    notes = [(d.get("severity", ""), d.get("kind", ""), d.get("message", "")) for d in bs.get("diagnostics", [])]
    notes += [("warning", "weak direction", w) for w in bs.get("weak_directions", [])]
    # a left-out measurement is one of the diagnoses (its kind says why); a summary that
    # lists it only among dropped_measurements still gets its row
    named = {str(d.get("subject")) for d in bs.get("diagnostics", [])}
    notes += [("warning", "dropped measurement", f"{d.get('measurement')}: {d.get('reason')}")
              for d in bs.get("dropped_measurements", []) if str(d.get("measurement")) not in named]
    return table(["Severity", "Kind", "Message"], notes, left=3) if notes else None


def build(run: RunData) -> dict:
    """The adjustment's figures from ``bundle_summary.json`` (and ``evaluation.json``)."""
    bs = run.json(run.rd.bundle_summary)
    if bs.get("black_boxes_only"):
        raise Missing("a rig of black-box scanners only has no sensor model, so no F, eps1 or eps2; each black "
                      "box's transform is under Scanners")
    sigma = bs.get("sigma_mm") or {}
    dof = bs.get("degrees_of_freedom") or {}
    return {
        "rms": _rms_table(run, bs),
        "accuracy": f"{parts(bs.get('one_part_in_1p96_sigma'))} of the "
                    f"{num(bs.get('volume_diagonal_mm'), '.1f', 'mm')} volume diagonal (1.96 × RMS ε2, 95 %)",
        "control_points": f"{bs.get('n_control_points', 'n/a')} in {bs.get('n_measurements', 'n/a')} artefact poses",
        "freedom": f"{bs.get('n_free_parameters', 'n/a')} / {dof.get('total', 'n/a')}",
        "weights": f"{', '.join(map(str, bs.get('gamma', [])))}; {bs.get('robust_loss', 'n/a')}",
        "iterations": f"{bs.get('iterations', 'n/a')} ({bs.get('evaluations', 'n/a')})",
        "converged": f"{'yes' if bs.get('converged') else 'NO'}: {bs.get('message', '')}",
        "start": bs.get("start"),
        "sigma": f"{um(sigma.get('alpha1'))}, {um(sigma.get('alpha2'))}; {um(sigma.get('sigma0'))}",
        "condition": num(bs.get("condition_number"), ".2e"),
        "wall_time": secs(bs["bundle_seconds"]) if finite(bs.get("bundle_seconds")) else None,
        "diagnoses": _diagnoses(bs)}
