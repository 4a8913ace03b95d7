"""The run's verdict: one answer from every verification a run ran.

A run verifies its calibration twice at most: the ball-bar verification
(``verification.json``: every length's error against the MPE, with the length's own
uncertainty budget) and the acceptance test (``acceptance.json``: P_F, P_S, SD, E and
F per scanner or for the cell, each against its limit). :func:`run_verdict` turns
the two documents into one verdict, which the summary (``summary.json``'s
``verdict``), the command line (``fringecal run``'s verdict line and exit status 3),
a served run's Prefect state and the report's badge all show. It is a pure function
of the two documents; it lives here, beside the acceptance test, because the report
(same layer) draws its badge from it and the run's summary (above) records it.

Decision rule (ISO 14253-1, stated in :data:`RULE`):

* every ball-bar length is one component: its error against the verification's MPE
  with the U of the length's own budget (``verification.json`` ``uncertainty``);
  conformance is proven when ``|error| + U <= MPE``, non-conformance when
  ``|error| - U > MPE``, else the length is in the uncertainty zone. A length without
  a budget has no known U: its conformance cannot be proven (uncertainty zone), as
  the acceptance test treats an E without U;
* every parameter of the acceptance test is one component, with the verdict
  ``acceptance.json`` gives it (over all its positions: :mod:`.evaluate`); a
  parameter without a limit is ``not limited`` and judges nothing;
* the run is ACCEPTED when every component with a limit has its conformance proven
  and each verification that ran has at least one such component (an acceptance test
  without any limit accepts nothing, as ``acceptance.json`` says); NOT ACCEPTED
  otherwise; NOT VERIFIED when neither verification ran (no ball-bar and no
  acceptance measurements). A NaN value never conforms.

Positions that could not be measured are listed by their documents and do not enter
the verdict (as in ``acceptance.json``).
"""

from __future__ import annotations

import math

from fringecal.acceptance.evaluate import verdict as iso14253

__all__ = ["RULE", "ACCEPTED", "NOT_ACCEPTED", "NOT_VERIFIED", "run_verdict", "ballbar_components",
           "acceptance_components", "failing_text", "unreadable"]

ACCEPTED, NOT_ACCEPTED, NOT_VERIFIED = "ACCEPTED", "NOT ACCEPTED", "NOT VERIFIED"

#: The decision rule, as summary.json states it.
RULE = ("ISO 14253-1 per component: conformance proven when |value| + U <= limit. Components: every ball-bar "
        "length (E, its own budget's U; without a budget U is unknown and conformance is not proven) and every "
        "parameter of the acceptance test (P_F, P_S, SD, E, F as acceptance.json judges them). ACCEPTED when "
        "every limited component's conformance is proven (each verification that ran having at least one "
        "limit); NOT VERIFIED when no verification ran.")

