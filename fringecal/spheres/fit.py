"""Least-squares sphere and plane fits (thesis sections 6.1, 6.2.1 and chapter 5).

:class:`SphereModel` minimises the sum of squared *orthogonal* distances
``|p_i - c| - R`` over the centre ``c`` (and the radius ``R`` unless it is fixed,
e.g. to the CMM value), as the thesis does with Levenberg-Marquardt. It starts from
the algebraic (linear) fit and runs Gauss-Newton steps, damped only when a step
would not reduce the sum of squares, until the step is below 1e-12 mm: at that point
it *is* the full geometric least-squares solution (the gradient vanishes), only
reached in a handful of iterations. :class:`PlaneModel` is the total-least-squares
plane (orthogonal distances), closed form.

Both follow scikit-image's estimator style: ``Model.from_estimate(points)`` returns
a fitted model; ``model.residuals(points)`` gives signed orthogonal distances.
Points are shifted to their mean before fitting, so data far from the origin (a
scanner at 2.5 m, a CMM at 10 m) loses no precision.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba as nb
import numpy as np

__all__ = ["FitError", "SphereModel", "PlaneModel", "angular_coverage", "centre_sandwich_covariance"]


class FitError(ValueError):
    """Too few points, degenerate geometry, or no convergence."""


def _as_points(points, min_points: int, what: str) -> np.ndarray:
    p = np.asarray(points, float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise FitError(f"{what}: points must have shape (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(p), axis=1)))
        raise FitError(f"{what}: {bad} point(s) are not finite")
    if len(p) < min_points:
        raise FitError(f"{what}: {len(p)} point(s); at least {min_points} are needed")
    return p


@nb.njit(cache=True)
def _normal_equations(q, cx, cy, cz, radius):
    """J^T J, J^T r and sum r^2 for r_i = |q_i - c| - R, J_i = [-(q_i - c)/|q_i - c|, -1]."""
    A = np.zeros((4, 4))
    g = np.zeros(4)
    ssr = 0.0
    for i in range(q.shape[0]):
        dx = q[i, 0] - cx
        dy = q[i, 1] - cy
        dz = q[i, 2] - cz
        d = np.sqrt(dx * dx + dy * dy + dz * dz)
        r = d - radius
        ux = dx / d
        uy = dy / d
        uz = dz / d
        # J row = (-ux, -uy, -uz, -1); accumulate J^T J and J^T r
        A[0, 0] += ux * ux
        A[0, 1] += ux * uy
        A[0, 2] += ux * uz
        A[1, 1] += uy * uy
        A[1, 2] += uy * uz
        A[2, 2] += uz * uz
        A[0, 3] += ux
        A[1, 3] += uy
        A[2, 3] += uz
        g[0] -= ux * r
        g[1] -= uy * r
        g[2] -= uz * r
        g[3] -= r
        ssr += r * r
    A[1, 0] = A[0, 1]
    A[2, 0] = A[0, 2]
    A[2, 1] = A[1, 2]
    A[3, 0] = A[0, 3]
    A[3, 1] = A[1, 3]
    A[3, 2] = A[2, 3]
    A[3, 3] = q.shape[0]
    return A, g, ssr


@nb.njit(cache=True)
def _sum_squares(q, cx, cy, cz, radius):
    s = 0.0
    for i in range(q.shape[0]):
        dx = q[i, 0] - cx
        dy = q[i, 1] - cy
        dz = q[i, 2] - cz
        r = np.sqrt(dx * dx + dy * dy + dz * dz) - radius
        s += r * r
    return s


@nb.njit(cache=True)
def _algebraic_normal_equations(q):
    """Normal equations of |q|^2 = 2 c.q + k, rows (2x, 2y, 2z, 1), in one pass."""
    A = np.zeros((4, 4))
    b = np.zeros(4)
    row = np.empty(4)
    for i in range(q.shape[0]):
        row[0] = 2 * q[i, 0]
        row[1] = 2 * q[i, 1]
        row[2] = 2 * q[i, 2]
        row[3] = 1.0
        rhs = q[i, 0] * q[i, 0] + q[i, 1] * q[i, 1] + q[i, 2] * q[i, 2]
        for j in range(4):
            b[j] += row[j] * rhs
            for k in range(j, 4):
                A[j, k] += row[j] * row[k]
    for j in range(4):
        for k in range(j):
            A[j, k] = A[k, j]
    return A, b


def _algebraic_sphere(q: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear fit |q|^2 = 2 c.q + k (q centred on its mean); R^2 = k + |c|^2.

    Normal equations suffice: q is centred and the result only starts the
    geometric iterations.
    """
    A, b = _algebraic_normal_equations(q)
    bad = FitError("sphere: the points do not determine a sphere (coplanar or collinear?)")
    if not np.all(np.isfinite(A)) or np.linalg.cond(A) > 1e13:
        raise bad
    sol = np.linalg.solve(A, b)
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not np.all(np.isfinite(sol)) or r2 <= 0:
        raise bad
    return c, float(np.sqrt(r2))


