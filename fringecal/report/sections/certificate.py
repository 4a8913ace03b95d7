"""The report's first page, the calibration certificate: who and what it is for (the
identity block), the run's one verdict with its decision rule and every component
(P_F, P_S, SD, F per scanner, E of the cell, the ball-bar lengths) against the stated
specification, the traceability chain from the artefact's CMM certificate to the
lengths, how many acceptance objects were measured outside the region of the images the
calibration observed, the certificate's number and the approval fields.

Each figure comes from the run directory's files: the identity from the run
configuration's ``certificate`` section (a data set's ``dataset.yaml`` supplies it,
:class:`~fringecal.acceptance.identity.CertificateIdentity`), the verdict from
``verification.json`` and ``acceptance.json`` (:func:`fringecal.acceptance.verdict.run_verdict`),
the specification from ``acceptance.json``, the chain from the artefact, the
calibration and the verification. The number is derived from the digests of the
inputs, the identity and the result documents
(:func:`fringecal.acceptance.identity.certificate_number`).
"""

from __future__ import annotations

import hashlib

from fringecal.acceptance.evaluate import PARAMETERS
from fringecal.acceptance.identity import certificate_number
from fringecal.acceptance.observed import outside_counts
from fringecal.acceptance.verdict import ACCEPTED, NOT_VERIFIED
from fringecal.digests import digest_value
from fringecal.report.formatting import finite, length, num, um
from fringecal.report.rundata import RunData

__all__ = ["build", "verdict_badge", "number_parts", "observed_line", "VERDICT_CLASSES"]

#: The badge of each verdict: its text and CSS class.
BADGES = {ACCEPTED: ("ACCEPTED", "pass"), NOT_VERIFIED: ("NOT VERIFIED", "none")}
#: ISO 14253-1 verdict -> CSS class of its cell.
VERDICT_CLASSES = {"conformance": "pass", "non-conformance": "fail", "uncertainty zone": "warn"}
#: Order of the rows of the verdict table.
ORDER = ("P_F", "P_S", "SD", "E", "F")
#: What a blank field of the identity block shows (a line to fill in by hand).
BLANK = ""


def _component(c: dict) -> str:
    """One failing component in words: what, where, its verdict and its figures."""
    what = f"ball-bar E {c['position']}" if c["test"] == "ball-bar" else f"{c['name']} ({c['scanner']})"
    return (f"{what}: {c['verdict']} (value {um(c['value_mm'])}, U {um(c['U_mm'])}, "
            f"limit {um(c['limit_mm'])})")


#: Up to this many failing components are named one by one on the certificate; more are
#: counted per parameter (the verdict table shows each), so that page one stays one page.
NAMED = 4


def verdict_badge(verdict: dict) -> dict:
    """The badge of a verdict (ACCEPTED, NOT ACCEPTED, NOT VERIFIED) and the sentence
    under it: what was judged, and the failing components (each named when there are
    at most :data:`NAMED`, else counted per test and parameter)."""
    text, klass = BADGES.get(verdict["word"], (verdict["word"], "fail"))
    limited = [c for c in verdict["components"] if c["limit_mm"] is not None]
    failing = [_component(c) for c in limited if c["verdict"] != "conformance"]
    if verdict["accepted"] is None:
        why = "no verification ran: the run has no ball-bar and no acceptance measurements."
    elif verdict["accepted"]:
        why = (f"conformance proven under ISO 14253-1 for all {len(limited)} limited components "
               f"({', '.join(verdict['ran'])}).")
    elif len(failing) > NAMED:
        why = (f"not accepted ({verdict['failing']}): conformance not proven for {len(failing)} of {len(limited)} "
               "limited components (the table below).")
    else:
        why = f"not accepted ({verdict['failing']}): " + ("; ".join(failing) or "conformance not proven") + "."
    return {"text": text, "klass": klass, "why": why}


