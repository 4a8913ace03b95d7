"""The ball-bar verification of a calibration (thesis 6.9.3, VDI/VDE 2634): the bar
measured in every position's stores with the calibrated sensors (which sphere each
scanner sees found from the data alone, :mod:`.measure`), every length compared with
the certified one (:mod:`.lengths`) and, with the calibration's covariance, given its
own uncertainty budget (:mod:`.uncertainty`).
"""

from __future__ import annotations

from dataclasses import replace

import pandas as pd

from fringecal.artefact import Artefact
from fringecal.rig import Rig
from fringecal.spheres.robust import RejectionConfig
from fringecal.verification.lengths import BallBarResult, ballbar_lengths, evaluate_ballbar
from fringecal.verification.measure import measure_positions, positions_outside
from fringecal.verification.settings import VerificationConfig
from fringecal.verification.uncertainty import ballbar_uncertainty

__all__ = ["verify_ballbar"]


def verify_ballbar(stores: dict, rig: Rig, ballbar: Artefact, rejection: dict, settings: VerificationConfig,
                   diagonal_mm: float, covariance: dict | None = None, halves: dict | None = None,
                   points_verdict: str | None = None, fit_factors: dict | None = None,
                   regions: dict | None = None) -> tuple[pd.DataFrame, pd.DataFrame, BallBarResult, dict | None]:
    """Centres, failures and the evaluated lengths of the ball-bar measured with ``rig``.

    Parameters
    ----------
    stores : position -> scanner -> store path
    ballbar : the bar's certificate (spheres A and B)
    rejection : the run's ``extraction.rejection`` settings
    diagonal_mm : the calibrated volume's diagonal (for "one part in N")
    covariance : the calibration's covariance arrays (``calibration_covariance.npz``); with
        them every length gets its budget, is corrected for the calibration's bias
        (bootstrap) and gets its model error (jackknife), else the budget is None
    halves, points_verdict : the cross-validation's half-calibrations and its verdict
    fit_factors : scanner -> factor on its sphere fits' uncertainty
        (:func:`~fringecal.verification.uncertainty.ballbar_uncertainty`)
    regions : sensor name -> the calibration's observed region of its image plane
        (``calibration.json``); with them the result states, per position, how many of
        the fits' pixels lie outside (:func:`~fringecal.verification.measure.positions_outside`)

    Returns
    -------
    centres, failures, result, budget
    """
    centres, failures, pixels = measure_positions(stores, rig, ballbar, RejectionConfig(**rejection), pixels=True)
    lengths = ballbar_lengths(centres, "ball-bar centres")
    reference_length = float(((ballbar.centres[1] - ballbar.centres[0]) ** 2).sum() ** 0.5)
    budget = None
    if covariance is not None and len(lengths):
        budget = ballbar_uncertainty(centres, pixels, stores, rig, lengths, reference_length, covariance,
                                     settings.uncertainty, settings.mpe_mm,
                                     settings.certificate_u_mm / settings.certificate_k, ballbar.ids[:2],
                                     halves=halves, points_verdict=points_verdict, fit_factors=fit_factors)
        # the lengths corrected for the calibration's bias (bootstrap), when it was estimated
        lengths = lengths.assign(length_mm=[e["length_mm"] for e in budget["lengths"]])
    result = evaluate_ballbar(lengths.length_mm, reference_length, lengths.measurement, settings.mpe_mm,
                              diagonal_mm, settings.certificate_u_mm, settings.certificate_k, settings.coverage_factor)
    if regions:
        result = replace(result, observed_region=positions_outside(stores, rig, pixels, regions))
    return centres, failures, result, budget
