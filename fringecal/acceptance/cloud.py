"""The acceptance test's objects measured in a black-box scanner's clouds (VDI/VDE 2634
part 2 on a scanner known only by its points).

A black box delivers its points in its own frame and no sensors, so its objects are
found and fitted in the cloud with the code that finds the artefact's spheres in it,
and carried into the world by its calibrated transform and scale
(:func:`fringecal.calibration.blackbox.transform_points`,
``x_world = R^T (k c) + t``):

- **Sphere (P_F, P_S)**: the sphere of the standard's diameter located by normal voting
  and the robust free-radius fit (:func:`fringecal.spheres.cloud_spheres.cloud_sphere_fits`,
  the run's rejection settings; the candidate with the most points); its points are
  every point within ``segment_mm`` of that sphere that the scanner sees at an
  incidence of at most ``max_incidence_deg`` from its line of sight (from the origin
  of its frame, where :mod:`fringecal.spheres.cloud_spheres` places the scanner).
  They are carried into the world and measured by
  :func:`fringecal.acceptance.measure.probe_sphere` as a modelled scanner's: P_F from
  the orthogonal fit's residual range, P_S from the fit along the lines of sight from
  the scanner's origin. The points cannot be corrected for pixel integration (no
  sensors): a fringe black box's P_S keeps that bias.
- **Flat (F)**: the largest plane of the cloud (RANSAC with ``segment_mm`` inlier
  distance, seeded, as for a store); of its inliers the largest patch connected on a
  grid in the plane (cells of 2.5 times the points' median spacing, the pixel
  neighbourhood a cloud lacks); a patch spanning more than 1.2 flat diagonals is a
  backdrop and is set aside for the next plane; the patch's border cells, two deep
  (the rim, where a side face joins and the points bend away), and points seen at more than ``max_incidence_deg`` are left
  out; :func:`fringecal.acceptance.measure.probe_flat` in the world.
- **Dumbbell (SD)**: measured as the ball-bar is measured in clouds
  (:func:`fringecal.verification.black_box.verify_with_black_boxes`: candidates, a
  candidate fitting ``ROUGH_FIT_RATIO`` times worse than the cloud's best set aside, the
  certified radius refitted with the rod masked and the rim left out), its length's
  uncertainty first order through the black boxes' joint covariance (for one scanner:
  its scale), each sphere fit's covariance with the scanner's measured scatter between
  spheres, and the dumbbell's certificate.

P_F and F do not depend on the transform (a rigid motion keeps every residual; the
scale, 1 within a few 1e-4, multiplies the ranges by as much); P_S and SD scale with
it, so their U holds the scale's standard uncertainty from the transform's covariance
(``u(k) d / k`` of a diameter; the length's through the joint covariance). A depth is
along the z axis of the scanner's own frame (a camera's axis: the frame the
specification's depths are measured in).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from fringecal.acceptance.evaluate import form_u
from fringecal.acceptance.measure import (
    BACKDROP_FACTOR,
    SEGMENT_MM,
    AcceptanceMeasurementError,
    FlatMeasurement,
    SphereMeasurement,
    largest_plane,
    probe_flat,
    probe_sphere,
)
from fringecal.acceptance.standards import AcceptanceStandards, FlatStandard, SphereStandard
from fringecal.calibration.blackbox import BlackBoxScanner, scanners_from_document, transform_points
from fringecal.scancloud import load_points
from fringecal.spheres.cloud_spheres import cloud_sphere_fits
from fringecal.spheres.fit import FitError, PlaneModel
from fringecal.spheres.robust import RejectionConfig
from fringecal.verification.black_box import verify_with_black_boxes
from fringecal.verification.settings import VerificationConfig

__all__ = [
    "GRID_SPACINGS",
    "RIM_CELLS",
    "cloud_acceptance_values",
    "local_depths",
    "measure_cloud_flat",
    "measure_cloud_sphere",
    "scale_u",
]

#: Grid cell of a flat's patch, in median point spacings: coarse enough that a patch of
#: points is one connected region, fine enough that its border is the flat's rim.
GRID_SPACINGS = 2.5
#: Border cells of a flat's patch left out (about 5 point spacings: a store leaves out its
#: edge pixels and 2 more, where the face meets a side face and the points bend away).
RIM_CELLS = 2


def scale_u(box: BlackBoxScanner) -> float:
    """Relative standard uncertainty of ``box``'s scale (0 when the scale was fixed)."""
    return float(np.sqrt(max(box.covariance[6, 6], 0.0))) / box.scale


def local_depths(box: BlackBoxScanner, world) -> np.ndarray:
    """Depths (mm) of world points (n, 3) along the z axis of ``box``'s own frame."""
    local = (np.atleast_2d(np.asarray(world, float)) - box.params[:3]) @ box.frame.R.T / box.scale
    return local[:, 2]


def _seen(points: np.ndarray, normals: np.ndarray, max_incidence_deg: float) -> np.ndarray:
    """Whether the scanner at the origin sees each point (n, 3) with its unit normal at
    an incidence of at most ``max_incidence_deg``."""
    sight = points / np.linalg.norm(points, axis=1, keepdims=True)
    return np.abs(np.einsum("ij,ij->i", normals, sight)) >= np.cos(np.radians(max_incidence_deg))


