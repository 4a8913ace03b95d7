"""A black-box scanner's point cloud: reading, checking and writing its file.

Most industrial 3-D scanners hand out point clouds in their own frame, not fringe
images and not a sensor model. fringecal takes such a cloud as one PLY file per
(measurement or position, scanner): a ``vertex`` element with ``x``, ``y``, ``z`` in mm
in the scanner's own frame (float or double, binary or ASCII), optionally ``nx``,
``ny``, ``nz`` and ``intensity``; other vertex properties and other elements (faces)
are ignored. E57 files are read when the optional ``pye57`` is installed
(``pip install fringecal[e57]``).

Every problem raises one :class:`CloudFileError` (a ``ValueError``) whose message
starts with the file:

* not a PLY file, or a PLY without a vertex element or without ``x``, ``y``, ``z``;
* an empty cloud, or one of more than :data:`fringecal.schemas.MAX_POINTS` points (every
  pixel of a 4096 x 4096 camera: the bound every points input has), refused from the
  header before any point is read;
* points with a NaN or infinite coordinate (the count and the first point's index);
* a cloud in metres: a header comment ``units: m`` (or any unit other than mm), or a
  cloud whose extent is smaller than a sphere it should hold: a scanner that sees an
  artefact sphere of diameter d mm sees at least a cap of it, so a cloud spanning less
  than d / 2 units is in metres (or another unit 1000 times too large).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from fringecal.atomic import atomic_paths
from fringecal.schemas import MAX_POINTS
from fringecal.store import open_store, store_attributes, write_store

__all__ = ["CLOUD_SUFFIXES", "CloudFileError", "ScannerCloud", "read_scanner_cloud", "write_scanner_cloud",
           "check_cloud_header", "check_cloud_units", "check_points", "CLOUD_ATTR", "write_cloud_store",
           "is_cloud_store", "read_cloud_store", "cloud_store_from_file", "load_points", "bounding_box"]

#: suffixes of a cloud file in a data set (lower case)
CLOUD_SUFFIXES = (".ply", ".e57")
_UNITS = re.compile(r"^\s*units?\s*[:=]\s*(\S+)", re.IGNORECASE)
_MM = {"mm", "millimeter", "millimeters", "millimetre", "millimetres"}


class CloudFileError(ValueError):
    """A cloud file that cannot be used; the message starts with the file."""


@dataclass(frozen=True)
class ScannerCloud:
    """The points of one cloud file, in mm in the scanner's own frame.

    Attributes
    ----------
    points : ndarray, shape (n, 3), float64
    normals : ndarray, shape (n, 3), or None
    intensity : ndarray, shape (n,), or None
    path : Path
    """

    points: np.ndarray
    normals: np.ndarray | None
    intensity: np.ndarray | None
    path: Path

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])


def _ply(path: Path, mmap: bool = True):
    from plyfile import PlyData, PlyParseError

    try:
        with open(path, "rb") as f:
            if f.read(4) != b"ply\n" and not _is_ply_crlf(path):
                raise CloudFileError(f"{path}: not a PLY file (it must start with the line 'ply')")
        return PlyData.read(str(path), mmap="r" if mmap else False)
    except CloudFileError:
        raise
    except (PlyParseError, ValueError, IndexError, EOFError, UnicodeDecodeError) as err:
        raise CloudFileError(f"{path}: corrupt or truncated PLY file ({err})") from None


def _is_ply_crlf(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(5) == b"ply\r\n"


def _vertex(path: Path, data):
    names = [e.name for e in data.elements]
    if "vertex" not in names:
        raise CloudFileError(f"{path}: no 'vertex' element (elements: {', '.join(names) or 'none'}); a cloud is "
                             "a PLY vertex element with x, y, z in mm")
    vertex = data["vertex"]
    props = [p.name for p in vertex.properties]
    missing = [c for c in "xyz" if c not in props]
    if missing:
        raise CloudFileError(f"{path}: vertex without {', '.join(missing)} (properties: {', '.join(props)}); a "
                             "cloud's vertices need x, y, z in mm")
    return vertex, props


def _header_units(path: Path, comments) -> None:
    for c in comments:
        m = _UNITS.match(c)
        if m and m.group(1).strip(".,;").lower() not in _MM:
            raise CloudFileError(f"{path}: the header says 'units: {m.group(1)}'; fringecal reads clouds in mm "
                                 "(multiply by 1000 for metres) in the scanner's own frame")


def check_cloud_header(path) -> int:
    """Check a cloud file's header only (PLY: the vertex element, x, y, z and a units
    comment; cheap: no point is read). Returns the number of points."""
    path = Path(path)
    if path.suffix.lower() == ".e57":
        return _e57(path).n_points
    data = _ply(path)
    vertex, _ = _vertex(path, data)
    _header_units(path, data.comments + data.obj_info)
    _check_count(path, int(vertex.count))
    return int(vertex.count)


def _check_count(path: Path, n: int) -> None:
    if n == 0:
        raise CloudFileError(f"{path}: empty cloud (0 vertices)")
    if n > MAX_POINTS:
        raise CloudFileError(f"{path}: {n} points; at most {MAX_POINTS} can be used (every pixel of a 4096 x 4096 "
                             "camera): thin the cloud")


def read_scanner_cloud(path, min_extent_mm: float = 0.0) -> ScannerCloud:
    """Read and check a cloud file (see the module notes).

    Parameters
    ----------
    path : path of a ``.ply`` (or, with pye57, ``.e57``) file
    min_extent_mm : float
        The cloud's bounding-box diagonal must reach this (half the artefact's smallest
        sphere diameter); a smaller one is taken as a cloud in metres and refused.
    """
    path = Path(path)
    if path.suffix.lower() == ".e57":
        cloud = _e57(path)
    else:
        data = _ply(path)
        vertex, props = _vertex(path, data)
        _header_units(path, data.comments + data.obj_info)
        _check_count(path, int(vertex.count))
        v = vertex.data
        try:
            pts = np.empty((len(v), 3))
            for i, c in enumerate("xyz"):
                pts[:, i] = v[c]
            normals = None
            if all(c in props for c in ("nx", "ny", "nz")):
                normals = np.empty((len(v), 3))
                for i, c in enumerate(("nx", "ny", "nz")):
                    normals[:, i] = v[c]
            intensity = np.asarray(v["intensity"], float) if "intensity" in props else None
        except (ValueError, TypeError, OSError) as err:
            raise CloudFileError(f"{path}: corrupt or truncated PLY file ({err})") from None
        cloud = ScannerCloud(pts, normals, intensity, path)
    check_points(cloud.points, path, min_extent_mm)
    return cloud


def check_points(points: np.ndarray, path, min_extent_mm: float = 0.0) -> None:
    """Refuse an empty cloud, non-finite coordinates and a cloud in metres."""
    if points.shape[0] == 0:
        raise CloudFileError(f"{path}: empty cloud (0 vertices)")
    # the bounding box first (a NaN or an infinity shows in it): a point-by-point mask
    # of 2 million points costs ten times as much and is needed only to name the bad ones
    lo, hi = bounding_box(points)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        bad = ~np.isfinite(points).all(axis=1)
        first = int(np.flatnonzero(bad)[0])
        raise CloudFileError(f"{path}: {int(bad.sum())} of {len(points)} points have a NaN or infinite coordinate "
                             f"(the first is vertex {first}); remove them from the cloud")
    check_cloud_units(points, path, min_extent_mm, (lo, hi))


def bounding_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each axis's min and max, one column at a time (``min(axis=0)`` of an (n, 3)
    array reduces three values a row: some 30 times slower on 2 million points)."""
    return (np.array([points[:, i].min() for i in range(3)]), np.array([points[:, i].max() for i in range(3)]))


