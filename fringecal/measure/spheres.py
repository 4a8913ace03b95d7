"""Spheres measured in a cloud, with the uncertainty of their positions and distances.

What a user compares with a CMM is usually a set of sphere centres (a sphere plate, a
ball-bar, tooling balls on a part) and the distances between them. Given the cloud of
``fringecal measure``, the stores it was measured from and the nominal position and
radius of each sphere (``SEARCH_MM`` off at most), each sphere is fitted in every scanner
that sees it and stated two ways:

* its **position in the rig's frame** (:func:`~fringecal.calibration.propagation.frame_free_covariance`):
  ``u_position_mm``, the square root of the trace of the centre's 3 x 3 covariance,
  the calibration's part (the covariance given, through the fit's Jacobian) and the
  fit's own (sandwich estimate of its residuals);
* every **distance** between two fitted centres (:func:`sphere_distances`):
  ``u_mm``, the calibration's part through the gradient of the distance over every
  sensor parameter (both centres' Jacobians at once, so what the two share cancels:
  a common orientation of the scanners, the frame) and both fits' own along the line;
  with the replicas a calibration file carries, the bootstrap's bias subtracted and the
  jackknife's model error added, as for the ball-bar's lengths. (A position gets
  neither: a replica's frame is its own reference camera's, which the adjustment
  determines only weakly, so a position's spread over the replicas is mostly the frame's.)
  A distance's u is far smaller than the positions' (on the thesis rig, tens of um
  against a few tenths of a mm): per point, the position's u says nothing about it.

Each sighting is found and fitted as the ball-bar's are, in the whole store (every
decoded pixel, whatever the cloud kept): the sphere candidate of the certified radius
(:func:`~fringecal.spheres.candidates.find_sphere_candidates`, normal voting) nearest
the nominal centre, within the radius plus ``SEARCH_MM``, gives the pixels; those within
``EDGE_WIDTH_PX`` of the decoded region's edge are left out, the rest fitted robustly
with the radius fixed
(:func:`~fringecal.spheres.robust.fit_sphere_robust`: a RANSAC start, then points
seen or lit at grazing incidence, rods, mounts and residual outliers dropped), the kept points' phases
corrected for the pixel integration over the sphere
(:mod:`fringecal.spheres.pixel_integration`, as the control points are; the rim, whose
bias cannot be predicted, left out) and fitted again. A sphere seen only in part
(fewer than ``MIN_DISC_FRACTION`` of its image disc kept) is not measured by that
scanner.
The linearised fit is :func:`fringecal.verification.budget.sighting_model`, the one
the ball-bar's length budget uses.

Each sighting also states how many of its fitted points have a camera pixel or
projector phases outside the calibration's observed region
(:func:`~fringecal.measure.cloud.outside_observed_region`): where the model was never
tested, its stated u does not cover what the extrapolation may do.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.calibration.propagation import extended_indices, triangulate_mm
from fringecal.lens.observed_region import ObservedRegion
from fringecal.measure.cloud import Cloud, outside_observed_region
from fringecal.pointcloud import triangulate_maps
from fringecal.rig import Rig
from fringecal.spheres.candidates import find_sphere_candidates
from fringecal.spheres.fit import FitError, SphereModel
from fringecal.spheres.pixel_integration import phase_integration_bias
from fringecal.spheres.regions import boundary_flags
from fringecal.spheres.robust import RejectionConfig, fit_sphere_robust
from fringecal.verification.budget import (
    SightingModel,
    SightingPoints,
    bootstrap_bias,
    jackknife_model_error,
    field_gradient,
    length_gradient,
    sighting_model,
)
from fringecal.verification.ballbar import disc_pixels
from fringecal.verification.measure import store_scanner
from fringecal.verification.uncertainty import scaled_fit

__all__ = ["MeasuredSphere", "measure_spheres", "sphere_distances", "DISTANCE_COLUMNS", "read_nominal_spheres", "NOMINAL_COLUMNS", "SEARCH_MM", "EDGE_WIDTH_PX", "MIN_POINTS",
           "MIN_DISC_FRACTION"]

#: a sphere is looked for this far beyond its nominal surface: the candidate nearest the
#: nominal centre, within the radius plus this (mm)
SEARCH_MM = 15.0
#: a scanner's sighting of a sphere needs at least this many points
MIN_POINTS = 50
#: a sighting keeps at least this fraction of the sphere's image disc: a sphere seen only
#: in part (the image's edge, another object in front) gives a fit biased by what hides
#: it, which no uncertainty here describes (a whole sphere keeps 0.5-0.6 of its disc)
MIN_DISC_FRACTION = 0.1
#: outliers along a line from the centre that make a rod or a stem (masked by a cone,
#: as the ball-bar's rod is); the artefact's 30 leave a ball-bar's rod seen over fewer
#: pixels (320 px images) in the fit, whose junction points then pull it by 0.1-0.5 mm
MIN_ROD_POINTS = 10
#: pixels this close to the edge of the decoded region (px) are left out, as the control
#: points' and the ball-bar's fits leave them out: they mix the sphere with what lies
#: behind its silhouette, and their pixel-integration bias is not the sphere's alone
EDGE_WIDTH_PX = 2


#: columns of a table of nominal spheres (``fringecal measure --spheres``)
NOMINAL_COLUMNS = ("sphere_id", "x_mm", "y_mm", "z_mm", "radius_mm")


def read_nominal_spheres(path) -> pd.DataFrame:
    """The nominal spheres of a CSV file (:data:`NOMINAL_COLUMNS`; centres in the
    calibration's world within ``SEARCH_MM``, certified radii).

    Raises
    ------
    ValueError
        One message naming the file, and the column or row at fault.
    """
    try:
        table = pd.read_csv(path, dtype={"sphere_id": str})
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: not a readable CSV table ({err})") from None
    missing = [c for c in NOMINAL_COLUMNS if c not in table.columns]
    if missing:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)} (needs {', '.join(NOMINAL_COLUMNS)})")
    if table.empty:
        raise ValueError(f"{path}: no spheres")
    for col in NOMINAL_COLUMNS[1:]:
        values = pd.to_numeric(table[col], errors="coerce")
        bad = ~np.isfinite(values.to_numpy(float)) | ((values <= 0).to_numpy() if col == "radius_mm" else False)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            what = "a radius > 0 mm" if col == "radius_mm" else "a finite number"
            raise ValueError(f"{path}: row {row + 2}, column {col}: {table[col].iloc[row]!r} is not {what}")
        table[col] = values.astype(float)
    ids = table["sphere_id"].fillna("").astype(str).str.strip()
    if (ids == "").any():
        raise ValueError(f"{path}: row {int(np.flatnonzero(ids == '')[0]) + 2}, column sphere_id: empty")
    if ids.duplicated().any():
        raise ValueError(f"{path}: sphere_id {ids[ids.duplicated()].iloc[0]!r} is given twice")
    return table.assign(sphere_id=ids)[list(NOMINAL_COLUMNS)]


@dataclass(frozen=True)
class MeasuredSphere:
    """One sphere as one scanner measured it: ``centre`` (3,) mm, ``u_position_mm`` its
    3-D standard uncertainty in the frame of the covariance given, the points kept and
    their fraction of the sphere's image disc, ``model`` the linearised fit (for
    distances), ``n_outside`` how many of its points lie outside the calibration's
    observed region (None: the calibration records no region for its sensors)."""

    sphere: str
    scanner: str
    centre: np.ndarray
    u_position_mm: float
    n_points: int
    disc_fraction: float
    model: SightingModel
    n_outside: int | None = None

    def as_dict(self) -> dict:
        return {"sphere": self.sphere, "scanner": self.scanner, "x_mm": float(self.centre[0]),
                "y_mm": float(self.centre[1]), "z_mm": float(self.centre[2]),
                "u_position_mm": self.u_position_mm, "n_points": self.n_points, "disc_fraction": self.disc_fraction,
                "n_outside_observed_region": self.n_outside}


def _point_noise_mm(X: np.ndarray, radius: float) -> float:
    """The points' noise along the normal, for the robust fit's thresholds when none is
    configured: 1.4826 MAD of the distances from a plain fixed-radius fit (a rod or a
    mount among the points widens it, which only widens the first inlier band; the
    robust fit then takes its threshold from its own inliers). Never below
    :class:`~fringecal.spheres.robust.RejectionConfig`'s default."""
    X = X[np.isfinite(X).all(axis=1)]
    if len(X) < MIN_POINTS:
        return RejectionConfig.noise_mm
    r = SphereModel.from_estimate(X, radius=radius).residuals(X)
    return max(RejectionConfig.noise_mm, 1.4826 * float(np.median(np.abs(r - np.median(r)))))


