"""Task-specific uncertainty of a measured length (GUM, and JCGM 101 Monte Carlo).

A ball-bar length (or any distance between two measured sphere centres) is

    L = | c_A - c_B |,   c = fixed-radius least-squares sphere through the points
                         X_i(theta) triangulated from the pixels the fit kept,

with theta the sensor parameters of the scanners that saw the spheres. Its inputs and
their standard uncertainties:

* ``calibration``: theta from the adjustment, covariance ``Cov_theta`` (sensors and
  poses adjusted together; the sensors' block, :mod:`fringecal.calibration.propagation`);
  with correction fields (:mod:`fringecal.lens.field`) theta holds their coefficients
  too: a coefficient moves a point as the principal point does, weighted by its basis
  function at the pixel (``dX/da_j = phi_j,x dX/dxi_h + phi_j,y dX/deta_h``), so its
  column comes from the same differences (this term, the two artefact terms and the
  Monte Carlo check's draws);
* ``artefact CMM``: the artefact table's own uncertainty moves theta by ``S Sigma_a S^T``
  (:mod:`fringecal.calibration.artefact_sensitivity`);
* ``artefact temperature``: a relative scale ``cte * u_T`` of the artefact moves theta
  along the scale response;
* ``sphere fits``: each fit's own noise, ``(A^T A)^-1 (sum r_i^2 a_i a_i^T) (A^T A)^-1
  n / (n - 3)`` (A the unit normals, r the fit's residuals): the sandwich estimator,
  because a point's noise along the normal grows towards the rim (the camera ray meets
  the surface obliquely), so the plain ``s^2 (A^T A)^-1`` understates the lateral
  components (by ~20 % for a ball-bar sphere);
* ``bar certificate`` and ``bar temperature``: the reference length's own uncertainty;
* ``model error (cross-validation)``: the spread of the length over the calibration's
  delete-one-measurement jackknife beyond the spread the same jackknife shows in worlds
  of noise alone, at the ``calibration`` term's scale (:func:`jackknife_model_error`):
  what differs between the measurements and the model leaves out; 0 when the replicas
  scatter no more than the noise makes them.

Linear propagation (GUM): the centre moves with the points as ``dc = (A^T A)^-1 A^T
(n_i . dX_i)`` (the fixed-radius fit linearised), ``dX_i/dtheta`` by central
differences of the triangulation, and ``dL = e . (dc_A - dc_B)`` with ``e`` the unit
vector from B to A. Monte Carlo (JCGM 101): theta drawn from the sum of the three
parameter covariances, every kept pixel re-triangulated, Gaussian noise of the fit's
RMS added along each normal, both spheres refitted (Gauss-Newton from the measured
centre), the length plus the reference-length draws. The two agree (JCGM 101 clause 8)
when both ends of the linear 95 % interval lie within ``delta`` of the Monte Carlo
interval's, ``delta`` the numerical tolerance of the standard uncertainty stated to
two significant digits, or, where the Monte Carlo's own scatter over its blocks of
draws exceeds that, within twice that scatter (reported as such).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fringecal.calibration.propagation import (
    ParameterCovariances,
    extended_indices,
    field_jacobian,
    point_jacobian,
    scanner_with,
    triangulate_mm,
    with_principal_point_steps,
)
from fringecal.lens.field import FIELD_DEGREE, field_terms
from fringecal.rig import Scanner
from fringecal.spheres.fit import centre_sandwich_covariance

__all__ = ["SightingPoints", "SightingModel", "sighting_model", "LengthBudget", "length_budget", "field_gradient",
           "monte_carlo_lengths", "refitted_length", "length_gradient", "numerical_tolerance", "validate_linear",
           "BUDGET_TERMS", "bootstrap_bias", "block_params", "jackknife_spread", "jackknife_variance",
           "jackknife_model_error"]

#: the contributions of a length's budget, in report order
BUDGET_TERMS = ("calibration", "calibration bias correction", "artefact CMM", "artefact temperature", "sphere fits",
                "bar certificate", "bar temperature", "model error (cross-validation)")


@dataclass(frozen=True)
class SightingPoints:
    """The pixels a sphere fit kept, in image-plane mm, and its result.

    scanner : the scanner (camera at the store's resolution) in the world frame
    block : index of the scanner in the rig (its 28 parameters sit at 28 * block)
    cam_mm, prj_mm : (n, 2); centre : (3,); radius_mm, rms_mm : float
    """

    scanner: Scanner
    block: int
    cam_mm: np.ndarray = field(repr=False)
    prj_mm: np.ndarray = field(repr=False)
    centre: np.ndarray
    radius_mm: float
    rms_mm: float

    @property
    def params(self) -> np.ndarray:
        """(28,) the scanner's camera then projector parameters."""
        return np.concatenate([self.scanner.camera.params, self.scanner.projector.params])


def block_params(sensor_params: np.ndarray, block: int) -> np.ndarray:
    """(28,) scanner ``block``'s parameters out of per-sensor ones (n_sensors, 14),
    the sensors in rig order (camera, projector of each scanner); out of replicas with
    correction fields (n_sensors, 14 + K): (28 + 2 K,), the 28, then the camera's and
    the projector's coefficients (:func:`fringecal.calibration.propagation.scanner_with`)."""
    cam, prj = sensor_params[2 * block], sensor_params[2 * block + 1]
    return np.concatenate([cam[:14], prj[:14], cam[14:], prj[14:]])


@dataclass(frozen=True)
class SightingModel:
    """Linearised fit of one sighting: ``J`` (3, 28) d(centre)/d(scanner parameters),
    ``C_fit`` (3, 3) covariance of the centre from the fit's own noise (sandwich),
    ``J_field`` (3, 2 K) d(centre)/d(camera's then projector's correction-field
    coefficients), None without a field."""

    points: SightingPoints
    J: np.ndarray
    C_fit: np.ndarray
    J_field: np.ndarray | None = None


def _normals(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    d = points - centre
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def sighting_model(s: SightingPoints, std28: np.ndarray) -> SightingModel:
    """Jacobian of the fitted centre by the scanner's parameters, and the fit's covariance."""
    X = triangulate_mm(s.scanner, s.cam_mm, s.prj_mm)
    A = _normals(X, s.centre)
    AtA_inv = np.linalg.inv(A.T @ A)
    with_field = any(se.field is not None and se.field.degree == FIELD_DEGREE for se in s.scanner.sensors)
    JX = point_jacobian(s.scanner, s.cam_mm, s.prj_mm,
                        with_principal_point_steps(std28) if with_field else std28)  # (n, 3, 28)
    J = AtA_inv @ (A.T @ np.einsum("ni,nij->nj", A, JX))
    J_field = None
    if with_field:
        JF = field_jacobian(s.scanner, s.cam_mm, s.prj_mm, JX, field_terms(FIELD_DEGREE))
        J_field = AtA_inv @ (A.T @ np.einsum("ni,nij->nj", A, JF))
    return SightingModel(s, J, centre_sandwich_covariance(X, s.centre, s.radius_mm), J_field)


@dataclass(frozen=True)
class LengthBudget:
    """Standard uncertainties (mm) of one length by contribution, and combined."""

    length_mm: float
    u_mm: dict

    @property
    def combined_mm(self) -> float:
        return float(math.sqrt(sum(v**2 for v in self.u_mm.values())))


def length_gradient(a: SightingModel, b: SightingModel, n_params: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(dL/dtheta over all sensor parameters, e, L)."""
    d = a.points.centre - b.points.centre
    L = float(np.linalg.norm(d))
    e = d / L
    g = np.zeros(n_params)
    g[28 * a.points.block:28 * a.points.block + 28] += e @ a.J
    g[28 * b.points.block:28 * b.points.block + 28] -= e @ b.J
    return g, e, L


def field_gradient(g: np.ndarray, a: SightingModel, b: SightingModel, e: np.ndarray, n_terms: int) -> np.ndarray:
    """``g`` (dL/d sensor parameters) extended by dL/d each sensor's correction-field
    coefficients (the extended vector of :class:`~fringecal.calibration.propagation.FieldCovariances`)."""
    n_sensors = len(g) // 14
    out = np.concatenate([g, np.zeros(n_sensors * n_terms)])
    for m, sign in ((a, 1.0), (b, -1.0)):
        if m.J_field is not None:  # the scanner's camera's, then its projector's coefficients
            out[extended_indices(n_sensors, m.points.block, n_terms)[28:]] += sign * (e @ m.J_field)
    return out


def length_budget(a: SightingModel, b: SightingModel, cov: ParameterCovariances, u_certificate_mm: float,
                  u_bar_temperature_rel: float, u_model_mm: float = 0.0, u_bias_mm: float = 0.0) -> LengthBudget:
    """Linear (GUM) budget of the length between sightings ``a`` and ``b``;
    ``u_model_mm`` the length's model error from the jackknife (0: none found),
    ``u_bias_mm`` the uncertainty of the calibration-bias correction
    (:func:`bootstrap_bias`; 0 without one)."""
    g, e, L = length_gradient(a, b, len(cov.scale))
    terms = cov
    if cov.field is not None and (a.J_field is not None or b.J_field is not None):
        g, terms = field_gradient(g, a, b, e, cov.field.n_terms), cov.field
    u = {
        "calibration": math.sqrt(max(float(g @ terms.calibration @ g), 0.0)),
        "calibration bias correction": float(u_bias_mm),
        "artefact CMM": math.sqrt(max(float(g @ terms.cmm @ g), 0.0)),
        "artefact temperature": abs(float(g @ terms.scale)) * cov.u_scale,
        "sphere fits": math.sqrt(float(e @ (a.C_fit + b.C_fit) @ e)),
        "bar certificate": float(u_certificate_mm),
        "bar temperature": float(u_bar_temperature_rel) * L,
        "model error (cross-validation)": float(u_model_mm),
    }
    return LengthBudget(L, u)


def _draw_sqrt(C: np.ndarray) -> np.ndarray:
    """A factor F with F F^T = C for a positive semi-definite C.

    Decomposed as a correlation matrix (unit diagonal): the parameters' variances span
    some 20 orders of magnitude (mm^2 of positions, 1e-20 of a k3), so an unscaled
    eigen-decomposition would swamp the small ones in rounding.
    """
    d = np.sqrt(np.clip(np.diag(C), 0, None))
    s = np.where(d > 0, d, 1.0)
    lam, V = np.linalg.eigh(0.5 * (C + C.T) / np.outer(s, s))
    return (V * np.sqrt(np.clip(lam, 0, None))[None, :]) * d[:, None]


def _refit(points: np.ndarray, centre: np.ndarray, radius: float, iterations: int = 3) -> np.ndarray:
    """Fixed-radius sphere centre by Gauss-Newton from ``centre`` (normal equations: the
    3 x 3 system is well conditioned for any cap the verification keeps)."""
    c = centre.copy()
    for _ in range(iterations):
        d = points - c
        r = np.sqrt(np.einsum("ij,ij->i", d, d))
        A = d / r[:, None]
        c = c + np.linalg.solve(A.T @ A, A.T @ (r - radius))
    return c


def monte_carlo_lengths(a: SightingPoints, b: SightingPoints, cov: ParameterCovariances, u_certificate_mm: float,
                        u_bar_temperature_rel: float, draws: int, rng: np.random.Generator,
                        u_model_mm: float = 0.0, shifts: tuple | None = None) -> np.ndarray:
    """``draws`` lengths (mm) through the full model (see the module docstring);
    ``shifts`` (two (3, 3) covariances or None): each refitted centre also moves as a
    whole by a draw of its own, the sighting's scatter beyond its points' noise."""
    blocks = sorted({a.block, b.block})
    idx = [np.arange(28 * k, 28 * k + 28) for k in blocks]
    total, width, base = cov.total, 28, {s.block: s.params for s in (a, b)}
    if cov.field is not None:  # draw the correction fields' coefficients too (block_params' order)
        K = cov.field.n_terms
        idx = [extended_indices(len(cov.scale) // 14, k, K) for k in blocks]
        total, width = cov.field_total, 28 + 2 * K
        base = {s.block: np.concatenate([s.params, *(se.field.coefficients if se.field is not None else np.zeros(K)
                                                      for se in s.scanner.sensors)]) for s in (a, b)}
    idx = np.concatenate(idx)
    F = _draw_sqrt(total[np.ix_(idx, idx)])
    X0 = {id(s): triangulate_mm(s.scanner, s.cam_mm, s.prj_mm) for s in (a, b)}
    normals = {id(s): _normals(X0[id(s)], s.centre) for s in (a, b)}
    shift = [None if S is None or not np.any(S) else _draw_sqrt(S) for S in (shifts or (None, None))]
    out = np.empty(draws)
    for m in range(draws):
        dtheta = F @ rng.standard_normal(F.shape[1])
        centres = []
        for k, s in enumerate((a, b)):
            j = blocks.index(s.block)
            sc = scanner_with(s.scanner, base[s.block] + dtheta[width * j:width * j + width])
            X = triangulate_mm(sc, s.cam_mm, s.prj_mm)
            X = X + normals[id(s)] * (s.rms_mm * rng.standard_normal(len(X)))[:, None]
            c = _refit(X, s.centre, s.radius_mm)
            centres.append(c if shift[k] is None else c + shift[k] @ rng.standard_normal(3))
        L = float(np.linalg.norm(centres[0] - centres[1]))
        out[m] = (L * (1 + u_bar_temperature_rel * rng.standard_normal()) + u_certificate_mm * rng.standard_normal()
                  + u_model_mm * rng.standard_normal())
    return out


def refitted_length(a: SightingPoints, b: SightingPoints, params_a: np.ndarray, params_b: np.ndarray) -> float:
    """The length with other parameters for the two sightings' scanners ((28,) each):
    every kept pixel re-triangulated and both spheres refitted."""
    centres = []
    for s, p in ((a, params_a), (b, params_b)):
        X = triangulate_mm(scanner_with(s.scanner, p), s.cam_mm, s.prj_mm)
        centres.append(_refit(X, s.centre, s.radius_mm))
    return float(np.linalg.norm(centres[0] - centres[1]))


def bootstrap_bias(a: SightingPoints, b: SightingPoints, params: np.ndarray) -> tuple[float, float, float]:
    """The calibration's bias on the length between ``a`` and ``b`` from bootstrap
    re-adjustments (:mod:`fringecal.calibration.bootstrap`; ``params`` (draws,
    n_sensors, 14)): ``(bias, u_bias, spread)`` in mm, ``bias = mean(L*) - L`` with
    every length refitted as :func:`refitted_length` does, ``spread = std(L*)`` and
    ``u_bias = spread / sqrt(draws)`` the uncertainty of the estimated bias. Subtract
    ``bias`` from the measured length.
    """
    L = refitted_length(a, b, a.params, b.params)
    Ls = np.array([refitted_length(a, b, block_params(p, a.block), block_params(p, b.block)) for p in params])
    spread = float(np.std(Ls, ddof=1))
    return float(Ls.mean() - L), spread / math.sqrt(len(Ls)), spread


def jackknife_variance(values) -> float:
    """``(n - 1) / n * sum (v_i - mean v)^2`` of the values of n delete-one replicas.

    >>> jackknife_variance([1.0, 2.0, 3.0])
    1.3333333333333333
    """
    v = np.asarray(values, float)
    if v.size < 2:
        raise ValueError(f"a jackknife variance needs at least 2 replicas, got {v.size}")
    return float((v.size - 1) / v.size * np.sum((v - v.mean()) ** 2))


def jackknife_spread(a: SightingPoints, b: SightingPoints, params: np.ndarray) -> float:
    """The length's jackknife standard deviation (mm) over the calibration's
    delete-one-measurement replicas (:mod:`fringecal.calibration.jackknife`; ``params``
    (n, n_sensors, 14)), each length refitted as :func:`refitted_length` does."""
    return math.sqrt(jackknife_variance([refitted_length(a, b, block_params(p, a.block), block_params(p, b.block))
                                         for p in params]))


def jackknife_model_error(a: SightingModel, b: SightingModel, params: np.ndarray, noise_params: np.ndarray,
                          adjustment: np.ndarray, field_terms_per_sensor: int = 0) -> dict:
    """The model-error term of the length between ``a`` and ``b``
    (:mod:`fringecal.calibration.jackknife`): its jackknife variance over ``params``
    (n, n_sensors, 14) against the mean of the same over the noise-only worlds
    ``noise_params`` (draws, n, n_sensors, 14), at the scale of its linear calibration
    term ``u = sqrt(g^T C g)`` (``adjustment`` the adjustment's sensor covariance,
    (14 n_sensors) square, or with ``field_terms_per_sensor`` K the extended one of
    :class:`~fringecal.calibration.propagation.FieldCovariances`): ``u sqrt(max(0,
    var_J / var_J,noise - 1))``.

    Returns ``spread_mm`` (sqrt var_J), ``noise_spread_mm`` (sqrt var_J,noise),
    ``u_calibration_mm``, ``model_error_mm``, ``replicas`` and ``noise_draws``."""
    spread = jackknife_spread(a.points, b.points, params)
    noise = math.sqrt(float(np.mean([jackknife_spread(a.points, b.points, p) ** 2 for p in noise_params])))
    n14 = adjustment.shape[0] * 14 // (14 + field_terms_per_sensor)
    g, e, _ = length_gradient(a, b, n14)
    if field_terms_per_sensor:
        g = field_gradient(g, a, b, e, field_terms_per_sensor)
    u_linear = math.sqrt(max(float(g @ adjustment @ g), 0.0))
    excess = max(0.0, (spread / noise) ** 2 - 1.0) if noise > 0 else 0.0
    return {"spread_mm": spread, "noise_spread_mm": noise, "u_calibration_mm": u_linear,
            "model_error_mm": u_linear * math.sqrt(excess), "replicas": int(len(params)),
            "noise_draws": int(len(noise_params))}


def numerical_tolerance(u: float, significant_digits: int = 2) -> float:
    """JCGM 101 7.9.2: u written as c x 10^l with ``significant_digits`` digits in c;
    the tolerance is half a unit of its last digit, 0.5 x 10^l."""
    if not u > 0:
        return 0.0
    exponent = math.floor(math.log10(u)) - (significant_digits - 1)
    return 0.5 * 10.0**exponent


def validate_linear(y: float, u_linear: float, k: float, samples: np.ndarray, blocks: int = 10) -> dict:
    """JCGM 101 clause 8: the linear interval ``y +- k u`` against the Monte Carlo's
    probabilistically symmetric interval of the same coverage (k = 2 -> 95.45 %).

    Returns the Monte Carlo's standard uncertainty, interval, the endpoint differences,
    the tolerance used and ``agree``. The tolerance is ``numerical_tolerance(u)``, or
    twice the scatter of the endpoints over ``blocks`` blocks of draws when the draws
    are too few to reach it (then ``tolerance_source`` says so).
    """
    p = math.erf(k / math.sqrt(2))
    q = [(1 - p) / 2, (1 + p) / 2]
    lo, hi = np.quantile(samples, q)
    parts = np.array_split(samples, blocks)
    ends = np.array([np.quantile(s, q) for s in parts])
    s_end = float(np.max(np.std(ends, axis=0, ddof=1) / math.sqrt(blocks)))
    delta = numerical_tolerance(u_linear)
    source = "two significant digits of u"
    if 2 * s_end > delta:
        delta, source = 2 * s_end, "twice the Monte Carlo's own scatter of the interval ends"
    d_low = abs(y - k * u_linear - lo)
    d_high = abs(y + k * u_linear - hi)
    u_mc = float(np.std(samples, ddof=1))
    return {"u_mc_mm": u_mc, "u_linear_mm": float(u_linear), "ratio": u_mc / u_linear if u_linear > 0 else None,
            "mc_interval_mm": [float(lo), float(hi)], "linear_interval_mm": [y - k * u_linear, y + k * u_linear],
            "d_low_mm": float(d_low), "d_high_mm": float(d_high), "tolerance_mm": float(delta),
            "tolerance_source": source, "draws": int(len(samples)), "agree": bool(max(d_low, d_high) <= delta)}
