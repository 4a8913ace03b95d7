"""The page's header: the run, its verdict and its key figures."""

from __future__ import annotations

from fringecal.acceptance.verdict import ACCEPTED, NOT_VERIFIED
from fringecal.report.formatting import finite, parts, um
from fringecal.report.rundata import RunData

__all__ = ["build", "verdict_badge"]

#: The badge of each verdict: its text and CSS class.
BADGES = {ACCEPTED: ("PASS", "pass"), NOT_VERIFIED: ("NOT VERIFIED", "none")}


def _component(c: dict) -> str:
    """One failing component in words: what, where, its verdict and its figures."""
    what = f"ball-bar E {c['position']}" if c["test"] == "ball-bar" else f"{c['name']} ({c['scanner']})"
    return (f"{what}: {c['verdict']} (value {um(c['value_mm'])}, U {um(c['U_mm'])}, "
            f"limit {um(c['limit_mm'])})")


def verdict_badge(verdict: dict) -> dict:
    """The badge of a verdict (PASS only when accepted, NOT ACCEPTED, NOT VERIFIED) and
    the sentence under it: what was judged, and every failing component."""
    text, klass = BADGES.get(verdict["word"], (verdict["word"], "fail"))
    limited = [c for c in verdict["components"] if c["limit_mm"] is not None]
    failing = [_component(c) for c in limited if c["verdict"] != "conformance"]
    if verdict["accepted"] is None:
        why = "no verification ran: the run has no ball-bar and no acceptance measurements."
    elif verdict["accepted"]:
        why = (f"accepted: conformance proven under ISO 14253-1 for all {len(limited)} limited components "
               f"({', '.join(verdict['ran'])}).")
    else:
        why = f"not accepted ({verdict['failing']}): " + ("; ".join(failing) or "conformance not proven") + "."
    return {"text": text, "klass": klass, "why": why}


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
    return {"name": run.name(), "verdict": verdict_badge(run.verdict()), "source": run.source_text(),
            "started": execution.get("created_utc") or "not recorded",
            "digest": str(run.manifest().get("config_digest") or "n/a")[:16], "generated": generated,
            "key": key, "has_key": any(v is not None for v in key.values())}