@nb.njit(cache=True)
def _coverage(q, cx, cy, cz, n_bands):
    """Cap angle about the mean direction and occupied-cell fraction of q - c."""
    n = q.shape[0]
    mx = 0.0
    my = 0.0
    mz = 0.0
    for i in range(n):
        dx, dy, dz = q[i, 0] - cx, q[i, 1] - cy, q[i, 2] - cz
        inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        mx += dx * inv
        my += dy * inv
        mz += dz * inv
    norm = np.sqrt(mx * mx + my * my + mz * mz)
    surrounded = norm <= 1e-9 * n
    cells = np.zeros(2 * n_bands * n_bands, np.bool_)
    lowest = 1.0
    for i in range(n):
        dx, dy, dz = q[i, 0] - cx, q[i, 1] - cy, q[i, 2] - cz
        inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        ux, uy, uz = dx * inv, dy * inv, dz * inv
        if not surrounded:
            lowest = min(lowest, (ux * mx + uy * my + uz * mz) / norm)
        band = min(int((uz + 1) / 2 * n_bands), n_bands - 1)
        sector = min(int((np.arctan2(uy, ux) + np.pi) / (2 * np.pi) * 2 * n_bands), 2 * n_bands - 1)
        cells[band * 2 * n_bands + sector] = True
    cap = np.pi if surrounded else np.arccos(max(-1.0, min(1.0, lowest)))
    return cap, cells.sum() / cells.size


def angular_coverage(directions: np.ndarray, n_bands: int = 12) -> tuple[float, float]:
    """How much of a sphere unit ``directions`` (n, 3) cover, seen from the centre.

    Returns ``(cap_angle_rad, fraction)``: the half-angle of the smallest cap about
    the mean direction that holds every direction (pi when they surround the centre;
    about the *sample* mean, so a few hundred points scatter it by a few degrees),
    and the fraction of ``2 n_bands^2`` equal-area cells (bands of equal height in
    z, equal azimuth sectors) that hold at least one direction. The fraction depends
    on point density; with thousands of points a hemisphere gives ~0.5.
    """
    cap, frac = _coverage(np.ascontiguousarray(directions, dtype=float), 0.0, 0.0, 0.0, n_bands)
    return float(cap), float(frac)


def centre_sandwich_covariance(points, centre, radius: float) -> np.ndarray:
    """Covariance (3, 3) of the centre of a fixed-radius sphere fit to ``points`` (n, 3),
    from each point's own residual ``r_i = |p_i - c| - R``:
    ``(A^T A)^-1 (sum r_i^2 a_i a_i^T) (A^T A)^-1 n / (n - 3)``, ``a_i`` the unit normal
    at the point. Unlike ``SphereModel.covariance`` it holds noise that grows towards
    the rim (oblique rays), which the plain ``s^2 (A^T A)^-1`` understates laterally
    (by ~20 % for a ball-bar sphere)."""
    p = np.asarray(points, float)
    d = p - np.asarray(centre, float)
    dist = np.linalg.norm(d, axis=1)
    A = d / dist[:, None]
    r = dist - radius
    inv = np.linalg.inv(A.T @ A)
    n = len(p)
    return inv @ ((A * (r**2)[:, None]).T @ A) @ inv * (n / max(n - 3, 1))


