"""Levenberg-Marquardt with Fletcher's damping strategy and a step-length search
(thesis section 2.3.6, eqs. 2-27..2-31), on dense normal equations.

With H = 2 N the Gauss-Newton Hessian of F and g = 2 b its gradient, each iteration solves

    (N_s + mu I) d_s = -b_s,   N_s = D^-1 N D^-1,  b_s = D^-1 b,  d = D^-1 d_s,
    D = sqrt(diag N)                                    (eq. 2-30 in scaled variables)

so mu is dimensionless and the step does not depend on the parameters' units (mm, rad,
mm^-6 ...). The trial point is x + alpha d (eq. 2-31). With ``increments`` (a
:class:`~.increments.RotationIncrements`) the angle triples of sensors and poses are
stepped as small rotations instead: N and b are taken into the increments' coordinates
and the trial point is the rotation R(angles) Exp(alpha d) written back as angles, which
avoids crawling along the curved valleys that Euler angles make near gimbal lock.

* Step acceptance: a trial is accepted only if F decreases, so F never increases.
  If x + alpha d does not decrease F, the step length alpha is replaced by the minimiser
  of the quadratic through F(0), F'(0) = 2 alpha b.d and F(alpha) (safeguarded to
  [0.1, 0.5] alpha) and tried once more (the thesis's step-length search); the new alpha
  is kept for the following iterations, and doubled (up to 1) after each very
  successful step (ratio > 0.75) so one bad step does not slow the rest.
* Damping (Fletcher 1971): with the gain ratio R = actual / predicted decrease,
  R > 0.75: mu <- mu / 2, and mu <- 0 once below the critical value mu_c (the smallest
  eigenvalue of N_s); R < 0.25: nu = 2 - (F_trial - F)/(alpha g.d) clipped to [2, 10]; if
  mu = 0, mu <- mu_c and nu <- nu / 2; mu <- nu mu. Gauss-Newton (mu = 0) is used
  whenever it works, so convergence near the solution is quadratic-like.
* Convergence (any of):
  ``ftol``: actual and predicted relative decrease of F both <= ftol, or a rejected step
  whose predicted relative decrease was already <= ftol (F at its rounding level), or
  (``stop_on_promise``) the undamped (Gauss-Newton) step from the current point promises
  a relative decrease b N^-1 b / F <= ftol (tested before the step is evaluated);
  ``xtol``: |d_s| <= xtol (|D x| + xtol);
  ``gtol``: max_i |b_i| / sqrt(N_ii F) <= gtol (the residual vector is orthogonal to every
  Jacobian column to within gtol);
  otherwise stop after ``max_iterations`` or when mu exceeds 1e16 without a decrease
  (no descent possible at machine precision), reported as not converged / stalled.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

__all__ = ["LMOptions", "LMReport", "levenberg_marquardt", "irls_weights"]


@dataclass(frozen=True)
class LMOptions:
    """Tolerances of :func:`levenberg_marquardt` (module notes). ``stop_on_promise``: also
    stop, without evaluating it, when the Gauss-Newton step promises a relative decrease
    below ``ftol``; that saves the last evaluation, and the point is then within about
    sqrt(ftol (2n - p)) standard uncertainties of the minimum (1e-3 for the default run):
    enough for bootstrap replicas, not for re-adjustments that measure small changes."""

    max_iterations: int = 100
    ftol: float = 1e-10
    xtol: float = 1e-10
    gtol: float = 1e-10
    mu0: float = 0.0
    stop_on_promise: bool = False


@dataclass
class LMReport:
    x: np.ndarray
    cost: float
    iterations: int
    evaluations: int
    jacobians: int
    converged: bool
    message: str
    history: list = field(default_factory=list)
    evaluation: object = None  # the evaluate() result at x, with normal equations


def _solve(Ns, bs, mu):
    try:
        cf = scipy.linalg.cho_factor(Ns + mu * np.eye(len(Ns)), lower=False, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    d = scipy.linalg.cho_solve(cf, -bs, check_finite=False)
    return d if np.all(np.isfinite(d)) else None


def _mu_critical(Ns):
    lam = scipy.linalg.eigvalsh(Ns, subset_by_index=[0, 0], check_finite=False)[0]
    return max(float(lam), 1e-12)


def levenberg_marquardt(evaluate, x0, gamma, options: LMOptions = LMOptions(), start=None,
                        increments=None) -> LMReport:
    """Minimise F(x) = gamma1 sum rho(alpha1) + gamma2 sum rho(alpha2).

    ``evaluate(x, want_jac)`` returns an object with ``cost`` and, with ``want_jac``,
    ``normal(gamma1, gamma2)`` (N, (p, p)) and ``b`` (p,). ``gamma`` = (gamma1, gamma2);
    ``start``: evaluate(x0, True) if already at hand. Trial points are evaluated with the
    normal equations (most steps are accepted, and then they are needed at once); the
    step-length search evaluates F alone. ``increments``: steps the angle triples as
    rotations (:class:`~.increments.RotationIncrements`); None: plain steps x + alpha d.
    """
    move = (lambda x, d: x + d) if increments is None else increments.retract

    def normal_equations(ev, x):  # N and b at x, in the coordinates the steps are taken in
        N, b = ev.normal(*gamma), ev.b
        return (N, b) if increments is None else increments.transform(x, N, b)
    x = np.asarray(x0, float).copy()
    ev = start if start is not None else evaluate(x, True)
    n_eval, n_jac = (0, 0) if start is not None else (1, 1)
    F = ev.cost
    if not np.isfinite(F):
        return LMReport(x, F, 0, n_eval, n_jac, False, "the start point gives no finite objective", [], ev)
    history = [dict(iteration=0, cost=F, mu=0.0, alpha=1.0, accepted=True)]
    mu, alpha = float(options.mu0), 1.0
    N, b = normal_equations(ev, x)
    message, converged = f"stopped after {options.max_iterations} iterations", False
    it = 0
    while it < options.max_iterations:
        D = np.sqrt(np.diag(N))
        D[D == 0] = 1.0
        Ns = N / np.outer(D, D)
        bs = b / D
        if F == 0 or np.max(np.abs(bs)) <= options.gtol * np.sqrt(F):
            converged, message = True, "gtol: gradient orthogonal to the residuals"
            break
        ds = _solve(Ns, bs, mu)
        while ds is None:  # not positive definite: more damping
            mu = max(10 * mu, _mu_critical(Ns) if mu == 0 else 0, 1e-12)
            ds = _solve(Ns, bs, mu)
        if options.stop_on_promise and mu == 0 and -(bs @ ds) <= options.ftol * F:
            # the Gauss-Newton step promises less than ftol (its decrease is b N^-1 b):
            # F is at its minimum to within ftol, and the step need not be evaluated
            converged, message = True, "ftol: the Gauss-Newton step promises a relative decrease below ftol"
            break
        it += 1
        d = ds / D
        gd = 2.0 * b @ d  # F'(0) along d (< 0)
        dNd = d @ N @ d
        a_used = alpha
        x_new = move(x, alpha * d)
        ev_new = evaluate(x_new, True)
        F_new = ev_new.cost
        n_eval += 1
        n_jac += 1
        if not (F_new < F):
            ev_new = None
            # step-length search (eq. 2-31): minimiser of the quadratic through F(0), F'(0), F(alpha)
            if np.isfinite(F_new):
                curv = F_new - F - gd * alpha
                a_new = -gd * alpha**2 / (2 * curv) if curv > 0 else 0.5 * alpha
                a_new = float(np.clip(a_new, 0.1 * alpha, 0.5 * alpha))
            else:
                a_new = 0.25 * alpha
            x_try = move(x, a_new * d)
            F_try = evaluate(x_try, False).cost
            n_eval += 1
            if F_try < F:
                alpha, a_used, x_new, F_new = a_new, a_new, x_try, F_try
        pred = -(a_used * gd + a_used**2 * dNd)
        R = (F - F_new) / pred if pred > 0 and np.isfinite(F_new) else -np.inf
        accepted = F_new < F
        # Fletcher's damping update
        if R > 0.75:
            mu = mu / 2
            if mu > 0 and mu < _mu_critical(Ns):
                mu = 0.0
            alpha = min(1.0, 2 * alpha)
        elif R < 0.25:
            nu = 10.0
            if np.isfinite(F_new) and gd < 0:
                nu = float(np.clip(2.0 - (F_new - F) / (a_used * gd), 2.0, 10.0))
            if mu == 0:
                mu = _mu_critical(Ns)
                nu /= 2
            mu *= nu
        history.append(dict(iteration=it, cost=F_new if accepted else F, mu=mu, alpha=a_used, accepted=accepted,
                            ratio=float(R)))
        if not accepted:
            if pred <= options.ftol * F:
                # the model promises less than ftol and even that is not realised: F is at
                # the level of its own rounding
                converged, message = True, "ftol: predicted decrease below ftol and not achieved"
                break
            if mu > 1e16:
                message = "stalled: no decrease of F possible (mu > 1e16)"
                break
            continue
        dF = F - F_new
        x, F = x_new, F_new
        if ev_new is None:  # accepted after the step-length search
            ev_new = evaluate(x, True)
            n_eval += 1
            n_jac += 1
        ev = ev_new
        N, b = normal_equations(ev, x)
        if dF <= options.ftol * F and pred <= options.ftol * F:
            converged, message = True, "ftol: relative decrease of F below ftol"
            break
        if np.linalg.norm(a_used * ds) <= options.xtol * (np.linalg.norm(D * x) + options.xtol):
            converged, message = True, "xtol: scaled step below xtol"
            break
    return LMReport(x, F, it, n_eval, n_jac, converged, message, history, ev)


def irls_weights(res, loss: str, scales) -> np.ndarray:
    """(n, 2) weights of the residuals ``res`` (n, 2) under a robust ``loss`` (``none``,
    ``huber``, ``cauchy``) with scales (alpha1, alpha2): iteratively reweighted least squares."""
    if loss in ("none", "linear"):
        return np.ones_like(res)
    a = np.abs(res) / np.asarray(scales)[None, :]
    if loss == "huber":
        return np.where(a <= 1, 1.0, 1.0 / np.maximum(a, 1e-300))
    return 1.0 / (1.0 + a**2)
