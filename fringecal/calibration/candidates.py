"""The sensor-model candidates of a run and how a problem is adjusted with one.

What each candidate frees, and how the run chooses among them, is in
:mod:`fringecal.calibration.models`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fringecal.calibration.bundle import BundleOptions, BundleResult, bundle_adjust
from fringecal.calibration.model import BundleProblem, Evaluator

__all__ = ["CANDIDATES", "SENSOR_MODELS", "SPANS_THIN_PRISM", "FIELD_PRIOR_MM", "prism_free_of", "with_model",
           "fit_model"]

#: the candidates in order of size, with the thin-prism terms each frees (s1, s2, s3, s4)
#: and whether it frees a correction field
CANDIDATES = {"brown14": ((False, False, False, False), False), "thin_prism": ((True, False, True, False), False),
              "thin_prism4": ((True, True, True, True), False), "field": ((False, False, False, False), True)}
SENSOR_MODELS = ("auto", *CANDIDATES)
#: the candidates that adjust the first-order thin-prism terms (the field spans them)
SPANS_THIN_PRISM = ("thin_prism", "thin_prism4", "field")
#: prior standard deviation of each correction-field coefficient (mm): lens errors beyond
#: Brown's terms of a micrometre RMS over the image plane per term
FIELD_PRIOR_MM = 1e-3


def prism_free_of(model: str, n_sensors: int) -> np.ndarray:
    """Thin-prism free flags (n_sensors, 4) of a candidate model."""
    if model not in CANDIDATES:
        raise ValueError(f"unknown sensor model {model!r}; choose one of {', '.join(SENSOR_MODELS)}")
    return np.tile(np.array(CANDIDATES[model][0], bool), (n_sensors, 1))


def with_model(problem: BundleProblem, model: str) -> BundleProblem:
    """``problem`` with the sensors of ``model`` freed (its thin-prism terms, its field and
    the field's prior weight, module :mod:`.models`)."""
    rig = problem.rig.with_prism_free(prism_free_of(model, len(problem.rig.sensors)))
    rig = rig.with_field_free(CANDIDATES[model][1])
    out = problem.with_start(rig=rig)
    if CANDIDATES[model][1]:
        ev = Evaluator(problem)
        e = ev.evaluate(ev.layout.pack_rig(problem.rig, problem.poses), False)
        s0 = e.cost / max(2 * int(e.ok.sum()), 1)
        out = replace(out, field_prior_weight=float(s0 / FIELD_PRIOR_MM ** 2))
    return out


def fit_model(problem: BundleProblem, options: BundleOptions, model: str) -> BundleResult:
    """:func:`.bundle.bundle_adjust` of ``problem`` with the sensors of ``model``."""
    return bundle_adjust(with_model(problem, model), options)
