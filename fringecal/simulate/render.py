"""Render one measurement of a scanner: camera frames plus per-pixel ground truth.

For each camera pixel an n x n grid of sub-samples over the pixel footprint (eq. 2-21
pixel centres, sub-sample rays through the full camera model) is cast into the
scene. At each hit the projector coordinate (tau_x, tau_y) follows from the full
projector model; a ray from the projector pinhole decides whether the projector
lights the point (shadows, back faces, outside the SLM). Shading, ambient light and
projector defocus are described in :mod:`fringecal.simulate.config`.

Speed: per pixel, orientation and fringe count t the sub-samples reduce to one
phasor ``Z_t = sum_s w_s P_s m_t,s exp(i t tau_s)``; every phase step is then
``I_k = ambient + A S + B Re(exp(i 2 pi k/N) Z_t)`` with ``S = sum_s w_s P_s``.
Candidate primitives are culled per image tile with bounding cones. The whole
pipeline, noise included, is one parallel numba kernel over tiles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from numba import njit, prange

from ..fringe.sequence import FringeSequence
from ..rig import Scanner
from . import geometry as g
from .config import RenderConfig
from .noise import quantise, record, stream
from .scene import Scene

__all__ = ["GroundTruth", "Measurement", "render_measurement", "LIGHT_NO_HIT", "LIGHT_LIT",
           "LIGHT_SHADOW", "LIGHT_OUTSIDE"]

#: Codes of :attr:`GroundTruth.light`.
LIGHT_NO_HIT, LIGHT_LIT, LIGHT_SHADOW, LIGHT_OUTSIDE = 0, 1, 2, 3


@dataclass(frozen=True)
class GroundTruth:
    """Per-pixel truth of one rendered measurement; maps have shape (rows, cols).

    Attributes
    ----------
    tau_x, tau_y : float64
        Projector coordinates (rad, eq. 2-22) averaged over the lit sub-samples that
        hit :attr:`object_index` (area-weighted); NaN where none is lit.
    tau_x_centre, tau_y_centre : float64
        Projector coordinates of the pixel-centre ray's hit; NaN unless it is lit.
    point : float64, shape (rows, cols, 3)
        World point (mm) hit by the pixel-centre ray; NaN where it hits nothing.
    object_index : int16
        Dominant object (most sub-samples) as an index into :attr:`object_names`;
        -1 = most sub-samples hit nothing.
    centre_object_index : int16
        Object hit by the pixel-centre ray (-1 none).
    sphere_index : int16
        Index into :attr:`sphere_ids` where the dominant object is a sphere, else -1.
    purity : float32
        Fraction of the pixel footprint (sub-samples) on the dominant object.
    lit_fraction : float32
        Fraction of the footprint that receives projector light.
    light : int8
        Pixel-centre ray: 0 no hit, 1 lit, 2 shadow (the projector's view of the point
        is blocked, by another object or by the object itself), 3 outside the SLM.
    irradiance : float64
        ``S = sum_s w_s P_s``: the frames are ``ambient_level + A S + B Re(...)``.
    ambient_level : float64
        Ambient contribution (fraction of full scale).
    object_names, object_kinds : tuple of str
        Per object index.
    sphere_ids : tuple of str
        Per sphere index.
    """

    tau_x: np.ndarray
    tau_y: np.ndarray
    tau_x_centre: np.ndarray
    tau_y_centre: np.ndarray
    point: np.ndarray
    object_index: np.ndarray
    centre_object_index: np.ndarray
    sphere_index: np.ndarray
    purity: np.ndarray
    lit_fraction: np.ndarray
    light: np.ndarray
    irradiance: np.ndarray
    ambient_level: np.ndarray
    object_names: tuple[str, ...]
    object_kinds: tuple[str, ...]
    sphere_ids: tuple[str, ...]

    _LABELS = ("object_names", "object_kinds", "sphere_ids")

    @property
    def shape(self) -> tuple[int, int]:
        return self.tau_x.shape

    def objects_of_kind(self, kind: str) -> np.ndarray:
        """Object indices of ``kind``."""
        return np.array([i for i, k in enumerate(self.object_kinds) if k == kind], int)

    def sphere_mask(self, sphere_id: str | None = None, min_purity: float = 1.0) -> np.ndarray:
        """Pixels whose dominant object is a sphere (``sphere_id`` or any), at least
        ``min_purity`` of the footprint on it and lit by the projector."""
        if sphere_id is None:
            m = self.sphere_index >= 0
        else:
            m = self.sphere_index == self.sphere_ids.index(str(sphere_id))
        return m & (self.purity >= min_purity) & np.isfinite(self.tau_x)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def save(self, path) -> Path:
        """Write to ``path`` (.npz), atomically."""
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        arrays = {k: v for k, v in self.to_dict().items() if k not in self._LABELS}
        labels = {k: np.array(getattr(self, k), dtype=str) for k in self._LABELS}
        np.savez_compressed(tmp, **arrays, **labels)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path) -> "GroundTruth":
        with np.load(Path(path)) as z:
            kw = {k: (tuple(str(x) for x in z[k]) if k in cls._LABELS else z[k]) for k in z.files}
        return cls(**kw)


@dataclass(frozen=True)
class Measurement:
    """Frames (n_frames, rows, cols) uint16 in ``sequence.frames()`` order, and truth."""

    frames: np.ndarray
    truth: GroundTruth
    sequence: FringeSequence
    scanner: str


def render_measurement(scanner: Scanner, scene: Scene, config: RenderConfig, rng: np.random.Generator,
                       sequence: FringeSequence | None = None) -> Measurement:
    """Render the fringe sequence of ``scanner`` looking at ``scene``.

    Parameters
    ----------
    scanner : Scanner
        Camera and projector with their 14-parameter models and formats.
    scene : Scene
        Objects in world coordinates; every material must be in ``config.materials``.
    config : RenderConfig
    rng : numpy.random.Generator
        Source of the noise key; the same generator state gives the same frames.
    sequence : FringeSequence, default the thesis's 2 x 7 x 7

    Returns
    -------
    Measurement
        ``frames`` uint16 (n_frames, rows, cols) and ``truth``.
    """
    seq = sequence or FringeSequence()
    missing = sorted({o.material for o in scene.objects} - set(config.materials))
    if missing:
        raise ValueError(f"scene materials {missing} are not in the render configuration "
                         f"(have {sorted(config.materials)})")
    cam, prj = scanner.camera, scanner.projector
    H, W = cam.format.shape
    prims, kinds, owner = scene.packed()
    mats = np.array([[config.materials[o.material].albedo, config.materials[o.material].specular,
                      config.materials[o.material].shininess] for o in scene.objects], float).reshape(-1, 3)
    obj_sphere = scene.object_sphere_index()
    orient = np.array([0 if o == "x" else 1 for o in seq.orientations], np.int64)
    counts = np.array(seq.fringe_counts, float)
    phases = seq.step_phases()
    optics = np.array([config.offset, config.amplitude, config.ambient, config.reference_distance_mm,
                       config.focus_distance_mm, config.blur_at_focus_mm, config.blur_per_mm])
    sigma_e = math.hypot(config.read_noise_e, config.excess_noise * config.full_well_e)
    noise = np.array([config.full_well_e, sigma_e, 1.0 / config.gain_e_per_dn, float(config.max_dn),
                      1.0 if config.shot_noise else 0.0])
    key = np.uint64(rng.integers(0, 2**63, dtype=np.int64))
    cam_fmt = np.array([W, H, cam.format.width_mm, cam.format.height_mm], float)
    prj_fmt = np.array([prj.format.width_mm, prj.format.height_mm], float)

    frames = np.empty((seq.n_frames, H, W), np.uint16)
    tau = np.empty((2, H, W))
    tau_c = np.empty((2, H, W))
    point = np.empty((H, W, 3))
    ints = np.empty((3, H, W), np.int16)  # dominant object, centre object, sphere index
    fracs = np.empty((2, H, W), np.float32)  # purity, lit fraction
    light = np.empty((H, W), np.int8)
    levels = np.empty((2, H, W))  # irradiance, ambient
    _render(g.sensor_pack(cam), cam_fmt, g.sensor_pack(prj), prj_fmt, prims, kinds, owner, mats, obj_sphere,
            config.supersampling, orient, counts, np.cos(phases), np.sin(phases), optics, noise, key,
            config.tile_px, frames, tau, tau_c, point, ints, fracs, light, levels)
    truth = GroundTruth(
        tau_x=tau[0], tau_y=tau[1], tau_x_centre=tau_c[0], tau_y_centre=tau_c[1], point=point,
        object_index=ints[0], centre_object_index=ints[1], sphere_index=ints[2],
        purity=fracs[0], lit_fraction=fracs[1], light=light, irradiance=levels[0], ambient_level=levels[1],
        object_names=scene.names, object_kinds=tuple(o.kind for o in scene.objects),
        sphere_ids=scene.sphere_ids,
    )
    return Measurement(frames, truth, seq, scanner.name)


@njit(cache=True)
def _shade(prims, kinds, owner, mats, cand, n_cand, prj, prj_fmt, optics, cam_o, X, Y, Z, nx, ny, nz, obj):
    """Projector light at a hit: (code, tau_x, tau_y, P, projector depth z')."""
    xi, eta, zp = g.project_point(X, Y, Z, prj)
    if not zp > 0 or abs(xi) > prj_fmt[0] / 2 or abs(eta) > prj_fmt[1] / 2:
        return LIGHT_OUTSIDE, np.nan, np.nan, 0.0, zp
    tx = 2 * math.pi * xi / prj_fmt[0]
    ty = 2 * math.pi * eta / prj_fmt[1]
    lx, ly, lz = prj[0] - X, prj[1] - Y, prj[2] - Z
    D = math.sqrt(lx * lx + ly * ly + lz * lz)
    lx, ly, lz = lx / D, ly / D, lz / D
    cos_i = nx * lx + ny * ly + nz * lz
    if cos_i <= 0:
        return LIGHT_SHADOW, tx, ty, 0.0, zp
    t, j, _, _, _ = g.nearest_hit(prims, kinds, cand, n_cand, prj[0], prj[1], prj[2], -lx, -ly, -lz, 0.0)
    if t < D * (1 - 1e-9) - 1e-7:
        return LIGHT_SHADOW, tx, ty, 0.0, zp
    albedo, spec, shin = mats[obj, 0], mats[obj, 1], mats[obj, 2]
    p = albedo * cos_i
    if spec > 0:
        vx, vy, vz = cam_o[0] - X, cam_o[1] - Y, cam_o[2] - Z
        vn = math.sqrt(vx * vx + vy * vy + vz * vz)
        hx, hy, hz = lx + vx / vn, ly + vy / vn, lz + vz / vn
        hn = math.sqrt(hx * hx + hy * hy + hz * hz)
        ch = (nx * hx + ny * hy + nz * hz) / hn
        if ch > 0:
            p += spec * ch ** shin
    r = optics[3] / D
    return LIGHT_LIT, tx, ty, p * r * r, zp


@njit(cache=True)
def _add_phasors(zre, zim, oi, p, w, a, mfac, icounts, pr, pim):
    """zre/zim[oi, t, p] += a m_t exp(i t w) for every fringe count: exp(i 2^b w) by
    repeated squaring, exp(i t w) as the product over t's bits (no trig per count)."""
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


@njit(parallel=True, cache=True)
def _render(cam, cam_fmt, prj, prj_fmt, prims, kinds, owner, mats, obj_sphere, n, orient, counts, step_cos,
            step_sin, optics, noise, key, tile, frames, tau, tau_c, point, ints, fracs, light, levels):
    H, W = frames.shape[1], frames.shape[2]
    n_o, n_t, n_k = orient.shape[0], counts.shape[0], step_cos.shape[0]
    ns = n * n
    extra = 1 if n % 2 == 0 else 0
    nray = ns + extra
    centre_slot = ns if extra else (n // 2) * n + n // 2
    w_s = 1.0 / ns
    A, B, amb = optics[0], optics[1], optics[2]
    focus, blur0, blur_k = optics[4], optics[5], optics[6]
    full_well, sigma_e, inv_gain, max_dn, shot = noise[0], noise[1], noise[2], int(noise[3]), noise[4] > 0
    noisy = shot or sigma_e > 0
    scale = full_well * inv_gain
    icounts = np.empty(n_t, np.int64)
    for ti in range(n_t):
        icounts[ti] = int(counts[ti])
    n_bits = 1
    while (1 << n_bits) <= icounts.max():
        n_bits += 1
    tiles_x = (W + tile - 1) // tile
    tiles_y = (H + tile - 1) // tile
    n_prim = prims.shape[0]
    for tid in prange(tiles_x * tiles_y):
        r0 = (tid // tiles_x) * tile
        c0 = (tid % tiles_x) * tile
        nr = min(tile, H - r0)
        nc = min(tile, W - c0)
        npx = nr * nc
        dirs = np.empty((npx, nray, 3))
        okr = np.zeros((npx, nray), np.bool_)
        sx = sy = sz = 0.0
        shx = shy = 0.0
        for p in range(npx):
            row = r0 + p // nc
            col = c0 + p % nc
            for s in range(nray):
                if s < ns:
                    du = (s % n + 0.5) / n - 0.5
                    dv = (s // n + 0.5) / n - 0.5
                else:
                    du = dv = 0.0
                xi = ((col + du) / (cam_fmt[0] - 1) - 0.5) * cam_fmt[2]
                eta = ((row + dv) / (cam_fmt[1] - 1) - 0.5) * cam_fmt[3]
                dx, dy, dz, ok, ddx, ddy = g.image_ray(xi, eta, cam, shx, shy)
                dirs[p, s, 0], dirs[p, s, 1], dirs[p, s, 2] = dx, dy, dz
                okr[p, s] = ok
                if ok:
                    shx, shy = ddx, ddy
                    sx += dx
                    sy += dy
                    sz += dz
        # bounding cone of the tile's rays
        sn = math.sqrt(sx * sx + sy * sy + sz * sz)
        cand = np.empty(n_prim, np.int64)
        n_cand = 0
        if sn > 0:
            ax, ay, az = sx / sn, sy / sn, sz / sn
            cmin = 1.0
            for p in range(npx):
                for s in range(nray):
                    if okr[p, s]:
                        c = dirs[p, s, 0] * ax + dirs[p, s, 1] * ay + dirs[p, s, 2] * az
                        cmin = min(cmin, c)
            n_cand = g.cone_candidates(prims, cam[0], cam[1], cam[2], ax, ay, az, cmin, cand)
        hit_t = np.full((npx, nray), np.inf)
        hit_j = np.full((npx, nray), -1, np.int64)
        hit_n = np.empty((npx, nray, 3))
        lx = ly = lz = 0.0
        any_hit = False
        for p in range(npx):
            for s in range(nray):
                if okr[p, s] and n_cand > 0:
                    t, j, hx, hy, hz = g.nearest_hit(prims, kinds, cand, n_cand, cam[0], cam[1], cam[2],
                                                     dirs[p, s, 0], dirs[p, s, 1], dirs[p, s, 2], 0.0)
                    hit_t[p, s], hit_j[p, s] = t, j
                    hit_n[p, s, 0], hit_n[p, s, 1], hit_n[p, s, 2] = hx, hy, hz
                    if j >= 0:
                        any_hit = True
                        vx = cam[0] + t * dirs[p, s, 0] - prj[0]
                        vy = cam[1] + t * dirs[p, s, 1] - prj[1]
                        vz = cam[2] + t * dirs[p, s, 2] - prj[2]
                        vn = math.sqrt(vx * vx + vy * vy + vz * vz)
                        lx += vx / vn
                        ly += vy / vn
                        lz += vz / vn
        # bounding cone, from the projector pinhole, of the shadow rays
        scand = np.empty(n_prim, np.int64)
        n_scand = 0
        ln = math.sqrt(lx * lx + ly * ly + lz * lz)
        if any_hit and ln > 0:
            ax, ay, az = lx / ln, ly / ln, lz / ln
            cmin = 1.0
            for p in range(npx):
                for s in range(nray):
                    if hit_j[p, s] >= 0:
                        t = hit_t[p, s]
                        vx = cam[0] + t * dirs[p, s, 0] - prj[0]
                        vy = cam[1] + t * dirs[p, s, 1] - prj[1]
                        vz = cam[2] + t * dirs[p, s, 2] - prj[2]
                        c = (vx * ax + vy * ay + vz * az) / math.sqrt(vx * vx + vy * vy + vz * vz)
                        cmin = min(cmin, c)
            n_scand = g.cone_candidates(prims, prj[0], prj[1], prj[2], ax, ay, az, cmin, scand)

        zre = np.zeros((n_o, n_t, npx))
        zim = np.zeros((n_o, n_t, npx))
        S = np.zeros(npx)
        objs = np.empty(nray, np.int64)
        pr = np.empty(n_bits)
        pim = np.empty(n_bits)
        lit = np.zeros(nray, np.bool_)
        txs = np.empty(nray)
        tys = np.empty(nray)
        a_s = np.empty(nray)
        z_s = np.empty(nray)
        done = np.empty(nray, np.bool_)
        mfac = np.empty((n_o, n_t))
        for p in range(npx):
            row = r0 + p // nc
            col = c0 + p % nc
            amb_level = 0.0
            n_lit = 0
            for s in range(nray):
                j = hit_j[p, s]
                lit[s] = False
                txs[s] = np.nan
                tys[s] = np.nan
                code = LIGHT_NO_HIT
                if j < 0:
                    objs[s] = -1
                else:
                    obj = owner[j]
                    objs[s] = obj
                    t = hit_t[p, s]
                    X = cam[0] + t * dirs[p, s, 0]
                    Y = cam[1] + t * dirs[p, s, 1]
                    Z = cam[2] + t * dirs[p, s, 2]
                    code, tx, ty, P, zp = _shade(prims, kinds, owner, mats, scand, n_scand, prj, prj_fmt,
                                                 optics, cam, X, Y, Z, hit_n[p, s, 0], hit_n[p, s, 1],
                                                 hit_n[p, s, 2], obj)
                    if code == LIGHT_LIT:
                        lit[s] = True
                        txs[s], tys[s] = tx, ty
                    if s < ns:
                        amb_level += w_s * mats[obj, 0] * amb
                        if code == LIGHT_LIT:
                            n_lit += 1
                            a_s[s] = w_s * P
                            z_s[s] = zp
                            S[p] += a_s[s]
                if s == centre_slot:
                    light[row, col] = code
                    ints[1, row, col] = objs[s]
                    tau_c[0, row, col], tau_c[1, row, col] = txs[s], tys[s]
                    if j >= 0:
                        t = hit_t[p, s]
                        for i in range(3):
                            point[row, col, i] = cam[i] + t * dirs[p, s, i]
                    else:
                        point[row, col, 0] = point[row, col, 1] = point[row, col, 2] = np.nan
            # phasors, object by object: defocus from the object's mean projector depth
            # in this footprint (depth varies by far less than the depth of field)
            for s in range(ns):
                done[s] = not lit[s]
            for s in range(ns):
                if done[s]:
                    continue
                zsum, zn = 0.0, 0
                for q in range(s, ns):
                    if not done[q] and objs[q] == objs[s]:
                        zsum += z_s[q]
                        zn += 1
                blur = blur0 + blur_k * abs(zsum / zn - focus)
                for oi in range(n_o):
                    f = 2 * math.pi * blur / prj_fmt[orient[oi]]
                    for ti in range(n_t):
                        mfac[oi, ti] = math.exp(-0.5 * (f * counts[ti]) ** 2)
                for q in range(s, ns):
                    if not done[q] and objs[q] == objs[s]:
                        done[q] = True
                        for oi in range(n_o):
                            w = txs[q] if orient[oi] == 0 else tys[q]
                            _add_phasors(zre, zim, oi, p, w, a_s[q], mfac, icounts, pr, pim)
            # dominant object of the footprint (ties: the first sub-sample's)
            best, best_n = -1, -1
            for s in range(ns):
                cnt = 0
                for q in range(ns):
                    if objs[q] == objs[s]:
                        cnt += 1
                if cnt > best_n:
                    best, best_n = objs[s], cnt
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
            levels[0, row, col] = S[p]
            levels[1, row, col] = amb_level

        # frames: every step of every (orientation, fringe count) from the phasors;
        # each pixel draws its noise from its own stream, frame after frame
        base = np.empty(npx)
        for p in range(npx):
            base[p] = levels[1, r0 + p // nc, c0 + p % nc] + A * S[p]
        states = np.empty(npx, np.uint64)
        for p in range(npx):
            states[p] = stream(key, (r0 + p // nc) * W + c0 + p % nc)
        for oi in range(n_o):
            for ti in range(n_t):
                for k in range(n_k):
                    f = (oi * n_t + ti) * n_k + k
                    bc, bs = B * step_cos[k], B * step_sin[k]
                    for r in range(nr):
                        out = frames[f, r0 + r, c0:c0 + nc]
                        for c in range(nc):
                            p = r * nc + c
                            val = base[p] + bc * zre[oi, ti, p] - bs * zim[oi, ti, p]
                            if noisy:
                                states[p], out[c] = record(val * full_well, states[p], shot, sigma_e,
                                                           inv_gain, max_dn)
                            else:
                                out[c] = quantise(val * scale, max_dn)
