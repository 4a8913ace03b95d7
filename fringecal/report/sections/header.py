"""The page's header: the run, its verdict and its key figures."""

from __future__ import annotations

from fringecal.report.formatting import finite, parts, um
from fringecal.report.rundata import RunData

__all__ = ["build"]


def _key_figures(run: RunData) -> dict:
    """The figures a customer looks at first; each None when the run has not got it."""
    bs = run.maybe_json(run.rd.bundle_summary) or {}
    ver = (run.maybe_json(run.rd.verification) or {}).get("calibrated")
    ver = ver if isinstance(ver, dict) else {}
    eps2 = (bs.get("after") or {}).get("rms_eps2_mm")
    n = bs.get("one_part_in_1p96_sigma")
    error = ver.get("max_abs_error_mm")
    diagonal_parts = None
    if finite(error) and finite(ver.get("volume_diagonal_mm")):
        diagonal_parts = parts(ver["volume_diagonal_mm"] / error if error else float("inf"))
    return {"rms_eps2": um(eps2) if finite(eps2) else None, "accuracy": parts(n) if finite(n) else None,
            "ballbar_error": um(error) if finite(error) else None, "ballbar_parts": diagonal_parts,
            "mpe": um(ver["mpe_mm"]) if finite(ver.get("mpe_mm")) else None}


def build(run: RunData, generated: str, execution: dict) -> dict:
    """The header's facts: name, verdict, source, when it ran and was written, key figures."""
    key = _key_figures(run)
    return {"name": run.name(), "verified": run.verified(), "source": run.source_text(),
            "started": execution.get("created_utc") or "not recorded",
            "digest": str(run.manifest().get("config_digest") or "n/a")[:16], "generated": generated,
            "key": key, "has_key": any(v is not None for v in key.values())}
