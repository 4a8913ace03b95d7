"""Compiled geometry for the virtual scanner: ray/primitive intersection and the
14-parameter sensor model, one point at a time (numba).

Primitives are packed into a float array ``prims`` of shape (n, N_PRIM_COLS) with
a parallel int array ``kinds``:

==========  =========================================================================
kind        columns used
==========  =========================================================================
SPHERE      P = centre, RADIUS
CYLINDER    P = start of the axis, A = unit axis, RADIUS, LENGTH (closed, flat ends)
BOX         P = centre, A, B, C = unit local axes, HALF = half sizes along them
PLANE       P = a point, A = unit normal (two-sided, infinite)
PANEL       P = origin of the panel frame, A, B = its unit x and y axes (z = A x B),
            PANEL_K = curvatures (kx, ky) 1/mm, PANEL_HALF = half sizes (a, b) mm,
            PANEL_CUBIC = cubic coefficients (c30, c21, c12, c03) mm (two-sided, open)
==========  =========================================================================

plus a bounding sphere (``BOUND`` centre, ``BOUND_R`` radius; infinite for planes)
used to cull primitives per image tile. Normals are outward (for planes and panels:
facing the ray).

The panel is the free-form patch z = f(x, y) of its own frame over |x| <= a, |y| <= b::

    f = kx x^2 / 2 + ky y^2 / 2 + c30 u^3 + c21 u^2 v + c12 u v^2 + c03 v^3,   u = x/a, v = y/b

(a paraboloid osculating the sphere of radius 1/kx, 1/ky at its vertex, plus a
smooth cubic; each c is the cubic's sag at the patch edge in mm). Along a ray f - z
is a polynomial of degree 2 (no cubic: solved in closed form) or 3 (its real roots
are bracketed between the critical points within the patch's t-interval and polished
by safeguarded Newton).

The sensor model mirrors :mod:`fringecal.sensor` exactly (distortion of ideal
coordinates, Newton inversion), packed as ``sensor_pack``, plus a thin-prism term
outside the 14-parameter model (``xi += s1 r^2, eta += s2 r^2``, r the ideal radius;
zero unless the simulation's ``thin_prism_corner_px`` switch is on), which the
calibration cannot represent. Its inversion wraps the Newton iteration in a
fixed-point loop on the (micrometre-sized) prism term.

A sensor with a correction field (:attr:`fringecal.sensor.Sensor.field`, e.g. the
simulation's ``lens_field_rms_um``) gets a longer pack: after the 22 entries above the
clamp (width, height mm), ``1 / R`` and the degree D, then the field's coefficients over
the scalar monomials ``u^a v^b`` (b = 0..D, a = 0..D-b; x then y per monomial) in
``u, v = m / R`` (:func:`field_pack`). :func:`image_ray` then corrects the measured point
``m`` to ``m - f(m)`` first, and :func:`project_point` returns the measured point of the
14-parameter (+prism) projection ``b``, the root of ``m - f(m) = b`` that
:meth:`fringecal.lens.field.CorrectionField.measured` finds (by Newton here:
:func:`field_measured`). Without a field the pack keeps its
22 entries and both functions are the same arithmetic as before.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fringecal.lens.field import CorrectionField, _basis_matrix, _exponents
from fringecal.lens.inversion import newton_step
from fringecal.sensor import Sensor

SPHERE, CYLINDER, BOX, PLANE, PANEL = 0, 1, 2, 3, 4
P, A, B, C = 0, 3, 6, 9
RADIUS, LENGTH, HALF, BOUND, BOUND_R = 12, 13, 14, 17, 20
#: the panel's own columns (its z axis is not stored: A x B)
PANEL_K, PANEL_HALF, PANEL_CUBIC = 9, 11, 13
N_PRIM_COLS = 21

NO_HIT = np.inf


#: Entries of a sensor pack without a correction field.
PACK_SIZE = 22


def field_pack(field: CorrectionField) -> np.ndarray:
    """The pack's tail for a correction field (module notes): clamp, 1 / R, D, then
    (x, y) coefficients of ``u^a v^b`` for b = 0..D, a = 0..D-b."""
    D = int(field.degree)
    mono = _basis_matrix(float(field.width_mm), float(field.height_mm), D) @ field.coefficients
    table = np.zeros((D + 1, D + 1, 2))  # [power of v, power of u, axis]
    for c, (a, b, axis) in zip(mono, _exponents(D)):
        table[b, a, axis] += c
    coefs = [table[b, a] for b in range(D + 1) for a in range(D + 1 - b)]
    return np.concatenate([[field.width_mm, field.height_mm, 1.0 / field.radius_mm, D], np.ravel(coefs)])


def sensor_pack(sensor: Sensor, prism=(0.0, 0.0)) -> np.ndarray:
    """(22,) float: pinhole (3), R row-major (9), xi_h, eta_h, c, k1, k2, k3, p1, p2,
    thin prism s1, s2 (mm^-1; the renderer's only, see the module notes); followed by
    :func:`field_pack` when the sensor has a correction field."""
    p = sensor.params
    pack = np.concatenate([p[0:3], sensor.R.ravel(), p[6:14], np.asarray(prism, float).reshape(2)])
    if sensor.has_field:
        pack = np.concatenate([pack, field_pack(sensor.field)])
    return pack


@njit(cache=True)
def _field_eval(mx, my, s, jacobian):
    """(fx, fy, dfx/dmx, dfx/dmy, dfy/dmx, dfy/dmy) of the field of pack ``s`` at the
    measured point (mm; derivatives only if ``jacobian``, else 0): Horner in u, then v."""
    wx, wy, inv_r = s[22], s[23], s[24]
    D = int(s[25])
    u = min(max(mx, -wx), wx) * inv_r
    v = min(max(my, -wy), wy) * inv_r
    fx = fy = fxu = fyu = fxv = fyv = 0.0
    for b in range(D, -1, -1):  # v^b rows, highest first
        row = 26 + 2 * (b * (D + 1) - b * (b - 1) // 2)
        px = py = pxu = pyu = 0.0
        for a in range(D - b, -1, -1):
            k = row + 2 * a
            if jacobian:
                pxu = pxu * u + px
                pyu = pyu * u + py
            px = px * u + s[k]
            py = py * u + s[k + 1]
        if jacobian:
            fxv = fxv * v + fx
            fyv = fyv * v + fy
            fxu = fxu * v + pxu
            fyu = fyu * v + pyu
        fx = fx * v + px
        fy = fy * v + py
    # d/dm = d/du / R inside the clamp, 0 beyond it
    su = inv_r if abs(mx) < wx else 0.0
    sv = inv_r if abs(my) < wy else 0.0
    return fx, fy, fxu * su, fxv * sv, fyu * su, fyv * sv


@njit(cache=True)
def field_value(mx, my, s):
    """The correction field f (mm) of pack ``s`` at the measured point (mx, my) mm
    (clamped to +-(width, height) like :meth:`.CorrectionField.basis`)."""
    fx, fy, _, _, _, _ = _field_eval(mx, my, s, False)
    return fx, fy


@njit(cache=True)
def field_measured(bx, by, s):
    """The measured point m with ``m - f(m) = b`` (mm): Newton on ``m - f(m) - b`` from
    ``b`` (the same root as :meth:`.CorrectionField.measured`'s fixed point, in 3
    evaluations instead of ~6 for a field of micrometres)."""
    mx, my = bx, by
    for _ in range(30):
        fx, fy, jxx, jxy, jyx, jyy = _field_eval(mx, my, s, True)
        rx, ry = mx - fx - bx, my - fy - by
        a, b_, c, d = 1.0 - jxx, -jxy, -jyx, 1.0 - jyy
        det = a * d - b_ * c
        dx = -(d * rx - b_ * ry) / det
        dy = -(a * ry - c * rx) / det
        mx, my = mx + dx, my + dy
        if not max(abs(dx), abs(dy)) > 1e-13:
            break
    return mx, my


@njit(cache=True)
def _newton_undistort(mx, my, s, gx, gy):
    k1, k2, k3, p1, p2 = s[15], s[16], s[17], s[18], s[19]
    x, y = gx, gy
    if k1 == 0.0 and k2 == 0.0 and k3 == 0.0 and p1 == 0.0 and p2 == 0.0:
        return mx, my, True
    ok = False
    for _ in range(30):
        x, y, step, det, tr = newton_step(x, y, mx, my, k1, k2, k3, p1, p2)
        if step <= 1e-13 * (1 + abs(x) + abs(y)):
            ok = det > 0 and tr > 0
            break
    return x, y, ok


@njit(cache=True)
def undistort_point(mx, my, s, gx, gy):
    """Distorted (relative to the principal point) -> ideal image mm, by Newton from
    the guess (gx, gy).

    Same iteration and tolerance as :func:`fringecal.sensor.undistort`; returns
    (x, y, converged). With a thin-prism term, Newton inverts the 14-parameter part
    for ``m - s r(u)^2`` and a fixed-point loop updates ``u`` (contraction factor
    ~ 2 |s| r, below 1e-5 for micrometre terms).
    """
    s1, s2 = s[20], s[21]
    if s1 == 0.0 and s2 == 0.0:
        return _newton_undistort(mx, my, s, gx, gy)
    x, y, ok = gx, gy, False
    for _ in range(20):
        r2 = x * x + y * y
        nx, ny, ok = _newton_undistort(mx - s1 * r2, my - s2 * r2, s, x, y)
        moved = abs(nx - x) + abs(ny - y)
        x, y = nx, ny
        if moved <= 1e-13 * (1 + abs(x) + abs(y)):
            break
    return x, y, ok


@njit(cache=True)
def image_ray(xi, eta, s, shift_x, shift_y):
    """Image-plane mm -> (dx, dy, dz, ok, ideal - distorted x, y): the unit world
    direction from the pinhole; Newton starts from the distorted point plus the
    (ideal - distorted) shift of a nearby point, so neighbours converge in 1-2 steps.
    With a correction field the measured point is corrected first (``m - f(m)``)."""
    if s.shape[0] > PACK_SIZE:
        fx, fy = field_value(xi, eta, s)
        xi, eta = xi - fx, eta - fy
    mx, my = xi - s[12], eta - s[13]
    x, y, ok = undistort_point(mx, my, s, mx + shift_x, my + shift_y)
    lx, ly, lz = -x, -y, s[14]
    # world = R^T local (R row-major at s[3:12])
    dx = s[3] * lx + s[6] * ly + s[9] * lz
    dy = s[4] * lx + s[7] * ly + s[10] * lz
    dz = s[5] * lx + s[8] * ly + s[11] * lz
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    return dx / n, dy / n, dz / n, ok, x - mx, y - my


@njit(cache=True)
def project_point(X, Y, Z, s):
    """World point -> (xi, eta, z') on the image plane (mm, distorted); z' <= 0 is behind.
    With a correction field: the measured point ``m`` with ``m - f(m)`` = the projection."""
    vx, vy, vz = X - s[0], Y - s[1], Z - s[2]
    xs = s[3] * vx + s[4] * vy + s[5] * vz
    ys = s[6] * vx + s[7] * vy + s[8] * vz
    zs = s[9] * vx + s[10] * vy + s[11] * vz
    if zs <= 0:
        return np.nan, np.nan, zs
    x = -s[14] * xs / zs
    y = -s[14] * ys / zs
    k1, k2, k3, p1, p2 = s[15], s[16], s[17], s[18], s[19]
    r2 = x * x + y * y
    q = r2 * (k1 + r2 * (k2 + r2 * k3))
    xi = s[12] + x + x * q + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y
    eta = s[13] + y + y * q + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y
    if s[20] != 0.0 or s[21] != 0.0:  # thin prism (renderer only)
        xi += s[20] * r2
        eta += s[21] * r2
    if s.shape[0] > PACK_SIZE:  # correction field: the measured point m = b + f(m)
        xi, eta = field_measured(xi, eta, s)
    return xi, eta, zs


@njit(cache=True)
def _sphere(pr, ox, oy, oz, dx, dy, dz, tmin):
    cx, cy, cz, r = pr[P], pr[P + 1], pr[P + 2], pr[RADIUS]
    ocx, ocy, ocz = ox - cx, oy - cy, oz - cz
    b = ocx * dx + ocy * dy + ocz * dz
    # distance of the centre from the ray, computed without cancellation
    qx, qy, qz = ocx - b * dx, ocy - b * dy, ocz - b * dz
    disc = r * r - (qx * qx + qy * qy + qz * qz)
    if disc < 0:
        return NO_HIT, 0.0, 0.0, 0.0
    h = math.sqrt(disc)
    t = -b - h
    if t <= tmin:
        t = -b + h
        if t <= tmin:
            return NO_HIT, 0.0, 0.0, 0.0
    nx, ny, nz = (ox + t * dx - cx) / r, (oy + t * dy - cy) / r, (oz + t * dz - cz) / r
    return t, nx, ny, nz


@njit(cache=True)
def _cylinder(pr, ox, oy, oz, dx, dy, dz, tmin):
    px, py, pz = pr[P], pr[P + 1], pr[P + 2]
    ax, ay, az = pr[A], pr[A + 1], pr[A + 2]
    r, L = pr[RADIUS], pr[LENGTH]
    ocx, ocy, ocz = ox - px, oy - py, oz - pz
    oa = ocx * ax + ocy * ay + ocz * az
    da = dx * ax + dy * ay + dz * az
    # components perpendicular to the axis
    wx, wy, wz = ocx - oa * ax, ocy - oa * ay, ocz - oa * az
    ex, ey, ez = dx - da * ax, dy - da * ay, dz - da * az
    best = NO_HIT
    nx = ny = nz = 0.0
    qa = ex * ex + ey * ey + ez * ez
    if qa > 1e-300:
        qb = wx * ex + wy * ey + wz * ez
        # w + t e closest to the axis at t0 = -qb/qa; stable form of the discriminant
        t0 = -qb / qa
        mx, my, mz = wx + t0 * ex, wy + t0 * ey, wz + t0 * ez
        disc = (r * r - (mx * mx + my * my + mz * mz)) / qa
        if disc >= 0:
            h = math.sqrt(disc)
            for t in (t0 - h, t0 + h):
                if t > tmin and t < best:
                    ha = oa + t * da
                    if 0.0 <= ha <= L:
                        best = t
                        nx = (wx + t * ex) / r
                        ny = (wy + t * ey) / r
                        nz = (wz + t * ez) / r
    if abs(da) > 1e-300:
        for end in range(2):
            ha = 0.0 if end == 0 else L
            t = (ha - oa) / da
            if t > tmin and t < best:
                rx, ry, rz = wx + t * ex, wy + t * ey, wz + t * ez
                if rx * rx + ry * ry + rz * rz <= r * r:
                    best = t
                    sgn = -1.0 if end == 0 else 1.0
                    nx, ny, nz = sgn * ax, sgn * ay, sgn * az
    return best, nx, ny, nz


@njit(cache=True)
def _box(pr, ox, oy, oz, dx, dy, dz, tmin):
    vx, vy, vz = ox - pr[P], oy - pr[P + 1], oz - pr[P + 2]
    tnear, tfar = -np.inf, np.inf
    near_axis, near_sign = -1, 1.0
    far_axis, far_sign = -1, 1.0
    for i in range(3):
        base = A + 3 * i
        ux, uy, uz = pr[base], pr[base + 1], pr[base + 2]
        o = vx * ux + vy * uy + vz * uz
        d = dx * ux + dy * uy + dz * uz
        h = pr[HALF + i]
        if abs(d) < 1e-300:
            if abs(o) > h:
                return NO_HIT, 0.0, 0.0, 0.0
            continue
        t1 = (-h - o) / d
        t2 = (h - o) / d
        s1 = -1.0
        if t1 > t2:
            t1, t2 = t2, t1
            s1 = 1.0
        if t1 > tnear:
            tnear, near_axis, near_sign = t1, i, s1
        if t2 < tfar:
            tfar, far_axis, far_sign = t2, i, -s1
    if tnear > tfar or tfar <= tmin:
        return NO_HIT, 0.0, 0.0, 0.0
    if tnear > tmin:
        t, axis, sgn = tnear, near_axis, near_sign
    else:
        t, axis, sgn = tfar, far_axis, far_sign
    base = A + 3 * axis
    return t, sgn * pr[base], sgn * pr[base + 1], sgn * pr[base + 2]


@njit(cache=True)
def _plane(pr, ox, oy, oz, dx, dy, dz, tmin):
    nx, ny, nz = pr[A], pr[A + 1], pr[A + 2]
    den = dx * nx + dy * ny + dz * nz
    if abs(den) < 1e-300:
        return NO_HIT, 0.0, 0.0, 0.0
    t = ((pr[P] - ox) * nx + (pr[P + 1] - oy) * ny + (pr[P + 2] - oz) * nz) / den
    if t <= tmin:
        return NO_HIT, 0.0, 0.0, 0.0
    if den > 0:
        return t, -nx, -ny, -nz
    return t, nx, ny, nz


@njit(cache=True)
def _cubic_terms(c30, c21, c12, c03, u, v):
    """Cubic part of the panel height and its derivatives in u = x/a, v = y/b:
    (value, d/du, d/dv, d2/du2, d2/dudv, d2/dv2)."""
    val = ((c30 * u + c21 * v) * u + c12 * v * v) * u + c03 * v * v * v
    du = (3 * c30 * u + 2 * c21 * v) * u + c12 * v * v
    dv = (c21 * u + 2 * c12 * v) * u + 3 * c03 * v * v
    return val, du, dv, 6 * c30 * u + 2 * c21 * v, 2 * c21 * u + 2 * c12 * v, 2 * c12 * u + 6 * c03 * v


@njit(cache=True)
def _poly3(g0, g1, g2, g3, t):
    return ((g3 * t + g2) * t + g1) * t + g0


@njit(cache=True)
def _root_in(g0, g1, g2, g3, a, b, ga):
    """The root of the cubic g in [a, b], where g is monotone and changes sign
    (``ga`` = g(a)): Newton steps kept inside a shrinking bracket, else bisection."""
    lo, hi = a, b
    t = 0.5 * (a + b)
    for _ in range(200):
        gt = _poly3(g0, g1, g2, g3, t)
        if gt == 0.0:
            return t
        if (gt < 0) == (ga < 0):
            lo = t
        else:
            hi = t
        slope = (3 * g3 * t + 2 * g2) * t + g1
        step_ok = False
        if slope != 0.0:
            tn = t - gt / slope
            if lo < tn < hi:
                step_ok = True
        if not step_ok:
            tn = 0.5 * (lo + hi)
        if abs(tn - t) <= 1e-13 * (1.0 + abs(t)) or hi - lo <= 1e-13 * (1.0 + abs(t)):
            return tn
        t = tn
    return t


@njit(cache=True)
def _panel(pr, ox, oy, oz, dx, dy, dz, tmin):
    px, py, pz = pr[P], pr[P + 1], pr[P + 2]
    ax, ay, az = pr[A], pr[A + 1], pr[A + 2]
    bx, by, bz = pr[B], pr[B + 1], pr[B + 2]
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    kx, ky = pr[PANEL_K], pr[PANEL_K + 1]
    ha, hb = pr[PANEL_HALF], pr[PANEL_HALF + 1]
    c30, c21, c12, c03 = pr[PANEL_CUBIC], pr[PANEL_CUBIC + 1], pr[PANEL_CUBIC + 2], pr[PANEL_CUBIC + 3]
    # start from the ray's point nearest the panel origin (small numbers, no cancellation)
    t0 = (px - ox) * dx + (py - oy) * dy + (pz - oz) * dz
    sx, sy, sz = ox + t0 * dx - px, oy + t0 * dy - py, oz + t0 * dz - pz
    lx, ly, lz = sx * ax + sy * ay + sz * az, sx * bx + sy * by + sz * bz, sx * cx + sy * cy + sz * cz
    ex, ey, ez = dx * ax + dy * ay + dz * az, dx * bx + dy * by + dz * bz, dx * cx + dy * cy + dz * cz
    tl = tmin - t0
    # g(s) = z - f(x, y) along the ray x = l + s e: g0 + g1 s + g2 s^2 + g3 s^3
    g0 = lz - 0.5 * (kx * lx * lx + ky * ly * ly)
    g1 = ez - (kx * lx * ex + ky * ly * ey)
    g2 = -0.5 * (kx * ex * ex + ky * ey * ey)
    g3 = 0.0
    s_hit = NO_HIT
    if c30 == 0.0 and c21 == 0.0 and c12 == 0.0 and c03 == 0.0:
        r1 = r2 = NO_HIT
        if g2 == 0.0:
            if g1 != 0.0:
                r1 = -g0 / g1
        else:
            disc = g1 * g1 - 4.0 * g2 * g0
            if disc >= 0.0:
                q = -0.5 * (g1 + math.copysign(math.sqrt(disc), g1))
                if q != 0.0:
                    r1, r2 = q / g2, g0 / q
                else:
                    r1 = 0.0
                if r2 < r1:
                    r1, r2 = r2, r1
        for r in (r1, r2):
            if r > tl and r < NO_HIT:
                if abs(lx + r * ex) <= ha and abs(ly + r * ey) <= hb:
                    s_hit = r
                    break
    else:
        u0, u1, v0, v1 = lx / ha, ex / ha, ly / hb, ey / hb
        q0, qu, qv, quu, quv, qvv = _cubic_terms(c30, c21, c12, c03, u0, v0)
        q3 = _cubic_terms(c30, c21, c12, c03, u1, v1)[0]
        g0 -= q0
        g1 -= qu * u1 + qv * v1
        g2 -= 0.5 * (quu * u1 * u1 + 2.0 * quv * u1 * v1 + qvv * v1 * v1)
        g3 = -q3
        # the ray's parameter interval over the patch (|x| <= a, |y| <= b)
        lo, hi = tl, np.inf
        inside = True
        for o, e, h in ((lx, ex, ha), (ly, ey, hb)):
            if abs(e) < 1e-300:
                if abs(o) > h:
                    inside = False
            else:
                s1, s2 = (-h - o) / e, (h - o) / e
                if s1 > s2:
                    s1, s2 = s2, s1
                lo, hi = max(lo, s1), min(hi, s2)
        if inside and lo <= hi:
            if hi == np.inf:  # along the panel's z axis: g is linear
                if g1 != 0.0 and -g0 / g1 > tl:
                    s_hit = -g0 / g1
            else:
                # split [lo, hi] at the critical points of g: monotone pieces
                cuts = np.empty(4)
                cuts[0] = lo
                n_cut = 1
                da, db, dc = 3.0 * g3, 2.0 * g2, g1
                c1 = c2 = np.inf
                if da == 0.0:
                    if db != 0.0:
                        c1 = -dc / db
                else:
                    disc = db * db - 4.0 * da * dc
                    if disc >= 0.0:
                        q = -0.5 * (db + math.copysign(math.sqrt(disc), db))
                        c1 = q / da
                        c2 = dc / q if q != 0.0 else c1
                        if c2 < c1:
                            c1, c2 = c2, c1
                for c in (c1, c2):
                    if lo < c < hi:
                        cuts[n_cut] = c
                        n_cut += 1
                cuts[n_cut] = hi
                n_cut += 1
                for i in range(n_cut - 1):
                    a_, b_ = cuts[i], cuts[i + 1]
                    ga, gb = _poly3(g0, g1, g2, g3, a_), _poly3(g0, g1, g2, g3, b_)
                    if ga == 0.0 and a_ > tl:
                        s_hit = a_
                        break
                    if gb == 0.0 or (ga < 0) != (gb < 0):
                        r = b_ if gb == 0.0 else _root_in(g0, g1, g2, g3, a_, b_, ga)
                        if r > tl:
                            s_hit = r
                            break
    if s_hit == NO_HIT:
        return NO_HIT, 0.0, 0.0, 0.0
    x, y = lx + s_hit * ex, ly + s_hit * ey
    _, qu, qv, _, _, _ = _cubic_terms(c30, c21, c12, c03, x / ha, y / hb)
    fx, fy = kx * x + qu / ha, ky * y + qv / hb
    nn = math.sqrt(fx * fx + fy * fy + 1.0)
    # local normal (-fx, -fy, 1) / nn to the world: R^T n
    nx = (-fx * ax - fy * bx + cx) / nn
    ny = (-fx * ay - fy * by + cy) / nn
    nz = (-fx * az - fy * bz + cz) / nn
    if nx * dx + ny * dy + nz * dz > 0:
        nx, ny, nz = -nx, -ny, -nz
    return t0 + s_hit, nx, ny, nz


@njit(cache=True)
def intersect(prims, kinds, j, ox, oy, oz, dx, dy, dz, tmin):
    """First hit (t, nx, ny, nz) of the ray o + t d (t > tmin) with primitive j (unit d)."""
    k = kinds[j]
    pr = prims[j]
    if k == SPHERE:
        return _sphere(pr, ox, oy, oz, dx, dy, dz, tmin)
    if k == CYLINDER:
        return _cylinder(pr, ox, oy, oz, dx, dy, dz, tmin)
    if k == BOX:
        return _box(pr, ox, oy, oz, dx, dy, dz, tmin)
    if k == PLANE:
        return _plane(pr, ox, oy, oz, dx, dy, dz, tmin)
    return _panel(pr, ox, oy, oz, dx, dy, dz, tmin)


@njit(cache=True)
def nearest_hit(prims, kinds, cand, n_cand, ox, oy, oz, dx, dy, dz, tmin):
    """Nearest hit among primitives ``cand[:n_cand]``: (t, primitive or -1, nx, ny, nz)."""
    best, jbest = NO_HIT, -1
    bnx = bny = bnz = 0.0
    for c in range(n_cand):
        j = cand[c]
        t, nx, ny, nz = intersect(prims, kinds, j, ox, oy, oz, dx, dy, dz, tmin)
        if t < best:
            best, jbest, bnx, bny, bnz = t, j, nx, ny, nz
    return best, jbest, bnx, bny, bnz


@njit(cache=True)
def form_deviation(form, j, nx, ny, nz):
    """Radial form error (mm) of sphere primitive ``j`` at the outward unit normal n:
    ``sum_m a_m P_l(u_m . n)`` over the rows (ux, uy, uz, a, l) of ``form[j]``
    (zonal terms, Legendre polynomial P_l by its recurrence)."""
    d = 0.0
    for m in range(form.shape[1]):
        a = form[j, m, 3]
        if a == 0.0:
            continue
        c = form[j, m, 0] * nx + form[j, m, 1] * ny + form[j, m, 2] * nz
        p_prev, p = 1.0, c
        for k in range(1, int(form[j, m, 4])):
            p_prev, p = p, ((2 * k + 1) * c * p - k * p_prev) / (k + 1)
        d += a * p
    return d


@njit(cache=True)
def form_hit(form, kinds, j, t, dx, dy, dz, nx, ny, nz):
    """Ray parameter of the as-built surface near the nominal hit ``t`` on primitive j:
    a sphere's radial deviation delta moves the hit by ``-delta / cos i`` along the
    unit ray d (first order; ``cos i`` held above 0.1 at grazing incidence). The
    normal stays the nominal one (form slopes are ~1e-4 rad). ``form`` (n_prim, m, 5)
    is empty when form errors are off."""
    if form.shape[0] == 0 or kinds[j] != SPHERE:
        return t
    cos_i = abs(dx * nx + dy * ny + dz * nz)
    return t - form_deviation(form, j, nx, ny, nz) / max(cos_i, 0.1)


@njit(cache=True)
def cone_candidates(prims, ox, oy, oz, ax, ay, az, cos_half, max_dist, out):
    """Primitives whose bounding sphere meets the cone (apex o, unit axis a, half-angle
    acos(cos_half)) within ``max_dist`` of the apex; writes their indices to ``out``
    and returns how many."""
    half = math.acos(min(1.0, max(-1.0, cos_half)))
    n = 0
    for j in range(prims.shape[0]):
        rb = prims[j, BOUND_R]
        vx, vy, vz = prims[j, BOUND] - ox, prims[j, BOUND + 1] - oy, prims[j, BOUND + 2] - oz
        dist = math.sqrt(vx * vx + vy * vy + vz * vz)
        if dist - rb > max_dist:
            continue
        if not rb < np.inf or dist <= rb * (1 + 1e-9) + 1e-9:
            out[n] = j
            n += 1
            continue
        cb = (vx * ax + vy * ay + vz * az) / dist
        beta = math.acos(min(1.0, max(-1.0, cb)))
        if beta <= half + math.asin(rb / dist) + 1e-9:
            out[n] = j
            n += 1
    return n
