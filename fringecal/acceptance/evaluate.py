"""The quality parameters of the acceptance test from its raw values, each against its
limit with its expanded uncertainty and the ISO 14253-1 decision rule.

A **value** is one position's result (one row of ``acceptance_values.csv``): test,
parameter, position, scanner, the value (mm) and its expanded uncertainty U. A
**parameter** (one row of the certificate) gathers the values of one quality
parameter of one scanner (VDI/VDE 2634 part 2: P_F, P_S, SD, F inside one scanner's
volume) or of the whole cell (part 3: E, lengths across scanners):

- its **measured value** is the position's value of largest magnitude (P_F and F are
  ranges and never negative; P_S, SD and E keep their sign);
- its **U** is the expanded uncertainty of that position;
- its **verdict** (ISO 14253-1, :func:`verdict`) is *conformance* when every position
  is proven inside the MPE (|value| + U <= MPE), *non-conformance* when any position
  is proven outside it (|value| - U > MPE), the *uncertainty zone* otherwise, and
  *not limited* when the configuration gives no MPE;
- ``within_mpe`` is the guideline's own comparison without uncertainty (|value| <=
  MPE at every position), reported beside the verdict.

Uncertainties of the values (stated per value where it is measured):

- SD and E: the length's task-specific budget (:mod:`fringecal.verification.budget`,
  with the dumbbell's certificate in place of the ball-bar's), expanded with the
  acceptance's coverage factor;
- P_S: the certificate's diameter uncertainty and the fit's (combined in quadrature);
- P_F and F: the object's own form from its certificate, taken as a rectangular
  distribution of full width ``form_mm`` (u = form / sqrt(3) -- the measured range
  holds the object's form as well as the scanner's), and for the flat the
  certificate's uncertainty of its flatness. The calibration's effect on a range is
  what the test measures, so it is no term of its uncertainty.
"""

from __future__ import annotations

import math

import pandas as pd

from fringecal.acceptance.standards import PARAMETERS, AcceptanceLimits, ScannerSpecification
from fringecal.verification.uncertainty import iso14253_verdict

__all__ = ["VALUE_COLUMNS", "DEPTH_COLUMNS", "verdict", "parameters", "certificate", "form_u", "CELL"]

#: Columns of the raw values table.
VALUE_COLUMNS = ["test", "parameter", "position", "scanner", "value_mm", "U_mm", "n_points", "n_excluded"]
#: Where a position's object was, at the calibrated camera's depth (mm): ``depth_mm``
#: (the sphere's centre, the flat's centroid, the dumbbell's farther sphere) and, for
#: the dumbbell, ``depth_near_mm`` (its nearer sphere); empty for E.
DEPTH_COLUMNS = ["depth_near_mm", "depth_mm"]

#: The ``scanner`` of a parameter of the whole cell (part 3).
CELL = "cell"

_ORDER = ("P_F", "P_S", "SD", "E", "F")
_RANGES = ("P_F", "F")


def form_u(form_mm: float) -> float:
    """Standard uncertainty of a range from an object's form deviation ``form_mm``
    (rectangular over its full width).

    >>> round(form_u(0.002) * 1000, 3)
    1.155
    """
    return float(form_mm) / math.sqrt(3.0)


def verdict(value_mm: float, U_mm: float, mpe_mm: float | None) -> str:
    """ISO 14253-1: ``conformance``, ``non-conformance``, ``uncertainty zone`` or
    ``not limited`` (no MPE).

    >>> verdict(0.06, 0.03, 0.1), verdict(0.14, 0.03, 0.1), verdict(-0.09, 0.03, 0.1)
    ('conformance', 'non-conformance', 'uncertainty zone')
    """

    return "not limited" if mpe_mm is None else iso14253_verdict(value_mm, U_mm, mpe_mm)


def _combine(verdicts: list[str]) -> str:
    if "not limited" in verdicts:
        return "not limited"
    if "non-conformance" in verdicts:
        return "non-conformance"
    if all(v == "conformance" for v in verdicts):
        return "conformance"
    return "uncertainty zone"


