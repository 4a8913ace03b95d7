"""The lens model's Newton inversion as compiled scalar functions, shared by the
compiled kernels (point clouds, the virtual scanner, the bundle adjustment).

Same model and iteration as :func:`fringecal.sensor.undistort`: distortion ``d(u)`` of
ideal coordinates ``u`` relative to the principal point (radial k1..k3, Brown
tangential p1, p2), inverted by Newton's method on ``u + d(u) = m``. Inlined into
their callers, so they compile with the caller's flags.
"""

from __future__ import annotations

import numba as nb

__all__ = ["first_order_inverse", "newton_step"]


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
