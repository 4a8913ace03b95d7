"""How the calibration moves when the artefact is not exactly its CMM table.

The adjustment holds the artefact's sphere centres and radii fixed at their CMM
values ``a``; their uncertainty therefore never enters its covariance. At the
solution the gradient of F vanishes, ``J_x^T W r(x, a) = 0`` (W = diag(gamma1,
gamma2) per control point), so to first order a change ``da`` of the table moves the
solution by

    dx = S da,   S = -N^-1 J_x^T W J_a,   N = J_x^T W J_x

(the implicit-function theorem; N is the normal matrix of the adjustment). ``J_a``
(the residuals' derivative by the artefact's 4 numbers per sphere: centre x, y, z and
radius) is taken by central differences of the residuals alone, which is cheap (no
Jacobian; 8 evaluations, since a control point depends on its own sphere only) and
follows the model's own definition of alpha2. Only alpha2 depends on the artefact.

From S:

* the covariance the CMM uncertainty gives the parameters, ``S Sigma_a S^T`` with
  ``Sigma_a = diag(u^2, u^2, u^2, (u/2)^2)`` per sphere (``u`` the table's standard
  uncertainty per centre coordinate; a diameter measured like a coordinate gives its
  radius half of it);
* the parameters' response to a uniform scale of the artefact (thermal expansion),
  ``S da_scale`` with ``da_scale = (c - c_mean, r)`` per unit of relative scale.

Robust losses are treated as their final weights (IRLS), the same approximation the
covariance itself makes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from fringecal.calibration.model import Evaluator
from fringecal.calibration.solver import irls_weights
from fringecal.calibration.uncertainty import UNOBSERVABLE

__all__ = ["ArtefactBlocks", "ArtefactSensitivity", "artefact_blocks", "artefact_sensitivity", "STEP_MM"]

#: central-difference step on the artefact's centres and radii (mm)
STEP_MM = 1e-3


@dataclass(frozen=True)
class ArtefactSensitivity:
    """d(adjusted vector)/d(artefact) at a solution.

    Attributes
    ----------
    S : (p, 4 n_spheres)
        Columns per sphere (artefact order): centre x, y, z, radius.
    u_artefact : (4 n_spheres,)
        Standard uncertainties of those numbers from the CMM table.
    scale : (p,)
        Response of the adjusted vector to a relative scale of the artefact (per unit).
    """

    S: np.ndarray
    u_artefact: np.ndarray
    scale: np.ndarray

    @property
    def covariance_cmm(self) -> np.ndarray:
        """(p, p) covariance of the adjusted vector from the CMM uncertainty."""
        Su = self.S * self.u_artefact[None, :]
        return Su @ Su.T


def _weights(result) -> np.ndarray:
    return irls_weights(result.residuals, result.options.robust_loss, result.robust_scales)


@dataclass(frozen=True)
class ArtefactBlocks:
    """The adjustment's derivatives by the artefact at a solution (inputs of
    :func:`artefact_sensitivity`, and of any analysis that adjusts the artefact too).

    Attributes
    ----------
    Ja : (n, 2, 4)
        Each control point's alpha1, alpha2 by its sphere's centre x, y, z and radius.
    w : (n, 2)
        Weights of the residuals in F (gamma times the robust loss's final IRLS weight;
        0 where a ray cannot be formed).
    B : (p, n_spheres, 4)
        ``J_x^T W J_a``: the cross block of the normal equations.
    N : (p, p)
        ``J_x^T W J_x``: the normal matrix of the adjustment at the solution.
    residuals : (n, 2)
        alpha1, alpha2 at the solution.
    """

    Ja: np.ndarray
    w: np.ndarray
    B: np.ndarray
    N: np.ndarray
    residuals: np.ndarray

    def solved(self) -> np.ndarray:
        """``N^-1 B`` (p, n_spheres, 4), unobservable directions dropped as in the
        covariance: minus the response of the adjusted vector to the artefact."""
        p, n_s, _ = self.B.shape
        return _solve(self.N, self.B.reshape(p, 4 * n_s)).reshape(p, n_s, 4)


def artefact_blocks(result) -> ArtefactBlocks:
    """:class:`ArtefactBlocks` of a :class:`~fringecal.calibration.bundle.BundleResult`."""
    pr = result.problem
    art = pr.artefact
    gamma = np.array([pr.gamma1, pr.gamma2])
    ev = Evaluator(pr, result.layout)
    x = result.x
    n_s = len(art.ids)
    base = np.concatenate([art.centres, art.radii[:, None]], axis=1)  # (n_s, 4)
    # a control point's alpha2 depends on its own sphere only: moving every sphere at once
    # gives each point's derivative by its sphere's coordinate in 2 evaluations, not 2 n_s
    Ja = np.zeros((pr.n_points, 2, 4))
    for c in range(4):
        res = []
        for sign in (1.0, -1.0):
            a = base.copy()
            a[:, c] += sign * STEP_MM
            res.append(ev.with_artefact(a[:, :3], a[:, 3]).evaluate(x, want_jac=False).res)
        Ja[:, :, c] = (res[0] - res[1]) / (2 * STEP_MM)
    w = _weights(result) * gamma[None, :]
    _, J, ok = ev.jacobian_rows(x)
    w = w * ok[:, None]
    cols = ev.global_columns()
    B = np.zeros((result.layout.n, n_s, 4))
    start, stop, _, _ = pr.groups()
    for a0, b0 in zip(start, stop):
        sl = slice(a0, b0)
        spheres = pr.sphere_idx[sl]
        g = cols[a0]
        keep = g >= 0
        for sph in np.unique(spheres):
            m = spheres == sph
            local = np.einsum("nt,ntk,ntj->kj", w[sl][m], J[sl][m], Ja[sl][m])  # (34, 4)
            B[g[keep], sph, :] += local[keep]
    e = ev.evaluate(x, want_jac=True)
    return ArtefactBlocks(Ja, w, B, pr.gamma1 * e.N1 + pr.gamma2 * e.N2, e.res)


def artefact_sensitivity(result) -> ArtefactSensitivity:
    """:class:`ArtefactSensitivity` of a :class:`~fringecal.calibration.bundle.BundleResult`."""
    pr = result.problem
    art = pr.artefact
    n_s = len(art.ids)
    S = -artefact_blocks(result).solved().reshape(result.layout.n, 4 * n_s)
    u = np.repeat(art.u, 4).reshape(n_s, 4) * np.array([1.0, 1.0, 1.0, 0.5])
    da_scale = np.concatenate([art.centres - art.centres.mean(0), art.radii[:, None]], axis=1).reshape(-1)
    return ArtefactSensitivity(S, u.reshape(-1), S @ da_scale)


def _solve(N: np.ndarray, B: np.ndarray) -> np.ndarray:
    """N^-1 B in scaled variables, unobservable directions dropped (as the covariance)."""

    d = np.sqrt(np.diag(N))
    d[d == 0] = 1.0
    lam, V = scipy.linalg.eigh(N / np.outer(d, d), check_finite=False)
    keep = lam > UNOBSERVABLE * lam[-1]
    return ((V[:, keep] / lam[keep]) @ (V[:, keep].T @ (B / d[:, None]))) / d[:, None]
