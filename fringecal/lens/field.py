"""A smooth correction field over a sensor's image plane: what a lens or a projector's
optics do beyond the 14 parameters and the thin-prism terms.

The field acts on *measured* image-plane coordinates ``m`` (camera pixels or projector
phases as mm, :meth:`fringecal.sensor.SensorFormat.pixel_to_mm`, centred on the format):
the sensor treats a measured point as the point ``m - f(m)`` of its 14-parameter model.
Because ``f`` depends on the observation alone, never on the other parameters, a
coefficient's derivative is the principal point's weighted by the basis function at the
observation (:mod:`fringecal.calibration.kernels`), and every consumer of a calibration
gets the field by correcting its observations first (:meth:`.Sensor.brown_image_mm`).
This is the "correction grid" of close-range photogrammetry, with a polynomial basis
instead of a grid so that a few hundred control points per image determine it.

Basis (``degree`` D, 4 for the calibration's ``field`` model)
-------------------------------------------------------------
Vector polynomials ``(u^a v^b, 0)`` and ``(0, u^a v^b)`` of total degree 2..D in
``u, v = m / R``, R half the format's diagonal, made orthonormal over the format (mean
squared length 1 on a 41 x 41 grid, Gram-Schmidt in the order of degree, power of v,
axis) and orthogonal to every field the 14 parameters absorb to first order, which are
taken out first:

* every field of degree 0 and 1 (principal point, principal distance, the rotation about
  the axis; the field also holds no affinity or shear, which the thesis's model lacks),
* the tangential terms p1 ``(3u^2 + v^2, 2uv)`` and p2 ``(2uv, u^2 + 3v^2)``,
* the tilts ``(u^2, uv)`` and ``(uv, v^2)`` (a small rotation about a sensor axis),
* the first radial term ``(u r^2, v r^2)``.

That span does not change when the origin moves (a principal point off the format's
centre), so the basis needs no parameter of the sensor. Of the 24 vector monomials of
degree 2..4, five lie in it: D = 4 leaves 19 basis fields per sensor, D = 6 leaves 45,
and the first 19 of those are D = 4's (the order of Gram-Schmidt), so a degree-6 field
holds the degree-4 model plus what it cannot describe. The thin-prism terms s1..s4 lie
in the degree-2 and degree-4 span: a model with the field does not free them as well.

Coefficients are in mm: ``f(m) = sum_j a_j phi_j(m / R)``, each ``phi_j`` of RMS length
1 over the format, so ``a_j`` is the RMS of term j's displacement on the image plane.

>>> f = CorrectionField(15.1, 15.1, 4, np.zeros(19))
>>> f.n_terms, f.basis(np.zeros((1, 2))).shape
(19, (1, 2, 19))
>>> g = f.with_coefficients(np.eye(19)[0] * 1e-3)
>>> float(np.sqrt(np.mean(np.sum(g.value(format_grid(15.1, 15.1)) ** 2, axis=-1))))
0.001
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

__all__ = ["CorrectionField", "FIELD_DEGREE", "field_terms", "field_names", "format_grid", "FORMAT_GRID_POINTS"]

#: highest total degree of the calibration's correction field
FIELD_DEGREE = 4
#: grid points per axis of :func:`format_grid`
FORMAT_GRID_POINTS = 41
_DEPENDENT = 1e-8


def _exponents(degree: int) -> list[tuple[int, int, int]]:
    """(power of u, power of v, axis) of every vector monomial of degree 0..``degree``."""
    return [(d - i, i, axis) for d in range(degree + 1) for i in range(d + 1) for axis in (0, 1)]


def _monomials(uv: np.ndarray, degree: int) -> np.ndarray:
    """Vector monomials at normalised points (..., 2) -> (..., 2, M)."""
    exps = _exponents(degree)
    u, v = uv[..., 0], uv[..., 1]
    out = np.zeros(uv.shape[:-1] + (2, len(exps)))
    for j, (a, b, axis) in enumerate(exps):
        out[..., axis, j] = u ** a * v ** b
    return out


def format_grid(width_mm: float, height_mm: float) -> np.ndarray:
    """The 41 x 41 grid (n, 2) over the format, edges included, in mm from its centre:
    the grid the basis is orthonormal on (a field's RMS over it is ``|coefficients|``)."""
    x = np.linspace(-width_mm / 2, width_mm / 2, FORMAT_GRID_POINTS)
    y = np.linspace(-height_mm / 2, height_mm / 2, FORMAT_GRID_POINTS)
    return np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)


def _absorbed(degree: int) -> np.ndarray:
    """Coefficients (M, 11) over the vector monomials of the fields the 14 parameters absorb."""
    index = {e: j for j, e in enumerate(_exponents(degree))}
    fields = [{(0, 0, 0): 1}, {(0, 0, 1): 1}, {(1, 0, 0): 1}, {(0, 1, 0): 1}, {(1, 0, 1): 1}, {(0, 1, 1): 1},
              {(2, 0, 0): 3, (0, 2, 0): 1, (1, 1, 1): 2},     # p1
              {(1, 1, 0): 2, (2, 0, 1): 1, (0, 2, 1): 3},     # p2
              {(2, 0, 0): 1, (1, 1, 1): 1},                   # tilt about y
              {(1, 1, 0): 1, (0, 2, 1): 1},                   # tilt about x
              {(3, 0, 0): 1, (1, 2, 0): 1, (2, 1, 1): 1, (0, 3, 1): 1}]  # radial r^2
    out = np.zeros((len(index), len(fields)))
    for k, f in enumerate(fields):
        for e, c in f.items():
            out[index[e], k] = c
    return out


