"""Timing: the wall time of each step of the execution that produced the run, and the
part of it numba spent compiling kernels (the first run on a machine only)."""

from __future__ import annotations

from fringecal.report.formatting import finite, secs
from fringecal.report.rundata import Missing, RunData

__all__ = ["build"]


def _recorded(run: RunData) -> dict:
    """The timings the run's summary recorded (older summaries: the adjustment and total only)."""
    summary = run.maybe_json(run.rd.summary) or {}
    timings = dict(summary.get("timings") or {})
    if not timings and finite(summary.get("bundle_seconds")):
        timings["bundle"] = summary["bundle_seconds"]
    if timings and finite(summary.get("total_seconds")):
        timings["total"] = summary["total_seconds"]
    return timings


def build(run: RunData, timings: dict | None, compile_seconds: dict | None = None) -> dict:
    """Each step's wall time, share of the total and seconds of kernel compilation.

    Parameters
    ----------
    run : the run directory as the report reads it
    timings : step -> seconds (``"total"``: the whole execution) passed in; without
        them those recorded in the run's summary
    compile_seconds : step -> seconds of its time spent compiling numba kernels,
        passed in with ``timings``; otherwise as the summary recorded them

    Returns
    -------
    ``steps`` (name, wall time, share, compilation), ``total``, ``compiled`` (the total
    compilation, "" when none) and ``source`` (where the timings come from).
    """
    source = "this run"
    if not timings:
        timings = _recorded(run)
        compile_seconds = (run.maybe_json(run.rd.summary) or {}).get("compile_seconds")
        source = f"{run.rd.summary.rel} (recorded when the run executed)"
    compile_seconds = {k: float(v) for k, v in (compile_seconds or {}).items() if finite(v) and v > 0}
    if not timings:
        raise Missing(f"no step timings were passed in and {run.rd.summary.rel} records none")
    steps = {str(k).removesuffix("_seconds"): float(v) for k, v in timings.items() if finite(v)}
    total = steps.pop("total") if "total" in steps else sum(steps.values())
    return {"steps": [(k, secs(v), f"{100 * v / total:.0f} %" if total > 0 else "",
                       secs(compile_seconds[k]) if k in compile_seconds else "") for k, v in steps.items()],
            "total": secs(total), "source": source,
            "compiled": secs(sum(compile_seconds.values())) if compile_seconds else ""}
