"""Compiled per-control-point kernels of the object-space bundle adjustment.

For one control point (a camera pixel with its decoded projector phases, on sphere i
of the artefact in measurement m) the two residuals of thesis eqs. 2-24 and 6-15 are

    alpha1 = signed closest-approach distance of the camera and projector rays
             (fringecal.triangulation convention: (o_p - o_c) . n,  n = d_c x d_p / |.|)
    alpha2 = |S - S_t| - r_i,   S the midpoint of closest approach,
             S_t = R_m^T s_i + t_m the CMM centre moved by the pose T_world_artefact of m.

Each depends on at most 34 parameters: the 14 of the camera, the 14 of the projector
(local slots 0..13 and 14..27) and the 6 of the pose (slots 28..33); alpha1 does not
depend on the pose. With free thin-prism terms (s1..s4 of camera and projector,
:mod:`fringecal.sensor`) there are 42: camera prism 34..37 and projector prism 38..41
after the 34 (:func:`local_slots`). With free correction fields
(:mod:`fringecal.lens.field`, K coefficients per sensor) 2 K more follow: camera field,
then projector field. A field corrects the observation, ``m - f(m)``, and depends on the
observation alone, so a coefficient's derivative is the principal point's weighted by its
basis function there: ``d/d a_j = phi_j,x(m) d/d xi_h + phi_j,y(m) d/d eta_h``; the
kernels take the observations already corrected and the basis at each one. The kernels
read the slot counts from their output shapes and basis arrays, and run the 34 slots'
loops with constant bounds and the same arithmetic either way. The analytic derivatives:

* ray of a sensor: direction D = R^T (-x, -y, c) (unnormalised; the midpoint and alpha1
  do not depend on the length of D), (x, y) the ideal image coordinates solving
  u + d(u; k, p) = m - h (Newton, as fringecal.sensor.undistort). By the implicit
  function theorem du/dtheta = -A^-1 dG/dtheta with A = I + dd/du, for theta in
  (xi_h, eta_h, k1, k2, k3, p1, p2); dD/dangle_k = (dR/dangle_k)^T v; dD/dc = R^T e3;
  the origin is the pinhole (x0, y0, z0).
* closest approach: with w = o_p - o_c, m = d_c x d_p, n = m/|m| and w_perp the part of
  w normal to n, d alpha1/d o_c = -n, d alpha1/d o_p = n,
  d alpha1/d d_c = (d_p x w_perp)/|m|, d alpha1/d d_p = (w_perp x d_c)/|m|.
  The midpoint's parameters s, t satisfy r.d_c = r.d_p = 0 (r = p_c - p_p); differentiating
  that 2x2 system gives dS, which only enters through q = (S - S_t)/|S - S_t|.
* sphere centre: dS_t/dt = I, dS_t/d angle_k = (dR/dangle_k)^T s_i.

``assemble`` sums, per chunk of control points of one (scanner, measurement) group,
the weighted outer products of the two Jacobian rows into small dense blocks in
parallel (numba prange); ``scatter`` adds the blocks into the global normal matrices.
The cost is linear in the number of control points; the global matrices are only
parameters x parameters.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from fringecal.lens.inversion import first_order_inverse, first_order_inverse_prism, newton_step, newton_step_prism, prism_jacobian

__all__ = ["N_LOCAL", "local_slots", "assemble", "scatter", "residual_rows", "replica_gradients"]

#: Local parameter slots per control point: camera 14, projector 14, pose 6.
N_LOCAL = 34
N_PRISM = 4


def local_slots(prism_free: bool, n_field: int = 0) -> int:
    """Local parameter slots per control point: 34, plus 8 with free thin-prism terms,
    plus 2 ``n_field`` with free correction fields of ``n_field`` coefficients."""
    return N_LOCAL + (2 * N_PRISM if prism_free else 0) + 2 * n_field


@njit(cache=True, nogil=True, inline="always")
def _field_slots(k, f0, nf, phi_c, phi_p, j1, j2):
    """Correction-field slots f0.. of control point k from its principal-point slots."""
    for f in range(nf):
        cx = phi_c[k, f, 0]
        cy = phi_c[k, f, 1]
        px = phi_p[k, f, 0]
        py = phi_p[k, f, 1]
        j1[f0 + f] = cx * j1[6] + cy * j1[7]
        j2[f0 + f] = cx * j2[6] + cy * j2[7]
        j1[f0 + nf + f] = px * j1[20] + py * j1[21]
        j2[f0 + nf + f] = px * j2[20] + py * j2[21]


LOSS_CODES = {"none": 0, "linear": 0, "huber": 1, "cauchy": 2}

_NEWTON_TOL = 1e-13


@njit(cache=True, nogil=True)
def _sensor_ray(p, sp, R, dR, mx, my, want_jac, npr, D, dD):
    """Unnormalised world direction D (3,) of the ray through image point (mx, my) mm.

    dD (3, 15) receives dD/d(omega, phi, kappa, xi_h, eta_h, c, k1, k2, k3, p1, p2) in
    columns 0..10 and, for a sensor with thin-prism terms ``sp`` = (s1..s4), dD/d(s1..s4)
    in columns 11..14 (without prism terms: only if ``npr`` > 0, their slots being free).
    Returns False where the distortion model cannot be inverted.
    """
    if sp[0] != 0.0 or sp[1] != 0.0 or sp[2] != 0.0 or sp[3] != 0.0:
        return _sensor_ray_prism(p, sp, R, dR, mx, my, want_jac, D, dD)
    k1 = p[9]
    k2 = p[10]
    k3 = p[11]
    p1 = p[12]
    p2 = p[13]
    c = p[8]
    ux = mx - p[6]
    uy = my - p[7]
    x = ux
    y = uy
    distorted = (k1 != 0.0) or (k2 != 0.0) or (k3 != 0.0) or (p1 != 0.0) or (p2 != 0.0)
    if distorted:
        # start from the first-order inverse u = m - d(m): one Newton step saved
        x, y = first_order_inverse(ux, uy, k1, k2, k3, p1, p2)
        last = np.inf
        for _ in range(30):
            x, y, last, det, tr = newton_step(x, y, ux, uy, k1, k2, k3, p1, p2)
            if not (det > 0.0):
                return False
            if last <= _NEWTON_TOL * (1.0 + abs(x) + abs(y)):
                break
        # as fringecal.sensor.undistort: refuse what did not converge
        if not (last <= 1e3 * _NEWTON_TOL * (1.0 + abs(x) + abs(y))):
            return False
    r2 = x * x + y * y
    if distorted:
        q = r2 * (k1 + r2 * (k2 + r2 * k3))
        g = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        a11 = 1 + q + 2 * x * x * g + 6 * p1 * x + 2 * p2 * y
        a22 = 1 + q + 2 * y * y * g + 6 * p2 * y + 2 * p1 * x
        a12 = 2 * x * y * g + 2 * p1 * y + 2 * p2 * x
        det = a11 * a22 - a12 * a12
        if not (det > 0.0) or not (a11 + a22 > 0.0):
            return False
    else:
        a11 = 1.0
        a22 = 1.0
        a12 = 0.0
        det = 1.0
    v0 = -x
    v1 = -y
    for i in range(3):
        D[i] = v0 * R[0, i] + v1 * R[1, i] + c * R[2, i]
    if not want_jac:
        return True
    # angles
    for k in range(3):
        for i in range(3):
            dD[i, k] = v0 * dR[k, 0, i] + v1 * dR[k, 1, i] + c * dR[k, 2, i]
    # c
    for i in range(3):
        dD[i, 5] = R[2, i]
    # xi_h, eta_h, k1, k2, k3, p1, p2: du = -A^-1 dG/dtheta, dv = (-du_x, -du_y, 0)
    r4 = r2 * r2
    r6 = r4 * r2
    for col in range(7):
        if col == 0:
            gx = 1.0
            gy = 0.0
        elif col == 1:
            gx = 0.0
            gy = 1.0
        elif col == 2:
            gx = x * r2
            gy = y * r2
        elif col == 3:
            gx = x * r4
            gy = y * r4
        elif col == 4:
            gx = x * r6
            gy = y * r6
        elif col == 5:
            gx = r2 + 2 * x * x
            gy = 2 * x * y
        else:
            gx = 2 * x * y
            gy = r2 + 2 * y * y
        dux = -(a22 * gx - a12 * gy) / det
        duy = -(a11 * gy - a12 * gx) / det
        slot = 3 + col if col < 2 else 4 + col  # skip slot 5 (c)
        for i in range(3):
            dD[i, slot] = -dux * R[0, i] - duy * R[1, i]
    # thin-prism columns (only when they are free, npr = 4): G gains (r^2, 0), (r^4, 0),
    # (0, r^2), (0, r^4)
    for col in range(npr):
        gx = (r2 if col == 0 else r4) if col < 2 else 0.0
        gy = 0.0 if col < 2 else (r2 if col == 2 else r4)
        dux = -(a22 * gx - a12 * gy) / det
        duy = -(a11 * gy - a12 * gx) / det
        for i in range(3):
            dD[i, 11 + col] = -dux * R[0, i] - duy * R[1, i]
    return True


@njit(cache=True, nogil=True)
def _sensor_ray_prism(p, sp, R, dR, mx, my, want_jac, D, dD):
    """:func:`_sensor_ray` of a sensor with thin-prism terms (A = I + dd/du is then
    not symmetric); separate so that the 14-parameter path keeps its arithmetic."""
    k1 = p[9]
    k2 = p[10]
    k3 = p[11]
    p1 = p[12]
    p2 = p[13]
    s1 = sp[0]
    s2 = sp[1]
    s3 = sp[2]
    s4 = sp[3]
    c = p[8]
    ux = mx - p[6]
    uy = my - p[7]
    x, y = first_order_inverse_prism(ux, uy, k1, k2, k3, p1, p2, s1, s2, s3, s4)
    last = np.inf
    for _ in range(30):
        x, y, last, det, tr = newton_step_prism(x, y, ux, uy, k1, k2, k3, p1, p2, s1, s2, s3, s4)
        if not (det > 0.0):
            return False
        if last <= _NEWTON_TOL * (1.0 + abs(x) + abs(y)):
            break
    if not (last <= 1e3 * _NEWTON_TOL * (1.0 + abs(x) + abs(y))):
        return False
    a11, a12, a21, a22, _, _ = prism_jacobian(x, y, k1, k2, k3, p1, p2, s1, s2, s3, s4)
    det = a11 * a22 - a12 * a21
    if not (det > 0.0) or not (a11 + a22 > 0.0):
        return False
    v0 = -x
    v1 = -y
    for i in range(3):
        D[i] = v0 * R[0, i] + v1 * R[1, i] + c * R[2, i]
    if not want_jac:
        return True
    for k in range(3):
        for i in range(3):
            dD[i, k] = v0 * dR[k, 0, i] + v1 * dR[k, 1, i] + c * dR[k, 2, i]
    for i in range(3):
        dD[i, 5] = R[2, i]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    # xi_h, eta_h, k1, k2, k3, p1, p2, s1, s2, s3, s4: du = -A^-1 dG/dtheta
    for col in range(11):
        if col == 0:
            gx = 1.0
            gy = 0.0
        elif col == 1:
            gx = 0.0
            gy = 1.0
        elif col == 2:
            gx = x * r2
            gy = y * r2
        elif col == 3:
            gx = x * r4
            gy = y * r4
        elif col == 4:
            gx = x * r6
            gy = y * r6
        elif col == 5:
            gx = r2 + 2 * x * x
            gy = 2 * x * y
        elif col == 6:
            gx = 2 * x * y
            gy = r2 + 2 * y * y
        elif col == 7:
            gx = r2
            gy = 0.0
        elif col == 8:
            gx = r4
            gy = 0.0
        elif col == 9:
            gx = 0.0
            gy = r2
        else:
            gx = 0.0
            gy = r4
        dux = -(a22 * gx - a12 * gy) / det
        duy = -(a11 * gy - a21 * gx) / det
        slot = 3 + col if col < 2 else 4 + col  # skip slot 5 (c); prism at 11..14
        for i in range(3):
            dD[i, slot] = -dux * R[0, i] - duy * R[1, i]
    return True


@njit(cache=True, nogil=True)
def _control_point(pc, sc, Rc, dRc, pp, spr, Rp, dRp, tpose, Rpose, dRpose, centres, si, radius,
                   mcx, mcy, mpx, mpy, want_jac, npr, Dc, dDc, Dp, dDp, j1, j2, out):
    """Residuals of one control point into out[0:2]; Jacobian rows into j1 (28, or 42 with
    zeros in the pose slots 28..33 when thin-prism terms are free) and j2 (34 + 2 npr)
    (slot layout in :func:`local_slots`).

    Returns False where a ray cannot be formed or the rays are parallel.
    """
    if not _sensor_ray(pc, sc, Rc, dRc, mcx, mcy, want_jac, npr, Dc, dDc):
        return False
    if not _sensor_ray(pp, spr, Rp, dRp, mpx, mpy, want_jac, npr, Dp, dDp):
        return False
    o1x = pc[0]
    o1y = pc[1]
    o1z = pc[2]
    o2x = pp[0]
    o2y = pp[1]
    o2z = pp[2]
    w0x = o1x - o2x
    w0y = o1y - o2y
    w0z = o1z - o2z
    a = Dc[0] * Dc[0] + Dc[1] * Dc[1] + Dc[2] * Dc[2]
    b = Dc[0] * Dp[0] + Dc[1] * Dp[1] + Dc[2] * Dp[2]
    cc = Dp[0] * Dp[0] + Dp[1] * Dp[1] + Dp[2] * Dp[2]
    d = Dc[0] * w0x + Dc[1] * w0y + Dc[2] * w0z
    e = Dp[0] * w0x + Dp[1] * w0y + Dp[2] * w0z
    den = a * cc - b * b
    if not (den > 1e-14 * a * cc):
        return False
    s = (b * e - cc * d) / den
    t = (a * e - b * d) / den
    p1x = o1x + s * Dc[0]
    p1y = o1y + s * Dc[1]
    p1z = o1z + s * Dc[2]
    p2x = o2x + t * Dp[0]
    p2y = o2y + t * Dp[1]
    p2z = o2z + t * Dp[2]
    Sx = 0.5 * (p1x + p2x)
    Sy = 0.5 * (p1y + p2y)
    Sz = 0.5 * (p1z + p2z)
    mx_ = Dc[1] * Dp[2] - Dc[2] * Dp[1]
    my_ = Dc[2] * Dp[0] - Dc[0] * Dp[2]
    mz_ = Dc[0] * Dp[1] - Dc[1] * Dp[0]
    mn = np.sqrt(mx_ * mx_ + my_ * my_ + mz_ * mz_)
    nx = mx_ / mn
    ny = my_ / mn
    nz = mz_ / mn
    wx = -w0x
    wy = -w0y
    wz = -w0z
    alpha1 = wx * nx + wy * ny + wz * nz
    # sphere centre in the world: S_t = Rpose^T s + t
    c0 = centres[si, 0]
    c1 = centres[si, 1]
    c2 = centres[si, 2]
    Ctx = tpose[0] + Rpose[0, 0] * c0 + Rpose[1, 0] * c1 + Rpose[2, 0] * c2
    Cty = tpose[1] + Rpose[0, 1] * c0 + Rpose[1, 1] * c1 + Rpose[2, 1] * c2
    Ctz = tpose[2] + Rpose[0, 2] * c0 + Rpose[1, 2] * c1 + Rpose[2, 2] * c2
    qx = Sx - Ctx
    qy = Sy - Cty
    qz = Sz - Ctz
    dist = np.sqrt(qx * qx + qy * qy + qz * qz)
    alpha2 = dist - radius
    out[0] = alpha1
    out[1] = alpha2
    if not want_jac:
        return True
    qx /= dist
    qy /= dist
    qz /= dist
    # ---- alpha1 gradients w.r.t. origins and directions
    wn = wx * nx + wy * ny + wz * nz
    wpx = (wx - wn * nx) / mn
    wpy = (wy - wn * ny) / mn
    wpz = (wz - wn * nz) / mn
    # d alpha1 / d Dc = Dp x wp ; d alpha1 / d Dp = wp x Dc
    e1dcx = Dp[1] * wpz - Dp[2] * wpy
    e1dcy = Dp[2] * wpx - Dp[0] * wpz
    e1dcz = Dp[0] * wpy - Dp[1] * wpx
    e1dpx = wpy * Dc[2] - wpz * Dc[1]
    e1dpy = wpz * Dc[0] - wpx * Dc[2]
    e1dpz = wpx * Dc[1] - wpy * Dc[0]
    # ---- alpha2 gradients via the midpoint
    qa = qx * Dc[0] + qy * Dc[1] + qz * Dc[2]
    qb = qx * Dp[0] + qy * Dp[1] + qz * Dp[2]
    Kx = 0.5 * (qa * (b * Dp[0] - cc * Dc[0]) + qb * (a * Dp[0] - b * Dc[0])) / den
    Ky = 0.5 * (qa * (b * Dp[1] - cc * Dc[1]) + qb * (a * Dp[1] - b * Dc[1])) / den
    Kz = 0.5 * (qa * (b * Dp[2] - cc * Dc[2]) + qb * (a * Dp[2] - b * Dc[2])) / den
    rx = p1x - p2x
    ry = p1y - p2y
    rz = p1z - p2z
    fc = 0.5 * (cc * qa + b * qb) / den
    fp = 0.5 * (b * qa + a * qb) / den
    g2o1x = 0.5 * qx + Kx
    g2o1y = 0.5 * qy + Ky
    g2o1z = 0.5 * qz + Kz
    g2o2x = 0.5 * qx - Kx
    g2o2y = 0.5 * qy - Ky
    g2o2z = 0.5 * qz - Kz
    g2dcx = s * g2o1x - fc * rx
    g2dcy = s * g2o1y - fc * ry
    g2dcz = s * g2o1z - fc * rz
    g2dpx = t * g2o2x + fp * rx
    g2dpy = t * g2o2y + fp * ry
    g2dpz = t * g2o2z + fp * rz
    # camera slots 0..13, projector 14..27
    j1[0] = -nx
    j1[1] = -ny
    j1[2] = -nz
    j1[14] = nx
    j1[15] = ny
    j1[16] = nz
    j2[0] = g2o1x
    j2[1] = g2o1y
    j2[2] = g2o1z
    j2[14] = g2o2x
    j2[15] = g2o2y
    j2[16] = g2o2z
    for col in range(11):
        j1[3 + col] = e1dcx * dDc[0, col] + e1dcy * dDc[1, col] + e1dcz * dDc[2, col]
        j1[17 + col] = e1dpx * dDp[0, col] + e1dpy * dDp[1, col] + e1dpz * dDp[2, col]
        j2[3 + col] = g2dcx * dDc[0, col] + g2dcy * dDc[1, col] + g2dcz * dDc[2, col]
        j2[17 + col] = g2dpx * dDp[0, col] + g2dpy * dDp[1, col] + g2dpz * dDp[2, col]
    # pose slots 28..33: alpha2 = |S - S_t| - r
    j2[28] = -qx
    j2[29] = -qy
    j2[30] = -qz
    for k in range(3):
        vx = dRpose[k, 0, 0] * c0 + dRpose[k, 1, 0] * c1 + dRpose[k, 2, 0] * c2
        vy = dRpose[k, 0, 1] * c0 + dRpose[k, 1, 1] * c1 + dRpose[k, 2, 1] * c2
        vz = dRpose[k, 0, 2] * c0 + dRpose[k, 1, 2] * c1 + dRpose[k, 2, 2] * c2
        j2[31 + k] = -(qx * vx + qy * vy + qz * vz)
    # thin-prism slots 34..34+npr-1 (camera), 34+npr..34+2npr-1 (projector)
    for col in range(npr):
        j1[34 + col] = e1dcx * dDc[0, 11 + col] + e1dcy * dDc[1, 11 + col] + e1dcz * dDc[2, 11 + col]
        j1[34 + npr + col] = e1dpx * dDp[0, 11 + col] + e1dpy * dDp[1, 11 + col] + e1dpz * dDp[2, 11 + col]
        j2[34 + col] = g2dcx * dDc[0, 11 + col] + g2dcy * dDc[1, 11 + col] + g2dcz * dDc[2, 11 + col]
        j2[34 + npr + col] = g2dpx * dDp[0, 11 + col] + g2dpy * dDp[1, 11 + col] + g2dpz * dDp[2, 11 + col]
    return True


@njit(cache=True, nogil=True)
def _loss(alpha, loss, scale):
    """(rho(alpha), IRLS weight rho'(alpha) / (2 alpha)) of the robust loss."""
    if loss == 0:
        return alpha * alpha, 1.0
    a = abs(alpha)
    if loss == 1:  # Huber
        if a <= scale:
            return alpha * alpha, 1.0
        return 2.0 * scale * a - scale * scale, scale / a
    z = alpha * alpha / (scale * scale)  # Cauchy
    return scale * scale * np.log1p(z), 1.0 / (1.0 + z)


@njit(cache=True, nogil=True, inline="always")
def _accumulate_prism(ch, nl, f1, f2, w1, w2, j1, j2, A1, A2, bvec):
    """The thin-prism slots' part of one control point's normal blocks: columns 34..nl-1
    of the rows 0..33, and the rows 34..nl-1 (upper triangles; A1 skips the pose slots)."""
    for i in range(34):
        u2 = w2 * j2[i]
        for j in range(34, nl):
            A2[ch, i, j] += u2 * j2[j]
        if i < 28:
            u1 = w1 * j1[i]
            for j in range(34, nl):
                A1[ch, i, j] += u1 * j1[j]
    for i in range(34, nl):
        bvec[ch, i] += f1 * j1[i] + f2 * j2[i]
        u1 = w1 * j1[i]
        u2 = w2 * j2[i]
        for j in range(i, nl):
            A1[ch, i, j] += u1 * j1[j]
            A2[ch, i, j] += u2 * j2[j]


@njit(cache=True, parallel=True)
def assemble(chunk_start, chunk_stop, chunk_group, group_cam, group_prj, group_meas,
             sens_p, sens_s, sens_R, sens_dR, pose_t, pose_R, pose_dR, sphere_idx, centres, radii,
             cam_mm, prj_mm, phi_c, phi_p, gamma1, gamma2, loss, scale1, scale2, want_jac,
             res, ok, chunk_cost, A1, A2, bvec):
    """Residuals of every control point and, with ``want_jac``, per-chunk normal blocks.

    Parameters (shapes): chunk_* (n_chunks,), group_* (n_groups,), sens_p (n_sensors, 14),
    sens_s (n_sensors, 4) thin-prism terms,
    sens_R (n_sensors, 3, 3), sens_dR (n_sensors, 3, 3, 3), pose_t (n_meas, 3),
    pose_R / pose_dR like sensors, sphere_idx (n,), centres (n_spheres, 3), radii
    (n_spheres,), cam_mm / prj_mm (n, 2) image-plane mm (corrected by any correction
    field), phi_c / phi_p (n, nf, 2) the correction-field basis at each observation
    (nf = 0 without free fields).

    Outputs: res (n, 2) alpha1, alpha2; ok (n,) bool; chunk_cost (n_chunks,) the chunk's
    part of F = gamma1 sum rho(alpha1) + gamma2 sum rho(alpha2) (inf if a control point
    fails); A1 (n_chunks, n1, n1) = sum w1 j1 j1^T and A2 (n_chunks, nl, nl) = sum w2 j2 j2^T
    (upper triangles); bvec (n_chunks, nl) = sum gamma1 w1 alpha1 j1 + gamma2 w2 alpha2 j2.
    ``nl`` = bvec.shape[1] = 34 (``N_LOCAL``) or more with free thin-prism terms or
    fields (:func:`local_slots`), n1 = A1.shape[1] = 28 or nl (A1's pose rows and columns
    then stay zero); A1, A2 and bvec need only one chunk without ``want_jac``.
    """
    n_chunks = chunk_start.shape[0]
    nl = bvec.shape[1]
    nf = phi_c.shape[1]
    npr = (nl - N_LOCAL - 2 * nf) // 2
    f0 = N_LOCAL + 2 * npr
    n1 = A1.shape[1]  # 28, or nl
    for ch in prange(n_chunks):
        g = chunk_group[ch]
        ic = group_cam[g]
        ip = group_prj[g]
        im = group_meas[g]
        # views made once per chunk, not per control point
        pc, sc, Rc, dRc = sens_p[ic], sens_s[ic], sens_R[ic], sens_dR[ic]
        pp, spr, Rp, dRp = sens_p[ip], sens_s[ip], sens_R[ip], sens_dR[ip]
        tpose, Rpose, dRpose = pose_t[im], pose_R[im], pose_dR[im]
        Dc = np.empty(3)
        Dp = np.empty(3)
        dDc = np.zeros((3, 15))
        dDp = np.zeros((3, 15))
        j1 = np.zeros(n1)
        j2 = np.zeros(nl)
        out = np.empty(2)
        cost = 0.0
        if want_jac:
            for i in range(nl):
                bvec[ch, i] = 0.0
                for j in range(nl):
                    A2[ch, i, j] = 0.0
            for i in range(n1):
                for j in range(n1):
                    A1[ch, i, j] = 0.0
        for k in range(chunk_start[ch], chunk_stop[ch]):
            si = sphere_idx[k]
            good = _control_point(pc, sc, Rc, dRc, pp, spr, Rp, dRp, tpose, Rpose, dRpose, centres, si, radii[si],
                                  cam_mm[k, 0], cam_mm[k, 1], prj_mm[k, 0], prj_mm[k, 1], want_jac, npr,
                                  Dc, dDc, Dp, dDp, j1, j2, out)
            ok[k] = good
            if not good:
                res[k, 0] = np.nan
                res[k, 1] = np.nan
                cost = np.inf
                continue
            if want_jac and nf > 0:
                _field_slots(k, f0, nf, phi_c, phi_p, j1, j2)
            a1 = out[0]
            a2 = out[1]
            res[k, 0] = a1
            res[k, 1] = a2
            r1, w1 = _loss(a1, loss, scale1)
            r2, w2 = _loss(a2, loss, scale2)
            cost += gamma1 * r1 + gamma2 * r2
            if want_jac:
                f1 = gamma1 * w1 * a1
                f2 = gamma2 * w2 * a2
                # the 34 slots of the thesis's model with constant bounds (vectorised as before
                # the thin-prism terms existed), then the prism and field slots 34.. if free
                for i in range(28):
                    bvec[ch, i] += f1 * j1[i] + f2 * j2[i]
                    u1 = w1 * j1[i]
                    u2 = w2 * j2[i]
                    for j in range(i, 28):
                        A1[ch, i, j] += u1 * j1[j]
                    for j in range(i, 34):
                        A2[ch, i, j] += u2 * j2[j]
                for i in range(28, 34):
                    bvec[ch, i] += f2 * j2[i]
                    u2 = w2 * j2[i]
                    for j in range(i, 34):
                        A2[ch, i, j] += u2 * j2[j]
                if nl > N_LOCAL:
                    _accumulate_prism(ch, nl, f1, f2, w1, w2, j1, j2, A1, A2, bvec)
        chunk_cost[ch] = cost


@njit(cache=True)
def scatter(chunk_group, gmap, A1, A2, bvec, N1, N2, b):
    """Add the chunks' upper-triangle blocks into global N1, N2 (p, p) and b (p,).

    gmap (n_groups, nl) maps a group's local slots to global parameter indices (-1: fixed).
    The results are full symmetric matrices.
    """
    n_chunks = chunk_group.shape[0]
    nl = A2.shape[1]
    n1 = A1.shape[1]
    for ch in range(n_chunks):
        gm = gmap[chunk_group[ch]]
        for i in range(nl):
            gi = gm[i]
            if gi < 0:
                continue
            b[gi] += bvec[ch, i]
            for j in range(i, nl):
                gj = gm[j]
                if gj < 0:
                    continue
                v2 = A2[ch, i, j]
                N2[gi, gj] += v2
                if gi != gj:
                    N2[gj, gi] += v2
                if j < n1 and (j < 28 or j >= 34) and (i < 28 or i >= 34):  # A1: no pose slots
                    v1 = A1[ch, i, j]
                    N1[gi, gj] += v1
                    if gi != gj:
                        N1[gj, gi] += v1


@njit(cache=True, parallel=True)
def residual_rows(chunk_start, chunk_stop, chunk_group, group_cam, group_prj, group_meas,
                  sens_p, sens_s, sens_R, sens_dR, pose_t, pose_R, pose_dR, sphere_idx, centres, radii,
                  cam_mm, prj_mm, phi_c, phi_p, res, ok, J):
    """Residuals (n, 2) and full local Jacobian rows J (n, 2, nl), nl = 34 or more (:func:`local_slots`;
    the alpha1 row has zeros in the pose slots). For tests, finite-difference checks and scipy comparisons."""
    n_chunks = chunk_start.shape[0]
    nl = J.shape[2]
    nf = phi_c.shape[1]
    npr = (nl - N_LOCAL - 2 * nf) // 2
    f0 = N_LOCAL + 2 * npr
    n1 = 28 if nl == N_LOCAL else nl
    for ch in prange(n_chunks):
        g = chunk_group[ch]
        ic = group_cam[g]
        ip = group_prj[g]
        im = group_meas[g]
        # views made once per chunk, not per control point
        pc, sc, Rc, dRc = sens_p[ic], sens_s[ic], sens_R[ic], sens_dR[ic]
        pp, spr, Rp, dRp = sens_p[ip], sens_s[ip], sens_R[ip], sens_dR[ip]
        tpose, Rpose, dRpose = pose_t[im], pose_R[im], pose_dR[im]
        Dc = np.empty(3)
        Dp = np.empty(3)
        dDc = np.zeros((3, 15))
        dDp = np.zeros((3, 15))
        j1 = np.zeros(n1)
        j2 = np.zeros(nl)
        out = np.empty(2)
        for k in range(chunk_start[ch], chunk_stop[ch]):
            si = sphere_idx[k]
            good = _control_point(pc, sc, Rc, dRc, pp, spr, Rp, dRp, tpose, Rpose, dRpose, centres, si, radii[si],
                                  cam_mm[k, 0], cam_mm[k, 1], prj_mm[k, 0], prj_mm[k, 1], True, npr,
                                  Dc, dDc, Dp, dDp, j1, j2, out)
            ok[k] = good
            if good and nf > 0:
                _field_slots(k, f0, nf, phi_c, phi_p, j1, j2)
            res[k, 0] = out[0] if good else np.nan
            res[k, 1] = out[1] if good else np.nan
            for i in range(nl):
                J[k, 0, i] = j1[i] if (good and i < n1) else 0.0
                J[k, 1, i] = j2[i] if good else 0.0


@njit(cache=True, parallel=True)
def replica_gradients(chunk_start, chunk_stop, chunk_group, group_cam, group_prj, group_meas,
                      sens_p, sens_s, sens_R, sens_dR, pose_t, pose_R, pose_dR, sphere_idx, centres, radii,
                      cam_mm, prj_a, prj_b, phi_c, phi_p, flip, gamma1, gamma2, ok, dcost, dgrad):
    """Cost and gradient of many data replicas at one parameter vector, from two
    observation sets: replica r observes ``prj_b[k]`` where ``flip[r, k]``, else ``prj_a[k]``.

    Outputs, per chunk: dcost (n_chunks, R) and dgrad (n_chunks, R, nl), the replica's
    cost and its local gradient (gamma1 alpha1 j1 + gamma2 alpha2 j2) minus those with
    ``prj_a`` everywhere, summed over the chunk's control points (no robust loss);
    ok (n,) False where a ray cannot be formed with either observation.
    """
    n_chunks = chunk_start.shape[0]
    R = flip.shape[0]
    nl = dgrad.shape[2]
    nf = phi_c.shape[1]
    npr = (nl - N_LOCAL - 2 * nf) // 2
    f0 = N_LOCAL + 2 * npr
    n1 = 28 if nl == N_LOCAL else nl
    for ch in prange(n_chunks):
        g = chunk_group[ch]
        ic = group_cam[g]
        ip = group_prj[g]
        im = group_meas[g]
        pc, sc, Rc, dRc = sens_p[ic], sens_s[ic], sens_R[ic], sens_dR[ic]
        pp, spr, Rp, dRp = sens_p[ip], sens_s[ip], sens_R[ip], sens_dR[ip]
        tpose, Rpose, dRpose = pose_t[im], pose_R[im], pose_dR[im]
        Dc = np.empty(3)
        Dp = np.empty(3)
        dDc = np.zeros((3, 15))
        dDp = np.zeros((3, 15))
        ja1 = np.zeros(n1)
        ja2 = np.zeros(nl)
        jb1 = np.zeros(n1)
        jb2 = np.zeros(nl)
        out_a = np.empty(2)
        out_b = np.empty(2)
        diff = np.empty(nl)
        for r in range(R):
            dcost[ch, r] = 0.0
            for i in range(nl):
                dgrad[ch, r, i] = 0.0
        for k in range(chunk_start[ch], chunk_stop[ch]):
            si = sphere_idx[k]
            good = _control_point(pc, sc, Rc, dRc, pp, spr, Rp, dRp, tpose, Rpose, dRpose, centres, si, radii[si],
                                  cam_mm[k, 0], cam_mm[k, 1], prj_a[k, 0], prj_a[k, 1], True, npr,
                                  Dc, dDc, Dp, dDp, ja1, ja2, out_a)
            good = good and _control_point(pc, sc, Rc, dRc, pp, spr, Rp, dRp, tpose, Rpose, dRpose, centres, si,
                                           radii[si], cam_mm[k, 0], cam_mm[k, 1], prj_b[k, 0], prj_b[k, 1],
                                           True, npr, Dc, dDc, Dp, dDp, jb1, jb2, out_b)
            ok[k] = good
            if not good:
                for r in range(R):
                    if flip[r, k]:
                        dcost[ch, r] = np.inf
                continue
            if nf > 0:
                _field_slots(k, f0, nf, phi_c, phi_p, ja1, ja2)
                _field_slots(k, f0, nf, phi_c, phi_p, jb1, jb2)
            fa1 = gamma1 * out_a[0]
            fa2 = gamma2 * out_a[1]
            fb1 = gamma1 * out_b[0]
            fb2 = gamma2 * out_b[1]
            dc = fb1 * out_b[0] + fb2 * out_b[1] - fa1 * out_a[0] - fa2 * out_a[1]
            for i in range(28):
                diff[i] = fb1 * jb1[i] + fb2 * jb2[i] - fa1 * ja1[i] - fa2 * ja2[i]
            for i in range(28, 34):
                diff[i] = fb2 * jb2[i] - fa2 * ja2[i]
            for i in range(34, nl):
                diff[i] = fb1 * jb1[i] + fb2 * jb2[i] - fa1 * ja1[i] - fa2 * ja2[i]
            for r in range(R):
                if flip[r, k]:
                    dcost[ch, r] += dc
                    for i in range(nl):
                        dgrad[ch, r, i] += diff[i]
