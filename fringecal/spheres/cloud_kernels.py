"""Compiled single passes over a black-box scanner's cloud (millions of points).

numpy's version of each pass walks the cloud several times and allocates an array of
its size per step (``floor``, the keys, the sorted copy, the centred copy, six
products); on 2 million points that is some 0.7 s per cloud, against a few tens of
milliseconds here. The arithmetic is the same, term by term, so the sums differ from
numpy's only by the order of additions (rounding).
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["cube_keys", "cube_sums", "neighbourhood_sums", "within_reach", "within_reach_of_any"]

#: bits of each axis's cube index in a key (2 million cubes across)
KEY_BITS = 21


@nb.njit(cache=True, nogil=True)
def cube_keys(points, cell, origin):
    """One int64 per point: its cube of edge ``cell`` counted from ``origin`` (cube
    indices, (3,) float), ``KEY_BITS`` bits an axis, x highest."""
    n = points.shape[0]
    keys = np.empty(n, np.int64)
    for i in range(n):
        qx = np.int64(np.floor(points[i, 0] / cell) - origin[0])
        qy = np.int64(np.floor(points[i, 1] / cell) - origin[1])
        qz = np.int64(np.floor(points[i, 2] / cell) - origin[2])
        keys[i] = (qx << 42) | (qy << 21) | qz
    return keys


@nb.njit(cache=True, nogil=True)
def cube_sums(points, order, start, shift):
    """Per cube (the points ``order[start[k]:start[k + 1]]``): the sums of the points
    less ``shift`` (m, 3) and of their products xx, yy, zz, xy, xz, yz (m, 6)."""
    m = start.shape[0]
    s1 = np.zeros((m, 3))
    s2 = np.zeros((m, 6))
    n = order.shape[0]
    for k in range(m):
        end = start[k + 1] if k + 1 < m else n
        for j in range(start[k], end):
            i = order[j]
            x = points[i, 0] - shift[0]
            y = points[i, 1] - shift[1]
            z = points[i, 2] - shift[2]
            s1[k, 0] += x
            s1[k, 1] += y
            s1[k, 2] += z
            s2[k, 0] += x * x
            s2[k, 1] += y * y
            s2[k, 2] += z * z
            s2[k, 3] += x * y
            s2[k, 4] += x * z
            s2[k, 5] += y * z
    return s1, s2


@nb.njit(cache=True, nogil=True)
def neighbourhood_sums(keys, count, s1, s2, offsets):
    """Each cube's point count and sums (:func:`cube_sums`) with those of its occupied
    neighbours added, the neighbours in the order of ``offsets`` (key differences) as
    numpy's cube-by-cube version adds them (the same sums, bit for bit); ``keys``
    sorted ascending."""
    m = keys.shape[0]
    n = count.astype(np.float64)
    t1 = s1.copy()
    t2 = s2.copy()
    for o in range(offsets.shape[0]):
        j = 0  # the targets keys[i] + offset ascend with i: one merge-like walk per offset
        for i in range(m):
            target = keys[i] + offsets[o]
            while j < m and keys[j] < target:
                j += 1
            if j < m and keys[j] == target:
                n[i] += count[j]
                for a in range(3):
                    t1[i, a] += s1[j, a]
                for a in range(6):
                    t2[i, a] += s2[j, a]
    return n, t1, t2


@nb.njit(cache=True, nogil=True)
def within_reach(points, centre, reach):
    """Indices of the points at most ``reach`` from ``centre`` (Euclidean distance, as
    ``np.linalg.norm(points - centre, axis=1) <= reach``), in the cloud's order."""
    n = points.shape[0]
    out = np.empty(n, np.int64)
    count = 0
    for i in range(n):
        dx = points[i, 0] - centre[0]
        if dx > reach or dx < -reach:
            continue
        dy = points[i, 1] - centre[1]
        if dy > reach or dy < -reach:
            continue
        dz = points[i, 2] - centre[2]
        if dz > reach or dz < -reach:
            continue
        if np.sqrt(dx * dx + dy * dy + dz * dz) <= reach:
            out[count] = i
            count += 1
    return out[:count]


@nb.njit(cache=True, nogil=True)
def within_reach_of_any(points, centres, reach):
    """Indices of the points at most ``reach`` from at least one of ``centres`` (k, 3),
    in the cloud's order: one pass for all of a cloud's spheres, whose neighbourhoods
    :func:`within_reach` then picks from the few points left."""
    n = points.shape[0]
    out = np.empty(n, np.int64)
    count = 0
    for i in range(n):
        for k in range(centres.shape[0]):
            dx = points[i, 0] - centres[k, 0]
            if dx > reach or dx < -reach:
                continue
            dy = points[i, 1] - centres[k, 1]
            if dy > reach or dy < -reach:
                continue
            dz = points[i, 2] - centres[k, 2]
            if dz > reach or dz < -reach:
                continue
            if np.sqrt(dx * dx + dy * dy + dz * dz) <= reach:
                out[count] = i
                count += 1
                break
    return out[:count]