def _file_sha(f) -> str | None:
    return hashlib.sha256(f.path.read_bytes()).hexdigest() if f.path.is_file() else None


def number_parts(run: RunData) -> dict[str, str]:
    """What the certificate's number is derived from: the inputs' digests (the
    manifest's, without the machine's paths), the identity block's digest and the
    SHA-256 of the result documents (calibration, verification, acceptance)."""
    rd = run.rd
    inputs = run.manifest().get("inputs") or {}
    digests = sorted(str(d.get("sha256", "") if isinstance(d, dict) else d) for d in inputs.values())
    parts = {"inputs": digest_value(digests), "identity": digest_value(run.config().get("certificate") or {})}
    for f in (rd.calibration, rd.verification, rd.acceptance):
        sha = _file_sha(f)
        if sha is not None:
            parts[f.rel] = sha
    return parts


def _reference(ref) -> str:
    """A reference certificate in words: number, date, issuer (blank when not stated)."""
    if not isinstance(ref, dict) or not ref.get("number"):
        return BLANK
    extra = ", ".join(str(ref[k]) for k in ("date", "issuer") if ref.get(k))
    return f"{ref['number']}" + (f" ({extra})" if extra else "")


def _scanners(run: RunData, serials: dict) -> list[str]:
    """Each scanner of the calibration with its serial number (named in the identity)."""
    try:
        names = [s.name for s in run.load(run.rd.calibration).scanners]
    except Exception:  # noqa: BLE001 -- a missing or malformed calibration: the identity's names
        names = list(serials)
    return [f"{n}: serial {serials[n]}" if serials.get(n) else f"{n}: serial ______" for n in names]


def _identity(run: RunData, ident: dict, execution: dict) -> list[tuple[str, object]]:
    temps = ident.get("temperatures_c") or {}
    sim_t = run.simulation().get("temperature_c")
    if not temps and finite(sim_t):
        temps = {"artefact": sim_t}
    started = str(execution.get("created_utc") or "")[:10]
    return [("Customer", ident.get("customer") or BLANK), ("Cell", ident.get("cell") or BLANK),
            ("Place", ident.get("place") or BLANK),
            ("Date of calibration", str(ident.get("date") or "") or (f"{started} (run started)" if started else BLANK)),
            ("Operator", ident.get("operator") or BLANK),
            ("Scanners", _scanners(run, ident.get("scanners") or {})),
            ("Artefact (CMM) certificate", _reference(ident.get("artefact_certificate"))),
            ("Ball-bar certificate", _reference(ident.get("ballbar_certificate"))),
            ("Acceptance objects certificate", _reference(ident.get("standards_certificate"))),
            ("Temperatures", ", ".join(f"{k} {num(v, '.1f')} °C" for k, v in temps.items()) or BLANK),
            ("Data source", run.source_text())]


def _combined(verdicts: list[str]) -> str:
    if any(v == "non-conformance" for v in verdicts):
        return "non-conformance"
    if verdicts and all(v == "conformance" for v in verdicts):
        return "conformance"
    if verdicts and all(v == "not limited" for v in verdicts):
        return "not limited"
    return "uncertainty zone"


def _cell(components: list[dict], positions: int | None = None) -> dict:
    """One cell of the verdict table: the component of largest magnitude, its U and the
    verdict over all of them."""
    worst = max(components, key=lambda c: abs(c["value_mm"]) if finite(c["value_mm"]) else float("inf"))
    verdict = _combined([c["verdict"] for c in components])
    n = positions if positions is not None else len(components)
    return {"value": um(worst["value_mm"]), "U": um(worst["U_mm"]), "verdict": verdict,
            "klass": VERDICT_CLASSES.get(verdict, ""), "n": n}


