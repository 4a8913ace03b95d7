"""Ball-bar verification of a calibration (thesis 6.9.3, VDI/VDE 2634): the bar's
sphere centres measured in the stores of its positions from the data alone
(:func:`measure_position`, :func:`measure_positions`).

Every scanner's store of a position is searched for bar spheres, the sightings of all
scanners are grouped into the two spheres and named, and each sighting is refitted
with its certified radius and the rod masked. This is what a real cell has: the
recorded ``verification/<position>/<scanner>/`` measurements and nothing else; a
simulated run measures its rendered stores the same way (with the calibrated
sensors, and in the evaluation step with the true ones).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd

from fringecal.lens.observed_region import outside
from fringecal.rig import Rig, Scanner, scaled_scanner
from fringecal.spheres.fit import FitError
from fringecal.spheres.passes import measurement_maps
from fringecal.store import open_store
from fringecal.verification.ballbar import (
    Sighting,
    SightingConfig,
    cluster_centres,
    find_sightings,
    name_clusters,
    refit_sighting,
)

__all__ = ["measure_position", "measure_positions", "positions_outside", "store_sightings", "store_scanner", "store_maps", "CENTRE_COLUMNS", "FAILURE_COLUMNS"]

#: Columns of the centres and failures tables of :func:`measure_position`.
CENTRE_COLUMNS = ["position", "scanner", "sphere_id", "x_mm", "y_mm", "z_mm", "radius_mm", "rms_mm", "n_points"]
FAILURE_COLUMNS = ["position", "scanner", "sphere_id", "reason"]


# -- measuring a position from its stores alone --------------------------------------------


def store_scanner(ds, scanner: Scanner) -> Scanner:
    """``scanner`` with its camera resampled to the store's image size (dims ``v, u``)
    if that differs from its format: the same sensor binned, as a real scanner can."""
    rows, cols = int(ds.sizes["v"]), int(ds.sizes["u"])
    fmt = scanner.camera.format
    if (fmt.height_px, fmt.width_px) == (rows, cols):
        return scanner
    return scaled_scanner(scanner, cols, rows)


def store_maps(store, scanner: Scanner):
    """A store triangulated with ``scanner`` (world frame) at the store's image size:
    the scanner as resampled to it, the point maps and the store's validity mask."""
    with open_store(store) as ds:
        scanner = store_scanner(ds, scanner)
    ds, maps, valid = measurement_maps(store, scanner)
    ds.close()
    return scanner, maps, valid


def store_sightings(store, scanner: Scanner, ballbar, rejection_config,
                    config: SightingConfig | None = None) -> tuple[list[Sighting], list[str]]:
    """The bar spheres one store shows (:func:`fringecal.verification.ballbar.find_sightings`),
    triangulated with ``scanner`` (world frame) at the store's image size."""
    scanner, maps, valid = store_maps(store, scanner)
    return find_sightings(maps, valid, scanner, ballbar, rejection_config, config)


def _check_scanners(position: str, names, rig: Rig) -> None:
    known = [s.name for s in rig.scanners]
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"ball-bar position {position!r}: store(s) of scanner(s) {unknown} not in the rig "
                         f"(scanners: {known})")


def _count_text(n: int, scanners_per_sphere: list[list[str]]) -> str:
    seen = " | ".join(", ".join(dict.fromkeys(g)) for g in scanners_per_sphere)
    what = f"{n} sphere" + ("" if n == 1 else "s")
    return f"{what} found" + (f", seen by {seen}" if n else "") + "; a ball-bar position needs 2"


def _failure(position: str, scanner: str, sphere_id: str, reason: str) -> dict:
    return {"position": position, "scanner": scanner, "sphere_id": sphere_id, "reason": reason}


def _refit_all(position: str, sightings: list[Sighting], labels, names: dict, ballbar,
               rejection_config, config: SightingConfig | None = None) -> tuple[list[dict], list[dict]]:
    """Refit every sighting with its sphere's certified radius and the rod towards the
    other sphere (mean free-fit centre of its sightings) masked."""
    radii = dict(zip(ballbar.ids[:2], ballbar.radii[:2]))
    means = {k: np.mean([s.centre for s, lab in zip(sightings, labels) if lab == k], axis=0) for k in names}
    rows, failures = [], []
    for s, lab in zip(sightings, labels):
        sid = names[int(lab)]
        axis = means[1 - int(lab)] - s.centre
        try:
            m = refit_sighting(s, float(radii[sid]), axis / np.linalg.norm(axis), rejection_config,
                               (config or SightingConfig()).pixel_integration_px)
        except FitError as err:
            failures.append(_failure(position, s.scanner, sid, str(err)))
            continue
        rows.append({"position": position, "scanner": s.scanner, "sphere_id": sid, "x_mm": m.centre[0],
                     "y_mm": m.centre[1], "z_mm": m.centre[2], "radius_mm": m.radius_mm, "rms_mm": m.rms_mm,
                     "n_points": m.n_points, "pixels": m.pixels})
    return rows, failures


