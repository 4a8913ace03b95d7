"""The uncertainty of the ball-bar lengths: the GUM statement of the mean length, and
each length's expanded uncertainty, ISO 14253-1 verdict and budget."""

from __future__ import annotations

import numpy as np

from fringecal.report.formatting import num, um
from fringecal.report.tables import table
from fringecal.verification.uncertainty import monte_carlo_disagreement

__all__ = ["gum", "length_budget"]

#: ISO 14253-1 verdict of a length -> the words of the page.
ISO = {"conformance": "conformance proven", "non-conformance": "non-conformance proven",
       "uncertainty zone": "inside the uncertainty zone"}


def gum(cal: dict) -> dict | None:
    """The figures of the GUM statement of the mean length, None when none is recorded."""
    g = cal.get("uncertainty") or {}
    if not g:
        return None
    return {"mean": num(cal["mean_length_mm"], ".4f", "mm"), "U": um(g.get("expanded_mm")),
            "k": num(g.get("coverage_factor"), "g"), "u_c": um(g.get("u_combined_mm"), 2),
            "u_a": um(g.get("u_type_a_mm"), 2), "n": g.get("n_repeats"), "u_b": um(g.get("u_type_b_mm"), 2)}


def _monte_carlo(mc: dict | None) -> str:
    if mc is None:
        return "not run"
    return f"{um(mc['u_mc_mm'], 2)} ({mc['ratio']:.2f} x linear; {'agrees' if mc['agree'] else 'DOES NOT AGREE'})"


def _disagreements(unc: dict) -> list[str]:
    """Each length whose Monte Carlo check disagrees, with its numbers."""
    return [monte_carlo_disagreement(e["measurement"], e["monte_carlo"]) for e in unc["lengths"]
            if e.get("monte_carlo") is not None and not e["monte_carlo"]["agree"]]


def _budget(unc: dict) -> dict | None:
    b = unc.get("budget") or {}
    if not b:
        return None
    worst = b["largest_error"]
    rows = [[t, um(b["rms_mm"][t], 2), um(worst["budget_mm"][t], 2)] for t in b["terms"]]
    rows.append(["combined u", um(float(np.sqrt(sum(v ** 2 for v in b["rms_mm"].values()))), 2),
                 um(worst["u_mm"], 2)])
    return {"n_lengths": len(unc["lengths"]), "worst": worst["measurement"], "worst_error": um(worst["error_mm"]),
            "worst_U": um(worst["U_mm"]),
            "table": table(["Contribution", "RMS over lengths", f"At {worst['measurement']}"], rows, left=1)}


def length_budget(unc: dict | None) -> dict | None:
    """Each length's uncertainty and verdict, the lengths not covered, the Monte Carlo
    disagreements and the budget; None when the run recorded no uncertainty per length."""
    if not unc:
        return None
    corrected = any("calibration_bias" in e for e in unc["lengths"])
    rows = [[e["measurement"], um(e["error_mm"])]
            + ([um(e["calibration_bias"]["bias_mm"], 1) if "calibration_bias" in e else "-"] if corrected else [])
            + [um(e["u_mm"], 2), um(e["U_mm"]), _monte_carlo(e.get("monte_carlo")),
               ISO.get(e["iso14253"], e["iso14253"]),
               ("yes", "pass") if e["covered"] else ("NO: not covered by the budget", "fail")]
            for e in unc["lengths"]]
    mc = unc.get("monte_carlo")
    head = ["Length", "Error"] + (["Calibration bias subtracted (bootstrap)"] if corrected else [])
    return {"k": num(unc["coverage_factor"], "g"),
            "table": table(head + ["u (linear)", "U", "u (Monte Carlo, JCGM 101)", "ISO 14253-1", "|error| <= U"],
                           rows, left=1),
            "not_covered": ", ".join(unc["not_covered"]) if unc["not_covered"] else None,
            "disagree": ", ".join(mc["disagree"]) if mc is not None and not mc["all_agree"] else None,
            "disagreements": _disagreements(unc) if mc is not None and not mc["all_agree"] else [],
            "budget": _budget(unc)}