def _fit(scanner, block, uv, tau, edge, radius, footprint_px, rejection: RejectionConfig | None):
    """One sighting fitted as the ball-bar's are (:func:`~fringecal.verification.ballbar.refit_sighting`):
    the robust fixed-radius fit (:func:`~fringecal.spheres.robust.fit_sphere_robust`:
    the edge pixels, the silhouette against camera and projector, rods and mounts and
    residual outliers left out), then the kept points' phases corrected for pixel
    integration against it (the rim, whose bias cannot be predicted, left out) and
    fitted again; -> (SightingPoints, fraction of the image disc kept) or None."""
    cam = scanner.camera.image_mm(uv)
    X = triangulate_mm(scanner, cam, scanner.projector.image_mm(tau))
    views = [scanner.camera.pinhole, scanner.projector.pinhole]
    if rejection is not None:
        robust = fit_sphere_robust(X, radius, expected_radius=radius, flags={"edge": edge}, viewpoints=views,
                                   config=rejection)
    else:   # the noise from the data: a first guess, then the robust fit's own inliers' scale
        noise = _point_noise_mm(X[~edge], radius)
        for _ in range(2):
            robust = fit_sphere_robust(X, radius, expected_radius=radius, flags={"edge": edge}, viewpoints=views,
                                       config=RejectionConfig(noise_mm=noise, min_rod_points=MIN_ROD_POINTS))
            if robust.sigma_mm >= 0.9 * noise:
                break
            noise = max(RejectionConfig.noise_mm, robust.sigma_mm)
    keep = robust.kept
    uv, cam, tau = uv[keep], cam[keep], tau[keep]
    bias = phase_integration_bias(scanner.camera, scanner.projector, uv,
                                  np.broadcast_to(robust.model.centre, (len(uv), 3)), np.full(len(uv), radius),
                                  footprint_px)
    ok = np.isfinite(bias).all(axis=1)
    if ok.sum() < MIN_POINTS:
        return None
    cam, prj = cam[ok], scanner.projector.image_mm(tau[ok] - bias[ok])
    fit = SphereModel.from_estimate(triangulate_mm(scanner, cam, prj), radius=radius)
    fraction = len(cam) / disc_pixels(scanner.camera, fit.centre, radius)
    if fraction < MIN_DISC_FRACTION:
        return None
    return SightingPoints(scanner, block, cam, prj, np.asarray(fit.centre, float), float(radius),
                          float(fit.rms)), float(fraction)


