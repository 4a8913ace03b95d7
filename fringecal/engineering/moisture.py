"""Moisture uptake and hygral expansion (thesis section 3.6.2, eqs. 3-17..3-24).

Moisture content M (percent of the dry mass, eqs. 3-19/3-20) of a plate of
thickness h exposed on both faces follows Fick's second law (eq. 3-21); its
solution for a step in the surrounding humidity at t = 0 is (eq. 3-22)

    G(t) = (M - M0) / (M_inf - M0)
         = 1 - 8/pi^2 sum_n exp(-(2n+1)^2 pi^2 D t / h^2) / (2n+1)^2.

This series converges slowly at early times (the sum is needed to ~1/N at t = 0),
so G is evaluated with the equivalent short-time series (Crank, *The Mathematics
of Diffusion*, eq. 4.18, with ``l = h/2``)

    G(t) = 4 sqrt(tau) [1/sqrt(pi) + 2 sum_{n>=1} (-1)^n ierfc(n / (2 sqrt(tau)))],  tau = D t / h^2,

for tau < 0.05 and with eq. 3-22 above; both are then exact to rounding with a
few terms. Eq. 3-23 is the first term of the short-time series, so for
G <= 0.5 a straight line of G on sqrt(t) through the origin gives D (eq. 3-24).

A tube sealed at its ends takes moisture through its outer wall only: that is
half of a plate exposed on both faces, so pass ``h = 2 x wall``.

Units: time s, thickness mm, D mm^2/s (1 mm^2/s = 1e-6 m^2/s), M percent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.special import erfcx

from fringecal.engineering.errors import EngineeringInputError

__all__ = [
    "moisture_content_pct", "fickian_fraction", "EarlyTimeDiffusion", "FickianFit",
    "moisture_expansion_coefficient", "LengthChange",
]

_TAU_SWITCH = 0.05
_N_LONG = 12   # terms of eq. 3-22 for tau >= 0.05: exp(-pi^2 25^2 0.05) ~ 1e-134
_N_SHORT = 6   # ierfc terms for tau < 0.05: ierfc(6 * 2.24) ~ 1e-80


def moisture_content_pct(mass, dry_mass) -> np.ndarray:
    """Moisture content as a percentage of the dry mass (eqs. 3-19, 3-20).

    >>> moisture_content_pct([10.0, 10.05], 10.0)
    array([0. , 0.5])
    """
    m = np.asarray(mass, float)
    if not np.all(np.asarray(dry_mass, float) > 0):
        raise EngineeringInputError("dry mass must be > 0")
    return (m - dry_mass) / dry_mass * 100.0


def _ierfc(x):
    # ierfc(x) = exp(-x^2)/sqrt(pi) - x erfc(x), written with erfcx to avoid overflow
    return np.exp(-x * x) * (1 / np.sqrt(np.pi) - x * erfcx(x))


def fickian_fraction(t_s, D_mm2_s, h_mm) -> np.ndarray:
    """Fractional uptake G(t) of eq. 3-22, any shape of ``t_s``; 0 for t <= 0.

    >>> tau = np.array([0.0, 0.01, 0.05, 0.2, 1.0])
    >>> fickian_fraction(tau, 1.0, 1.0).round(6)
    array([0.      , 0.225676, 0.504088, 0.887403, 0.999958])
    """
    t = np.asarray(t_s, float)
    if not (D_mm2_s > 0 and h_mm > 0):
        raise EngineeringInputError(f"D ({D_mm2_s}) and h ({h_mm}) must be > 0")
    tau = np.clip(t, 0.0, None) * D_mm2_s / h_mm ** 2
    out = np.zeros_like(tau)
    short = (tau > 0) & (tau < _TAU_SWITCH)
    if short.any():
        ts = tau[short]
        n = np.arange(1, _N_SHORT + 1)
        s = np.sum((-1.0) ** n * _ierfc(n / (2 * np.sqrt(ts[..., None]))), axis=-1)
        out[short] = 4 * np.sqrt(ts) * (1 / np.sqrt(np.pi) + 2 * s)
    long = tau >= _TAU_SWITCH
    if long.any():
        k = 2 * np.arange(_N_LONG) + 1.0
        s = np.sum(np.exp(-(k ** 2) * np.pi ** 2 * tau[long][..., None]) / k ** 2, axis=-1)
        out[long] = 1 - 8 / np.pi ** 2 * s
    return out


def _series(t_s, m_pct):
    t = np.asarray(t_s, float).ravel()
    m = np.asarray(m_pct, float).ravel()
    if t.shape != m.shape:
        raise EngineeringInputError(f"moisture series: {t.size} times but {m.size} contents")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(m))):
        raise EngineeringInputError("moisture series: times and contents must be finite")
    if np.any(t < 0):
        raise EngineeringInputError("moisture series: times must be >= 0 (s since the humidity step)")
    return t, m


@dataclass(frozen=True)
class EarlyTimeDiffusion:
    """D from the initial sqrt(t) slope (eqs. 3-23, 3-24).

    Attributes
    ----------
    D_mm2_s, u_D_mm2_s : float
    slope_per_sqrt_s, u_slope_per_sqrt_s : float
        Slope of G = (M - M0)/(M_inf - M0) on sqrt(t), line through the origin.
    m_inf_pct, m0_pct, h_mm : float
    n_points : int
        Points with t > 0 and G <= max_fraction that were used.
    """

    D_mm2_s: float
    u_D_mm2_s: float
    slope_per_sqrt_s: float
    u_slope_per_sqrt_s: float
    m_inf_pct: float
    m0_pct: float
    h_mm: float
    n_points: int

    @classmethod
    def from_estimate(cls, t_s, m_pct, h_mm: float, m_inf_pct: float | None = None, m0_pct: float = 0.0,
                      u_m_inf_pct: float = 0.0, max_fraction: float = 0.5) -> "EarlyTimeDiffusion":
        """Fit the points with ``G <= max_fraction``.

        ``m_inf_pct`` defaults to the observed content farthest from ``m0_pct`` (eq. 3-19:
        the maximum for uptake, the minimum for desorption); that is low if the series
        has not reached equilibrium, so prefer a fitted M_inf (:class:`FickianFit`)
        when the plateau is not clear.
        """
        t, m = _series(t_s, m_pct)
        if m_inf_pct is None:
            m_inf_pct = float(m[np.argmax(np.abs(m - m0_pct))])
        span = m_inf_pct - m0_pct
        if span == 0:
            raise EngineeringInputError("moisture series: M_inf equals M0; no uptake to fit")
        G = (m - m0_pct) / span
        use = (t > 0) & (G <= max_fraction)
        if use.sum() < 2:
            raise EngineeringInputError(
                f"moisture series: {int(use.sum())} point(s) with t > 0 and M/M_inf <= {max_fraction}; "
                "the early-time slope needs at least 2")
        x, y = np.sqrt(t[use]), G[use]
        k = float(x @ y / (x @ x))
        resid = y - k * x
        u_k = float(np.sqrt((resid @ resid) / (use.sum() - 1) / (x @ x)))
        D = np.pi / 16 * h_mm ** 2 * k ** 2
        rel = np.hypot(u_k / k, u_m_inf_pct / abs(span))
        return cls(float(D), float(2 * D * rel), k, u_k, float(m_inf_pct), float(m0_pct), float(h_mm),
                   int(use.sum()))


@dataclass(frozen=True)
class FickianFit:
    """Nonlinear least-squares fit of eq. 3-22 to a whole series: D and M_inf.

    Attributes
    ----------
    D_mm2_s, u_D_mm2_s : float
    m_inf_pct, u_m_inf_pct : float
    correlation : float
        Correlation of ln D and M_inf.
    m0_pct, h_mm : float
    rms_pct : float
        RMS residual.
    n : int
    """

    D_mm2_s: float
    u_D_mm2_s: float
    m_inf_pct: float
    u_m_inf_pct: float
    correlation: float
    m0_pct: float
    h_mm: float
    rms_pct: float
    n: int

    @classmethod
    def from_estimate(cls, t_s, m_pct, h_mm: float, m0_pct: float = 0.0, D0_mm2_s: float | None = None,
                      m_inf0_pct: float | None = None) -> "FickianFit":
        """Fit ``M = M0 + (M_inf - M0) G(t; D)``; uncertainties from ``s^2 (J^T J)^-1``.

        The fit runs in ln D so D stays positive; starting values default to the
        farthest observed content and the D that puts G = 0.5 at the time the
        series first crosses half of it.
        """
        t, m = _series(t_s, m_pct)
        if t.size < 3:
            raise EngineeringInputError(f"moisture series: {t.size} point(s); fitting D and M_inf needs >= 3")
        if not h_mm > 0:
            raise EngineeringInputError(f"thickness h = {h_mm} mm must be > 0")
        if m_inf0_pct is None:
            m_inf0_pct = float(m[np.argmax(np.abs(m - m0_pct))])
        if D0_mm2_s is None:
            G = (m - m0_pct) / (m_inf0_pct - m0_pct) if m_inf0_pct != m0_pct else np.zeros_like(m)
            half = t[(G >= 0.5) & (t > 0)]
            t_half = float(half.min()) if half.size else float(t.max()) or 1.0
            D0_mm2_s = 0.0492 * h_mm ** 2 / t_half  # G(tau = 0.0492) = 0.5
        scale = max(abs(m_inf0_pct - m0_pct), 1e-12)

        def resid(p):
            return (m0_pct + (p[1] - m0_pct) * fickian_fraction(t, np.exp(p[0]), h_mm) - m) / scale

        sol = least_squares(resid, [np.log(D0_mm2_s), m_inf0_pct], method="lm", x_scale=[1.0, scale],
                            xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
        lnD, m_inf = sol.x
        r = sol.fun * scale
        dof = max(t.size - 2, 1)
        s2 = float(r @ r) / dof
        J = sol.jac * scale
        try:
            cov = s2 * np.linalg.inv(J.T @ J)
        except np.linalg.LinAlgError:
            raise EngineeringInputError("moisture series: D and M_inf cannot both be fitted from these "
                                        "points (singular normal equations)") from None
        u = np.sqrt(np.clip(np.diag(cov), 0, None))
        corr = float(cov[0, 1] / (u[0] * u[1])) if u[0] > 0 and u[1] > 0 else 0.0
        D = float(np.exp(lnD))
        return cls(D, D * float(u[0]), float(m_inf), float(u[1]), corr, float(m0_pct), float(h_mm),
                   float(np.sqrt(np.mean(r ** 2))), int(t.size))

    def predict(self, t_s) -> np.ndarray:
        """Moisture content (percent) at ``t_s``."""
        return self.m0_pct + (self.m_inf_pct - self.m0_pct) * fickian_fraction(t_s, self.D_mm2_s, self.h_mm)


def moisture_expansion_coefficient(delta_length_mm: float, length_mm: float, delta_mass_pct: float) -> float:
    """CME = (dl / l0) / (dM / M0 [%]) (eq. 3-17), per percent of mass.

    >>> moisture_expansion_coefficient(0.0003, 595.8808, 0.05)  # the thesis's order of magnitude
    1.00...e-05
    """
    if length_mm <= 0:
        raise EngineeringInputError(f"length {length_mm} mm must be > 0")
    if delta_mass_pct == 0:
        raise EngineeringInputError("mass change must not be zero")
    return float(delta_length_mm / length_mm / delta_mass_pct)


@dataclass(frozen=True)
class LengthChange:
    """Length record of a rod through a humidity step (table 3-6 style).

    Attributes
    ----------
    length_start_mm, length_end_mm : float
    change_mm : float
        End minus start.
    range_mm : float
        Largest minus smallest length (the thesis's "of the order 0.3 um").
    sd_mm : float
        Standard deviation of the record.
    n : int
    """

    length_start_mm: float
    length_end_mm: float
    change_mm: float
    range_mm: float
    sd_mm: float
    n: int

    @classmethod
    def from_lengths(cls, time, length_mm) -> "LengthChange":
        t = np.asarray(time, float).ravel()
        L = np.asarray(length_mm, float).ravel()
        if t.size != L.size or t.size < 2:
            raise EngineeringInputError("length record: need two or more (time, length) pairs")
        L = L[np.argsort(t, kind="stable")]
        return cls(float(L[0]), float(L[-1]), float(L[-1] - L[0]), float(L.max() - L.min()),
                   float(L.std(ddof=1)), int(L.size))