def _table(run: RunData, verdict: dict) -> dict | None:
    """The verdict table: one row per quality parameter (and the ball-bar lengths), one
    column per scanner, the limit; None when nothing was judged."""
    comps = verdict["components"]
    if not comps:
        return None
    acc = run.maybe_json(run.rd.acceptance) or {}
    positions = {(p.get("name"), p.get("scanner")): p.get("positions") for p in acc.get("parameters") or []}
    try:
        scanners = [s.name for s in run.load(run.rd.calibration).scanners]
    except Exception:  # noqa: BLE001 -- the components' own scanners
        scanners = []
    for c in comps:
        if c["scanner"] not in scanners and c["scanner"] != "cell":
            scanners.append(c["scanner"])
    rows = []
    for name in ORDER:
        mine = [c for c in comps if c["name"] == name and c["test"] == "acceptance"]
        if not mine:
            continue
        limit = next((c["limit_mm"] for c in mine if c["limit_mm"] is not None), None)
        cells = {s: _cell([c for c in mine if c["scanner"] == s], positions.get((name, s)))
                 for s in scanners if any(c["scanner"] == s for c in mine)}
        cell = _cell([c for c in mine if c["scanner"] == "cell"], positions.get((name, "cell"))) \
            if any(c["scanner"] == "cell" for c in mine) else None
        rows.append({"name": name, "title": PARAMETERS[name], "cells": cells, "cell": cell,
                     "limit": length(limit) if limit is not None else "not limited"})
    bar = [c for c in comps if c["test"] == "ball-bar"]
    if bar:
        limit = next((c["limit_mm"] for c in bar if c["limit_mm"] is not None), None)
        rows.append({"name": "ball-bar", "title": f"lengths of the ball-bar verification ({len(bar)} positions)",
                     "cells": {}, "cell": _cell(bar), "limit": length(limit) if limit is not None else "not limited"})
    return {"scanners": scanners, "rows": rows}


def _specification(run: RunData) -> dict | None:
    """The specification the cell is judged against: its name, measuring volume and the
    MPEs (``acceptance.json``, else the run configuration's ``acceptance``)."""
    acc = run.maybe_json(run.rd.acceptance) or {}
    spec = acc.get("specification")
    if not isinstance(spec, dict):
        cfg = run.config().get("acceptance") or {}
        spec = {**(cfg.get("specification") or {}), "mpe_mm": cfg.get("limits")} if cfg else None
    if not spec:
        return None
    depth = spec.get("depth_range_mm")
    volume = (f"depths {num(depth[0], '.0f')}-{num(depth[1], '.0f')} mm along each scanner's camera axis"
              if isinstance(depth, list) and len(depth) == 2 else "the volume the calibration covers")
    mpe = spec.get("mpe_mm") or {}
    limits = ", ".join(f"{k} {length(mpe[k])}" for k in ORDER if finite(mpe.get(k)))
    return {"name": spec.get("name") or "not named (the run configuration's acceptance limits)", "volume": volume,
            "limits": limits or "none"}


#: How each test's positions are named in the observed-region line.
TEST_WORDS = {"sphere": "spheres", "flat": "flats", "dumbbell": "dumbbells", "ballbar": "ball-bar (E)"}


def _positions(n: int) -> str:
    return f"{n} position" + ("" if n == 1 else "s")