def _number(x) -> float | None:
    """A finite float, else None (JSON has no NaN)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _component(name: str, test: str, scanner: str | None, position: str | None, value, U, limit,
               verdict: str) -> dict:
    return {"name": name, "test": test, "scanner": scanner, "position": position, "value_mm": _number(value),
            "U_mm": _number(U), "limit_mm": _number(limit), "verdict": verdict}


def ballbar_components(verification: dict) -> list[dict]:
    """One component per ball-bar length of ``verification.json``: its error, the U of
    its budget (None without one) and its ISO 14253-1 verdict against the MPE."""
    cal = verification["calibrated"]
    mpe = cal.get("mpe_mm")
    budget = {str(e["measurement"]): e for e in (verification.get("uncertainty") or {}).get("lengths") or []}
    out = []
    for p in cal["positions"]:
        name = str(p["measurement"])
        U = budget[name]["U_mm"] if name in budget else None
        error = float("nan") if p["error_mm"] is None else float(p["error_mm"])
        out.append(_component("E", "ball-bar", "cell", name, error, U, mpe,
                              iso14253(error, float("nan") if U is None else float(U), mpe)))
    return out


def acceptance_components(acceptance: dict) -> list[dict]:
    """One component per parameter of ``acceptance.json``, with the verdict it gives."""
    return [_component(p["name"], "acceptance", p.get("scanner"), p.get("worst_position"), p.get("measured_mm"),
                       p.get("U_mm"), p.get("mpe_mm"), p["verdict"]) for p in acceptance["parameters"]]


def _limited(components: list[dict]) -> list[dict]:
    return [c for c in components if c["limit_mm"] is not None]


def failing_text(components: list[dict], problems: list[str] = ()) -> str:
    """The failing components in brief, per test and parameter: how many of how many
    judged, e.g. ``ball-bar: E 3/3; acceptance: P_F 2/2, SD 1/2``; then any
    verification that judged nothing."""
    groups: dict[str, dict[str, list[int]]] = {}
    for c in _limited(components):
        n = groups.setdefault(c["test"], {}).setdefault(c["name"], [0, 0])
        n[1] += 1
        n[0] += c["verdict"] != "conformance"
    parts = []
    for test, names in groups.items():
        bad = [f"{name} {k}/{n}" for name, (k, n) in names.items() if k]
        if bad:
            parts.append(f"{test}: {', '.join(bad)}")
    return "; ".join(parts + list(problems))


def run_verdict(verification: dict | None, acceptance: dict | None) -> dict:
    """The run's verdict from its ``verification.json`` and ``acceptance.json`` (None: that
    verification did not run); the decision rule is the module's (:data:`RULE`).

    Returns
    -------
    dict
        ``accepted`` (True, False, or None when not verified), ``word`` (ACCEPTED, NOT
        ACCEPTED, NOT VERIFIED), ``failing`` (the failing components in brief, empty when
        accepted), ``ran`` (the verifications judged), ``components`` (name, test,
        scanner, position, value_mm, U_mm, limit_mm, verdict) and ``rule``.

    Examples
    --------
    >>> ver = {"calibrated": {"mpe_mm": 0.1, "positions": [{"measurement": "bb01", "error_mm": 0.03}]},
    ...        "uncertainty": {"lengths": [{"measurement": "bb01", "U_mm": 0.05}]}}
    >>> v = run_verdict(ver, None)
    >>> v["word"], v["components"][0]["verdict"]
    ('ACCEPTED', 'conformance')
    >>> acc = {"parameters": [{"name": "P_F", "scanner": "s1", "measured_mm": 0.6, "U_mm": 0.002,
    ...                        "mpe_mm": 0.5, "verdict": "non-conformance"}]}
    >>> v = run_verdict(ver, acc)
    >>> v["accepted"], v["failing"]
    (False, 'acceptance: P_F 1/1')
    >>> run_verdict(None, None)["word"]
    'NOT VERIFIED'
    """
    components, problems, ran = [], [], []
    for test, doc, extract in (("ball-bar", verification, ballbar_components),
                               ("acceptance", acceptance, acceptance_components)):
        if doc is None:
            continue
        ran.append(test)
        mine = extract(doc)
        if not _limited(mine):
            problems.append(f"{test}: no limit to conform to")
        components += mine
    if not ran:
        return {"accepted": None, "word": NOT_VERIFIED, "failing": "", "ran": [], "components": [], "rule": RULE}
    failing = failing_text(components, problems)
    accepted = not failing
    return {"accepted": accepted, "word": ACCEPTED if accepted else NOT_ACCEPTED, "failing": failing, "ran": ran,
            "components": components, "rule": RULE}


def unreadable(what: str) -> dict:
    """The verdict when a verification's document exists but cannot be read: nothing
    is proven, so the run is not accepted (``what`` says which file and why)."""
    return {"accepted": False, "word": NOT_ACCEPTED, "failing": f"{what} could not be read", "ran": [],
            "components": [], "rule": RULE}