def _assemble(position: str, found: dict, scanner_order: list[str], ballbar, rejection_config,
              config: SightingConfig | None) -> tuple[list[dict], list[dict]]:
    """Cluster, name and refit one position's sightings (``found``: scanner ->
    (sightings, notes)); rows only if both spheres were measured."""
    failures = [_failure(position, sc, "", note) for sc in scanner_order if sc in found for note in found[sc][1]]
    sightings = [s for sc in scanner_order if sc in found for s in found[sc][0]]
    labels = cluster_centres([s.centre for s in sightings], float(ballbar.radii[:2].min()))
    groups = [[s.scanner for s, lab in zip(sightings, labels) if lab == k] for k in sorted(set(labels.tolist()))]
    if len(groups) != 2:
        return [], failures + [_failure(position, "", "", f"position {position!r}: {_count_text(len(groups), groups)}")]
    names = name_clusters(sightings, labels, ballbar, scanner_order, config)
    rows, refit_failures = _refit_all(position, sightings, labels, names, ballbar, rejection_config, config)
    failures += refit_failures
    missing = [sid for sid in ballbar.ids[:2] if sid not in {r["sphere_id"] for r in rows}]
    if missing:
        return [], failures + [_failure(position, "", missing[0], f"position {position!r}: sphere {missing[0]!r} "
                                        "could not be measured, so the position has no length")]
    rows.sort(key=lambda r: (ballbar.ids.index(r["sphere_id"]), scanner_order.index(r["scanner"])))
    return rows, failures


def _frames(rows: list[dict], failures: list[dict]) -> tuple[pd.DataFrame, pd.DataFrame]:
    out = pd.DataFrame(rows, columns=CENTRE_COLUMNS)
    out["n_points"] = out["n_points"].astype(int)
    return out, pd.DataFrame(failures, columns=FAILURE_COLUMNS)