def parameters(values: pd.DataFrame, limits: AcceptanceLimits, scanners=()) -> list[dict]:
    """One entry per (parameter, scanner) of ``values`` (columns :data:`VALUE_COLUMNS`),
    in the order P_F, P_S, SD, E, F and scanners in ``scanners`` order (then
    :data:`CELL`).

    Examples
    --------
    >>> v = pd.DataFrame([("dumbbell", "SD", "d1", "s1", 0.020, 0.030, 0, 0),
    ...                   ("dumbbell", "SD", "d2", "s1", -0.050, 0.030, 0, 0)], columns=VALUE_COLUMNS)
    >>> p = parameters(v, AcceptanceLimits(SD=0.1))[0]
    >>> p["name"], p["measured_mm"], p["worst_position"], p["verdict"], p["within_mpe"]
    ('SD', -0.05, 'd2', 'conformance', True)
    """
    order = {s: i for i, s in enumerate(list(scanners) + [CELL])}
    out = []
    for (name, scanner), g in sorted(values.groupby(["parameter", "scanner"], sort=False),
                                     key=lambda kv: (_ORDER.index(kv[0][0]), order.get(kv[0][1], len(order)),
                                                     kv[0][1])):
        mpe = getattr(limits, name)
        worst = g.loc[g["value_mm"].abs().idxmax()]
        verdicts = [verdict(v, u, mpe) for v, u in zip(g["value_mm"], g["U_mm"])]
        out.append({
            "name": name, "title": PARAMETERS[name], "scanner": scanner,
            "part": 3 if scanner == CELL else 2, "test": str(worst["test"]), "positions": int(len(g)),
            "measured_mm": float(worst["value_mm"]), "mpe_mm": mpe, "U_mm": float(worst["U_mm"]),
            "verdict": _combine(verdicts),
            "within_mpe": None if mpe is None else bool((g["value_mm"].abs() <= mpe).all()),
            "worst_position": str(worst["position"]),
        })
    return out


def _records(values: pd.DataFrame) -> list[dict]:
    """The values as JSON records, with their depths where known (NaN left out)."""
    cols = VALUE_COLUMNS + [c for c in DEPTH_COLUMNS if c in values]
    out = []
    for r in values[cols].to_dict("records"):
        for c in DEPTH_COLUMNS:
            if c in r and not (isinstance(r[c], float) and math.isfinite(r[c])):
                del r[c]
        out.append(r)
    return out


def certificate(values: pd.DataFrame, limits: AcceptanceLimits, coverage_factor: float, exclude_fraction: float,
                scanners=(), failures: list | None = None, positions: list | None = None,
                specification: ScannerSpecification | None = None) -> dict:
    """The acceptance document (``acceptance.json``): the scanner specification it
    checks (its name, measuring volume and MPEs), the parameters, whether the cell is
    accepted (every limited parameter's conformance proven), the settings it was
    evaluated with, the raw values, the positions and what could not be measured or
    judged."""
    params = parameters(values, limits, scanners)
    limited = [p for p in params if p["mpe_mm"] is not None]
    spec = specification or ScannerSpecification()
    return {
        "standard": "VDI/VDE 2634 parts 2 and 3",
        "decision_rule": "ISO 14253-1 (conformance proven: |value| + U <= MPE)",
        "specification": {"name": spec.name, "depth_range_mm": None if spec.depth_range_mm is None
                          else [float(d) for d in spec.depth_range_mm], "mpe_mm": limits.model_dump()},
        "coverage_factor": float(coverage_factor),
        "exclude_fraction": float(exclude_fraction),
        "accepted": bool(limited) and all(p["verdict"] == "conformance" for p in limited),
        "within_mpe": bool(limited) and all(p["within_mpe"] for p in limited),
        "parameters": params,
        "values": _records(values),
        "positions": positions or [],
        "failures": failures or [],
    }