def check_cloud_units(points: np.ndarray, path, min_extent_mm: float, box: tuple | None = None) -> None:
    """A cloud spanning less than ``min_extent_mm`` units is refused as not in mm
    (``box``: the points' (min, max) per axis when already known)."""
    lo, hi = box if box is not None else bounding_box(points)
    diagonal = float(np.linalg.norm(hi - lo))
    if min_extent_mm > 0 and diagonal < min_extent_mm:
        raise CloudFileError(f"{path}: the cloud spans {diagonal:.4g} units, less than half the artefact's "
                             f"smallest sphere ({min_extent_mm:.4g} mm): in metres? x, y, z must be in mm in "
                             "the scanner's own frame")


def _e57(path: Path) -> ScannerCloud:
    try:
        import pye57  # lazy: an optional extra (fringecal[e57])
    except ImportError:
        raise CloudFileError(f"{path}: E57 needs the optional reader pye57 (pip install 'fringecal[e57]'), "
                             "or convert the cloud to PLY") from None
    try:
        e57 = pye57.E57(str(path))
        scans = [e57.read_scan(i, ignore_missing_fields=True) for i in range(e57.scan_count)]
    except Exception as err:  # pye57 raises its library's own exception types
        raise CloudFileError(f"{path}: corrupt E57 file ({err})") from None
    pts = np.concatenate([np.column_stack([s["cartesianX"], s["cartesianY"], s["cartesianZ"]]) for s in scans]
                         ) if scans else np.zeros((0, 3))
    _check_count(path, len(pts))
    # E57 stores metres (ASTM E2807): fringecal works in mm
    return ScannerCloud(1000.0 * pts, None, None, path)


