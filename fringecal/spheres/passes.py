"""Per-measurement point clouds, sphere fits and control points (issues 4 and 5).

:func:`first_pass` triangulates a measurement store with its scanner's current
parameters, writes ``x, y, z, eps1`` and the candidate regions to a maps store of
their own (the acquisition store stays as recorded), and fits every candidate. After
labelling, :func:`second_pass` refits the labelled candidates with rod cones, writes
each pixel's sphere label to a labels store and selects the control points from the
clean pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import xarray as xr

from fringecal.calibration.controlpoints import incidence_map, select_control_points
from fringecal.frames import Frame
from fringecal.pointcloud import PointMaps, provenance, triangulate_maps
from fringecal.rig import Scanner
from fringecal.spheres.extraction import fit_candidates
from fringecal.spheres.pixel_integration import correct_control_points
from fringecal.spheres.robust import rod_directions
from fringecal.store import open_store, write_store

__all__ = ["measurement_maps", "first_pass", "second_pass", "ExtractionResult"]


def measurement_maps(store, scanner: Scanner) -> tuple[xr.Dataset, PointMaps, np.ndarray]:
    """Open a store and triangulate it with ``scanner``'s parameters.

    Returns the dataset, the point maps (scanner's frame) and the validity mask.
    """
    ds = open_store(store)
    valid = ds["valid"].values.astype(bool)
    maps = triangulate_maps(scanner.camera, scanner.projector, ds["tau_x"].values, ds["tau_y"].values, valid)
    return ds, maps, valid


def first_pass(store, scanner: Scanner, radius_mm: float, candidate_config, rejection_config, measurement: str,
               maps_out) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Triangulate, write the point maps and candidate regions to ``maps_out``, fit candidates.

    Returns the sphere-fits rows (``sphere_id`` empty) and the candidates that could
    not be fitted (``measurement, scanner, candidate, sphere_id, reason``).
    """
    ds, maps, valid = measurement_maps(store, scanner)
    fits = fit_candidates(maps, valid, scanner.camera, scanner.projector, radius_mm, measurement, scanner.name,
                          candidate_config=candidate_config, rejection_config=rejection_config)
    ds.close()
    dims = ("v", "u")
    f32 = lambda a: xr.DataArray(np.where(maps.valid, a, np.nan).astype(np.float32), dims=dims)  # noqa: E731
    write_store(maps_out, xr.Dataset({"x": f32(maps.x), "y": f32(maps.y), "z": f32(maps.z), "eps1": f32(maps.eps1),
                                      "candidate": xr.DataArray(fits.regions, dims=dims)},
                                     attrs={"measurement": measurement, "scanner": scanner.name,
                                            "points": {**provenance(scanner.camera, scanner.projector),
                                                       "frame": f"scanner {scanner.name}"}}))
    rows = pd.DataFrame(fits.rows)
    failures = pd.DataFrame(fits.failures, columns=["measurement", "scanner", "candidate", "sphere_id", "reason"])
    return rows, failures


@dataclass(frozen=True)
class ExtractionResult:
    """Final fits, candidates that could not be fitted, and control points of one measurement."""

    fits: pd.DataFrame
    failures: pd.DataFrame
    control_points: pd.DataFrame


def second_pass(store, candidates, scanner: Scanner, artefact, rods: pd.DataFrame | None, labelled: pd.DataFrame,
                pose: Frame | None, rejection_config, control_point_config, measurement: str, labels_out,
                rod_cones: bool = True) -> ExtractionResult:
    """Refit the labelled candidates of one measurement and select its control points.

    Parameters
    ----------
    store : path
        The acquisition store.
    candidates : path
        The maps store of :func:`first_pass` (its ``candidate`` regions).
    labelled : DataFrame
        This measurement's rows of the labelled sphere-fits table.
    pose : Frame or None
        ``T_scanner_artefact`` from the labelling step; with rods (and ``rod_cones``),
        each sphere's rod directions become cones to mask (end caps and tubes).
    labels_out : path
        Store to write ``sphere_label`` (artefact sphere index per pixel, -1: none) to.
    """
    ds, maps, valid = measurement_maps(store, scanner)
    tau_x, tau_y = ds["tau_x"].values, ds["tau_y"].values
    ds.close()
    with open_store(candidates) as cands:
        regions = cands["candidate"].values.astype(np.int16)
    labelled = labelled[labelled["sphere_id"].astype(str) != ""]
    sids = {int(r.candidate): str(r.sphere_id) for r in labelled.itertuples()}
    use_cones = rod_cones and rods is not None and pose is not None
    axes = {c: rod_directions(artefact, rods, s, pose) for c, s in sids.items()} if use_cones else None
    radius = {c: float(artefact.radii[artefact.index([s])[0]]) for c, s in sids.items()}
    keep = np.where(np.isin(regions, list(sids)), regions, -1).astype(np.int16)
    fits = fit_candidates(maps, valid, scanner.camera, scanner.projector, float(np.median(artefact.radii)),
                          measurement, scanner.name, regions=keep, rod_axes=axes, sphere_ids=sids,
                          fixed_radius=radius, rejection_config=rejection_config)
    fitted = [int(r["candidate"]) for r in fits.rows]
    labels = np.where(np.isin(fits.kept, fitted), fits.kept, -1)
    incidence = None
    if control_point_config.max_incidence_deg is not None and fitted:
        # pixels seen obliquely integrate a larger, more sloped patch: their phases carry
        # the pixel-integration bias of thesis chapter 5, so the rim is left out
        index = np.full(int(labels.max()) + 1, -1)
        index[fitted] = np.arange(len(fitted))
        centres = np.array([[r["x_mm"], r["y_mm"], r["z_mm"]] for r in fits.rows])
        incidence = incidence_map(np.stack([maps.x, maps.y, maps.z], axis=-1),
                                  np.where(labels >= 0, index[np.maximum(labels, 0)], -1), centres,
                                  scanner.camera.pinhole)
    cps = select_control_points(labels, {c: sids[c] for c in fitted}, tau_x, tau_y, valid,
                                measurement=measurement, scanner=scanner.name,
                                spacing_px=control_point_config.spacing_px, erode_px=control_point_config.rim_px,
                                incidence=incidence,
                                max_incidence_deg=None if incidence is None else control_point_config.max_incidence_deg)
    rows = pd.DataFrame(fits.rows)
    cps = correct_control_points(cps, rows, scanner, control_point_config.pixel_integration_px)
    dims = ("v", "u")
    sphere_index = np.full(labels.shape, -1, np.int16)
    for c in fitted:
        sphere_index[labels == c] = artefact.index([sids[c]])[0]
    write_store(labels_out, xr.Dataset({"sphere_label": xr.DataArray(sphere_index, dims=dims)},
                                       attrs={"measurement": measurement, "scanner": scanner.name,
                                              "sphere_label_ids": list(artefact.ids)}))
    failures = pd.DataFrame(fits.failures, columns=["measurement", "scanner", "candidate", "sphere_id", "reason"])
    return ExtractionResult(rows, failures, cps)
