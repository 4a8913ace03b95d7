"""Degenerate calibrations, detected and explained before they return nonsense.

Structural checks (before solving, from the control points alone):

* ``too_few_control_points`` (error): fewer residuals than free parameters, overall or
  for one scanner's free sensor parameters.
* ``scanner_without_control_points`` (error): a scanner with free parameters but no
  control points; nothing determines them.
* ``measurement_without_control_points`` (warning): a pose of the pose table that no
  control point refers to; it is left out of the adjustment.
* ``pose_unobservable``: a measurement whose control points lie on fewer than three
  spheres: a sphere is invariant under rotation about its centre, so with one sphere the
  pose's rotation, with two spheres the rotation about the line through their centres,
  is not determined. A warning where the problem came from tables
  (:meth:`BundleProblem.from_tables` leaves such a measurement out, its points with it);
  an error for a problem built with that measurement in it.
* ``single_pose`` (warning): a scanner saw the artefact in one measurement only. Its
  principal distances, principal points and distortion are then fitted to a single
  placement of a few spheres: c trades off against the pinhole's distance along the
  viewing direction, the principal point against the angles, and distortion is only
  seen where those spheres happen to image. The message names the scanner's parameters
  in the weakest directions of the normal matrix.
* ``single_standoff`` (warning): the artefact's distance from a scanner's camera varies by
  less than ``STANDOFF_SPREAD`` of the mean over its measurements: only the artefact's own
  depth then separates the principal distance from the sensor's distance (image scale
  c / z); reported with their correlation after the adjustment.

Numerical check (at the start values and again at the solution): the rank of the scaled
normal matrix of the free parameters. Eigenvalues below ``UNOBSERVABLE`` times the
largest mean a parameter combination that no control point constrains
(``unobservable``, error); the parameters dominating that null direction are named,
with the usual cause (the world frame not fixed when the reference camera's external
parameters are free). Eigenvalues below ``NEAR_SINGULAR`` are reported as
``near_singular`` warnings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.calibration.model import BundleProblem, ParameterLayout, too_few_spheres
from fringecal.calibration.uncertainty import NEAR_SINGULAR, UNOBSERVABLE, weak_directions
from fringecal.frames import Frame
from fringecal.sensor import PARAM_NAMES

__all__ = ["Diagnosis", "DegenerateCalibrationError", "check_structure", "check_rank", "STANDOFF_SPREAD"]

STANDOFF_SPREAD = 0.05
_INTERNAL = ("xi_h", "eta_h", "c", "k1", "k2", "k3", "p1", "p2")


@dataclass(frozen=True)
class Diagnosis:
    """One finding. ``severity`` is ``error`` or ``warning``. An error found before
    solving refuses the adjustment (:class:`DegenerateCalibrationError`); the one error
    attached to a result, ``floor_not_reached`` (:mod:`.convergence`), says that no start
    reached the noise floor: the result is the lowest minimum found, not a calibration."""

    kind: str
    severity: str
    subject: str
    message: str
    parameters: tuple = ()

    def to_dict(self) -> dict:
        return {"kind": self.kind, "severity": self.severity, "subject": self.subject,
                "message": self.message, "parameters": list(self.parameters)}


class DegenerateCalibrationError(ValueError):
    """The calibration is degenerate; ``diagnoses`` says why."""

    def __init__(self, diagnoses):
        self.diagnoses = list(diagnoses)
        errors = [d for d in self.diagnoses if d.severity == "error"]
        lines = ["the bundle adjustment is degenerate:"] + [f"  - [{d.kind}] {d.message}" for d in errors]
        super().__init__("\n".join(lines))


def _free_names(problem: BundleProblem, sensor_rows) -> list[str]:
    sensors = problem.rig.sensors
    return [f"{sensors[i].name}.{PARAM_NAMES[j]}" for i in sensor_rows for j in range(14) if problem.rig.free[i, j]]


def check_structure(problem: BundleProblem) -> list[Diagnosis]:
    """Structural findings (see module docstring)."""
    out: list[Diagnosis] = []
    rig = problem.rig
    n = problem.n_points
    p = int(rig.free.sum() + problem.pose_free.sum())
    for m, reason in problem.dropped:
        kind = "measurement_without_control_points" if reason == "no control points" else "pose_unobservable"
        out.append(Diagnosis(kind, "warning", m,
                             f"measurement {m} has {reason}: its pose cannot be adjusted and it is left out"))
    if 2 * n < p:
        out.append(Diagnosis("too_few_control_points", "error", "all",
                             f"{n} control points give {2 * n} residuals for {p} free parameters"))
    for si, sc in enumerate(rig.scanners):
        sel = problem.scanner_idx == si
        k = int(sel.sum())
        free = _free_names(problem, (2 * si, 2 * si + 1))
        if k == 0:
            if free:
                out.append(Diagnosis("scanner_without_control_points", "error", sc.name,
                                     f"scanner {sc.name} has no control points, so its {len(free)} free "
                                     "parameters are undetermined; fix them or supply control points", tuple(free)))
            continue
        if 2 * k < len(free):
            out.append(Diagnosis("too_few_control_points", "error", sc.name,
                                 f"scanner {sc.name} has {k} control points for {len(free)} free sensor parameters"))
        meas = np.unique(problem.meas_idx[sel])
        internal = [f for f in free if f.split(".")[1] in _INTERNAL]
        if len(meas) == 1 and internal:
            out.append(Diagnosis(
                "single_pose", "warning", sc.name,
                f"scanner {sc.name} saw the artefact only in measurement {problem.measurements[meas[0]]}: its "
                "internal and distortion parameters are fitted to one placement of "
                f"{len(np.unique(problem.sphere_idx[sel]))} sphere(s); the principal distance cannot be told "
                "from the distance to the artefact, nor the principal point from the angles, except through "
                "the artefact's own depth. Add measurements at other positions and stand-offs, or fix the "
                "internal parameters", tuple(internal)))
        elif len(meas) > 1 and ("c" in {f.split(".")[1] for f in internal}):
            cam = sc.camera
            seen = np.unique(problem.sphere_idx[sel])  # the same spheres in every pose
            depth = []
            for m in meas:
                w = Frame.from_params(problem.poses[m]).to_world(problem.artefact.centres[seen])
                depth.append(float(np.mean(cam.to_sensor(w)[:, 2])))
            depth = np.asarray(depth)
            spread = (depth.max() - depth.min()) / depth.mean()
            if spread < STANDOFF_SPREAD:
                cs = [f for f in internal if f.split(".")[1] == "c"]
                out.append(Diagnosis(
                    "single_standoff", "warning", sc.name,
                    f"scanner {sc.name}: all {len(meas)} measurements at one stand-off "
                    f"({depth.mean():.0f} mm, spread {100 * spread:.1f} % < {100 * STANDOFF_SPREAD:.0f} %): "
                    "only the artefact's own depth tells the principal distances from the sensors' "
                    "distances along the viewing direction (image scale c/z), so they are correlated "
                    "and less certain; move the artefact through the depth of the volume",
                    tuple(cs)))
    for mi, m in enumerate(problem.measurements):
        sel = problem.meas_idx == mi
        spheres = np.unique(problem.sphere_idx[sel])
        if 0 < len(spheres) < 3 and problem.pose_free[mi, 3:].any():
            ids = [problem.artefact.ids[s] for s in spheres]
            out.append(Diagnosis("pose_unobservable", "error", m,
                                 f"measurement {m} has {too_few_spheres(ids)}; drop the measurement or fix its "
                                 "angles", tuple(f"pose[{m}].{a}" for a in ("omega", "phi", "kappa"))))
    return out


def check_rank(N: np.ndarray, layout: ParameterLayout, problem: BundleProblem, where: str,
               uncertainty=None) -> list[Diagnosis]:
    """Null space (error) and near-singular directions (warning) of the normal matrix N
    (taken from ``uncertainty.weak`` when given: the same N, already decomposed)."""
    out = []
    if uncertainty is not None:
        weak = list(uncertainty.weak)
    else:
        weak, _ = weak_directions(N, layout.names, threshold=NEAR_SINGULAR,
                                  regularised=layout.field_slots(problem.field_prior_weight))
    ref_cam = problem.rig.scanner(problem.rig.reference).camera.name
    ref_row = [s.name for s in problem.rig.sensors].index(ref_cam)
    gauge_free = bool(problem.rig.free[ref_row, :6].any())
    null = [w for w in weak if w.ratio < UNOBSERVABLE]
    if null:
        hint = ""
        if gauge_free:
            hint = (f" The world frame is not fixed: the reference camera {ref_cam} has free external "
                    "parameters, so every sensor and pose can move together; fix its x0, y0, z0, omega, "
                    "phi, kappa.")
        names = tuple(dict.fromkeys(n for w in null for n in w.parameters))
        text = "; ".join(f"({w.describe()})" for w in null)
        out.append(Diagnosis("unobservable", "error", where,
                             f"{len(null)} combination(s) of free parameters that no control point determines: "
                             f"{text}.{hint}", names))
    for w in weak:
        if w.ratio >= UNOBSERVABLE:
            out.append(Diagnosis("near_singular", "warning", where,
                                 f"weakly determined combination at the {where} ({w.describe()})", w.parameters))
    return out