def measure_cloud_sphere(points, box: BlackBoxScanner, standard: SphereStandard, exclude_fraction: float = 0.003,
                         max_incidence_deg: float = 70.0, rejection: RejectionConfig | None = None,
                         segment_mm: float = SEGMENT_MM, name: str = "cloud") -> tuple[SphereMeasurement, float]:
    """P_F and P_S of the sphere in a black box's cloud ``points`` (n, 3; its frame),
    in the world, and its centre's depth in the scanner's frame.

    Raises
    ------
    AcceptanceMeasurementError
        No sphere of the standard's diameter in the cloud (``name`` starts the message).
    """
    p = np.asarray(points, float)
    radius = standard.diameter_mm / 2
    fits, failures = cloud_sphere_fits(p, "", box.name, radius, rejection=rejection)
    if not len(fits):
        why = "; ".join(failures["reason"].head(3)) or "no candidate"
        raise AcceptanceMeasurementError(f"{name}: no sphere of diameter {standard.diameter_mm:g} mm found ({why})")
    best = fits.loc[fits["n_points"].idxmax()]
    centre, r = best[["x_mm", "y_mm", "z_mm"]].to_numpy(float), float(best["radius_mm"])
    near = p[np.abs(np.linalg.norm(p - centre, axis=1) - r) <= segment_mm]
    normals = (near - centre) / np.linalg.norm(near - centre, axis=1, keepdims=True)
    near = near[_seen(near, normals, max_incidence_deg)]
    try:
        m = probe_sphere(transform_points(box, near), standard, exclude_fraction, origin=box.params[:3])
    except (FitError, AcceptanceMeasurementError) as err:
        raise AcceptanceMeasurementError(f"{name}: sphere: {err}") from None
    return m, float(centre[2])


def _spacing(p: np.ndarray, sample: int = 2000) -> float:
    """Median distance (mm) of a point of ``p`` to its nearest neighbour."""
    q = p[np.random.default_rng(0).choice(len(p), min(sample, len(p)), replace=False)]
    d, _ = cKDTree(p).query(q, k=2)
    return float(np.median(d[:, 1]))


def _patch(p: np.ndarray, plane: PlaneModel) -> tuple[np.ndarray, np.ndarray, float]:
    """The largest grid-connected patch of plane points ``p`` (n, 3): its mask (n,), the
    mask of its points off the patch's border cells, and its diagonal (mm)."""
    st = (p - plane.point) @ plane.axes.T
    cell = GRID_SPACINGS * _spacing(p)
    ij = np.floor((st - st.min(axis=0)) / cell).astype(int)
    grid = np.zeros(ij.max(axis=0) + 1, bool)
    grid[ij[:, 0], ij[:, 1]] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3), bool))
    sizes = np.bincount(labels[ij[:, 0], ij[:, 1]], minlength=count + 1)
    sizes[0] = 0
    region = labels == int(np.argmax(sizes))
    inside = ndimage.binary_erosion(region, np.ones((3, 3), bool), iterations=RIM_CELLS)
    member = region[ij[:, 0], ij[:, 1]]
    span = st[member].max(axis=0) - st[member].min(axis=0)
    return member, inside[ij[:, 0], ij[:, 1]], float(np.linalg.norm(span))


def measure_cloud_flat(points, box: BlackBoxScanner, standard: FlatStandard, exclude_fraction: float = 0.003,
                       max_incidence_deg: float = 70.0, segment_mm: float = SEGMENT_MM, seed: int = 0,
                       max_planes: int = 3, name: str = "cloud") -> tuple[FlatMeasurement, float]:
    """F of the flat in a black box's cloud ``points`` (n, 3; its frame), in the world,
    and the depth of the flat's centroid in the scanner's frame.

    Raises
    ------
    AcceptanceMeasurementError
        No plane patch of the flat's size in the cloud (``name`` starts the message).
    """
    p = np.asarray(points, float)
    rng = np.random.default_rng(seed)
    diagonal = float(np.hypot(standard.length_mm, standard.width_mm))
    candidates = np.ones(len(p), bool)
    for _ in range(max_planes):
        idx = np.flatnonzero(candidates)
        if len(idx) < 10:
            break
        inl = largest_plane(p[idx], rng, segment_mm)
        if inl is None:
            break
        on = p[idx[inl]]
        if len(on) < 10:
            break
        plane = PlaneModel.from_estimate(on, toward=np.zeros(3))
        member, inside, span = _patch(on, plane)
        if span > BACKDROP_FACTOR * diagonal:
            candidates[idx[inl][member]] = False
            continue
        q = on[member & inside]
        q = q[_seen(q, np.broadcast_to(plane.normal, q.shape), max_incidence_deg)]
        try:
            m = probe_flat(transform_points(box, q), exclude_fraction, toward=box.params[:3])
        except (FitError, AcceptanceMeasurementError) as err:
            raise AcceptanceMeasurementError(f"{name}: flat: {err}") from None
        return m, float(q[:, 2].mean())
    raise AcceptanceMeasurementError(f"{name}: no plane patch of the flat's size ({standard.length_mm:g} x "
                                     f"{standard.width_mm:g} mm) found")


