"""Cross-validation: the two half-calibrations compared (``crossval.json``), and the
calibration's jackknife (``bundle_summary.json``) with the model error it gives the lengths."""

from __future__ import annotations

import numpy as np

from fringecal.report.formatting import um
from fringecal.report.rundata import RunData
from fringecal.report.tables import table

__all__ = ["build"]

FRAMES = ("scanner", "reference", "world")


def _agreement(frame: dict) -> str:
    return (f"{frame['mean_z2_over_3']:.2f} ({um(frame['rms_difference_mm'])} vs "
            f"{um(frame['rms_predicted_mm'])})")


def _jackknife(bundle: dict | None, verification: dict | None) -> str | None:
    """The jackknife's replicas (``bundle_summary.json``) and, from the verification, the
    model-error term it gave the lengths (RMS and largest)."""
    jk = (bundle or {}).get("jackknife")
    if not jk:
        return None
    text = (f"{jk['replicas']} replicas, each without one measurement, in the data and in "
            f"{jk.get('noise_draws', 0)} worlds of noise alone")
    if jk.get("skipped"):
        text += f" (none without {', '.join(jk['skipped'])}: " + "; ".join(jk["skipped"].values()) + ")"
    lengths = ((verification or {}).get("uncertainty") or {}).get("lengths") or []
    terms = [(e["measurement"], e["jackknife"]) for e in lengths if "jackknife" in e]
    if terms:
        worst = max(terms, key=lambda t: t[1]["model_error_mm"])
        rms = float(np.sqrt(np.mean([t[1]["model_error_mm"] ** 2 for t in terms])))
        text += (f"; model error of the ball-bar lengths (their spread over the replicas beyond the noise "
                 f"worlds', at the calibration term's scale) {um(rms)} RMS, largest "
                 f"{um(worst[1]['model_error_mm'])} at {worst[0]}")
    elif jk["replicas"] < jk.get("min_replicas", 0):
        text += f": fewer than {jk['min_replicas']}, no model-error term"
    return text


def build(run: RunData) -> dict:
    """Per scanner the halves' agreement in three frames, the halves, the largest
    parameter difference and the jackknife; only ``reason`` (and the jackknife) when
    the split was not possible."""
    cv = run.json(run.rd.crossval)
    jackknife = _jackknife(run.maybe_json(run.rd.bundle_summary), run.maybe_json(run.rd.verification))
    if cv.get("verdict") == "not possible":
        return {"not_possible": f"Not possible: {cv.get('reason')}", "jackknife": jackknife}
    rows = [[name, *(_agreement(sc[f]) for f in FRAMES),
             (sc["verdict"], "pass" if sc["verdict"] == "consistent" else "fail"), um(sc["model_error_mm"])]
            for name, sc in cv["scanners"].items()]
    par = cv.get("parameters") or {}
    halves = "; ".join(f"{len(h['measurements'])} measurements, eps1/eps2 {um(h['rms_eps1_mm'])} / "
                       f"{um(h['rms_eps2_mm'])}" for h in cv.get("halves") or [])
    return {"not_possible": None, "verdict": cv["verdict"],
            "table": table(["Scanner", "Own frame: z²/3 (RMS difference vs predicted)", "Aligned on the reference",
                            "World (reported only)", "Verdict", "Model error per half"], rows, left=1),
            "halves": halves or None, "jackknife": jackknife,
            "largest": (f"{par.get('parameter')}: {par.get('max_normalised', 0):.1f} times its combined "
                        f"uncertainty (RMS over all {par.get('rms_normalised', 0):.2f})" if par else None)}
