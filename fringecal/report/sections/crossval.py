"""Cross-validation: the two half-calibrations compared (``crossval.json``)."""

from __future__ import annotations

from fringecal.report.formatting import um
from fringecal.report.rundata import RunData
from fringecal.report.tables import table

__all__ = ["build"]

FRAMES = ("scanner", "reference", "world")


def _agreement(frame: dict) -> str:
    return (f"{frame['mean_z2_over_3']:.2f} ({um(frame['rms_difference_mm'])} vs "
            f"{um(frame['rms_predicted_mm'])})")


def build(run: RunData) -> dict:
    """Per scanner the halves' agreement in three frames, the halves and the largest
    parameter difference; only ``reason`` when the split was not possible."""
    cv = run.json(run.rd.crossval)
    if cv.get("verdict") == "not possible":
        return {"not_possible": f"Not possible: {cv.get('reason')}"}
    rows = [[name, *(_agreement(sc[f]) for f in FRAMES),
             (sc["verdict"], "pass" if sc["verdict"] == "consistent" else "fail"), um(sc["model_error_mm"])]
            for name, sc in cv["scanners"].items()]
    par = cv.get("parameters") or {}
    halves = "; ".join(f"{len(h['measurements'])} measurements, eps1/eps2 {um(h['rms_eps1_mm'])} / "
                       f"{um(h['rms_eps2_mm'])}" for h in cv.get("halves") or [])
    return {"not_possible": None, "verdict": cv["verdict"],
            "table": table(["Scanner", "Own frame: z²/3 (RMS difference vs predicted)", "Aligned on the reference",
                            "World (reported only)", "Verdict", "Model error per half"], rows, left=1),
            "halves": halves or None,
            "largest": (f"{par.get('parameter')}: {par.get('max_normalised', 0):.1f} times its combined "
                        f"uncertainty (RMS over all {par.get('rms_normalised', 0):.2f})" if par else None)}
