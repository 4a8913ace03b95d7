"""Acceptance test (VDI/VDE 2634 parts 2 and 3): the certificate, the decision under
ISO 14253-1, the positions in the measurement volume and the value of every position."""

from __future__ import annotations

from fringecal.report import figures
from fringecal.report.figures import Image
from fringecal.report.formatting import finite, num, percent, truthy, um
from fringecal.report.rundata import RunData, guard
from fringecal.report.sections.placements import ballbar_segments, pinholes, placement
from fringecal.report.tables import table

__all__ = ["build"]

#: ISO 14253-1 verdict of acceptance.json -> CSS class of its cell (not limited: plain).
VERDICT_CLASSES = {"conformance": "pass", "non-conformance": "fail", "uncertainty zone": "warn"}


def build(run: RunData) -> dict:
    """The section from ``acceptance.json``; ``absent`` names the file when the run has no acceptance test."""
    f = run.rd.acceptance
    if not f.exists():
        return {"absent": f.rel}
    doc = run.json(f)
    params = doc.get("parameters") or []
    boxes = [str(b) for b in doc.get("black_boxes") or []]
    k = num(doc.get("coverage_factor"), "g")
    return {"absent": None, "standard": doc.get("standard", "VDI/VDE 2634 parts 2 and 3"), "k": k,
            "decision_rule": doc.get("decision_rule", "ISO 14253-1"),
            "certificate": table(["Test", "Scanner", "Positions", "Measured", "Limit (MPE)", f"U (k = {k})",
                                  "Verdict"], [_certificate_row(p, boxes) for p in params], left=2),
            "black_boxes": ", ".join(boxes),
            "decision": _decision(doc, params), "figure": guard(figure, run, doc),
            "per_position": _values(doc), "failures": [_failure(f) for f in doc.get("failures") or []]}


def _verdict_cell(v) -> tuple | str:
    """The verdict cell: coloured as the verification's PASS/FAIL (uncertainty zone: warning)."""
    klass = VERDICT_CLASSES.get(str(v))
    return (str(v), klass) if klass else str(v)


def _certificate_row(p: dict, boxes=()) -> list:
    mpe = p.get("mpe_mm")
    scanner = f"{p.get('scanner')} (black box)" if p.get("scanner") in boxes else p.get("scanner")
    return [f"{p.get('name')} {p.get('title') or ''}".strip(), scanner, p.get("positions"),
            um(p.get("measured_mm")), um(mpe) if mpe is not None else "not limited", um(p.get("U_mm")),
            _verdict_cell(p.get("verdict"))]


def _decision(doc: dict, params: list) -> dict:
    """ACCEPTED or not, why, the outliers excluded, and what the simple comparison would say when it differs."""
    accepted = truthy(doc.get("accepted"))
    limited = [p for p in params if p.get("mpe_mm") is not None]
    if not limited:
        why = "no parameter has a limit (MPE) to conform to"
    elif accepted:
        why = "conformance proven for every limited parameter"
    else:
        short = [f"{p.get('name')} ({p.get('scanner')}): {p.get('verdict')}" for p in limited
                 if p.get("verdict") != "conformance"]
        why = "conformance not proven for " + (", ".join(short) or "every limited parameter")
    within = doc.get("within_mpe")
    differs = within is not None and truthy(within) != accepted
    return {"accepted": accepted, "why": why, "excluded": percent(doc.get("exclude_fraction")),
            "simple": ("accept" if truthy(within) else "not accept") if differs else None}


def _values(doc: dict):
    """The raw value of every position (None when none was measured), with the share of
    its fits' pixels outside the calibration's observed region when the document states
    it (an acceptance.json written before it did has no such column)."""
    def count(n, parameter):
        return int(n) if finite(n) and (n > 0 or parameter not in ("SD", "E")) else "–"

    region = doc.get("observed_region")
    rows = [[v.get("test"), v.get("parameter"), v.get("position"), v.get("scanner"), um(v.get("value_mm")),
             um(v.get("U_mm")), count(v.get("n_points"), v.get("parameter")),
             count(v.get("n_excluded"), v.get("parameter"))] + ([_outside(region, v)] if region is not None else [])
            for v in doc.get("values") or []]
    heads = ["Test", "Parameter", "Position", "Scanner", "Value", "U", "Points", "Excluded"]
    heads += ["Outside observed region"] if region is not None else []
    return table(heads, rows, left=4) if rows else None


def _outside(region: dict, v: dict) -> str:
    """The share of a value's fits' pixels outside the observed region: its scanner's for
    a sphere or a flat (one scanner's store), its position's for a length; "not known"
    where the calibration has no regions or the object was measured in a cloud."""
    position = str(v.get("position"))
    entry = next((o for o in region.get("objects") or [] if o.get("test") == v.get("test")
                  and str(o.get("position")) in (position, position.split(":")[0])), None)
    if entry is None or entry.get("outside") is None:
        return "not known"
    mine = (entry.get("scanners") or {}).get(str(v.get("scanner")))
    if v.get("test") in ("sphere", "flat") and mine and mine.get("points"):
        return f"{100 * mine['outside'] / mine['points']:.0f} %"
    return f"{100 * entry['fraction']:.0f} %"


def _failure(f: dict) -> str:
    return f"{f.get('test')} position {f.get('position')}, scanner {f.get('scanner')}: {f.get('reason')}"


def figure(run: RunData, doc: dict) -> dict:
    """The positions drawn in the world frame; ``missing`` says why when none are stated."""
    positions = doc.get("positions") or []
    if not positions:
        return {"missing": f"No positions to draw: {run.rd.acceptance.rel} states no placements of the objects "
                           "(a recorded data set holds its measurements, not where the objects stood)."}
    standards = run.maybe_json(run.rd.acceptance_standards) or {}
    shapes = [s for s in (placement(p, standards) for p in positions) if s is not None]
    holes = pinholes(run)
    png = figures.acceptance_png(shapes, holes, ballbar_segments(run))
    return {"missing": None, "image": Image(png, "acceptance test positions in the measurement volume"),
            "n": len(shapes), "file": run.rd.acceptance.rel,
            "frame": f"the reference scanner {holes[0][2]}'s frame" if holes else "the world frame"}
