"""The ball-bar verification of a cell with black-box scanners.

A position's spheres may be seen by modelled scanners (stores of phase maps,
triangulated with the calibrated sensors and searched as in :mod:`.measure`) and by
black-box scanners (clouds: candidates by normal voting and the robust fit of
:mod:`fringecal.spheres.cloud_spheres`, each centre carried into the world by its
scanner's calibrated transform and scale). The sightings of all scanners are clustered
by centre distance (closer than the bar's radius: one sphere); exactly two clusters
make a position, and every pair of sightings of the two spheres one length (as
:func:`.lengths.ballbar_lengths` pairs them).

A modelled scanner's sighting is refitted as the modelled-only verification refits it
(certified radius, rod masked, its points corrected for the pixel-integration bias
with the footprint of ``control_points.pixel_integration_px``:
:func:`.ballbar.refit_sighting`), as its control points were corrected before the
bundle adjustment: its centre then means what the calibration's poses mean. A
black box's sighting cannot be corrected (no sensors), and need not be: its transform
was fitted to its own artefact centres, which carry the same bias (a sphere of the same
size in the same field), so the transform carries it into the world and the bar
sphere's bias cancels, up to how the bias varies across the field.

Each length's uncertainty (k: the verification's coverage factor) is propagated to
first order through the joint covariance of every sensor parameter and every black
box's transform and scale (``black_boxes.json`` ``joint_covariance``: the adjustment
of the black boxes together with the bundle's parameters), with each modelled
sighting's centre linearised in its scanner's 28 parameters
(:func:`.budget.sighting_model`) and each black-box centre in its scanner's 7; plus
each sphere fit's own covariance (the black box's carried into the world), for a
black-box sighting its scanner's measured scatter between spheres (``rms_mm`` of the
adjustment's residuals per coordinate: what differs from sphere to sphere and pose to
pose, such as the bias's variation across the field, which one sighting does not
average), and the certificate's standard uncertainty. A scanner seeing both spheres contributes once
(its translation cancels).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.calibration.blackbox import BlackBoxScanner, scanners_from_document, transform_points
from fringecal.rig import Rig
from fringecal.scancloud import load_points
from fringecal.spheres.cloud_spheres import cloud_sphere_fits, refit_cloud_sphere
from fringecal.spheres.fit import FitError
from fringecal.spheres.robust import RejectionConfig
from fringecal.verification.ballbar import refit_sighting
from fringecal.verification.budget import sighting_model
from fringecal.verification.lengths import evaluate_ballbar
from fringecal.verification.measure import store_sightings
from fringecal.verification.uncertainty import iso14253_verdict, sighting_points

__all__ = ["ROUGH_FIT_RATIO", "black_box_scanners_of", "verify_with_black_boxes"]

#: A black box's candidate whose residual RMS exceeds this many times the best fit of its
#: cloud straddles a sphere's edge and the rod (its radius within the search's 20 %, its
#: residuals ten times a sphere's on the black-box row): set aside, as a bar's (or a
#: dumbbell's) two spheres are alike. On the mixed thesis rig such a candidate made
#: ball-bar position 5 "3 bar spheres found" in every seed.
ROUGH_FIT_RATIO = 3.0


def black_box_scanners_of(doc: dict) -> dict[str, BlackBoxScanner]:
    """The black-box scanners of ``black_boxes.json`` (or calibration.json's ``black_boxes``)."""
    return scanners_from_document(doc)


def _world_jacobian(box: BlackBoxScanner, c: np.ndarray, step: float = 1e-7) -> np.ndarray:
    """d(world centre)/d(box params), (3, 7), central differences."""
    J = np.empty((3, 7))
    for i in range(7):
        h = step * max(1.0, abs(box.params[i]))
        p = box.params.copy()
        p[i] += h
        up = transform_points(BlackBoxScanner(box.name, p, box.covariance, 0, 0), c[None])[0]
        p[i] -= 2 * h
        dn = transform_points(BlackBoxScanner(box.name, p, box.covariance, 0, 0), c[None])[0]
        J[:, i] = (up - dn) / (2 * h)
    return J


def _sightings(position: str, stores: dict, rig: Rig, boxes: dict, ballbar: Artefact,
               rejection: RejectionConfig) -> tuple[list[dict], list[dict]]:
    radius = float(np.mean(ballbar.radii[:2]))
    out, failures = [], []
    for scanner, store in stores.items():
        if scanner in boxes:
            box = boxes[scanner]
            points, normals = load_points(store)
            fits, fails = cloud_sphere_fits(points, position, scanner, radius, rejection=rejection, normals=normals)
            failures += [{"position": position, "scanner": scanner, "sphere_id": "", "reason": f.reason}
                         for f in fails.itertuples()]
            if len(fits):
                rough = fits["rms_mm"] > ROUGH_FIT_RATIO * fits["rms_mm"].min()
                failures += [{"position": position, "scanner": scanner, "sphere_id": "",
                              "reason": f"candidate {f.candidate}: residual RMS {f.rms_mm:.2f} mm, more than "
                                        f"{ROUGH_FIT_RATIO:g} times the cloud's best fit (a sphere's edge and its rod)"}
                             for f in fits[rough].itertuples()]
                fits = fits[~rough]
            for f in fits.itertuples():
                c = np.array([f.x_mm, f.y_mm, f.z_mm])
                M = box.matrix()[:3, :3]
                out.append({"scanner": scanner, "centre": transform_points(box, c[None])[0],
                            "C_fit": M @ np.diag([f.u_x_mm, f.u_y_mm, f.u_z_mm]) ** 2 @ M.T + _scatter(box),
                            "box": box, "local": c, "radius_mm": f.radius_mm, "rms_mm": f.rms_mm,
                            "n_points": int(f.n_points), "points": points})
        else:
            found, problems = store_sightings(store, rig.scanner(scanner), ballbar, rejection)
            failures += [{"position": position, "scanner": scanner, "sphere_id": "", "reason": p} for p in problems]
            out += [{"scanner": scanner, "centre": np.asarray(x.centre, float), "sighting": x, "store": store,
                     "box": None} for x in found]
    return out, failures


def _scatter(box: BlackBoxScanner) -> np.ndarray:
    """A black box's measured scatter of sphere centres between spheres, per coordinate
    and net of its fits' own noise (``scatter_mm``, which a sighting's fit covariance
    already holds), as a covariance (3, 3) of one sighting. A document without
    ``scatter_mm`` falls back to the adjustment's RMS residual per coordinate
    (``rms_mm`` / sqrt 3, fit noise included); zero when it carries neither (true
    transforms)."""
    s = box.scatter_mm if np.isfinite(box.scatter_mm) else box.rms_mm / np.sqrt(3.0)
    return (s**2 if np.isfinite(s) else 0.0) * np.eye(3)


def _refit_box(sighting: dict, other: np.ndarray, radius: float, rejection: RejectionConfig,
               max_incidence_deg: float | None) -> dict:
    """A black box's sighting refitted in its cloud (certified radius, rod toward the
    other sphere masked, rim left out: :func:`fringecal.spheres.cloud_spheres.refit_cloud_sphere`)."""
    box = sighting["box"]
    M = box.matrix()[:3, :3]
    axis = np.linalg.solve(M, other - sighting["centre"])
    fit = refit_cloud_sphere(sighting["points"], sighting["local"], radius, (axis / np.linalg.norm(axis))[None],
                             rejection, max_incidence_deg)
    m = fit.model
    c = np.asarray(m.centre, float)
    return {**sighting, "local": c, "centre": transform_points(box, c[None])[0],
            "C_fit": M @ m.covariance[:3, :3] @ M.T + _scatter(box), "radius_mm": m.radius, "rms_mm": m.rms,
            "n_points": int(m.n_points)}


def _refit_modelled(sighting: dict, other: np.ndarray, radius: float, rig: Rig, std: np.ndarray,
                    rejection: RejectionConfig, footprint_px: float) -> dict:
    """A modelled sighting refitted (certified radius, rod masked, its points corrected
    for pixel integration: :func:`.ballbar.refit_sighting`), with its linear model."""
    axis = other - sighting["centre"]
    m = refit_sighting(sighting["sighting"], radius, axis / np.linalg.norm(axis), rejection, footprint_px)
    points = sighting_points(sighting["store"], rig, sighting["scanner"], m.pixels, m.centre, m.radius_mm,
                             m.rms_mm)
    block = points.block
    model = sighting_model(points, np.where(std[28 * block:28 * block + 28] > 0, std[28 * block:28 * block + 28],
                                            1e-6))
    return {**sighting, "centre": np.asarray(m.centre, float), "C_fit": model.C_fit, "J": model.J, "block": block,
            "radius_mm": m.radius_mm, "rms_mm": m.rms_mm, "n_points": int(m.n_points)}


def _clusters(sightings: list[dict], radius: float) -> list[list[int]]:
    """Single-linkage clusters of sightings closer than ``radius``."""
    label = list(range(len(sightings)))
    for i in range(len(sightings)):
        for j in range(i):
            if np.linalg.norm(sightings[i]["centre"] - sightings[j]["centre"]) < radius:
                old, new = label[i], label[j]
                label = [new if x == old else x for x in label]
    groups: dict[int, list[int]] = {}
    for i, g in enumerate(label):
        groups.setdefault(g, []).append(i)
    return list(groups.values())


def _length_u(a: dict, b: dict, joint: dict, u_certificate: float) -> tuple[float, float]:
    """Length and its combined standard uncertainty (first order, see the module notes)."""
    d = b["centre"] - a["centre"]
    L = float(np.linalg.norm(d))
    e = d / L
    n_s, names, C = joint["n_sensor_parameters"], joint["black_boxes"], joint["matrix"]
    grad = np.zeros(C.shape[0])
    for s, sign in ((a, -1.0), (b, 1.0)):
        if s["box"] is not None:
            k = n_s + 7 * names.index(s["scanner"])
            grad[k:k + 7] += sign * e @ _world_jacobian(s["box"], s["local"])
        else:
            grad[28 * s["block"]:28 * s["block"] + 28] += sign * e @ s["J"]
    var = grad @ C @ grad + e @ (a["C_fit"] + b["C_fit"]) @ e + u_certificate**2
    return L, float(np.sqrt(max(var, 0.0)))


def verify_with_black_boxes(stores: dict, rig: Rig, black_boxes: dict, ballbar: Artefact, rejection: dict, settings,
                            diagonal_mm: float, max_incidence_deg: float | None = 60.0,
                            pixel_integration_px: float = 0.0) -> tuple[pd.DataFrame, pd.DataFrame, dict, dict]:
    """Centres, failures, the evaluated lengths (:func:`.lengths.evaluate_ballbar`
    as a dict) and the lengths' budgets of every position (``stores``: position ->
    scanner -> store path), modelled and black-box scanners together
    (``black_boxes``: the document of ``black_boxes.json``); ``pixel_integration_px``:
    the footprint the modelled sightings' phases are corrected with (the control
    points', ``control_points.pixel_integration_px``; 0: as decoded). A black box's
    candidate fit whose residual RMS exceeds :data:`ROUGH_FIT_RATIO` times the best of
    its cloud is set aside."""
    rejection = RejectionConfig(**rejection)
    boxes = black_box_scanners_of(black_boxes)
    joint = dict(black_boxes["joint_covariance"])
    joint["matrix"] = np.asarray(joint["matrix"], float)
    std = np.sqrt(np.clip(np.diag(joint["matrix"])[:joint["n_sensor_parameters"]], 0, None))
    radii = dict(zip(ballbar.ids[:2], ballbar.radii[:2]))
    radius = float(np.min(ballbar.radii[:2]))
    u_cert = settings.certificate_u_mm / settings.certificate_k
    reference = float(np.linalg.norm(ballbar.centres[1] - ballbar.centres[0]))
    rows, failures, lengths = [], [], []
    for position, by_scanner in stores.items():
        sightings, fails = _sightings(position, by_scanner, rig, boxes, ballbar, rejection)
        failures += fails
        groups = _clusters(sightings, radius)
        if len(groups) != 2:
            seen = ", ".join(sorted({sightings[i]["scanner"] for g in groups for i in g})) or "none"
            failures.append({"position": position, "scanner": "", "sphere_id": "",
                             "reason": f"{len(groups)} bar sphere(s) found (scanners: {seen}); a length needs 2"})
            continue
        means = [np.mean([sightings[i]["centre"] for i in g], axis=0) for g in groups]
        for k, (sid, g) in enumerate(zip(ballbar.ids[:2], groups)):
            for i in g:
                try:
                    if sightings[i]["box"] is None:
                        sightings[i] = _refit_modelled(sightings[i], means[1 - k], float(radii[sid]), rig, std,
                                                       rejection, pixel_integration_px)
                    else:
                        sightings[i] = _refit_box(sightings[i], means[1 - k], float(radii[sid]), rejection,
                                                  max_incidence_deg)
                except (FitError, ValueError) as err:
                    failures.append({"position": position, "scanner": sightings[i]["scanner"],
                                     "sphere_id": sid, "reason": str(err)})
                    sightings[i] = None
                    continue
                s = sightings[i]
                rows.append({"position": position, "scanner": s["scanner"], "sphere_id": sid,
                             "x_mm": s["centre"][0], "y_mm": s["centre"][1], "z_mm": s["centre"][2],
                             "radius_mm": s["radius_mm"], "rms_mm": s["rms_mm"], "n_points": s["n_points"]})
        pairs = [(i, j) for i in groups[0] for j in groups[1]
                 if sightings[i] is not None and sightings[j] is not None]
        for i, j in pairs:
            a, b = sightings[i], sightings[j]
            L, u = _length_u(a, b, joint, u_cert)
            name = position if len(pairs) == 1 else f"{position}:{a['scanner']}/{b['scanner']}"
            lengths.append({"measurement": name, "position": position, "scanner_a": a["scanner"],
                            "scanner_b": b["scanner"], "length_mm": L, "u_mm": u})
    table = pd.DataFrame(lengths, columns=["measurement", "position", "scanner_a", "scanner_b", "length_mm", "u_mm"])
    result = evaluate_ballbar(table.length_mm, reference, table.measurement, settings.mpe_mm, diagonal_mm,
                              settings.certificate_u_mm, settings.certificate_k, settings.coverage_factor)
    k = settings.coverage_factor
    entries = []
    for r in table.itertuples():
        error = r.length_mm - reference
        U = k * r.u_mm
        entries.append({"measurement": r.measurement, "scanner_a": r.scanner_a, "scanner_b": r.scanner_b,
                        "length_mm": r.length_mm, "error_mm": error, "u_mm": r.u_mm,
                        "U_mm": U, "covered": bool(abs(error) <= U),
                        "iso14253": iso14253_verdict(error, U, settings.mpe_mm)})
    budget = {"method": "first-order propagation of the black-box transforms' covariance and the sphere fits "
                        "(fringecal.verification.black_box)", "coverage_factor": k, "lengths": entries,
              "not_covered": [e["measurement"] for e in entries if not e["covered"]], "budget": None,
              "monte_carlo": None}
    centres = pd.DataFrame(rows, columns=["position", "scanner", "sphere_id", "x_mm", "y_mm", "z_mm", "radius_mm",
                                          "rms_mm", "n_points"])
    return centres, pd.DataFrame(failures, columns=["position", "scanner", "sphere_id", "reason"]), \
        result.to_dict(), budget