def _object_rows(kind: str, position: str, scanner: str, path: str, box: BlackBoxScanner,
                 standards: AcceptanceStandards, config, rejection: RejectionConfig) -> list[dict]:
    k = config.coverage_factor
    points, _ = load_points(path)
    if kind == "sphere":
        s = standards.sphere
        m, depth = measure_cloud_sphere(points, box, s, config.exclude_fraction, config.max_incidence_deg,
                                        rejection, name=str(path))
        u_size = np.sqrt(s.diameter_u_mm**2 + m.diameter_u_fit_mm**2 + (m.diameter_mm * scale_u(box))**2)
        common = {"test": kind, "position": position, "scanner": scanner, "n_points": m.n_points,
                  "n_excluded": m.n_excluded, "depth_mm": depth}
        return [{**common, "parameter": "P_F", "value_mm": m.form_mm, "U_mm": k * form_u(s.form_mm)},
                {**common, "parameter": "P_S", "value_mm": m.size_mm, "U_mm": k * float(u_size)}]
    f = standards.flat
    m, depth = measure_cloud_flat(points, box, f, config.exclude_fraction, config.max_incidence_deg, name=str(path))
    return [{"test": kind, "parameter": "F", "position": position, "scanner": scanner, "value_mm": m.flatness_mm,
             "U_mm": k * float(np.hypot(form_u(f.flatness_mm), f.flatness_u_mm)), "n_points": m.n_points,
             "n_excluded": m.n_excluded, "depth_mm": depth}]


def _dumbbell_rows(stores: dict, boxes_doc: dict, boxes: dict, standards: AcceptanceStandards, config,
                   rejection: dict) -> tuple[list[dict], list[dict]]:
    bell = standards.dumbbell
    settings = VerificationConfig(mpe_mm=config.limits.SD or 1.0, certificate_u_mm=2 * bell.length_u_mm,
                                  certificate_k=2.0, coverage_factor=config.coverage_factor)
    centres, fails, _, budget = verify_with_black_boxes(stores, None, boxes_doc, bell.artefact(), rejection,
                                                        settings, bell.length_mm, config.max_incidence_deg)
    measured = {e["measurement"].split(":")[0] for e in budget["lengths"]}
    # a candidate set aside at a position that gave its length (the rod, a vote elsewhere) is no failure
    failures = [{"test": "dumbbell", "position": f.position, "scanner": f.scanner or "", "reason": f.reason}
                for f in fails.itertuples() if f.position not in measured]
    rows = []
    for e in budget["lengths"]:
        scanner = e["scanner_a"] if e["scanner_a"] == e["scanner_b"] else f"{e['scanner_a']}/{e['scanner_b']}"
        position = e["measurement"].split(":")[0]
        ends = centres[centres["position"].astype(str) == position]
        z = local_depths(boxes[e["scanner_a"]], ends[["x_mm", "y_mm", "z_mm"]].to_numpy(float))
        rows.append({"test": "dumbbell", "parameter": "SD", "position": e["measurement"], "scanner": scanner,
                     "value_mm": float(e["error_mm"]), "U_mm": float(e["U_mm"]), "n_points": 0, "n_excluded": 0,
                     "depth_near_mm": float(z.min()), "depth_mm": float(z.max())})
    return rows, failures


def cloud_acceptance_values(stores: dict, boxes_doc: dict, standards: AcceptanceStandards, config,
                            rejection: dict) -> tuple[list[dict], list[dict]]:
    """Value rows (:data:`fringecal.acceptance.evaluate.VALUE_COLUMNS` and depths) and
    failures (test, position, scanner, reason) of the black boxes' acceptance clouds.

    Parameters
    ----------
    stores : kind -> position -> scanner -> cloud store or file, of black-box scanners only
    boxes_doc : ``black_boxes.json`` (the transforms, their covariance, ``joint_covariance``)
    standards, config : the certificates and the ``acceptance`` settings
    rejection : the run's ``extraction.rejection`` settings
    """
    boxes = scanners_from_document(boxes_doc)
    rej = RejectionConfig(**rejection)
    rows, failures = [], []
    for kind in ("sphere", "flat"):
        if getattr(standards, kind) is None:
            continue
        for position, by_scanner in stores.get(kind, {}).items():
            for scanner, path in by_scanner.items():
                try:
                    rows += _object_rows(kind, position, scanner, path, boxes[scanner], standards, config, rej)
                except AcceptanceMeasurementError as err:
                    failures.append({"test": kind, "position": position, "scanner": scanner, "reason": str(err)})
    if standards.dumbbell is not None and stores.get("dumbbell"):
        r, f = _dumbbell_rows(stores["dumbbell"], boxes_doc, boxes, standards, config, rejection)
        rows += r
        failures += f
    return rows, failures
