"""Verification (ball-bar): the length error per position, the GUM statement and the
uncertainty of each length under ISO 14253-1."""

from __future__ import annotations

from fringecal.acceptance.verdict import run_verdict
from fringecal.report import figures
from fringecal.report.figures import Image
from fringecal.report.formatting import finite, num, parts, truthy, um
from fringecal.report.rundata import Missing, RunData
from fringecal.report.sections.budget import gum, length_budget
from fringecal.report.tables import column_note, pass_cell, table

__all__ = ["build"]

#: How a simulated run placed its ball-bar (``simulate.verification.scheme``).
SCHEMES = {"thesis9": "placed as in thesis section 6.9.3", "vdi7": "placed after the scheme of VDI/VDE 2634"}


def _true_ballbar(run: RunData) -> tuple[dict | None, str]:
    """The ball-bar measured with the true sensors (``evaluation.json``), or why there is none."""
    try:
        ev = run.evaluation()
    except (Missing, ValueError):
        return None, run.no_truth()
    true = ev.get("verification_true_params")
    if not isinstance(true, dict) or not isinstance(true.get("positions"), list):
        return None, f"not evaluated ({run.rd.evaluation.rel} has no ball-bar measured with the true sensors)"
    return true, ""


def _verification(run: RunData) -> dict:
    """``verification.json``; a run without ball-bar recordings says why it has none."""
    try:
        return run.json(run.rd.verification)
    except Missing as why:
        try:
            acq = run.table(run.rd.acquisition)
            if not (acq["kind"] == "ballbar").any():
                why = Missing(f"{why}: the run has no ball-bar recordings, so the calibration is not verified")
        except (Missing, ValueError, KeyError):
            pass
        raise why from None


def _where(run: RunData, cal: dict, recorded: dict) -> str:
    scheme = (run.simulation().get("verification") or {}).get("scheme") if run.source() == "simulated" else None
    n_positions = len(recorded) or len({str(p["measurement"]).split(":")[0] for p in cal["positions"]})
    return f"{n_positions} positions" + (f", {SCHEMES[scheme]}" if scheme in SCHEMES else "")


def _positions(cal: dict, true: dict | None, no_true: str, recorded: dict):
    true_by = {str(p.get("measurement")): p for p in (true or {}).get("positions", [])}
    region = cal.get("observed_region")  # absent: a calibration without observed regions
    rows = []
    for p in cal["positions"]:
        name = str(p["measurement"])
        scanners = recorded.get(name, recorded.get(name.split(":")[0], []))
        row = [name, ", ".join(map(str, scanners)), num(p["length_mm"], ".4f", "mm"), um(p["error_mm"]),
               pass_cell(p["pass"])]
        if region is not None:
            e = region.get(name, region.get(name.split(":")[0]))
            row += [f"{100 * e['fraction']:.0f} %" if e else "-"]
        if true is not None:
            t = true_by.get(name)
            row += [um(t["error_mm"]), pass_cell(t["pass"])] if t else ["not measured", ""]
        rows.append(row)
    heads = ["Position", "Recorded by", "Length", "Error", "Pass"]
    if region is not None:
        heads += ["Outside observed region"]
    if true is not None:
        heads += ["Error (true parameters)", "Pass (true parameters)"]
    else:
        heads += ["True parameters (simulation)"]
        rows = column_note(rows, no_true)
    return table(heads, rows, left=2)


def _ballbar_verdict(ver: dict) -> dict:
    """The ball-bar's part of the run's verdict (each length, its own U, ISO 14253-1)."""
    v = run_verdict(ver, None)
    return {"text": v["word"], "klass": "pass" if v["accepted"] else "fail", "failing": v["failing"] or None}


def build(run: RunData) -> dict:
    """The section from ``verification.json`` and, for a simulated run, ``evaluation.json``."""
    ver = _verification(run)
    cal = ver["calibrated"]
    true, no_true = _true_ballbar(run)
    recorded = ver.get("recorded_by") or {}
    fails = ver.get("failures") or []
    ratio = None
    if true is not None and finite(true.get("max_abs_error_mm")) and true["max_abs_error_mm"] > 0:
        ratio = (f"max |error| {um(true['max_abs_error_mm'])}; calibrated / true = "
                 f"{cal['max_abs_error_mm'] / true['max_abs_error_mm']:.2f}")
    return {
        "where": _where(run, cal, recorded), "within": "yes" if truthy(cal["pass"]) else "no",
        "ballbar": _ballbar_verdict(ver),
        "reference": num(cal["reference_length_mm"], ".4f", "mm"), "mean": num(cal["mean_length_mm"], ".4f", "mm"),
        "mean_error": um(cal.get("mean_error_mm")),
        "max_error": f"{um(cal['max_abs_error_mm'])} = {parts(cal.get('one_part_in'))} of the "
                     f"{num(cal.get('volume_diagonal_mm'), '.1f', 'mm')} volume diagonal",
        "mpe": um(cal.get("mpe_mm")) if finite(cal.get("mpe_mm")) else "none set",
        "counts": (f"{len(recorded)} recorded, {len(cal['positions'])} length(s) measured, {len(fails)} problem(s)"
                   if recorded else None),
        "with_true": ratio if true is not None else no_true,
        "positions": _positions(cal, true, no_true, recorded),
        "figure": Image(figures.ballbar_png(cal, true), "ball-bar length error per position"),
        "gum": gum(cal), "budget": length_budget(ver.get("uncertainty")),
        "failures": table(["Position", "Scanner", "Sphere", "Reason"],
                          [[f.get("position"), f.get("scanner"), f.get("sphere_id"), f.get("reason")] for f in fails],
                          left=4) if fails else None}