def observed_line(doc: dict | None) -> str | None:
    """The certificate's line on the observed region: per test, the positions measured
    partly outside it (wholly outside, largest share), from ``acceptance.json``
    (:func:`fringecal.acceptance.observed.outside_counts`); "not known" where the
    calibration carries no regions (or the document predates the count), never 0;
    None without an acceptance test or objects on image planes.

    >>> observed_line({"observed_region": {"known": False, "objects": [{"test": "flat", "outside": None}]}})
    'not known: the calibration records no region of its images (flats: 1 position)'
    """
    if doc is None:
        return None
    if "observed_region" not in doc:
        return "not known: acceptance.json does not count them (written before the count existed)"
    counts = outside_counts(doc["observed_region"])["tests"]
    if not counts:
        return None
    if all(c["partly_outside"] is None for c in counts.values()):
        listed = ", ".join(f"{TEST_WORDS[t]}: {_positions(c['positions'])}" for t, c in counts.items())
        return f"not known: the calibration records no region of its images ({listed})"
    parts = []
    for t, c in counts.items():
        if c["partly_outside"] is None:
            parts.append(f"{TEST_WORDS[t]} not known")
        elif c["partly_outside"] == 0:
            parts.append(f"{TEST_WORDS[t]} 0 of {_positions(c['positions'])}")
        else:
            parts.append(f"{TEST_WORDS[t]} {c['partly_outside']} of {_positions(c['positions'])} "
                         f"({c['wholly_outside']} wholly, "
                         f"up to {100 * c['max_fraction']:.0f} %)")
    return ("positions measured partly outside the region of the images the calibration observed, where its "
            "model extrapolates (share of their fits' pixels): " + "; ".join(parts))


def _chain(run: RunData, ident: dict) -> list[dict]:
    """The traceability chain: CMM certificate -> artefact -> calibration -> lengths."""
    rd = run.rd
    chain = [{"step": "CMM certificate", "what": _reference(ident.get("artefact_certificate")) or "not stated"}]
    try:
        art = run.load(rd.artefact)
        chain.append({"step": "Artefact", "what": f"{len(art)} spheres, {rd.artefact.rel} "
                                                   f"SHA-256 {(_file_sha(rd.artefact) or '')[:12]}"})
    except Exception:  # noqa: BLE001 -- shown as not available
        chain.append({"step": "Artefact", "what": f"not available ({rd.artefact.rel})"})
    bs = run.maybe_json(rd.bundle_summary) or {}
    cal = _file_sha(rd.calibration)
    chain.append({"step": "Calibration", "what": (
        f"{bs.get('n_control_points', 'n/a'):,} control points in {bs.get('n_measurements', 'n/a')} measurements, "
        f"RMS ε2 {um((bs.get('after') or {}).get('rms_eps2_mm'))}; {rd.calibration.rel} SHA-256 {cal[:12]}"
        if cal and bs else f"not available ({rd.calibration.rel})")})
    ver = (run.maybe_json(rd.verification) or {}).get("calibrated") or {}
    bar = _reference(ident.get("ballbar_certificate"))
    if ver:
        n = len(ver.get("positions") or [])
        chain.append({"step": "Lengths", "what": (
            f"ball-bar {num(ver.get('reference_length_mm'), '.4f', 'mm')}"
            + (f" (certificate {bar})" if bar else "") + f", {n} lengths measured, largest |error| "
            f"{um(ver.get('max_abs_error_mm'))}")})
    else:
        chain.append({"step": "Lengths", "what": "not verified (no ball-bar recordings)"})
    return chain


def build(run: RunData, generated: str, execution: dict) -> dict:
    """The certificate page's facts."""
    ident = run.config().get("certificate") or {}
    verdict = run.verdict()
    sim = run.source() == "simulated"
    profile = (run.simulation().get("errors") or {}).get("profile") if sim else None
    return {"name": run.name(), "number": certificate_number(number_parts(run)), "verdict": verdict_badge(verdict),
            "rule": verdict["rule"], "identity": _identity(run, ident, execution), "spec": _specification(run),
            "table": _table(run, verdict), "chain": _chain(run, ident),
            "observed": observed_line(run.maybe_json(run.rd.acceptance)),
            "operator": ident.get("operator") or BLANK, "approved_by": ident.get("approved_by") or BLANK,
            "remarks": ident.get("remarks"),
            "simulated": (f"A simulated run (simulation profile {profile or 'ideal'}): this certificate "
                          "certifies no physical cell.") if sim else None,
            "started": execution.get("created_utc") or "not recorded", "generated": generated,
            "digest": str(run.manifest().get("config_digest") or "n/a")[:16]}
