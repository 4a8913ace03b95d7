"""Point-cloud files: binary PLY (plyfile) and a zarr store (xarray) for large clouds.

PLY (binary little-endian, one ``vertex`` element) is what CloudCompare, MeshLab and
Open3D open; the per-point fields of :data:`fringecal.measure.cloud.POINT_DTYPE` are
scalar properties of the vertex (``scanner`` is an index; the header's ``comment``
lines name the scanners in order, the calibration file and the units). The zarr store
holds the same fields as variables on one dimension ``point`` with the scanner names
and provenance as attributes, chunked, so a cloud of hundreds of millions of points
can be read in parts. Both are written under a temporary name and renamed into place:
an interrupted write leaves no half file. A cloud written before the
``outside_observed_region`` field existed reads with it 0 (nothing flagged).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fringecal.atomic import atomic_paths
from fringecal.measure.cloud import OUTSIDE, POINT_DTYPE, Cloud
from fringecal.store import open_store, write_store

__all__ = ["CLOUD_SUFFIXES", "write_cloud", "read_cloud", "write_ply", "read_ply"]

CLOUD_SUFFIXES = (".ply", ".zarr")
_SCANNERS = "scanners: "
_MEASUREMENTS = "measurements: "


def write_ply(cloud: Cloud, path, comments: dict | None = None) -> Path:
    """Binary PLY of ``cloud``; ``comments`` (key -> JSON value) become header comments."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    lines = [_SCANNERS + json.dumps(list(cloud.scanners)), _MEASUREMENTS + json.dumps(list(cloud.measurements)),
             "units: mm",
             *(f"{k}: {json.dumps(v)}" for k, v in (comments or {}).items())]
    data = PlyData([PlyElement.describe(np.ascontiguousarray(cloud.points), "vertex")], text=False,
                   byte_order="<", comments=lines)
    with atomic_paths([path]) as (tmp,):
        data.write(str(tmp))
    return path


def read_ply(path) -> Cloud:
    """A cloud written by :func:`write_ply` (any PLY with the same vertex fields)."""
    from plyfile import PlyData

    data = PlyData.read(str(path))
    vertex = data["vertex"].data
    missing = [n for n in POINT_DTYPE.names if n not in vertex.dtype.names and n != OUTSIDE]
    if missing:
        raise ValueError(f"{path}: vertex has no {', '.join(missing)} (fields: {', '.join(vertex.dtype.names)})")
    pts = np.zeros(len(vertex), POINT_DTYPE)
    for n in POINT_DTYPE.names:
        if n in vertex.dtype.names:
            pts[n] = vertex[n]
    def listed(prefix):
        return tuple(next((json.loads(c[len(prefix):]) for c in data.comments if c.startswith(prefix)), []))

    return Cloud(pts, listed(_SCANNERS), listed(_MEASUREMENTS))


def _write_zarr(cloud: Cloud, path: Path, comments: dict | None) -> Path:
    import xarray as xr

    ds = xr.Dataset({n: ("point", cloud.points[n]) for n in POINT_DTYPE.names},
                    attrs={"scanners": list(cloud.scanners), "measurements": list(cloud.measurements), "units": "mm",
                           **(comments or {})})
    return write_store(path, ds)


def write_cloud(cloud: Cloud, path, comments: dict | None = None) -> Path:
    """Write ``cloud`` as PLY (``.ply``) or zarr (``.zarr``), by the suffix."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return write_ply(cloud, path, comments)
    if suffix == ".zarr":
        return _write_zarr(cloud, path, comments)
    raise ValueError(f"{path}: a cloud is written as {' or '.join(CLOUD_SUFFIXES)}, not {suffix or 'no suffix'!r}")


def read_cloud(path) -> Cloud:
    """A cloud of :func:`write_cloud`."""
    path = Path(path)
    if path.suffix.lower() == ".zarr":
        with open_store(path) as ds:
            pts = np.zeros(ds.sizes["point"], POINT_DTYPE)
            for n in POINT_DTYPE.names:
                if n in ds or n != OUTSIDE:
                    pts[n] = ds[n].values
            return Cloud(pts, tuple(ds.attrs["scanners"]), tuple(ds.attrs["measurements"]))
    return read_ply(path)
