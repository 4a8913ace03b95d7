"""Sensor parameters: each scanner's 14 + 14 parameters with uncertainties, and the
strongest correlations of the adjustment."""

from __future__ import annotations

import numpy as np
from markupsafe import Markup

from fringecal.report.formatting import PARAM_LABELS, PARAM_UNITS, plus_minus
from fringecal.report.rundata import RunData, guard
from fringecal.report.tables import table
from fringecal.sensor import PARAM_NAMES

__all__ = ["build", "correlations"]


def _value(rig, i: int, j: int):
    value = float(rig.sensors[i].params[j])
    if not rig.free[i, j]:
        return Markup('<span class="fixed">{} (fixed)</span>').format(f"{value:.7g}")
    return plus_minus(value, None if rig.uncertainty is None else float(rig.uncertainty[i, j]))


def build(run: RunData) -> dict:
    """One table per scanner (``calibration.json``) and the correlations (``bundle_summary.json``)."""
    rig = run.load(run.rd.calibration)
    scanners = []
    first = 0
    for sc in rig.scanners:
        sensors = range(first, first + len(sc.sensors))
        first += len(sc.sensors)
        rows = [[PARAM_LABELS[p], PARAM_UNITS[p], *(_value(rig, i, j) for i in sensors)]
                for j, p in enumerate(PARAM_NAMES)]
        heads = ["Parameter", "Unit"] + [f"{s.name} ({s.role})" for s in sc.sensors]
        scanners.append((sc.name, table(heads, rows, left=2)))
    return {"scanners": scanners, "correlations": guard(correlations, run)}


def correlations(run: RunData, k: int = 10) -> dict:
    """The ``k`` strongest correlations between sensor parameters, and how many pairs of
    adjusted parameters (artefact poses included) correlate by more than 0.99."""
    corr = run.json(run.rd.bundle_summary)["correlation"]
    names = list(corr["names"])
    m = np.asarray(corr["matrix"], float)
    iu = np.triu_indices(len(names), 1)
    r = m[iu]
    sensor = np.array([not n.startswith("pose[") for n in names])
    both = sensor[iu[0]] & sensor[iu[1]]
    top = np.flatnonzero(both)[np.argsort(-np.abs(r[both]), kind="stable")[:k]]
    rows = [[names[iu[0][t]], names[iu[1][t]], f"{r[t]:+.4f}"] for t in top]
    return {"table": table(["Parameter", "Parameter", "Correlation"], rows, left=2),
            "n_high": int((np.abs(r) > 0.99).sum())}
