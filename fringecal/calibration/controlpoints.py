"""Control-point selection (thesis section 6.4).

Pixels on a regular grid (default every 10 px in both directions) inside each fitted
sphere's image region, away from its rim, become control points: the camera pixel, the
decoded projector phases there and the sphere's id. Excluded are

* pixels the decoding marked invalid or the sphere extraction rejected (rods, end caps,
  glints, edges: ``rejected``),
* pixels within ``erode_px`` of the region's edge (the rim, where the surface is seen
  at grazing incidence, and the borders with rods or other spheres): a pixel is kept only
  if every pixel within a disc of that radius belongs to the same sphere's valid region,
* optionally pixels whose surface normal is more than ``max_incidence_deg`` from the
  direction to the camera, given an ``incidence`` map (see :func:`incidence_map`).

The grid is anchored at pixel (0, 0) (columns and rows that are multiples of the
spacing, plus ``offset_px``), so the same pixels are chosen in every measurement and the
selection does not depend on where a region starts.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from scipy import ndimage

from fringecal.schemas import ControlPointsTable, validate_table

__all__ = ["select_control_points", "incidence_map", "CONTROL_POINT_COLUMNS"]

CONTROL_POINT_COLUMNS = ["measurement", "scanner", "sphere_id", "u_px", "v_px", "tau_x_rad", "tau_y_rad"]


def _disc(radius: int) -> np.ndarray:
    r = int(radius)
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return x * x + y * y <= r * r


def incidence_map(points_world: np.ndarray, labels: np.ndarray, centres_world: np.ndarray,
                  camera_origin) -> np.ndarray:
    """Angle (rad) between each pixel's sphere normal and its direction to the camera.

    Parameters
    ----------
    points_world : (H, W, 3) triangulated points
    labels : (H, W) int, index into ``centres_world`` (negative: no sphere)
    centres_world : (k, 3) fitted sphere centres
    camera_origin : (3,) camera pinhole

    Returns (H, W), NaN where there is no sphere.
    """
    labels = np.asarray(labels)
    out = np.full(labels.shape, np.nan)
    m = labels >= 0
    p = np.asarray(points_world, float)[m]
    n = p - np.asarray(centres_world, float)[labels[m]]
    v = np.asarray(camera_origin, float) - p
    cosang = np.einsum("ij,ij->i", n, v) / (np.linalg.norm(n, axis=1) * np.linalg.norm(v, axis=1))
    out[m] = np.arccos(np.clip(cosang, -1.0, 1.0))
    return out


def select_control_points(labels: np.ndarray, sphere_ids: Sequence | Mapping, tau_x: np.ndarray,
                          tau_y: np.ndarray, valid: np.ndarray | None = None,
                          rejected: np.ndarray | None = None, *, measurement: str, scanner: str,
                          spacing_px: int = 10, offset_px: int = 0, erode_px: int = 2,
                          incidence: np.ndarray | None = None,
                          max_incidence_deg: float | None = None) -> pd.DataFrame:
    """Control points of one (measurement, scanner) from its maps.

    Parameters
    ----------
    labels : (H, W) int
        Per pixel the fitted sphere region it belongs to: a key of ``sphere_ids``
        (an index if ``sphere_ids`` is a sequence), negative for none.
    sphere_ids : sequence or mapping
        Artefact sphere id of each label value.
    tau_x, tau_y : (H, W) decoded phases (rad)
    valid : (H, W) bool, optional (default: finite phases)
    rejected : (H, W) bool, optional; pixels the sphere extraction rejected
    spacing_px, offset_px : grid spacing and offset (section 6.4: 10 px)
    erode_px : rim exclusion radius in pixels (0: none)
    incidence, max_incidence_deg : optional angular rim limit (see :func:`incidence_map`)

    Returns
    -------
    DataFrame of the ControlPointsTable contract, ordered by sphere, row, column.

    Examples
    --------
    >>> lab = -np.ones((40, 40), int); yy, xx = np.mgrid[:40, :40]
    >>> lab[(xx - 20) ** 2 + (yy - 20) ** 2 <= 12 ** 2] = 0
    >>> cp = select_control_points(lab, ["7"], xx * 0.01, yy * 0.01, measurement="1",
    ...                            scanner="s1", spacing_px=10, erode_px=2)
    >>> cp[["u_px", "v_px"]].values.tolist()
    [[20.0, 10.0], [10.0, 20.0], [20.0, 20.0], [30.0, 20.0], [20.0, 30.0]]
    """
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"labels must be an (H, W) image, got shape {labels.shape}")
    shape = labels.shape
    tau_x = np.asarray(tau_x, float)
    tau_y = np.asarray(tau_y, float)
    for name, arr in (("tau_x", tau_x), ("tau_y", tau_y), ("valid", valid), ("rejected", rejected),
                      ("incidence", incidence)):
        if arr is not None and np.shape(arr) != shape:
            raise ValueError(f"{name} has shape {np.shape(arr)}, labels {shape}")
    if spacing_px < 1 or not (0 <= offset_px < spacing_px):
        raise ValueError(f"need spacing_px >= 1 and 0 <= offset_px < spacing_px, got {spacing_px}, {offset_px}")
    if max_incidence_deg is not None and incidence is None:
        raise ValueError("max_incidence_deg needs an incidence map (fringecal.calibration.controlpoints.incidence_map)")
    ids = dict(sphere_ids) if isinstance(sphere_ids, Mapping) else dict(enumerate(sphere_ids))
    good = np.isfinite(tau_x) & np.isfinite(tau_y)
    if valid is not None:
        good &= np.asarray(valid, bool)
    if rejected is not None:
        good &= ~np.asarray(rejected, bool)
    if max_incidence_deg is not None:
        with np.errstate(invalid="ignore"):
            good &= np.asarray(incidence, float) <= np.radians(max_incidence_deg)
    on_grid = np.zeros(shape, bool)
    on_grid[offset_px::spacing_px, offset_px::spacing_px] = True
    footprint = _disc(erode_px) if erode_px > 0 else None
    rows = []
    present = [k for k in np.unique(labels) if k >= 0]
    unknown = [int(k) for k in present if k not in ids]
    if unknown:
        raise ValueError(f"label values {unknown} have no sphere id")
    objects = ndimage.find_objects(np.where(labels >= 0, labels + 1, 0))
    pad = max(erode_px, 0) + 1
    for k in present:
        sl = objects[k]
        if sl is None:
            continue
        r0, r1 = max(sl[0].start - pad, 0), min(sl[0].stop + pad, shape[0])
        c0, c1 = max(sl[1].start - pad, 0), min(sl[1].stop + pad, shape[1])
        region = (labels[r0:r1, c0:c1] == k) & good[r0:r1, c0:c1]
        if footprint is not None:
            region = ndimage.binary_erosion(region, structure=footprint, border_value=0)
        keep = region & on_grid[r0:r1, c0:c1]
        v, u = np.nonzero(keep)
        if not len(v):
            continue
        v = v + r0
        u = u + c0
        rows.append(pd.DataFrame({"sphere_id": str(ids[k]), "u_px": u.astype(float), "v_px": v.astype(float),
                                  "tau_x_rad": tau_x[v, u], "tau_y_rad": tau_y[v, u]}))
    if rows:
        df = pd.concat(rows, ignore_index=True)
    else:
        df = pd.DataFrame({c: pd.Series(dtype=float) for c in ("u_px", "v_px", "tau_x_rad", "tau_y_rad")})
        df.insert(0, "sphere_id", pd.Series(dtype=str))
    df.insert(0, "scanner", str(scanner))
    df.insert(0, "measurement", str(measurement))
    df = df[CONTROL_POINT_COLUMNS]
    if len(df):
        df = validate_table(df, ControlPointsTable, f"control points of measurement {measurement}, scanner {scanner}")
    return df.reset_index(drop=True)
