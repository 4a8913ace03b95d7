"""The compiled rendering kernel: one parallel loop over image tiles (numba).

Per tile: sub-sample rays through the camera model, a bounding cone of those rays
to cull primitives, first hits, a second cone from the projector pinhole to cull
the shadow tests, projector light per hit, then per pixel the phasors
``Z_t = sum_s w_s P_s m_t exp(i t tau_s)`` and the truth, and finally every frame
of the sequence from the phasors, noise included. Array layouts are documented on
:func:`render_tiles`; :mod:`fringecal.simulate.render` is the Python entry point.

The unmodelled errors of :mod:`fringecal.simulate.errors` enter as arrays of fixed
dtype and dimension, empty or trivial when off, so switching them on or off never
compiles a new specialisation: sphere form errors (``form``, empty when off), a
projector intensity non-linearity as harmonics h = 1..H of every fringe count
(phasors of the counts h t; H = 1 when off) with the per-frame weights ``fcos``,
``fsin`` that also carry a pattern drift during the sequence, a per-pixel phase
field (``field``, empty when off) and the camera response (``noise[5]``). A sensor's
correction field (a lens field) lengthens its sensor pack instead, which
:mod:`.geometry` reads (:func:`~.geometry.sensor_pack`).

Primitives (spheres, cylinders, boxes, planes, free-form panels) are intersected by
:mod:`.geometry`. numba's on-disk cache (``cache=True``) is keyed on this file's bytes
alone, not on the functions it calls: a change to :mod:`.geometry` or :mod:`.noise`
must come with a change to this file (as this note came with the panel and with the
row-wise noise of :func:`~.noise.record_pixels`) , or a stale compiled kernel is used.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from fringecal.simulate import geometry as g
from fringecal.simulate.noise import quantise, record_pixels, stream

#: Illumination codes of a hit (the truth's ``light`` map).
LIGHT_NO_HIT, LIGHT_LIT, LIGHT_SHADOW, LIGHT_OUTSIDE = 0, 1, 2, 3


@njit(cache=True)
def tile_rays(cam, cam_fmt, n, r0, c0, nr, nc, dirs, ok):
    """Unit rays of the n x n sub-samples (slots 0..n^2-1, row-major over the pixel)
    and, for even n, of the pixel centre (slot n^2) of every pixel of the tile."""
    ns = n * n
    shift_x = shift_y = 0.0
    for p in range(nr * nc):
        row, col = r0 + p // nc, c0 + p % nc
        for s in range(dirs.shape[1]):
            du = (s % n + 0.5) / n - 0.5 if s < ns else 0.0
            dv = (s // n + 0.5) / n - 0.5 if s < ns else 0.0
            xi = ((col + du) / (cam_fmt[0] - 1) - 0.5) * cam_fmt[2]  # eq. 2-21
            eta = ((row + dv) / (cam_fmt[1] - 1) - 0.5) * cam_fmt[3]
            dx, dy, dz, good, sx, sy = g.image_ray(xi, eta, cam, shift_x, shift_y)
            dirs[p, s, 0], dirs[p, s, 1], dirs[p, s, 2] = dx, dy, dz
            ok[p, s] = good
            if good:
                shift_x, shift_y = sx, sy


@njit(cache=True)
def bounding_cone(dirs, mask):
    """Axis and cosine of the half-angle of a cone holding the unit vectors
    ``dirs[mask]``: (ax, ay, az, cos_half, found)."""
    sx = sy = sz = 0.0
    for p in range(dirs.shape[0]):
        for s in range(dirs.shape[1]):
            if mask[p, s]:
                sx += dirs[p, s, 0]
                sy += dirs[p, s, 1]
                sz += dirs[p, s, 2]
    norm = math.sqrt(sx * sx + sy * sy + sz * sz)
    if norm == 0:
        return 0.0, 0.0, 1.0, 1.0, False
    ax, ay, az = sx / norm, sy / norm, sz / norm
    cos_half = 1.0
    for p in range(dirs.shape[0]):
        for s in range(dirs.shape[1]):
            if mask[p, s]:
                cos_half = min(cos_half, dirs[p, s, 0] * ax + dirs[p, s, 1] * ay + dirs[p, s, 2] * az)
    return ax, ay, az, cos_half, True


@njit(cache=True)
def cast_tile(prims, kinds, form, cam, prj, dirs, ok, hit_t, hit_j, hit_n, to_hit, prj_dist):
    """First hits of the tile's rays (on the as-built surface, :func:`.geometry.form_hit`);
    ``to_hit`` gets the unit direction from the projector pinhole to each hit,
    ``prj_dist`` its distance. Returns whether anything was hit."""
    cand = np.empty(prims.shape[0], np.int64)
    ax, ay, az, cos_half, found = bounding_cone(dirs, ok)
    n_cand = g.cone_candidates(prims, cam[0], cam[1], cam[2], ax, ay, az, cos_half, np.inf, cand) if found else 0
    any_hit = False
    for p in range(dirs.shape[0]):
        for s in range(dirs.shape[1]):
            hit_j[p, s] = -1
            if not ok[p, s] or n_cand == 0:
                continue
            dx, dy, dz = dirs[p, s, 0], dirs[p, s, 1], dirs[p, s, 2]
            t, j, nx, ny, nz = g.nearest_hit(prims, kinds, cand, n_cand, cam[0], cam[1], cam[2], dx, dy, dz, 0.0)
            if j < 0:
                continue
            t = g.form_hit(form, kinds, j, t, dx, dy, dz, nx, ny, nz)
            any_hit = True
            hit_t[p, s], hit_j[p, s] = t, j
            hit_n[p, s, 0], hit_n[p, s, 1], hit_n[p, s, 2] = nx, ny, nz
            vx, vy, vz = cam[0] + t * dx - prj[0], cam[1] + t * dy - prj[1], cam[2] + t * dz - prj[2]
            vn = math.sqrt(vx * vx + vy * vy + vz * vz)
            to_hit[p, s, 0], to_hit[p, s, 1], to_hit[p, s, 2] = vx / vn, vy / vn, vz / vn
            prj_dist[p, s] = vn
    return any_hit


@njit(cache=True)
def shadow_candidates(prims, prj, owner, n_obj, hit_j, to_hit, prj_dist):
    """Culled primitives for the shadow tests, one list per object hit in the tile
    (a tile straddling a depth edge would otherwise need one wide cone):
    (group of each object or -1, lists (n_groups, n_prim), their lengths)."""
    group_of = np.full(n_obj, -1, np.int64)
    group = np.full(hit_j.shape, -1, np.int64)
    n_groups = 0
    for p in range(hit_j.shape[0]):
        for s in range(hit_j.shape[1]):
            if hit_j[p, s] >= 0:
                obj = owner[hit_j[p, s]]
                if group_of[obj] < 0:
                    group_of[obj] = n_groups
                    n_groups += 1
                group[p, s] = group_of[obj]
    lists = np.empty((n_groups, prims.shape[0]), np.int64)
    lengths = np.zeros(n_groups, np.int64)
    for gi in range(n_groups):
        mask = group == gi
        far = 0.0
        for p in range(hit_j.shape[0]):
            for s in range(hit_j.shape[1]):
                if mask[p, s]:
                    far = max(far, prj_dist[p, s])
        ax, ay, az, cos_half, _ = bounding_cone(to_hit, mask)
        lengths[gi] = g.cone_candidates(prims, prj[0], prj[1], prj[2], ax, ay, az, cos_half, far, lists[gi])
    return group_of, lists, lengths


@njit(cache=True)
def shade(prims, kinds, form, mats, cand, n_cand, prj, prj_fmt, optics, cam, X, Y, Z, nx, ny, nz, obj, j):
    """Projector light at a hit on primitive j: (code, tau_x, tau_y, P, projector depth z').

    P is the relative irradiance times reflectance of :mod:`.config`; 0 unless lit.
    With form errors a sphere never shadows its own (moved) hit -- a convex surface
    only turns its back, which ``cos_i`` tests -- another occluder's hit is moved to
    its as-built surface too and must be 0.1 um nearer than the point.
    """
    xi, eta, zp = g.project_point(X, Y, Z, prj)
    if not zp > 0 or abs(xi) > prj_fmt[0] / 2 or abs(eta) > prj_fmt[1] / 2:
        return LIGHT_OUTSIDE, np.nan, np.nan, 0.0, zp
    tx = 2 * math.pi * xi / prj_fmt[0]  # eq. 2-22
    ty = 2 * math.pi * eta / prj_fmt[1]
    lx, ly, lz = prj[0] - X, prj[1] - Y, prj[2] - Z
    dist = math.sqrt(lx * lx + ly * ly + lz * lz)
    lx, ly, lz = lx / dist, ly / dist, lz / dist
    cos_i = nx * lx + ny * ly + nz * lz
    if cos_i <= 0:  # the surface turns its back on the projector
        return LIGHT_SHADOW, tx, ty, 0.0, zp
    t, js, snx, sny, snz = g.nearest_hit(prims, kinds, cand, n_cand, prj[0], prj[1], prj[2], -lx, -ly, -lz, 0.0)
    slack = 1e-7
    if form.shape[0] > 0:
        slack = 1e-4
        if js == j and kinds[j] == g.SPHERE:
            t = np.inf
        elif js >= 0:
            t = g.form_hit(form, kinds, js, t, -lx, -ly, -lz, snx, sny, snz)
    if t < dist * (1 - 1e-9) - slack:  # something nearer the projector is in the way
        return LIGHT_SHADOW, tx, ty, 0.0, zp
    albedo, spec, shininess = mats[obj, 0], mats[obj, 1], mats[obj, 2]
    reflect = albedo * cos_i
    if spec > 0:
        vx, vy, vz = cam[0] - X, cam[1] - Y, cam[2] - Z
        vn = math.sqrt(vx * vx + vy * vy + vz * vz)
        hx, hy, hz = lx + vx / vn, ly + vy / vn, lz + vz / vn
        cos_h = (nx * hx + ny * hy + nz * hz) / math.sqrt(hx * hx + hy * hy + hz * hz)
        if cos_h > 0:
            reflect += spec * cos_h ** shininess
    r = optics[3] / dist
    return LIGHT_LIT, tx, ty, reflect * r * r, zp


@njit(cache=True)
def add_phasors(zre, zim, oi, p, w, a, mfac, icounts, n_h, pr, pim):
    """zre/zim[oi, t, p] += a m_t exp(i t w) for every fringe count: exp(i 2^b w) by
    repeated squaring, exp(i t w) as the product over t's bits (no trig per count);
    for harmonics h = 2..n_h also the counts h t (index (h - 1) n_t + t), by powers
    of exp(i t w)."""
    pr[0], pim[0] = math.cos(w), math.sin(w)
    for b in range(1, pr.shape[0]):
        pr[b] = pr[b - 1] * pr[b - 1] - pim[b - 1] * pim[b - 1]
        pim[b] = 2 * pr[b - 1] * pim[b - 1]
    for ti in range(icounts.shape[0]):
        er, ei = 1.0, 0.0
        bits, b = icounts[ti], 0
        while bits:
            if bits & 1:
                er, ei = er * pr[b] - ei * pim[b], er * pim[b] + ei * pr[b]
            bits >>= 1
            b += 1
        m = a * mfac[oi, ti]
        zre[oi, ti, p] += m * er
        zim[oi, ti, p] += m * ei
        hr, hi = er, ei
        for h in range(1, n_h):
            hr, hi = hr * er - hi * ei, hr * ei + hi * er
            k = h * icounts.shape[0] + ti
            m = a * mfac[oi, k]
            zre[oi, k, p] += m * hr
            zim[oi, k, p] += m * hi


@njit(cache=True)
def defocus_factors(z_mean, optics, prj_fmt, orient, counts, mfac):
    """mfac[o, t] = exp(-(2 pi t sigma / N_o)^2 / 2), sigma the SLM blur at depth z_mean."""
    blur = optics[5] + optics[6] * abs(z_mean - optics[4])
    for oi in range(orient.shape[0]):
        f = 2 * math.pi * blur / prj_fmt[orient[oi]]
        for ti in range(counts.shape[0]):
            mfac[oi, ti] = math.exp(-0.5 * (f * counts[ti]) ** 2)


@njit(cache=True)
def dominant(objs, ns):
    """(object hit by most of the first ns sub-samples, their count); ties: first seen."""
    best, best_n = -1, -1
    for s in range(ns):
        cnt = 0
        for q in range(ns):
            if objs[q] == objs[s]:
                cnt += 1
        if cnt > best_n:
            best, best_n = objs[s], cnt
    return best, best_n


@njit(cache=True)
def write_frames(frames, r0, c0, nr, nc, base, zre, zim, fcos, fsin, key, noise):
    """Every frame f of the tile from its phasors:
    I = base + sum_h Re((fcos[f, h] + i fsin[f, h]) Z_(h+1)t), i.e. for harmonic
    amplitudes B_h and a frame's extra phase psi_f: fcos = B_h cos(h (delta_k + psi_f)),
    fsin = B_h sin(...); then the camera response ``I + 4 e I (1 - I)`` (e =
    ``noise[5]``), camera noise (one random stream per pixel, frame after frame) and
    quantisation."""
    W = frames.shape[2]
    full_well, sigma_e, inv_gain, max_dn, shot = noise[0], noise[1], noise[2], int(noise[3]), noise[4] > 0
    lin = noise[5]
    noisy = shot or sigma_e > 0
    scale = full_well * inv_gain
    n_h = fcos.shape[1]
    n_o, n_t = zre.shape[0], zre.shape[1] // n_h
    n_k = fcos.shape[0] // (n_o * n_t)
    states = np.empty(nr * nc, np.uint64)
    mean = np.empty(nr * nc)
    dn = np.empty(nr * nc, np.uint16)
    scratch = np.empty((3, nr * nc))
    for p in range(nr * nc):
        states[p] = stream(key, (r0 + p // nc) * W + c0 + p % nc)
    for oi in range(n_o):
        for ti in range(n_t):
            for k in range(n_k):
                f = (oi * n_t + ti) * n_k + k
                for p in range(nr * nc):
                    val = base[p]
                    for h in range(n_h):
                        q = h * n_t + ti
                        val = val + fcos[f, h] * zre[oi, q, p]
                        val = val - fsin[f, h] * zim[oi, q, p]
                    if lin != 0.0:
                        val = val + 4.0 * lin * val * (1.0 - val)
                    mean[p] = val * (full_well if noisy else scale)
                if noisy:
                    record_pixels(mean, states, shot, sigma_e, inv_gain, max_dn, dn, scratch)
                else:
                    for p in range(nr * nc):
                        dn[p] = quantise(mean[p], max_dn)
                for r in range(nr):
                    frames[f, r0 + r, c0:c0 + nc] = dn[r * nc:(r + 1) * nc]


@njit(parallel=True, cache=True)
def render_tiles(cam, cam_fmt, prj, prj_fmt, prims, kinds, owner, mats, obj_sphere, form, n, orient, counts, fcos,
                 fsin, optics, noise, field, key, tile, frames, tau, tau_c, point, ints, fracs, light, levels):
    """Render every tile of the image in parallel.

    Inputs: ``cam``, ``prj`` sensor packs (22,); ``cam_fmt`` (cols, rows, width mm,
    height mm); ``prj_fmt`` (SLM width, height mm); ``prims``, ``kinds``, ``owner``
    (object of each primitive); ``mats`` (n_obj, 3) albedo, specular, shininess;
    ``obj_sphere`` (n_obj,) sphere index or -1; ``form`` (n_prim, m, 5) sphere form
    terms or (0, m, 5); ``n`` sub-samples per side; ``orient`` (n_o,) 0 = x, 1 = y;
    ``counts`` (H n_t,) the fringe counts then their harmonics h t, h = 2..H;
    ``fcos``, ``fsin`` (n_frames, H) frame weights (:func:`write_frames`); ``optics``
    (A, B, ambient, d_ref, focus, blur at focus, blur per mm); ``noise`` (full well,
    sigma_e, 1/gain, max DN, shot flag, camera linearity error); ``field`` (2, rows,
    cols) phase added to tau_x, tau_y before the phasors, or (2, 0, 0); ``key`` uint64.

    Outputs: ``frames`` (n_o n_t N, rows, cols) uint16; ``tau``, ``tau_c`` (2, rows,
    cols) area-mean and centre tau; ``point`` (rows, cols, 3); ``ints`` (3, rows,
    cols) dominant object, centre object, sphere index; ``fracs`` (2, rows, cols)
    purity, lit fraction; ``light`` (rows, cols); ``levels`` (2, rows, cols)
    irradiance S, ambient level.
    """
    H, W = frames.shape[1], frames.shape[2]
    n_h = fcos.shape[1]
    n_o, n_q = orient.shape[0], counts.shape[0]
    n_t = n_q // n_h
    has_field = field.shape[1] > 0
    ns = n * n
    nray = ns + (1 if n % 2 == 0 else 0)
    centre = ns if n % 2 == 0 else (n // 2) * n + n // 2
    icounts = np.empty(n_t, np.int64)
    for ti in range(n_t):
        icounts[ti] = int(counts[ti])
    n_bits = 1
    while (1 << n_bits) <= icounts.max():
        n_bits += 1
    tiles_x = (W + tile - 1) // tile
    tiles_y = (H + tile - 1) // tile
    for tid in prange(tiles_x * tiles_y):
        r0, c0 = (tid // tiles_x) * tile, (tid % tiles_x) * tile
        nr, nc = min(tile, H - r0), min(tile, W - c0)
        npx = nr * nc
        dirs = np.empty((npx, nray, 3))
        ok = np.empty((npx, nray), np.bool_)
        tile_rays(cam, cam_fmt, n, r0, c0, nr, nc, dirs, ok)
        hit_t = np.empty((npx, nray))
        hit_j = np.empty((npx, nray), np.int64)
        hit_n = np.empty((npx, nray, 3))
        to_hit = np.empty((npx, nray, 3))
        prj_dist = np.empty((npx, nray))
        cast_tile(prims, kinds, form, cam, prj, dirs, ok, hit_t, hit_j, hit_n, to_hit, prj_dist)
        group_of, shadow_lists, shadow_n = shadow_candidates(prims, prj, owner, mats.shape[0], hit_j, to_hit,
                                                             prj_dist)

        zre = np.zeros((n_o, n_q, npx))
        zim = np.zeros((n_o, n_q, npx))
        base = np.zeros(npx)
        objs = np.empty(nray, np.int64)
        lit = np.empty(nray, np.bool_)
        txs = np.empty(nray)
        tys = np.empty(nray)
        a_s = np.empty(nray)
        z_s = np.empty(nray)
        done = np.empty(nray, np.bool_)
        mfac = np.empty((n_o, n_q))
        pr = np.empty(n_bits)
        pim = np.empty(n_bits)
        for p in range(npx):
            row, col = r0 + p // nc, c0 + p % nc
            irradiance = ambient = 0.0
            n_lit = 0
            for s in range(nray):
                j = hit_j[p, s]
                objs[s] = -1 if j < 0 else owner[j]
                lit[s] = False
                txs[s] = tys[s] = np.nan
                code = LIGHT_NO_HIT
                if j >= 0:
                    t = hit_t[p, s]
                    X, Y, Z = cam[0] + t * dirs[p, s, 0], cam[1] + t * dirs[p, s, 1], cam[2] + t * dirs[p, s, 2]
                    gi = group_of[objs[s]]
                    code, tx, ty, P, zp = shade(prims, kinds, form, mats, shadow_lists[gi], shadow_n[gi], prj, prj_fmt,
                                                optics, cam, X, Y, Z, hit_n[p, s, 0], hit_n[p, s, 1],
                                                hit_n[p, s, 2], objs[s], j)
                    if code == LIGHT_LIT:
                        lit[s] = True
                        txs[s], tys[s] = tx, ty
                        a_s[s], z_s[s] = P / ns, zp
                    if s < ns:
                        ambient += mats[objs[s], 0] * optics[2] / ns
                        if lit[s]:
                            n_lit += 1
                            irradiance += a_s[s]
                    if s == centre:
                        point[row, col, 0], point[row, col, 1], point[row, col, 2] = X, Y, Z
                if s == centre:
                    light[row, col] = code
                    ints[1, row, col] = objs[s]
                    tau_c[0, row, col], tau_c[1, row, col] = txs[s], tys[s]
                    if j < 0:
                        point[row, col, 0] = point[row, col, 1] = point[row, col, 2] = np.nan
            # phasors object by object, defocus at the object's mean projector depth in
            # this footprint (it varies by far less than the depth of field)
            for s in range(ns):
                done[s] = not lit[s]
            for s in range(ns):
                if done[s]:
                    continue
                z_sum, z_n = 0.0, 0
                for q in range(s, ns):
                    if not done[q] and objs[q] == objs[s]:
                        z_sum += z_s[q]
                        z_n += 1
                defocus_factors(z_sum / z_n, optics, prj_fmt, orient, counts, mfac)
                for q in range(s, ns):
                    if not done[q] and objs[q] == objs[s]:
                        done[q] = True
                        for oi in range(n_o):
                            w = txs[q] if orient[oi] == 0 else tys[q]
                            if has_field:
                                w += field[orient[oi], row, col]
                            add_phasors(zre, zim, oi, p, w, a_s[q], mfac, icounts, n_h, pr, pim)
            best, best_n = dominant(objs, ns)
            mx = my = 0.0
            m_n = 0
            for s in range(ns):
                if objs[s] == best and lit[s]:
                    mx += txs[s]
                    my += tys[s]
                    m_n += 1
            tau[0, row, col] = mx / m_n if m_n > 0 else np.nan
            tau[1, row, col] = my / m_n if m_n > 0 else np.nan
            ints[0, row, col] = best
            ints[2, row, col] = obj_sphere[best] if best >= 0 else -1
            fracs[0, row, col] = best_n / ns
            fracs[1, row, col] = n_lit / ns
            levels[0, row, col] = irradiance
            levels[1, row, col] = ambient
            base[p] = ambient + optics[0] * irradiance
        write_frames(frames, r0, c0, nr, nc, base, zre, zim, fcos, fsin, key, noise)
