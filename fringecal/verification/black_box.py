"""The ball-bar verification of a cell with black-box scanners.

A position's spheres may be seen by modelled scanners (stores of phase maps,
triangulated with the calibrated sensors and searched as in :mod:`.measure`) and by
black-box scanners (clouds: candidates by normal voting and the robust fit of
:mod:`fringecal.spheres.cloud_spheres`, each centre carried into the world by its
scanner's calibrated transform and scale). The sightings of all scanners are clustered
by centre distance (closer than the bar's radius: one sphere); exactly two clusters
make a position, and every pair of sightings of the two spheres one length (as
:func:`.lengths.ballbar_lengths` pairs them).

Each length's uncertainty (k = 2 with the verification's coverage factor) is
propagated to first order from:

* each black-box centre's covariance (its sphere fit's residuals) carried into the
  world frame;
* each black-box scanner's transform and scale covariance
  (:class:`fringecal.calibration.blackbox.BlackBoxScanner`), once per scanner (a scanner
  seeing both spheres contributes only through its rotation and scale);
* a modelled scanner's sighting: its fit scatter, ``2 rms / sqrt(n)`` per coordinate
  (a cap's centre is about twice as uncertain as the mean of its points); the
  calibrated sensors' own covariance is not propagated here (the modelled-only
  verification, :mod:`.uncertainty`, does that pixel by pixel);
* the certificate's standard uncertainty.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.calibration.blackbox import BlackBoxScanner, transform_points
from fringecal.rig import Rig
from fringecal.scancloud import read_cloud_store
from fringecal.spheres.cloud_spheres import cloud_sphere_fits
from fringecal.spheres.robust import RejectionConfig
from fringecal.verification.lengths import evaluate_ballbar
from fringecal.verification.measure import store_sightings
from fringecal.verification.uncertainty import iso14253_verdict

__all__ = ["black_box_scanners_of", "verify_with_black_boxes"]


def black_box_scanners_of(doc: dict) -> dict[str, BlackBoxScanner]:
    """The black-box scanners of ``black_boxes.json`` (or calibration.json's ``black_boxes``)."""
    names = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad", "scale")
    return {d["scanner"]: BlackBoxScanner(d["scanner"], np.array([d[n] for n in names], float),
                                          np.array(d["covariance"], float), float(d["rms_mm"]), int(d["n_centres"]))
            for d in doc["scanners"]}


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
            points, normals = read_cloud_store(store)
            fits, fails = cloud_sphere_fits(points, position, scanner, radius, rejection=rejection, normals=normals)
            failures += [{"position": position, "scanner": scanner, "sphere_id": "", "reason": f.reason}
                         for f in fails.itertuples()]
            for f in fits.itertuples():
                c = np.array([f.x_mm, f.y_mm, f.z_mm])
                M = box.matrix()[:3, :3]
                out.append({"scanner": scanner, "centre": transform_points(box, c[None])[0],
                            "cov": M @ np.diag([f.u_x_mm, f.u_y_mm, f.u_z_mm]) ** 2 @ M.T,
                            "box": box, "local": c, "radius_mm": f.radius_mm, "rms_mm": f.rms_mm,
                            "n_points": int(f.n_points)})
        else:
            found, problems = store_sightings(store, rig.scanner(scanner), ballbar, rejection)
            failures += [{"position": position, "scanner": scanner, "sphere_id": "", "reason": p} for p in problems]
            for s in found:
                u = 2 * s.rms_mm / np.sqrt(max(s.n_points, 1))
                out.append({"scanner": scanner, "centre": np.asarray(s.centre, float), "cov": u**2 * np.eye(3),
                            "box": None, "local": None, "radius_mm": s.radius_mm, "rms_mm": s.rms_mm,
                            "n_points": int(s.n_points)})
    return out, failures


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


def _length_u(a: dict, b: dict, u_certificate: float) -> tuple[float, float]:
    """Length and its combined standard uncertainty (first order)."""
    d = b["centre"] - a["centre"]
    L = float(np.linalg.norm(d))
    g = d / L
    var = g @ (a["cov"] + b["cov"]) @ g + u_certificate**2
    grads: dict = {}  # a scanner seeing both spheres: one gradient, its translation cancels
    for s, sign in ((a, -1.0), (b, 1.0)):
        if s["box"] is not None:
            box, acc = grads.get(s["scanner"], (s["box"], np.zeros(7)))
            grads[s["scanner"]] = (box, acc + sign * g @ _world_jacobian(s["box"], s["local"]))
    for box, J in grads.values():
        var += J @ box.covariance @ J
    return L, float(np.sqrt(var))


def verify_with_black_boxes(stores: dict, rig: Rig, boxes: dict, ballbar: Artefact, rejection: dict, settings,
                            diagonal_mm: float) -> tuple[pd.DataFrame, pd.DataFrame, dict, dict]:
    """Centres, failures, the evaluated lengths (:func:`.lengths.evaluate_ballbar`
    as a dict) and the lengths' budgets of every position (``stores``: position ->
    scanner -> store path), modelled and black-box scanners together."""
    rejection = RejectionConfig(**rejection)
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
        for sid, g in zip(ballbar.ids[:2], groups):
            for i in g:
                s = sightings[i]
                rows.append({"position": position, "scanner": s["scanner"], "sphere_id": sid,
                             "x_mm": s["centre"][0], "y_mm": s["centre"][1], "z_mm": s["centre"][2],
                             "radius_mm": s["radius_mm"], "rms_mm": s["rms_mm"], "n_points": s["n_points"]})
        pairs = [(i, j) for i in groups[0] for j in groups[1]]
        for i, j in pairs:
            a, b = sightings[i], sightings[j]
            L, u = _length_u(a, b, u_cert)
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
        entries.append({"measurement": r.measurement, "length_mm": r.length_mm, "error_mm": error, "u_mm": r.u_mm,
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