def measure_position(stores: dict, rig: Rig, ballbar, rejection_config, position: str,
                     config: SightingConfig | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Sphere centres of one ball-bar position from its stores alone: no plan, no truth.

    Decisions (settings in :class:`fringecal.verification.ballbar.SightingConfig`):

    1. Every store is triangulated with its scanner's sensors (world frame); a store
       whose image (dims ``v, u``) is smaller or larger than the camera's format is a
       binned readout of the same sensor, so the camera is rescaled to it
       (:func:`fringecal.rig.scaled_scanner`). Sphere candidates of the
       bar's radius are fitted robustly with a free radius; a fit is a sighting if its
       radius is within ``radius_tolerance`` (10 %) of a certified radius and it kept
       at least ``min_disc_fraction`` (25 %) of the pixels of the sphere's image disc.
       A scanner gives 0, 1 or 2 sightings.
    2. The sightings of all scanners are clustered by centre distance: two closer than
       the bar's (smaller) radius are the same sphere (single linkage). Exactly two
       clusters make a position; otherwise one failure row names the position, how
       many spheres were found and which scanners saw them, and it gets no rows.
    3. The clusters are named with the bar's ids (:func:`fringecal.verification.ballbar.name_clusters`):
       by fitted radius if the certified diameters differ by more than
       ``distinct_diameter_mm`` (1 mm); else the first id goes to the sphere seen first
       in rig order, and if that scanner sees both, to the one with the smaller mean
       camera column (further left in its image). A length does not depend on the
       names; they only say which certified radius is fixed and label the rows.
    4. Every sighting is refitted with its sphere's certified radius fixed and the rod
       masked by a cone about the axis from its free-fit centre to the mean free-fit
       centre of the other sphere (as :func:`fringecal.verification.ballbar.measure_sphere` with
       the planned axis).

    Parameters
    ----------
    stores : dict scanner name -> store path
        The position's measurements, one per scanner that recorded it.
    rig : Rig
        Sensors in the world frame (e.g. the calibration); any camera resolution.
    ballbar : Artefact
        The bar; its first two sphere ids name the spheres (``A``, ``B``).
    rejection_config : RejectionConfig or None
    position : str
    config : SightingConfig, optional

    Returns
    -------
    rows : DataFrame
        ``position, scanner, sphere_id, x_mm, y_mm, z_mm, radius_mm, rms_mm, n_points``,
        one per sighting (a sphere seen by two scanners has two rows), ordered by
        sphere then rig order; both spheres or none.
    failures : DataFrame
        ``position, scanner, sphere_id ('' if unknown), reason``: candidates that were
        no sightings, a store with no sphere, refits that failed, and the position
        itself when it does not give a length (``scanner`` empty).

    Raises
    ------
    ValueError
        A store's scanner is not in the rig.
    StoreError
        An incomplete or corrupt store.
    """
    _check_scanners(position, stores, rig)
    order = [s.name for s in rig.scanners]
    found = {name: store_sightings(stores[name], rig.scanner(name), ballbar, rejection_config, config)
             for name in order if name in stores}
    return _frames(*_assemble(position, found, order, ballbar, rejection_config, config))


def measure_positions(stores: dict, rig: Rig, ballbar, rejection_config, workers: int = 2,
                      config: SightingConfig | None = None, pixels: bool = False):
    """:func:`measure_position` for every position (``stores``: position -> scanner ->
    store path); the stores are searched ``workers`` at a time in a thread pool, then
    each position is assembled. Returns the concatenated tables in ``stores`` order,
    and with ``pixels`` a third item: (position, scanner, sphere_id) -> (rows, cols) of
    the camera pixels each refit kept (for the length's uncertainty)."""
    for position, by_scanner in stores.items():
        _check_scanners(position, by_scanner, rig)
    order = [s.name for s in rig.scanners]
    jobs = [(pos, name) for pos, by_scanner in stores.items() for name in order if name in by_scanner]
    search = lambda job: store_sightings(stores[job[0]][job[1]], rig.scanner(job[1]), ballbar,  # noqa: E731
                                         rejection_config, config)
    with ThreadPoolExecutor(max_workers=workers) as pool:  # numpy and zarr release the GIL
        found = dict(zip(jobs, pool.map(search, jobs)))
        per_position = {pos: {name: found[(pos, name)] for (p, name) in jobs if p == pos} for pos in stores}
        done = list(pool.map(lambda pos: _assemble(pos, per_position[pos], order, ballbar, rejection_config, config),
                             stores))
    rows = [r for rows, _ in done for r in rows]
    tables = _frames(rows, [f for _, fails in done for f in fails])
    if not pixels:
        return tables
    return (*tables, {(r["position"], r["scanner"], r["sphere_id"]): r["pixels"] for r in rows})


def positions_outside(stores: dict, rig: Rig, pixels: dict, regions) -> dict:
    """Per ball-bar position, how many of the pixels its sphere fits kept lie outside the
    calibration's observed region of the camera or projector that saw them
    (:func:`fringecal.lens.observed_region.outside`; ``regions``: sensor name ->
    region).

    Parameters
    ----------
    stores : position -> scanner -> store path
    pixels : (position, scanner, sphere_id) -> (rows, cols) of the kept camera pixels
        (:func:`measure_positions` with ``pixels``)

    Returns
    -------
    position -> {"points", "outside", "fraction", "scanners": scanner -> {"points", "outside"}}
    """
    out: dict = {}
    by_store: dict = {}
    for (position, name, _), rc in sorted(pixels.items()):
        by_store.setdefault((position, name), []).append(np.asarray(rc, np.int64))
    for (position, name), kept in by_store.items():   # each store read once, for all its spheres
        rows = np.concatenate([k[0] for k in kept])
        cols = np.concatenate([k[1] for k in kept])
        with open_store(stores[position][name]) as ds:
            scanner = store_scanner(ds, rig.scanner(name))
            tau = np.stack([np.asarray(ds["tau_x"])[rows, cols], np.asarray(ds["tau_y"])[rows, cols]], axis=-1)
        cam_mm = scanner.camera.image_mm(np.stack([cols, rows], axis=-1).astype(float))
        flags = outside(regions, ((scanner.camera.name, cam_mm), (scanner.projector.name,
                                                                  scanner.projector.image_mm(tau))))
        entry = out.setdefault(position, {"points": 0, "outside": 0, "scanners": {}})
        entry["scanners"][name] = {"points": int(len(flags)), "outside": int(flags.sum())}
        entry["points"] += int(len(flags))
        entry["outside"] += int(flags.sum())
    for entry in out.values():
        entry["fraction"] = entry["outside"] / entry["points"] if entry["points"] else 0.0
    return out