@dataclass(frozen=True)
class SphereModel:
    """A least-squares sphere.

    Attributes
    ----------
    centre : ndarray, shape (3,), mm
    radius : float, mm
    rms : float
        Root mean square of the orthogonal residuals, mm.
    n_points : int
    covariance : ndarray, shape (4, 4)
        Of (cx, cy, cz, R): ``s^2 (J^T J)^-1`` with ``s^2 = sum r^2 / (n - p)``;
        the radius row and column are zero when the radius was fixed.
    radius_fixed : bool
    cap_angle_rad, coverage : float
        Angular coverage of the points seen from the centre (:func:`angular_coverage`).
    iterations : int
        Gauss-Newton iterations from the algebraic start.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> u = rng.normal(size=(2000, 3)); u /= np.linalg.norm(u, axis=1, keepdims=True)
    >>> u = u[u[:, 2] > 0.3]                              # a cap
    >>> pts = [100.0, -50.0, 2000.0] + 25.0 * u + rng.normal(0, 0.01, (len(u), 1)) * u
    >>> s = SphereModel.from_estimate(pts)
    >>> np.round(s.centre, 2).tolist(), round(s.radius, 2), round(s.rms, 3)
    ([100.0, -50.0, 2000.0], 25.0, 0.01)
    >>> bool(np.all(s.centre_uncertainty < 0.002))
    True
    """

    centre: np.ndarray
    radius: float
    rms: float
    n_points: int
    covariance: np.ndarray = field(repr=False)
    radius_fixed: bool = False
    cap_angle_rad: float = float("nan")
    coverage: float = float("nan")
    iterations: int = 0

    @classmethod
    def from_estimate(cls, points, radius: float | None = None, max_iter: int = 100,
                      step_tol_mm: float = 1e-12) -> "SphereModel":
        """Fit a sphere to ``points`` (n, 3); ``radius`` fixes the radius (mm).

        Raises
        ------
        FitError
            Fewer than 4 points (3 with a fixed radius), non-finite points, points
            that do not determine a sphere, or no convergence.
        """
        fixed = radius is not None
        p = _as_points(points, 3 if fixed else 4, "sphere")
        shift = p.mean(axis=0)
        q = p - shift
        c, r = _algebraic_sphere(q) if len(q) >= 4 else (np.zeros(3), float(radius))
        if fixed:
            r = float(radius)
            if not r > 0:
                raise FitError(f"sphere: fixed radius must be positive, got {radius}")
        npar = 3 if fixed else 4
        lam = 0.0
        it = 0
        while True:
            it += 1
            if it > max_iter:
                raise FitError(f"sphere: no convergence in {max_iter} iterations")
            A, g, ssr = _normal_equations(q, c[0], c[1], c[2], r)
            A = A[:npar, :npar]
            g = g[:npar]
            try:
                step = np.linalg.solve(A + lam * np.diag(np.diag(A)), -g)
            except np.linalg.LinAlgError:
                raise FitError("sphere: singular normal equations (degenerate point set)") from None
            c_new = c + step[:3]
            r_new = r + step[3] if not fixed else r
            if lam == 0.0 and np.max(np.abs(step)) <= step_tol_mm:
                c, r = c_new, r_new  # the gradient vanishes: the least-squares solution
                break
            # Accept a step that lowers the sum of squares, or whose predicted decrease
            # is below what rounding lets us see (the quadratic regime near the optimum).
            predicted = -float(g @ step)
            if predicted <= 1e-12 * ssr or _sum_squares(q, c_new[0], c_new[1], c_new[2], r_new) <= ssr:
                c, r = c_new, r_new
                lam = lam / 10 if lam > 1e-6 else 0.0
            else:
                lam = max(lam * 10, 1e-6)  # Levenberg-Marquardt damping, only when needed
        A, g, ssr = _normal_equations(q, c[0], c[1], c[2], r)
        n = len(q)
        cov = np.zeros((4, 4))
        if n > npar:
            try:
                cov[:npar, :npar] = ssr / (n - npar) * np.linalg.inv(A[:npar, :npar])
            except np.linalg.LinAlgError:
                cov[:] = np.nan
        else:
            cov[:npar, :npar] = np.nan
        cap, frac = _coverage(q, c[0], c[1], c[2], 12)
        return cls(c + shift, float(r), float(np.sqrt(ssr / n)), n, cov, fixed, cap, frac, it)

    @property
    def params(self) -> np.ndarray:
        """(cx, cy, cz, R)."""
        return np.r_[self.centre, self.radius]

    @property
    def centre_uncertainty(self) -> np.ndarray:
        """Standard uncertainty of each centre coordinate (3,), mm (from the fit only)."""
        return np.sqrt(np.diag(self.covariance)[:3])

    @property
    def radius_uncertainty(self) -> float:
        return float(np.sqrt(self.covariance[3, 3]))

    def residuals(self, points) -> np.ndarray:
        """Signed orthogonal distances ``|p - c| - R``, shape (n,); positive outside."""
        p = np.asarray(points, float)
        return np.linalg.norm(p - self.centre, axis=-1) - self.radius

    def to_dict(self) -> dict:
        u = self.centre_uncertainty
        return {
            "x_mm": float(self.centre[0]), "y_mm": float(self.centre[1]), "z_mm": float(self.centre[2]),
            "radius_mm": float(self.radius), "radius_fixed": bool(self.radius_fixed),
            "rms_mm": float(self.rms), "n_points": int(self.n_points),
            "u_x_mm": float(u[0]), "u_y_mm": float(u[1]), "u_z_mm": float(u[2]),
            "u_radius_mm": float(self.radius_uncertainty),
            "cap_angle_deg": float(np.degrees(self.cap_angle_rad)), "coverage": float(self.coverage),
            "iterations": int(self.iterations),
        }


