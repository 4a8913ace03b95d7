"""Thermal expansion: CTE from a cooling log, compensation of artefact coordinates.

The CTE of a ball-bar (thesis section 3.6.1, table 3-5) is the slope of the
measured sphere-to-sphere length on temperature (ordinary least squares) divided
by the length at the reference temperature; its standard uncertainty is the
slope's standard error (``s / sqrt(Sxx)``, residual scatter only) over the same
length. Table 3-5 gives 1.897e-6 +- 0.101e-6 per deg C, the thesis's 1.9e-6.

Compensation scales the CMM coordinates (taken at the reference temperature,
20 deg C) isotropically to the measurement temperature about a centre:
``x(T) = c + (1 + alpha (T - T_ref)) (x - c)``. The centre only decides a
translation of the whole artefact (``alpha dT (c1 - c2)``), which the pose
estimate absorbs; inter-sphere distances are the same for any centre. The default
centre is the centroid of the sphere centres, which moves the spheres least on
average and keeps the artefact frame's origin region where it was; pass
``centre=(0, 0, 0)`` to scale about the CMM origin instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.engineering.errors import EngineeringInputError

__all__ = ["CteFit", "compensate_temperature", "DEFAULT_CTE_PER_C", "REFERENCE_TEMPERATURE_C"]

#: Effective CTE of the thesis's rods (section 3.6.1), per deg C.
DEFAULT_CTE_PER_C = 1.9e-6
#: CMM reference temperature, deg C.
REFERENCE_TEMPERATURE_C = 20.0


@dataclass(frozen=True)
class CteFit:
    """Straight line ``length = L_ref + slope (T - T_ref)`` fitted to a cooling log.

    Attributes
    ----------
    slope_mm_per_c, u_slope_mm_per_c : float
    length_ref_mm, u_length_ref_mm : float
        Fitted length at ``reference_c``.
    reference_c : float
    cte_per_c, u_cte_per_c : float
        ``slope / L_ref`` and its standard uncertainty.
    rms_mm : float
        RMS of the residuals.
    n : int
    temperature_c, length_mm : ndarray, shape (n,)
    """

    slope_mm_per_c: float
    u_slope_mm_per_c: float
    length_ref_mm: float
    u_length_ref_mm: float
    reference_c: float
    cte_per_c: float
    u_cte_per_c: float
    rms_mm: float
    n: int
    temperature_c: np.ndarray
    length_mm: np.ndarray

    @classmethod
    def from_estimate(cls, temperature_c, length_mm, reference_c: float = REFERENCE_TEMPERATURE_C) -> "CteFit":
        """Fit length on temperature; needs three or more points at two or more temperatures.

        >>> T = np.array([40.0, 30.0, 25.0, 20.0])
        >>> fit = CteFit.from_estimate(T, 600 * (1 + 2e-6 * (T - 20)))
        >>> round(fit.cte_per_c, 15), fit.u_cte_per_c < 1e-12
        (2e-06, True)
        """
        T = np.asarray(temperature_c, float).ravel()
        L = np.asarray(length_mm, float).ravel()
        if T.shape != L.shape:
            raise EngineeringInputError(f"cooling log: {T.size} temperatures but {L.size} lengths")
        if T.size < 3:
            raise EngineeringInputError(f"cooling log: {T.size} point(s); a line with an uncertainty needs >= 3")
        if not (np.all(np.isfinite(T)) and np.all(np.isfinite(L))):
            raise EngineeringInputError("cooling log: temperatures and lengths must be finite")
        dT = T - T.mean()
        sxx = float(dT @ dT)
        if sxx <= 1e-12 * max(1.0, float(np.abs(T).max()) ** 2):
            raise EngineeringInputError("cooling log: all temperatures are equal; the slope is undetermined")
        slope = float(dT @ (L - L.mean()) / sxx)
        resid = L - (L.mean() + slope * dT)
        s2 = float(resid @ resid) / (T.size - 2)
        u_slope = np.sqrt(s2 / sxx)
        L_ref = float(L.mean() + slope * (reference_c - T.mean()))
        u_L = float(np.sqrt(s2 * (1 / T.size + (reference_c - T.mean()) ** 2 / sxx)))
        return cls(slope, float(u_slope), L_ref, u_L, float(reference_c), slope / L_ref, float(u_slope) / L_ref,
                   float(np.sqrt(np.mean(resid ** 2))), int(T.size), T, L)

    @classmethod
    def from_log(cls, log: pd.DataFrame, reference_c: float = REFERENCE_TEMPERATURE_C) -> "CteFit":
        """From a ThermalLogTable frame (``time_s, temperature_c, length_mm``)."""
        return cls.from_estimate(log["temperature_c"].to_numpy(float), log["length_mm"].to_numpy(float),
                                 reference_c)

    def residuals(self) -> np.ndarray:
        """Measured minus fitted length, mm, shape (n,)."""
        return self.length_mm - (self.length_ref_mm + self.slope_mm_per_c * (self.temperature_c - self.reference_c))

    def summary(self) -> dict:
        return {
            "n": self.n, "reference_c": self.reference_c,
            "slope_um_per_c": self.slope_mm_per_c * 1e3, "u_slope_um_per_c": self.u_slope_mm_per_c * 1e3,
            "length_ref_mm": self.length_ref_mm, "u_length_ref_mm": self.u_length_ref_mm,
            "cte_per_c": self.cte_per_c, "u_cte_per_c": self.u_cte_per_c, "rms_um": self.rms_mm * 1e3,
        }


def compensate_temperature(artefact: Artefact, temperature_c: float, cte_per_c: float = DEFAULT_CTE_PER_C,
                           reference_c: float = REFERENCE_TEMPERATURE_C, centre=None,
                           u_cte_per_c: float = 0.0, u_temperature_c: float = 0.0) -> Artefact:
    """The artefact at ``temperature_c`` from its CMM coordinates at ``reference_c``.

    Parameters
    ----------
    artefact : Artefact
    temperature_c : float
        Temperature of the measurement (acquisition).
    cte_per_c : float
        Effective CTE of the structure (default 1.9e-6, thesis section 3.6.1).
    reference_c : float
        Temperature of the CMM coordinates.
    centre : array_like, shape (3,), optional
        Fixed point of the scaling; default the centroid of the sphere centres.
    u_cte_per_c, u_temperature_c : float
        Standard uncertainties; their effect ``u_s |x - c|`` with
        ``u_s^2 = (dT u_alpha)^2 + (alpha u_T)^2`` is added in quadrature to ``u``.

    Sphere diameters are left as measured: only the centres define the artefact.

    >>> a = Artefact(("1", "2"), [[0, 0, 0], [600, 0, 0]], [50, 50])
    >>> b = compensate_temperature(a, 30.0)
    >>> round(float(np.linalg.norm(b.centres[1] - b.centres[0]) - 600), 9)  # 600 mm * 1.9e-6 * 10
    0.0114
    """
    if not np.isfinite(temperature_c):
        raise EngineeringInputError(f"temperature {temperature_c!r} is not a number")
    c = artefact.centres.mean(axis=0) if centre is None else np.asarray(centre, float).reshape(3)
    dT = float(temperature_c) - float(reference_c)
    r = artefact.centres - c
    u_s = np.hypot(dT * u_cte_per_c, cte_per_c * u_temperature_c)
    u = np.hypot(artefact.u, u_s * np.linalg.norm(r, axis=1))
    moved = artefact.centres + (cte_per_c * dT) * r  # = c + (1 + alpha dT)(x - c), without round-off at dT = 0
    return Artefact(artefact.ids, moved, artefact.diameters, u, f"{artefact.name}@{temperature_c:g}C")
