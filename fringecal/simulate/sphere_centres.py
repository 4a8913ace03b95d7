"""Sphere centres as scanners with imperfect prior calibrations measure them, for
testing and benchmarking the labelling (no images).

A rig's views come from :mod:`fringecal.simulate.control_points` (which spheres each
scanner sees in each pose, occlusion included). Each scanner then reports the centres
in its own, arbitrary frame (origin at its camera's pinhole, axes turned at random),
through a prior calibration with the errors the labelling's defaults are sized for
(:class:`PriorErrors`): a scale error about the scanner's origin, a smooth quadratic
warp and noise. The planned poses are the true poses moved by the hexapod's errors and
expressed in another arbitrary fixed frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.frames import POSE_COLUMNS, Frame
from fringecal.registration import kabsch
from fringecal.rotation import rotation_matrix
from fringecal.simulate import control_points as syn

__all__ = ["PriorErrors", "RigObservations", "observe_rig", "rig_views", "link_errors", "RIGS"]

#: The three rigs of the labelling tests and benchmark.
RIGS = ("thesis", "three_scanner_row", "ring6")


@dataclass(frozen=True)
class PriorErrors:
    """Errors of the scanners' prior calibrations and of the plan.

    ``scale``: each scanner's scale is off by a fraction drawn from
    ``[scale_min, scale]`` with a random sign (about its origin); ``warp_mm``: RMS
    of a smooth quadratic distortion field over the scanner's measured centres;
    ``noise_mm``: per coordinate; ``plan_mm`` / ``plan_rad``: standard deviation of
    each planned pose's translation (per axis) and rotation (per angle).
    """

    scale: float = 0.006
    scale_min: float = 0.004
    warp_mm: float = 1.0
    noise_mm: float = 0.1
    plan_mm: float = 1.0
    plan_rad: float = 0.001


@dataclass(frozen=True)
class RigObservations:
    """Sphere fits as the labelling step reads them, with the truth.

    ``fits``: :class:`fringecal.schemas.SphereFitsTable` rows (empty ``sphere_id``) plus
    ``truth`` (the true sphere id, "" for a false candidate); ``planned``:
    measurement -> planned ``T_world_artefact``; ``own``: scanner -> true
    ``T_world_scanner`` of its own frame; ``scales``: scanner -> its prior's scale;
    ``true_links``: scanner -> true ``T_reference_scanner``; ``rms_mm``: RMS over
    views of the centres' distance from the CMM geometry after the best rigid fit.
    """

    name: str
    artefact: Artefact
    reference: str
    fits: pd.DataFrame
    planned: dict
    own: dict
    scales: dict
    true_links: dict
    rms_mm: float


def rig_views(name: str, seed: int = 0):
    """(rig, artefact, true poses, views) of one of :data:`RIGS`; ``views`` is a
    DataFrame (measurement, scanner, sphere_id) of the spheres each scanner sees.

    ``thesis``: table 6-8's two scanners and table 6-1's poses (six spheres per view);
    ``three_scanner_row``: :func:`~fringecal.simulate.control_points.three_scanner_truth`
    with its ``spheres_of`` masks (scanner1 sees only the triangle 1-3);
    ``ring6``: six scanners on a ring, ten random poses turned about the vertical, and
    a narrow field: a scanner sees the spheres within 450 mm of its optical axis (3-14
    spheres; views of fewer than three are dropped).
    """

    spheres_of = None
    if name == "thesis":
        rig, art, poses = syn.thesis_truth()
    elif name == "three_scanner_row":
        rig, art, poses, spheres_of = syn.three_scanner_truth()
    elif name == "ring6":
        rig, art = syn.ring_truth(6)
        poses = syn.random_poses(10, seed + 3)
    else:
        raise ValueError(f"unknown rig {name!r}; known: {list(RIGS)}")
    sim = syn.simulate_control_points(rig, art, poses, spacing_px=40, noise_eps1_mm=0, spheres_of=spheres_of)
    views = sim.control_points[["measurement", "scanner", "sphere_id"]].drop_duplicates().reset_index(drop=True)
    if name == "ring6":
        keep = []
        for r in views.itertuples():
            cam = rig.scanner(r.scanner).camera
            T = Frame.from_params(poses.set_index("measurement").loc[r.measurement, list(POSE_COLUMNS)].to_numpy(float))
            c = T.to_world(art.centres_of([r.sphere_id]))[0] - cam.pinhole
            axis = cam.R[2]
            keep.append(np.linalg.norm(c - (c @ axis) * axis) <= 450.0)
        views = views[np.array(keep)]
    n = views.groupby(["measurement", "scanner"])["sphere_id"].transform("size")
    views = views[n >= 3].reset_index(drop=True)
    return rig, art, poses, views


def _random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _quadratic(x):
    return np.stack([x[:, 0] ** 2, x[:, 1] ** 2, x[:, 2] ** 2, x[:, 0] * x[:, 1], x[:, 1] * x[:, 2],
                     x[:, 2] * x[:, 0]], axis=1)


def observe_rig(name: str, errors: PriorErrors | None = None, seed: int = 0, false_candidates: int = 0
                ) -> RigObservations:
    """Observe one of :data:`RIGS` through imperfect prior calibrations.

    ``false_candidates``: that many views (chosen at random) get one extra candidate
    near the artefact that is no sphere of it.
    """
    err = errors or PriorErrors()
    rng = np.random.default_rng(seed)
    rig, art, poses, views = rig_views(name, seed)
    true_pose = {str(r.measurement): Frame.from_params([getattr(r, c) for c in POSE_COLUMNS])
                 for r in poses.itertuples()}
    own, scales, warps = {}, {}, {}
    for sc in rig.scanners:
        own[sc.name] = Frame.from_matrix(_random_rotation(rng), sc.camera.pinhole)
        scales[sc.name] = 1 + rng.choice([-1, 1]) * rng.uniform(err.scale_min, err.scale)
    rows = []
    for sc in rig.scanners:
        v = views[views["scanner"] == sc.name]
        if v.empty:
            continue
        world = np.concatenate([true_pose[m].to_world(art.centres_of(g["sphere_id"]))
                                for m, g in v.groupby("measurement", sort=False)])
        local = own[sc.name].to_local(world)
        centre = local.mean(axis=0)
        B = rng.normal(size=(3, 6))
        w = _quadratic((local - centre) / 1000.0) @ B.T
        B *= err.warp_mm / np.sqrt(np.mean(np.sum(w**2, axis=1)))
        warps[sc.name] = (centre, B)
    false_at = set(rng.choice(len(views.groupby(["measurement", "scanner"])), false_candidates, replace=False)) \
        if false_candidates else set()
    sq = []
    for k, ((m, s), g) in enumerate(views.groupby(["measurement", "scanner"], sort=False)):
        world = true_pose[m].to_world(art.centres_of(g["sphere_id"]))
        truth = list(g["sphere_id"])
        if k in false_at:  # a ball joint or a stray reflection near the artefact
            world = np.vstack([world, true_pose[m].to_world(rng.uniform([-700, -100, -300], [100, 2000, 700]))])
            truth.append("")
        local = own[s].to_local(world)
        centre, B = warps[s]
        X = scales[s] * local + _quadratic((local - centre) / 1000.0) @ B.T + rng.normal(0, err.noise_mm, local.shape)
        order = rng.permutation(len(X))
        for j, i in enumerate(order):
            rows.append({"measurement": m, "scanner": s, "candidate": f"c{j}", "sphere_id": "",
                         "x_mm": X[i, 0], "y_mm": X[i, 1], "z_mm": X[i, 2], "radius_mm": 25.0 * scales[s],
                         "rms_mm": 0.02, "n_points": 500, "u_x_mm": 0.002, "u_y_mm": 0.002, "u_z_mm": 0.002,
                         "cap_angle_deg": 70.0, "coverage": 0.3, "n_rejected": 0, "truth": truth[i]})
        if truth.count("") == 0:
            Y = art.centres_of(truth)

            M, t = kabsch(Y, X)
            sq.append(np.mean(np.sum((Y @ M.T + t - X) ** 2, axis=1)))
    plan_frame = Frame.from_matrix(_random_rotation(rng), rng.uniform(-2000, 2000, 3))
    planned = {}
    for m, T in true_pose.items():
        dT = Frame(rng.normal(0, err.plan_mm, 3), np.zeros(3))
        R_err = rotation_matrix(*rng.normal(0, err.plan_rad, 3))
        c = T.to_world(art.centres.mean(axis=0)[None])[0]  # the hexapod turns about the artefact's middle
        turned = Frame.from_matrix(T.R @ R_err, R_err.T @ (T.t - c) + c)
        planned[m] = plan_frame.compose(dT.compose(turned))
    ref = rig.reference
    links = {s: own[ref].inverse().compose(own[s]) for s in own}
    return RigObservations(name, art, ref, pd.DataFrame(rows), planned, own, scales, links,
                           float(np.sqrt(np.mean(sq))))


def link_errors(obs: "RigObservations", res) -> tuple[float, float]:
    """Largest error of the links of a :class:`~fringecal.spheres.poses_and_links.LabelPoseLink`
    against the truth, where each scanner measures (mm) and in angle (rad); NaN without links."""
    if res.links is None:
        return float("nan"), float("nan")
    worst_mm = worst_rad = 0.0
    for s, link in res.links.links.items():
        pts = obs.fits.loc[obs.fits["scanner"] == s, ["x_mm", "y_mm", "z_mm"]].to_numpy(float) / obs.scales[s]
        true = obs.true_links[s]
        worst_mm = max(worst_mm, float(np.linalg.norm(link.frame.to_world(pts) - true.to_world(pts), axis=1).max()))
        worst_rad = max(worst_rad, link.frame.difference(true)[1])
    return worst_mm, worst_rad
