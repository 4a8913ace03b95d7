"""Scanners as OpenCV ``FileStorage`` YAML in the layout of ``cv2.stereoCalibrate``.

One file per scanner, ``<scanner>.yml``, readable with ``cv2.FileStorage(path,
cv2.FILE_STORAGE_READ)``; the camera is OpenCV's first camera, the projector (an
inverse camera over its SLM's pixel grid) the second::

    imageSize1, imageSize2            (width, height) in pixels
    cameraMatrix1, distCoeffs1        camera: K (3x3), (k1, k2, p1, p2, k3) (1x5; 1x12 with thin-prism terms;
                                      1x14, fitted, with a correction field)
    cameraMatrix2, distCoeffs2        projector
    R, T                              x_prj = R x_cam + T (3x3, 3x1; mm), as cv2.stereoCalibrate
    E, F                              essential and fundamental matrix of (R, T)
    cameraRotationWorld               x_cam = cameraRotationWorld X + cameraTranslationWorld
    cameraTranslationWorld            for X in the world of the exported calibration
    projectorRotationWorld, projectorTranslationWorld
    scanner, cameraName, projectorName            fringecal's names
    sensorSizeMm1, sensorSizeMm2                  fringecal's formats in mm (OpenCV has none)
    projectorAnglesInCamera           (omega, phi, kappa) of the projector in the camera's
                                      fringecal frame: only picks the Euler-angle branch
    maxDiffPx1, rmsDiffPx1, maxDiffPx2, rmsDiffPx2   measured model difference (pixels)
    modelFit1, fitTolerancePx1, ...    only for a sensor with a correction field, whose OpenCV
                                      model is fitted (:func:`fringecal.interop.opencv.to_opencv`):
                                      "fits" (worst difference at most fitTolerancePx) or
                                      "approximates"; a comment at the top says the same in words
    observedHullPx1, observedHullPx2  only where the calibration knows it: the sensor's observed
                                      region (:mod:`fringecal.lens.observed_region`), the convex
                                      hull of the control points the calibration used (outside it
                                      the model extrapolates), m x 2 vertices (u, v) in that
                                      sensor's OpenCV pixels (0 x 2: nothing observed); a comment
                                      at the top says so
    observedFraction1, observedFraction2   the share of the format inside that hull
    observedCellCounts1, observedCellCounts2   with the hull: the control points per cell of the
                                      region's grid over the format (ny x nx; row 0 at the most
                                      negative image-plane y, column 0 at the most negative x)
    observedMinPoints1, observedMinPoints2     the points a cell needs to count as observed

A scanner whose sensors have no correction field and no observed region is written
exactly as before those existed (no extra key, no extra comment). The hull's vertices
are exact in pixels: a camera's hull was measured in its pixels, a projector's in its
phases, which map to its SLM's pixels linearly (:func:`fringecal.interop.opencv.points_px`);
:meth:`StereoFile.hull_mm` turns them back into image-plane mm and :meth:`StereoFile.region`
into the sensor's :class:`~fringecal.lens.observed_region.ObservedRegion` (``fringecal
import opencv`` keeps it).

Frames and pixel conventions: :mod:`fringecal.interop.opencv`.

Reading (:func:`read_stereo`) needs only the six keys of ``cv2.stereoCalibrate``'s
output: ``cameraMatrix1``, ``distCoeffs1``, ``cameraMatrix2``, ``distCoeffs2``, ``R``,
``T`` (``M1, D1, M2, D2`` of OpenCV's stereo sample are accepted too); the others are
optional. :func:`prior_scanner` turns it into a scanner's prior calibration in its own
frame, as a data set's ``sensors_prior.csv`` holds it (:mod:`fringecal.simulate.prior`):
the camera at the origin with angles exactly zero, i.e. the scanner's frame is OpenCV's
first camera frame turned by pi about the optical axis.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from fringecal.atomic import write_text
from fringecal.frames import Frame
from fringecal.interop.opencv import (
    DEPTHS_MM,
    FIT_TOLERANCE_PX,
    GRID,
    F,
    ImportedSensor,
    OpenCVCamera,
    from_opencv,
    points_mm,
    points_px,
    to_opencv,
)
from fringecal.lens.observed_region import MIN_POINTS_PER_CELL, ObservedRegion, grid_shape
from fringecal.names import check_name, confined
from fringecal.rig import Rig, Scanner
from fringecal.sensor import SensorFormat, sensor_in_frame

__all__ = [
    "REQUIRED_KEYS",
    "THESIS_WIDTH_MM",
    "OpenCVFileError",
    "StereoFile",
    "prior_scanner",
    "read_stereo",
    "stereo_text",
    "write_rig",
]

#: the thesis's format widths (section 6.9.1), the default when a file gives none
THESIS_WIDTH_MM = {"camera": 15.1, "projector": 19.0}
#: key -> accepted aliases, in the order they are looked up
REQUIRED_KEYS = {"cameraMatrix1": ("cameraMatrix1", "M1"), "distCoeffs1": ("distCoeffs1", "D1"),
                 "cameraMatrix2": ("cameraMatrix2", "M2"), "distCoeffs2": ("distCoeffs2", "D2"),
                 "R": ("R",), "T": ("T",)}


class OpenCVFileError(ValueError):
    """An OpenCV file that cannot be read or used; the message names the file and key."""


@dataclass(frozen=True)
class StereoFile:
    """The contents of one stereo calibration file (pixels and mm; see the module notes).

    ``K1, K2`` (3, 3); ``D1, D2`` (4,) .. (14,); ``R`` (3, 3); ``T`` (3,). Optional
    entries are None when the file lacks them.
    """

    path: Path
    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray
    T: np.ndarray
    size1: tuple[int, int] | None = None
    size2: tuple[int, int] | None = None
    size_mm1: tuple[float, float] | None = None
    size_mm2: tuple[float, float] | None = None
    scanner: str | None = None
    camera_name: str | None = None
    projector_name: str | None = None
    projector_angles: np.ndarray | None = None
    hull_px1: np.ndarray | None = None  # the observed region's hull (m, 2), OpenCV pixels
    hull_px2: np.ndarray | None = None
    counts1: np.ndarray | None = None  # the observed region's grid counts (ny, nx)
    counts2: np.ndarray | None = None
    min_points1: int | None = None  # points a cell needs to count as observed
    min_points2: int | None = None

    def hull_mm(self, i: int) -> np.ndarray | None:
        """The observed region's hull (m, 2) of sensor ``i`` (1 camera, 2 projector) in
        image-plane mm, as ``calibration.json`` holds it; None when the file has no hull
        or not the image size and format in mm it needs."""
        px, size, mm = getattr(self, f"hull_px{i}"), getattr(self, f"size{i}"), getattr(self, f"size_mm{i}")
        if px is None or size is None or mm is None:
            return None
        return points_mm("camera" if i == 1 else "projector", SensorFormat(size[0], size[1], *mm), px)

    def region(self, i: int) -> ObservedRegion | None:
        """The observed region of sensor ``i`` (1 camera, 2 projector): the hull in
        image-plane mm (:meth:`hull_mm`) with the grid's counts and threshold; a file
        with a hull but no counts gives a grid of zeros (only the hull is known). None
        when the file has no hull (or not the sizes it needs).

        Raises
        ------
        OpenCVFileError
            A hull or grid that is no region of the sensor's format, naming the file and key.
        """
        hull = self.hull_mm(i)
        if hull is None:
            return None
        w, h = getattr(self, f"size_mm{i}")
        counts = getattr(self, f"counts{i}")
        counts = np.zeros(grid_shape(w, h)) if counts is None else counts
        threshold = getattr(self, f"min_points{i}") or MIN_POINTS_PER_CELL
        try:
            return ObservedRegion(w, h, counts, hull, threshold)
        except ValueError as err:
            raise OpenCVFileError(f"{self.path}: key 'observedHullPx{i}' (with observedCellCounts{i}): not an observed "
                                  f"region of the {w} x {h} mm format ({err})") from None


def stereo_text(scanner: Scanner, grid: int = GRID, depths=DEPTHS_MM,
                regions: dict | None = None) -> tuple[str, OpenCVCamera, OpenCVCamera]:
    """The YAML document of ``scanner`` and its two verified OpenCV models; ``regions``
    (sensor name -> :class:`~fringecal.lens.observed_region.ObservedRegion`) adds each
    sensor's observed region it names, its hull in pixels."""
    cam, prj = to_opencv(scanner.camera, grid, depths), to_opencv(scanner.projector, grid, depths)
    R = prj.R @ cam.R.T
    T = prj.t - R @ cam.t
    tx = np.array([[0, -T[2], T[1]], [T[2], 0, -T[0]], [-T[1], T[0], 0]])
    E = tx @ R
    Fm = np.linalg.inv(prj.K).T @ E @ np.linalg.inv(cam.K)
    T_camera_world = Frame.from_matrix(scanner.camera.R, scanner.camera.pinhole).inverse()
    angles = sensor_in_frame(scanner.projector, T_camera_world).angles
    fs = cv2.FileStorage("scanner.yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML)
    fs.writeComment(f"fringecal scanner {scanner.name!r}: camera = 1, projector = 2 (inverse camera over its SLM "
                    "pixels); x_prj = R x_cam + T (mm), as cv2.stereoCalibrate")
    for i, m in ((1, cam), (2, prj)):
        if m.fitted:  # a correction field: the model is fitted, and the file says how well
            fs.writeComment(f"{m.role} (distCoeffs{i}, cameraMatrix{i}): {m.statement}")
    observed = [(i, s, regions[s.name]) for i, s in ((1, scanner.camera), (2, scanner.projector))
                if s.name in (regions or {})]
    if observed:
        fs.writeComment("observedHullPx1/2: the region of the camera's (1) and the projector's (2) image the "
                        "calibration observed, the convex hull of its control points (outside it the model "
                        "extrapolates); vertices (u, v) in PIXELS of that sensor (the projector's over its SLM), "
                        "pixel centres at integers; observedFraction1/2: the share of the format inside it")
    fs.write("scanner", scanner.name)
    fs.write("cameraName", cam.name)
    fs.write("projectorName", prj.name)
    for i, m in ((1, cam), (2, prj)):
        _write_seq(fs, f"imageSize{i}", m.image_size)
        fs.write(f"cameraMatrix{i}", m.K)
        fs.write(f"distCoeffs{i}", m.dist.reshape(1, -1))  # 5, 12 with thin-prism terms, 14 fitted to a field
    fs.write("R", R)
    fs.write("T", T.reshape(3, 1))
    fs.write("E", E)
    fs.write("F", Fm)
    for role, m in (("camera", cam), ("projector", prj)):
        fs.write(f"{role}RotationWorld", m.R)
        fs.write(f"{role}TranslationWorld", m.t.reshape(3, 1))
    for i, m in ((1, cam), (2, prj)):
        _write_seq(fs, f"sensorSizeMm{i}", m.size_mm)
    _write_seq(fs, "projectorAnglesInCamera", angles)
    for i, m in ((1, cam), (2, prj)):
        fs.write(f"maxDiffPx{i}", m.worst_px)
        fs.write(f"rmsDiffPx{i}", m.rms_px)
    for i, m in ((1, cam), (2, prj)):
        if m.fitted:
            fs.write(f"modelFit{i}", m.verdict)
            fs.write(f"fitTolerancePx{i}", FIT_TOLERANCE_PX)
    for i, sensor, region in observed:
        fs.write(f"observedHullPx{i}", points_px(sensor.role, sensor.format, region.hull))
        fs.write(f"observedFraction{i}", region.fraction)
        fs.write(f"observedCellCounts{i}", region.counts.astype(np.int32))
        fs.write(f"observedMinPoints{i}", int(region.min_points))
    return fs.releaseAndGetString(), cam, prj


def write_rig(rig: Rig, out_dir, grid: int = GRID, depths=DEPTHS_MM,
              regions: dict | None = None) -> dict[str, tuple[Path, OpenCVCamera, OpenCVCamera]]:
    """Write ``<out_dir>/<scanner>.yml`` for every scanner (all converted before any is
    written), with the observed regions of ``regions`` (sensor name -> region).

    Returns
    -------
    dict scanner -> (path, camera model, projector model)
    """
    out_dir = Path(out_dir)
    docs = {s.name: stereo_text(s, grid, depths, regions) for s in rig.scanners}
    paths = {name: confined(out_dir, f"{check_name(name, 'scanner')}.yml") for name in docs}  # all before any write
    out_dir.mkdir(parents=True, exist_ok=True)
    return {name: (write_text(paths[name], text), cam, prj) for name, (text, cam, prj) in docs.items()}


def read_stereo(path) -> StereoFile:
    """Read a stereo calibration written by ``cv2.FileStorage`` (YAML, XML or JSON).

    Raises
    ------
    OpenCVFileError
        Unreadable file, a missing required key, or a value of the wrong shape or type;
        the message names the file and the key.
    """
    path = Path(path)
    if not path.is_file():
        raise OpenCVFileError(f"{path}: no such file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as err:
        raise OpenCVFileError(f"{path}: not a readable OpenCV FileStorage file ({_cv_message(err)})") from None
    if not fs.isOpened():
        raise OpenCVFileError(f"{path}: not a readable OpenCV FileStorage file")
    try:
        req = {key: _matrix(fs, path, key, aliases) for key, aliases in REQUIRED_KEYS.items()}
        for key, shape in (("cameraMatrix1", (3, 3)), ("cameraMatrix2", (3, 3)), ("R", (3, 3))):
            if req[key].shape != shape:
                raise OpenCVFileError(f"{path}: key {key!r} must be a 3x3 matrix, found {_shape(req[key])}")
        for key in ("distCoeffs1", "distCoeffs2"):
            if 1 not in req[key].shape or req[key].size not in (4, 5, 8, 12, 14):
                raise OpenCVFileError(f"{path}: key {key!r} must be a row or column of 4, 5, 8, 12 or 14 "
                                      f"coefficients, found {_shape(req[key])}")
        if req["T"].size != 3:
            raise OpenCVFileError(f"{path}: key 'T' must be 3 values (3x1), found {_shape(req['T'])}")
        sizes = [_numbers(fs, path, f"imageSize{i}", 2) for i in (1, 2)]
        mms = [_numbers(fs, path, f"sensorSizeMm{i}", 2) for i in (1, 2)]
        angles = _numbers(fs, path, "projectorAnglesInCamera", 3)
        for i, s in enumerate(sizes, 1):
            if s is not None and (np.any(s != np.round(s)) or np.any(s < 2)):
                raise OpenCVFileError(f"{path}: key 'imageSize{i}' must be two whole numbers >= 2, found {s.tolist()}")
        for i, s in enumerate(mms, 1):
            if s is not None and not np.all(s > 0):
                raise OpenCVFileError(f"{path}: key 'sensorSizeMm{i}' must be two positive numbers, found {s.tolist()}")
        names = [_string(fs, path, k) for k in ("scanner", "cameraName", "projectorName")]
        hulls = [_hull(fs, path, f"observedHullPx{i}") for i in (1, 2)]
        counts = [_counts(fs, path, f"observedCellCounts{i}") for i in (1, 2)]
        thresholds = [_whole(fs, path, f"observedMinPoints{i}") for i in (1, 2)]
    finally:
        fs.release()
    return StereoFile(path, req["cameraMatrix1"], req["distCoeffs1"].ravel(), req["cameraMatrix2"],
                      req["distCoeffs2"].ravel(), req["R"], req["T"].ravel(),
                      *(None if s is None else (int(s[0]), int(s[1])) for s in sizes),
                      *(None if s is None else (float(s[0]), float(s[1])) for s in mms),
                      *names, angles, *hulls, *counts, *thresholds)


def prior_scanner(st: StereoFile, name: str, camera_name: str, projector_name: str, *,
                  camera_size: tuple[int, int] | None = None, projector_size: tuple[int, int] | None = None,
                  camera_width_mm: float | None = None, projector_width_mm: float | None = None,
                  grid: int = GRID, depths=DEPTHS_MM) -> tuple[Scanner, ImportedSensor, ImportedSensor]:
    """One scanner's prior calibration in its own frame from a stereo file.

    Image sizes and format widths come from the file when it has them, else from the
    arguments; widths default to :data:`THESIS_WIDTH_MM`. The camera sits at the origin
    with angles zero (OpenCV pose ``R = F``, ``t = 0``), the projector at OpenCV pose
    ``(R F, T)``; its Euler angles take the branch of ``projectorAnglesInCamera`` when
    the file has it (the convention of :func:`fringecal.sensor.sensor_in_frame`), else
    phi in [-pi/2, pi/2].

    Returns
    -------
    scanner, camera, projector : the Scanner and each sensor's :class:`ImportedSensor`
    """
    out = []
    for i, role, sensor_name, size, width in ((1, "camera", camera_name, camera_size, camera_width_mm),
                                               (2, "projector", projector_name, projector_size, projector_width_mm)):
        size = getattr(st, f"size{i}") or size
        if size is None:
            raise OpenCVFileError(f"{st.path}: no key 'imageSize{i}' (the {role}'s width, height in pixels) and no "
                                  f"{role} size given")
        mm = getattr(st, f"size_mm{i}")
        fmt = SensorFormat(size[0], size[1], *mm) if mm is not None else None
        width = (mm[0] if mm is not None else width) or THESIS_WIDTH_MM[role]
        K, D = getattr(st, f"K{i}"), getattr(st, f"D{i}")
        R, t = (F, np.zeros(3)) if role == "camera" else (st.R @ F, st.T)
        near = np.zeros(3) if role == "camera" else st.projector_angles
        try:
            imp = from_opencv(K, D, R, t, size, name=sensor_name, role=role, width_mm=width, fmt=fmt, near=near,
                              grid=grid, depths=depths)
        except ValueError as err:
            keys = f"cameraMatrix{i}, distCoeffs{i}" + (", R, T" if role == "projector" else "")
            raise OpenCVFileError(f"{st.path}: the {role} ({keys}): {err}") from None
        if role == "camera":  # exactly the origin, as a stereo calibration defines it
            p = imp.sensor.params.copy()
            p[:6] = 0.0
            imp = ImportedSensor(imp.sensor.with_params(p), imp.worst_px, imp.rms_px, imp.fitted)
        out.append(imp)
    return Scanner(name, out[0].sensor, out[1].sensor), out[0], out[1]


# -- FileStorage helpers ---------------------------------------------------------------

def _write_seq(fs, key: str, values) -> None:
    fs.startWriteStruct(key, cv2.FileNode_SEQ | cv2.FileNode_FLOW)
    for v in values:
        fs.write("", v.item() if hasattr(v, "item") else v)
    fs.endWriteStruct()


def _cv_message(err: BaseException) -> str:
    err = err.__cause__ or err
    text = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
    return text.split(") ", 1)[-1] if text.startswith("OpenCV(") else text


def _shape(m: np.ndarray) -> str:
    return "x".join(map(str, m.shape)) if m.ndim else "a scalar"


def _matrix(fs, path: Path, key: str, aliases) -> np.ndarray:
    for k in aliases:
        node = fs.getNode(k)
        if not node.empty() and not node.isNone():
            break
    else:
        also = f" (or {', '.join(repr(a) for a in aliases[1:])})" if len(aliases) > 1 else ""
        raise OpenCVFileError(f"{path}: missing key {key!r}{also}; a stereo calibration needs "
                              f"{', '.join(REQUIRED_KEYS)}")
    m = _map_matrix(node) if node.isMap() else _seq_values(node)
    if m is None or not isinstance(m, np.ndarray) or m.size == 0:
        raise OpenCVFileError(f"{path}: key {k!r} is not a matrix (!!opencv-matrix or a list of numbers)")
    m = np.asarray(m, float)
    if m.ndim == 1:
        m = m.reshape(-1, 1) if key == "T" else m.reshape(1, -1) if m.size != 9 else m.reshape(3, 3)
    if not np.all(np.isfinite(m)):
        raise OpenCVFileError(f"{path}: key {k!r} has non-finite values")
    return m


def _map_matrix(node) -> np.ndarray | None:
    """An ``!!opencv-matrix`` node's array; None for any other mapping."""
    try:
        return node.mat()
    except (cv2.error, SystemError):
        return None


def _seq_values(node) -> np.ndarray | None:
    if not node.isSeq():
        return None
    vals = []
    for i in range(node.size()):
        v = node.at(i)
        if v.isSeq():
            row = _seq_values(v)
            if row is None:
                return None
            vals.append(row)
        elif v.isReal() or v.isInt():
            vals.append(v.real())
        else:
            return None
    try:
        return np.array(vals, float)
    except ValueError:
        return None


def _numbers(fs, path: Path, key: str, n: int) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    v = _map_matrix(node) if node.isMap() else _seq_values(node)
    if not isinstance(v, np.ndarray) or v.size != n or not np.all(np.isfinite(v)):
        raise OpenCVFileError(f"{path}: key {key!r} must be a list of {n} numbers")
    return np.asarray(v, float).ravel()


def _hull(fs, path: Path, key: str) -> np.ndarray | None:
    """An observed region's hull: m x 2 vertices (m >= 3, or 0: nothing observed); None
    when the file has none."""
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    if node.isMap() and node.getNode("rows").real() == 0:  # a 0 x 2 matrix reads as no matrix
        return np.zeros((0, 2))
    m = _map_matrix(node) if node.isMap() else _seq_values(node)
    if not isinstance(m, np.ndarray) or m.ndim != 2 or m.shape[1] != 2 or len(m) < 3 or not np.all(np.isfinite(m)):
        raise OpenCVFileError(f"{path}: key {key!r} must be an m x 2 matrix of vertices (u, v), m >= 3 or 0")
    return np.asarray(m, float)


def _whole(fs, path: Path, key: str) -> int | None:
    """A whole number >= 1; None when the file has none."""
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    v = node.real() if node.isInt() or node.isReal() else float("nan")
    if not (v >= 1 and v == round(v)):
        raise OpenCVFileError(f"{path}: key {key!r} must be a whole number >= 1")
    return int(v)


def _counts(fs, path: Path, key: str) -> np.ndarray | None:
    """An observed region's grid counts: ny x nx whole numbers >= 0; None when the file has none."""
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    m = _map_matrix(node) if node.isMap() else _seq_values(node)
    if not isinstance(m, np.ndarray) or m.ndim != 2 or not m.size or not np.all(np.isfinite(m)) \
            or np.any(m < 0) or np.any(m != np.round(m)):
        raise OpenCVFileError(f"{path}: key {key!r} must be an ny x nx matrix of whole numbers >= 0")
    return np.asarray(m, np.int64)


def _string(fs, path: Path, key: str) -> str | None:
    node = fs.getNode(key)
    if node.empty() or node.isNone():
        return None
    if not node.isString():
        raise OpenCVFileError(f"{path}: key {key!r} must be a text")
    return node.string()