def write_scanner_cloud(path, points: np.ndarray, normals: np.ndarray | None = None, text: bool = False,
                        comments: tuple = ("units: mm",)) -> Path:
    """Write a cloud as a PLY vertex element (float32 x, y, z[, nx, ny, nz]), atomically."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    v = np.empty(len(points), fields)
    for i, c in enumerate("xyz"):
        v[c] = points[:, i]
    if normals is not None:
        for i, c in enumerate(("nx", "ny", "nz")):
            v[c] = normals[:, i]
    data = PlyData([PlyElement.describe(v, "vertex")], text=text, byte_order="<", comments=list(comments))
    with atomic_paths([path]) as (tmp,):
        data.write(str(tmp))
    return path


# -- the run's store of a cloud ---------------------------------------------------

#: attribute that marks a run's measurement store as a black-box scanner's cloud
CLOUD_ATTR = "black_box_cloud"


def write_cloud_store(path, points: np.ndarray, normals: np.ndarray | None = None, attrs: dict | None = None) -> Path:
    """A run's measurement store of a cloud: float32 ``x``, ``y``, ``z`` (and ``nx``,
    ``ny``, ``nz``) on one dimension ``point``, mm in the scanner's own frame (1-D fields
    are stored in chunks of 2**20 points), marked by :data:`CLOUD_ATTR`."""
    points = np.asarray(points, np.float32)
    data = {c: ("point", points[:, i]) for i, c in enumerate("xyz")}
    if normals is not None:
        normals = np.asarray(normals, np.float32)
        data.update({c: ("point", normals[:, i]) for i, c in enumerate(("nx", "ny", "nz"))})
    return write_store(path, xr.Dataset(data, attrs={**(attrs or {}), CLOUD_ATTR: True, "units": "mm"}))


def is_cloud_store(path) -> bool:
    """Whether the run's store at ``path`` holds a cloud (else decoded phase maps)."""
    return bool(store_attributes(path).get(CLOUD_ATTR, False))


def read_cloud_store(path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (n, 3) float64 and normals (or None) of a cloud store."""
    with open_store(path) as ds:
        points = np.column_stack([ds[c].values for c in "xyz"]).astype(float)
        normals = np.column_stack([ds[c].values for c in ("nx", "ny", "nz")]).astype(float) if "nx" in ds \
            else None
        return points, normals


def cloud_store_from_file(source, out, min_extent_mm: float = 0.0, attrs: dict | None = None) -> Path:
    """Read and check a cloud file and write it as a run's cloud store."""
    cloud = read_scanner_cloud(source, min_extent_mm)
    return write_cloud_store(out, cloud.points, cloud.normals, attrs)


def load_points(path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points and normals of a cloud file (``.ply``, ``.e57``) or of a run's cloud store."""
    path = Path(path)
    if path.suffix.lower() in CLOUD_SUFFIXES:
        cloud = read_scanner_cloud(path)
        return cloud.points, cloud.normals
    return read_cloud_store(path)
