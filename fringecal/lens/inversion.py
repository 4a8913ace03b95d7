"""The lens model's Newton inversion as compiled scalar functions, shared by the
compiled kernels (point clouds, the virtual scanner, the bundle adjustment).

Same model and iteration as :func:`fringecal.sensor.undistort`: distortion ``d(u)`` of
ideal coordinates ``u`` relative to the principal point (radial k1..k3, Brown
tangential p1, p2, and optionally OpenCV's thin-prism s1..s4), inverted by Newton's
method on ``u + d(u) = m``. Inlined into their callers, so they compile with the
caller's flags. The thin-prism variants are separate functions so that the
14-parameter path keeps its exact arithmetic (and speed) when the terms are zero.
"""

from __future__ import annotations

import numba as nb

__all__ = ["first_order_inverse", "newton_step", "first_order_inverse_prism", "newton_step_prism", "prism_jacobian"]


@nb.njit(cache=True, inline="always")
def first_order_inverse(mx, my, k1, k2, k3, p1, p2):
    """``m - d(m)``: a Newton start off by about ``|d'| |d|`` (~1e-3 mm for the thesis lenses)."""
    r2 = mx * mx + my * my
    q = r2 * (k1 + r2 * (k2 + r2 * k3))
    return (mx - (mx * q + p1 * (r2 + 2 * mx * mx) + 2 * p2 * mx * my),
            my - (my * q + p2 * (r2 + 2 * my * my) + 2 * p1 * mx * my))


@nb.njit(cache=True, inline="always")
def newton_step(x, y, mx, my, k1, k2, k3, p1, p2):
    """One Newton step for ``u + d(u) = m`` from ``(x, y)``.

    Returns the new ``(x, y)``, the step length ``|sx| + |sy|``, and the Jacobian's
    determinant and trace at the old point (both positive unless the model folds over).
    """
    r2 = x * x + y * y
    q = r2 * (k1 + r2 * (k2 + r2 * k3))
    fx = x + x * q + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y - mx
    fy = y + y * q + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y - my
    g = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    j11 = 1 + q + 2 * x * x * g + 6 * p1 * x + 2 * p2 * y
    j22 = 1 + q + 2 * y * y * g + 6 * p2 * y + 2 * p1 * x
    j12 = 2 * x * y * g + 2 * p1 * y + 2 * p2 * x
    det = j11 * j22 - j12 * j12
    inv = 1.0 / det
    sx = (j22 * fx - j12 * fy) * inv
    sy = (j11 * fy - j12 * fx) * inv
    return x - sx, y - sy, abs(sx) + abs(sy), det, j11 + j22


@nb.njit(cache=True, inline="always")
def first_order_inverse_prism(mx, my, k1, k2, k3, p1, p2, s1, s2, s3, s4):
    """:func:`first_order_inverse` with the thin-prism terms ``s1..s4`` (OpenCV's) added to d."""
    r2 = mx * mx + my * my
    q = r2 * (k1 + r2 * (k2 + r2 * k3))
    return (mx - (mx * q + p1 * (r2 + 2 * mx * mx) + 2 * p2 * mx * my + r2 * (s1 + s2 * r2)),
            my - (my * q + p2 * (r2 + 2 * my * my) + 2 * p1 * mx * my + r2 * (s3 + s4 * r2)))


@nb.njit(cache=True, inline="always")
def prism_jacobian(x, y, k1, k2, k3, p1, p2, s1, s2, s3, s4):
    """``A = I + dd/du`` of the model with thin-prism terms at ideal ``(x, y)``:
    ``(a11, a12, a21, a22, dx, dy)`` with ``d = (dx, dy)`` the distortion there.

    The thin-prism terms ``dx += s1 r^2 + s2 r^4, dy += s3 r^2 + s4 r^4`` make A
    non-symmetric (``a12 != a21``)."""
    r2 = x * x + y * y
    q = r2 * (k1 + r2 * (k2 + r2 * k3))
    dx = x * q + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y + r2 * (s1 + s2 * r2)
    dy = y * q + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y + r2 * (s3 + s4 * r2)
    g = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    t1 = 2 * (s1 + 2 * s2 * r2)
    t3 = 2 * (s3 + 2 * s4 * r2)
    j12 = 2 * x * y * g + 2 * p1 * y + 2 * p2 * x
    a11 = 1 + q + 2 * x * x * g + 6 * p1 * x + 2 * p2 * y + x * t1
    a22 = 1 + q + 2 * y * y * g + 6 * p2 * y + 2 * p1 * x + y * t3
    return a11, j12 + y * t1, j12 + x * t3, a22, dx, dy


@nb.njit(cache=True, inline="always")
def newton_step_prism(x, y, mx, my, k1, k2, k3, p1, p2, s1, s2, s3, s4):
    """:func:`newton_step` for the model with thin-prism terms (same returns)."""
    a11, a12, a21, a22, dx, dy = prism_jacobian(x, y, k1, k2, k3, p1, p2, s1, s2, s3, s4)
    fx = x + dx - mx
    fy = y + dy - my
    det = a11 * a22 - a12 * a21
    inv = 1.0 / det
    sx = (a22 * fx - a12 * fy) * inv
    sy = (a11 * fy - a21 * fx) * inv
    return x - sx, y - sy, abs(sx) + abs(sy), det, a11 + a22
