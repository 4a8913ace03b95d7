"""Standard uncertainties and correlations of the adjusted parameters.

At the solution, with N_t = sum w J_t^T J_t the normal matrix of term t (alpha1, alpha2;
w the robust weights, 1 without a robust loss) and N = gamma1 N1 + gamma2 N2:

* classical (what the normal equations give, thesis style)::

      Cov0 = sigma0^2 N^-1,   sigma0^2 = F / (2 n - p)

  with n control points (two residuals each) and p free parameters. It is exact only if
  gamma1 and gamma2 are the inverse variances of alpha1 and alpha2 up to a common factor.

* per-term variance factors (reported as the standard uncertainties)::

      Cov = N^-1 (gamma1^2 s1^2 N1 + gamma2^2 s2^2 N2) N^-1,
      s_t^2 = sum w alpha_t^2 / nu_t,   nu_t = n - gamma_t tr(N^-1 N_t)

  the covariance of the weighted least-squares estimate when alpha1 and alpha2 have
  different variances (in the simulated thesis rig alpha2 is ~3.5 times noisier than
  alpha1 while the thesis weighs both by 1). The two degrees of freedom nu_1 + nu_2 =
  2n - p split the redundancy between the terms; with s1 = s2 and gamma1 = gamma2 this
  is Cov0 exactly.

* heteroscedasticity-consistent (the sandwich over the points, what
  :func:`fringecal.calibration.bundle.bundle_adjust` reports by default)::

      Cov = N^-1 M N^-1 n / (n - p),   M = sum_i s_i s_i^T,
      s_i = gamma1 w alpha1_i J1_i + gamma2 w alpha2_i J2_i

  (:func:`score_meat`): each point's own residuals, so that points noisier than the
  term's average (low modulation, oblique incidence, far from focus) count as noisy
  as they are. With a single variance per term the rendered thesis rig at 512 px
  states its sensor parameters 1.2 times too precisely (error / u RMS over 20 seeds
  1.36, with the sandwich 1.13; ``benchmarks/parameter_coverage.py``); the per-term
  form is kept as ``covariance: per-term``. Residuals of neighbouring
  pixels are uncorrelated there (|corr| < 0.015 at lags 1-5), and the two residuals
  of a point nearly so (0.013), so the points are the independent units.

Near-singular directions come from the eigen-decomposition of the scaled normal matrix
N_s = D^-1 N D^-1 (D = sqrt diag N, so N_s has a unit diagonal and its eigenvalues are
unit-free): eigenvalues below ``NEAR_SINGULAR`` times the largest are reported with the
parameters that dominate their eigenvector.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

__all__ = ["Uncertainty", "estimate_uncertainty", "score_meat", "weak_directions", "NEAR_SINGULAR", "UNOBSERVABLE"]

#: eigenvalue ratio of the scaled normal matrix below which a direction is reported as weak
NEAR_SINGULAR = 1e-9
#: ... and below which it is taken as unobservable (rank deficient)
UNOBSERVABLE = 1e-13


@dataclass(frozen=True)
class WeakDirection:
    """An eigenvector of the scaled normal matrix with a small eigenvalue ratio."""

    ratio: float
    parameters: tuple  # names of the dominant parameters
    weights: tuple  # their components (signed, the largest normalised to 1)

    def describe(self) -> str:
        terms = " ".join(f"{w:+.2f}*{n}" for n, w in zip(self.parameters, self.weights))
        return f"eigenvalue ratio {self.ratio:.1e}: {terms}"


@dataclass(frozen=True)
class Uncertainty:
    """Covariance of the free parameters (order of ``names``) and its summaries.

    covariance, covariance_classical : (p, p); std : (p,); correlation : (p, p)
    sigma : (s1, s2) RMS-like per-term standard deviations (mm); sigma0 : classical
    dof : (nu_1, nu_2) and dof_total = 2n - p; condition : of the scaled normal matrix
    weak : tuple of WeakDirection
    """

    names: tuple
    covariance: np.ndarray
    covariance_classical: np.ndarray
    std: np.ndarray
    correlation: np.ndarray
    sigma: tuple
    sigma0: float
    dof: tuple
    dof_total: int
    condition: float
    weak: tuple

    def high_correlations(self, threshold: float = 0.99) -> list[tuple[str, str, float]]:
        """Parameter pairs with |correlation| above ``threshold``, strongest first."""
        C = self.correlation
        i, j = np.nonzero(np.triu(np.abs(C) > threshold, 1))
        pairs = [(self.names[a], self.names[b], float(C[a, b])) for a, b in zip(i, j)]
        return sorted(pairs, key=lambda t: -abs(t[2]))


def weak_directions(N: np.ndarray, names, threshold: float = NEAR_SINGULAR, top: int = 8,
                    min_component: float = 0.15, eig=None, regularised=None) -> tuple[list[WeakDirection], float]:
    """Eigen-directions of the scaled normal matrix with eigenvalue ratio below ``threshold``.

    Returns the directions (smallest first) and the condition number. Parameters with no
    influence at all (zero diagonal) come out as ratio 0 directions of their own.
    ``eig``: the eigen-decomposition of the scaled matrix, if already computed (only
    used when no parameter has a zero diagonal and nothing is ``regularised``).

    ``regularised`` (p,) bool marks parameters held by a prior in N (the correction
    fields' coefficients). They are marginalised out first (the Schur complement of
    their block), so a direction is reported when the other parameters are weakly
    determined among themselves with them free. Combinations of a field with the low-order
    parameters are expected: over the part of the image the control points cover, the
    field's basis is no longer orthogonal to a tilt or the principal point, and its prior
    holds those combinations (every stated u is the posterior's, so it carries them).
    On a simulated 3 um lens-field cell (``configs/run_thesis_lensfield.yaml``) such a
    combination has ratio 2.3e-11 in the whole matrix, while the 14 parameters' weakest
    direction with the field marginalised has 2.8e-9 (1.9e-9 without the field), above
    the threshold. The condition number is then the complement's.
    """
    if regularised is not None and np.any(regularised):
        r = np.asarray(regularised, bool)
        k = np.flatnonzero(~r)
        S = N[np.ix_(k, k)] - N[np.ix_(k, r)] @ np.linalg.solve(N[np.ix_(r, r)], N[np.ix_(r, k)])
        return weak_directions(S, [names[i] for i in k], threshold, top, min_component)
    d = np.sqrt(np.diag(N))
    out = []
    dead = np.flatnonzero(d == 0)
    for k in dead:
        out.append(WeakDirection(0.0, (names[k],), (1.0,)))
    live = np.flatnonzero(d > 0)
    if not len(live):
        return out, np.inf
    if eig is not None and not len(dead):
        lam, V = eig
    else:
        Ns = N[np.ix_(live, live)] / np.outer(d[live], d[live])
        lam, V = scipy.linalg.eigh(Ns, check_finite=False)
    lam_max = lam[-1]
    cond = float(lam_max / max(lam[0], 1e-300)) if not len(dead) else np.inf
    for k in np.flatnonzero(lam < threshold * lam_max):
        v = V[:, k] / np.max(np.abs(V[:, k]))
        idx = [i for i in np.argsort(-np.abs(v)) if abs(v[i]) >= min_component][:top]
        out.append(WeakDirection(float(max(lam[k], 0.0) / lam_max), tuple(names[live[i]] for i in idx),
                                 tuple(float(v[i]) for i in idx)))
    return out, cond


def score_meat(J: np.ndarray, columns: np.ndarray, res: np.ndarray, weights: np.ndarray, gamma, p: int,
               group_start, group_stop) -> np.ndarray:
    """``M = sum_i s_i s_i^T`` (p, p), ``s_i`` the gradient of point i's share of F.

    Parameters
    ----------
    J : (n, 2, k) local Jacobian rows of alpha1, alpha2; columns : (n, k) their global
        parameter index (-1: fixed), the same within each (scanner, measurement) group
    res, weights : (n, 2); gamma : (gamma1, gamma2); p : free parameters
    group_start, group_stop : the contiguous groups (one local column map each)
    """
    g = np.asarray(gamma, float)
    S = np.einsum("nt,ntk->nk", weights * g[None, :] * res, J)
    M = np.zeros((p, p))
    for a, b in zip(group_start, group_stop):
        cols = columns[a]
        keep = cols >= 0
        Sg = S[a:b][:, keep]
        M[np.ix_(cols[keep], cols[keep])] += Sg.T @ Sg
    return M


def estimate_uncertainty(N1, N2, res, weights, gamma, names, meat: np.ndarray | None = None,
                         regularised=None) -> Uncertainty:
    """Covariances from the normal matrices at the solution.

    Parameters
    ----------
    N1, N2 : (p, p) weighted normal matrices of alpha1 and alpha2 (no gamma)
    res : (n, 2) residuals alpha1, alpha2; weights : (n, 2) robust weights (ones without)
    gamma : (gamma1, gamma2); names : parameter names (p,)
    meat : (p, p) :func:`score_meat`, or None: the reported covariance is then the
        per-term one (one variance factor per term), else the sandwich over the points
    regularised : (p,) bool, optional: parameters held by a prior in N2, left out of the
        weak directions (:func:`weak_directions`)
    """
    g1, g2 = gamma
    N = g1 * N1 + g2 * N2
    p = len(N)
    n = len(res)
    d = np.sqrt(np.diag(N))
    d[d == 0] = 1.0
    Ns = N / np.outer(d, d)
    # pseudo-inverse in scaled variables: unobservable directions get no variance
    lam, V = scipy.linalg.eigh(Ns, check_finite=False)
    weak, cond = weak_directions(N, names, eig=(lam, V), regularised=regularised)
    keep = lam > UNOBSERVABLE * lam[-1]
    Ninv_s = (V[:, keep] / lam[keep]) @ V[:, keep].T
    Ninv = Ninv_s / np.outer(d, d)
    wr2 = np.sum(weights * res**2, axis=0)
    nu1 = n - g1 * float(np.sum(Ninv * N1))
    nu2 = n - g2 * float(np.sum(Ninv * N2))
    s1 = float(np.sqrt(wr2[0] / nu1)) if nu1 > 0 else np.nan
    s2 = float(np.sqrt(wr2[1] / nu2)) if nu2 > 0 else np.nan
    if meat is None:
        M = g1**2 * s1**2 * N1 + g2**2 * s2**2 * N2
    else:
        M = np.asarray(meat, float) * (n / (n - p) if n > p else np.nan)
    cov = Ninv @ M @ Ninv
    cov = 0.5 * (cov + cov.T)
    dof = 2 * n - p
    F = g1 * wr2[0] + g2 * wr2[1]
    sigma0 = float(np.sqrt(F / dof)) if dof > 0 else np.nan
    cov0 = sigma0**2 * Ninv
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr[~np.isfinite(corr)] = 0.0
    np.fill_diagonal(corr, 1.0)
    return Uncertainty(tuple(names), cov, cov0, std, corr, (s1, s2), sigma0, (nu1, nu2), dof, cond, tuple(weak))