def measure_spheres(cloud: Cloud, stores: Mapping[str, object], rig: Rig, covariance: np.ndarray,
                    spheres: pd.DataFrame, footprint_px: float = 1.0, measurement: int = 0,
                    rejection: RejectionConfig | None = None, fit_factors: dict | None = None,
                    regions: Mapping[str, ObservedRegion] | None = None) -> list[MeasuredSphere]:
    """Every sphere of ``spheres`` in every scanner that sees it.

    Parameters
    ----------
    cloud : the cloud of one measurement (:func:`fringecal.measure.measure_cloud`)
    stores : scanner -> the store it was measured from (``tau_x``, ``tau_y``)
    rig : the calibration
    covariance : (14 n_sensors, 14 n_sensors) sensor covariance in the frame the
        positions are to be stated in (the rig's: ``frame_free_covariance``), or the
        extended one with the correction fields' coefficients
        (:attr:`~fringecal.calibration.propagation.ParameterCovariances.field_total`), or None
        (``u_position_mm`` NaN)
    spheres : ``sphere_id, x_mm, y_mm, z_mm, radius_mm``: nominal centres (within a
        few mm) and the certified radii
    footprint_px : the pixel-integration footprint (0: no correction)
    measurement : which of the cloud's measurements
    rejection : the robust fit's settings; default: :class:`~fringecal.spheres.robust.RejectionConfig`
        with ``noise_mm`` estimated from each sighting's points
    fit_factors : scanner -> factor on its fits' uncertainty, the scatter of its centres
        between spheres in the calibration's views (``max(1, kappa)``, the calibration
        file's ``metadata.sighting_dispersion``; :mod:`fringecal.spheres.dispersion`)
    regions : sensor name -> its observed region (each sighting's ``n_outside``), or None
    """
    stated = covariance is not None
    if not stated:
        covariance = np.zeros((14 * len(rig.sensors),) * 2)
    std = np.sqrt(np.clip(np.diag(covariance), 0, None))
    out = []
    for k, name in enumerate(cloud.scanners):
        if name not in stores:
            continue
        ds = stores[name]
        scanner = store_scanner(ds, rig.scanner(name))
        block = [s.name for s in rig.scanners].index(name)
        sl = slice(28 * block, 28 * block + 28)
        tau_x, tau_y = np.asarray(ds["tau_x"]), np.asarray(ds["tau_y"])
        valid = np.asarray(ds["valid"], bool)
        edge_map = boundary_flags(valid, EDGE_WIDTH_PX)
        maps = triangulate_maps(scanner.camera, scanner.projector, tau_x, tau_y, valid)
        candidates = {}
        for s in spheres.itertuples():
            nominal = np.array([s.x_mm, s.y_mm, s.z_mm], float)
            r = float(s.radius_mm)
            if r not in candidates:
                candidates[r] = find_sphere_candidates(maps, r, scanner.camera.pinhole)
            near = [c for c in candidates[r] if np.linalg.norm(c.centre - nominal) < r + SEARCH_MM]
            if not near:
                continue
            region = min(near, key=lambda c: np.linalg.norm(c.centre - nominal)).region
            rows, cols = np.nonzero(region)
            if len(rows) < MIN_POINTS:
                continue
            uv = np.stack([cols, rows], axis=-1).astype(float)
            tau = np.stack([tau_x[rows, cols], tau_y[rows, cols]], axis=-1).astype(float)
            try:
                pts = _fit(scanner, block, uv, tau, edge_map[rows, cols], float(s.radius_mm), footprint_px,
                           rejection)
            except FitError:
                continue
            if pts is None:
                continue
            pts, fraction = pts
            model = scaled_fit(sighting_model(pts, std[sl]), (fit_factors or {}).get(name, 1.0))
            J, idx = model.J, np.arange(sl.start, sl.stop)
            if covariance.shape[0] > 14 * len(rig.sensors) and model.J_field is not None:  # with the fields
                J = np.concatenate([J, model.J_field], axis=1)
                idx = extended_indices(len(rig.sensors), block, model.J_field.shape[1] // 2)
            var = np.trace(J @ covariance[np.ix_(idx, idx)] @ J.T) + np.trace(model.C_fit)
            known = any(sensor.name in (regions or {}) for sensor in scanner.sensors)
            n_outside = int(outside_observed_region(scanner, regions, pts.cam_mm, pts.prj_mm).sum()) if known else None
            out.append(MeasuredSphere(str(s.sphere_id), name, pts.centre,
                                      float(np.sqrt(max(var, 0.0))) if stated else float("nan"),
                                      len(pts.cam_mm), fraction, model, n_outside))
    return out


DISTANCE_COLUMNS = ["sphere_a", "scanner_a", "sphere_b", "scanner_b", "distance_mm", "u_mm", "bias_mm",
                    "model_error_mm"]


def sphere_distances(measured: list[MeasuredSphere], covariance: np.ndarray | None,
                     adjustment: np.ndarray | None = None, replicas: Mapping[str, np.ndarray] | None = None,
                     field: tuple[np.ndarray, int, np.ndarray] | None = None) -> pd.DataFrame:
    """Every distance between two measured centres of different spheres, with its
    standard uncertainty, as the verification states a ball-bar length:
    ``sphere_a, scanner_a, sphere_b, scanner_b, distance_mm, u_mm, bias_mm, model_error_mm``.

    ``u_mm`` holds the calibration's part through both centres at once (``covariance``,
    (14 n_sensors) square) and the fits'; NaN without a covariance. With the
    calibration's ``replicas`` (:attr:`fringecal.calibration.file.Calibration.replicas`):
    the bootstrap's bias of the distance is subtracted (``bias_mm``; its u enters ``u_mm``,
    :func:`~fringecal.verification.budget.bootstrap_bias`) and the jackknife's spread
    beyond that of its noise-only worlds, at the scale of the linear term of
    ``adjustment`` (the adjustment's share of ``covariance``), enters as ``model_error_mm``
    (:func:`~fringecal.verification.budget.jackknife_model_error`). NaN where the
    calibration carries no such replicas. ``field``: the covariance over the extended
    vector with the correction fields' coefficients, their number per sensor and the
    adjustment's share (:class:`~fringecal.calibration.propagation.FieldCovariances`),
    which then replace ``covariance`` and ``adjustment`` for the distances whose
    sightings have a field (the replicas then carry the coefficients too)."""
    rows = []
    if not measured:
        return pd.DataFrame(rows, columns=DISTANCE_COLUMNS)
    stated = covariance is not None
    n = covariance.shape[0] if stated else 28 * (1 + max(m.model.points.block for m in measured))
    if not stated:
        covariance = np.zeros((n, n))
    boot = (replicas or {}).get("bootstrap")
    boot = boot if boot is not None and len(boot) >= 2 else None
    jack, noise = (replicas or {}).get("jackknife"), (replicas or {}).get("jackknife_noise")
    jack = jack if jack is not None and noise is not None and len(jack) >= 2 and adjustment is not None else None
    for i, a in enumerate(measured):
        for b in measured[i + 1:]:
            if a.sphere == b.sphere:
                continue
            g, e, L = length_gradient(a.model, b.model, n)
            C = covariance
            if field is not None and stated and (a.model.J_field is not None or b.model.J_field is not None):
                g, C = field_gradient(g, a.model, b.model, e, field[1]), field[0]
            var = float(g @ C @ g) + float(e @ (a.model.C_fit + b.model.C_fit) @ e)
            bias = model_error = float("nan")
            if boot is not None:
                bias, u_bias, _ = bootstrap_bias(a.model.points, b.model.points, boot)
                L, var = L - bias, var + u_bias**2
            if jack is not None:
                extended = field is not None and jack.shape[-1] > 14
                model_error = jackknife_model_error(a.model, b.model, jack, noise,
                                                    field[2] if extended else adjustment,
                                                    field[1] if extended else 0)["model_error_mm"]
                var += model_error**2
            rows.append({"sphere_a": a.sphere, "scanner_a": a.scanner, "sphere_b": b.sphere, "scanner_b": b.scanner,
                         "distance_mm": L, "u_mm": float(np.sqrt(max(var, 0.0))) if stated else float("nan"),
                         "bias_mm": bias, "model_error_mm": model_error})
    return pd.DataFrame(rows, columns=DISTANCE_COLUMNS)