@lru_cache(maxsize=64)
def _basis_matrix(width_mm: float, height_mm: float, degree: int) -> np.ndarray:
    """Coefficients (M, K) of the orthonormal basis fields over the vector monomials."""
    radius = float(np.hypot(width_mm, height_mm)) / 2
    mono = _monomials(format_grid(width_mm, height_mm) / radius, degree)  # (G, 2, M)
    G, _, M = mono.shape
    vectors = mono.reshape(2 * G, M) / np.sqrt(G)  # inner product: mean squared length
    kept_fields, kept_coefs = [], []

    def add(vec, coef):
        for q, c in zip(kept_fields, kept_coefs):
            dot = q @ vec
            vec, coef = vec - dot * q, coef - dot * c
        for q, c in zip(kept_fields, kept_coefs):  # twice is enough (Kahan)
            dot = q @ vec
            vec, coef = vec - dot * q, coef - dot * c
        norm = np.linalg.norm(vec)
        return vec / norm, coef / norm, norm

    absorbed = _absorbed(degree)
    for k in range(absorbed.shape[1]):
        q, c, _ = add(vectors @ absorbed[:, k], absorbed[:, k].copy())
        kept_fields.append(q)
        kept_coefs.append(c)
    n_absorbed = len(kept_fields)
    for j, (a, b, _) in enumerate(_exponents(degree)):
        if a + b < 2:
            continue
        unit = np.zeros(M)
        unit[j] = 1.0
        before = np.linalg.norm(vectors[:, j])
        q, c, norm = add(vectors[:, j].copy(), unit)
        if norm > _DEPENDENT * before:
            kept_fields.append(q)
            kept_coefs.append(c)
    basis = np.stack(kept_coefs[n_absorbed:], axis=1)
    basis.setflags(write=False)
    return basis


def field_terms(degree: int = FIELD_DEGREE) -> int:
    """Number of basis fields of a correction field of ``degree`` (19 for 4)."""
    return _basis_matrix(1.0, 1.0, degree).shape[1]


def field_names(degree: int = FIELD_DEGREE) -> tuple[str, ...]:
    """Names of the coefficients: ``f01`` .. ``f19`` for degree 4."""
    return tuple(f"f{j + 1:02d}" for j in range(field_terms(degree)))


@dataclass(frozen=True)
class CorrectionField:
    """A correction field ``f`` (module notes) on a format of ``width_mm`` x ``height_mm``.

    Attributes
    ----------
    width_mm, height_mm : float
        The format the basis is orthonormal over.
    degree : int
        Highest total degree of the vector polynomials.
    coefficients : ndarray, shape (K,)
        mm; K = :func:`field_terms` (degree).
    """

    width_mm: float
    height_mm: float
    degree: int
    coefficients: np.ndarray = field(repr=False)

    def __post_init__(self):
        a = np.asarray(self.coefficients, float).reshape(-1)
        if a.shape[0] != self.n_terms:
            raise ValueError(f"a degree-{self.degree} correction field has {self.n_terms} coefficients, "
                             f"got {a.shape[0]}")
        a.setflags(write=False)
        object.__setattr__(self, "coefficients", a)

    @classmethod
    def zero(cls, width_mm: float, height_mm: float, degree: int = FIELD_DEGREE) -> "CorrectionField":
        return cls(float(width_mm), float(height_mm), int(degree), np.zeros(field_terms(degree)))

    @property
    def n_terms(self) -> int:
        return _basis_matrix(float(self.width_mm), float(self.height_mm), int(self.degree)).shape[1]

    @property
    def radius_mm(self) -> float:
        return float(np.hypot(self.width_mm, self.height_mm)) / 2

    @property
    def is_zero(self) -> bool:
        return not np.any(self.coefficients != 0.0)

    def with_coefficients(self, coefficients) -> "CorrectionField":
        return replace(self, coefficients=np.asarray(coefficients, float))

    def basis(self, image_mm) -> np.ndarray:
        """Basis fields at measured image-plane points (..., 2) mm -> (..., 2, K), dimensionless
        (NaN where a point is NaN)."""
        m = np.asarray(image_mm, float)
        B = _basis_matrix(float(self.width_mm), float(self.height_mm), int(self.degree))
        # beyond half a format outside the image the polynomials are clamped: nothing is
        # observed there, and a point projected from far outside must not blow up
        reach = np.array([self.width_mm, self.height_mm])
        return _monomials(np.clip(m, -reach, reach) / self.radius_mm, self.degree) @ B

    def value(self, image_mm) -> np.ndarray:
        """The field f (..., 2) mm at measured image-plane points (..., 2) mm."""
        return self.basis(image_mm) @ self.coefficients

    def corrected(self, image_mm) -> np.ndarray:
        """``m - f(m)``: the point of the 14-parameter model a measured point stands for."""
        m = np.asarray(image_mm, float)
        return m - self.value(m)

    def measured(self, corrected_mm, tol_mm: float = 1e-13, max_iter: int = 60) -> np.ndarray:
        """Inverse of :meth:`corrected`: the measured point ``m`` with ``m - f(m) = b``.

        Fixed-point iteration ``m = b + f(m)``: it contracts by the field's slope (about
        1e-5 for a field of micrometres over millimetres), so a few steps reach
        ``tol_mm``; NaN points stay NaN.
        """
        b = np.asarray(corrected_mm, float)
        m = b
        for _ in range(max_iter):
            nxt = b + self.value(m)
            step = np.nanmax(np.abs(nxt - m), initial=0.0)
            m = nxt
            if not step > tol_mm:
                break
        return m