@dataclass(frozen=True)
class PlaneModel:
    """A total-least-squares plane ``normal . x = offset``.

    Attributes
    ----------
    normal : ndarray, shape (3,), unit
    point : ndarray, shape (3,)
        The centroid of the points (lies on the plane).
    offset : float
        ``normal . point``, mm (signed distance of the plane from the origin).
    rms : float
        RMS orthogonal residual (the "standard deviation of plate flatness"), mm.
    flatness : float
        Peak-to-valley of the residuals, mm.
    n_points : int
    spread : ndarray, shape (2,)
        Sums of squared in-plane coordinates along ``axes`` (for uncertainties).
    axes : ndarray, shape (2, 3)
        In-plane principal directions.

    Examples
    --------
    >>> rng = np.random.default_rng(2)
    >>> st = rng.uniform(-50, 50, (500, 2))
    >>> pts = np.c_[st, 0.002 * rng.standard_normal(500)] + [0, 0, 1e4]
    >>> pl = PlaneModel.from_estimate(pts, toward=[0, 0, 2e4])
    >>> round(float(pl.normal[2]), 6), round(pl.offset, 3), round(pl.rms, 3)
    (1.0, 10000.0, 0.002)
    """

    normal: np.ndarray
    point: np.ndarray
    rms: float
    flatness: float
    n_points: int
    spread: np.ndarray = field(repr=False)
    axes: np.ndarray = field(repr=False)

    @property
    def offset(self) -> float:
        return float(self.normal @ self.point)

    @classmethod
    def from_estimate(cls, points, toward=None) -> "PlaneModel":
        """Fit a plane to ``points`` (n, 3).

        ``toward`` (a point, e.g. the camera pinhole) orients the normal to that side;
        otherwise the normal's largest component is made positive.
        """
        p = _as_points(points, 3, "plane")
        centroid = p.mean(axis=0)
        q = p - centroid
        w, v = np.linalg.eigh(q.T @ q)
        if w[1] <= 1e-12 * max(w[2], 1e-300):
            raise FitError("plane: the points are collinear; the plane is undetermined")
        n = v[:, 0]
        if toward is not None:
            if n @ (np.asarray(toward, float) - centroid) < 0:
                n = -n
        elif n[np.argmax(np.abs(n))] < 0:
            n = -n
        r = q @ n
        return cls(n, centroid, float(np.sqrt(np.mean(r * r))), float(r.max() - r.min()), len(p),
                   np.array([w[2], w[1]]), np.stack([v[:, 2], v[:, 1]]))

    def residuals(self, points) -> np.ndarray:
        """Signed orthogonal distances, shape (n,); positive on the normal's side."""
        return (np.asarray(points, float) - self.point) @ self.normal

    def distance(self, point) -> float:
        """Signed distance of one point (3,) from the plane."""
        return float((np.asarray(point, float) - self.point) @ self.normal)

    def distance_variance(self, point) -> float:
        """Variance of :meth:`distance` from the plane fit's own noise, mm^2.

        Offset error ``s^2/n`` plus the tilt errors ``s^2 / spread_k`` times the
        squared in-plane lever arm of ``point`` from the centroid along each axis.
        """
        if self.n_points <= 3:
            return float("nan")
        s2 = self.rms**2 * self.n_points / (self.n_points - 3)
        lever = self.axes @ (np.asarray(point, float) - self.point)
        return float(s2 * (1.0 / self.n_points + np.sum(lever**2 / self.spread)))

    def to_dict(self) -> dict:
        return {
            "nx": float(self.normal[0]), "ny": float(self.normal[1]), "nz": float(self.normal[2]),
            "offset_mm": self.offset, "x_mm": float(self.point[0]), "y_mm": float(self.point[1]),
            "z_mm": float(self.point[2]), "rms_mm": self.rms, "flatness_mm": self.flatness,
            "n_points": self.n_points,
        }
