"""Simulated control points, exactly as a scanner would see them, without images.

For every measurement (an artefact pose T_world_artefact), every scanner of a truth rig
and every sphere in view: camera pixels on a regular grid over the sphere's image, the
camera ray's first intersection with that sphere, and the projector phases of the hit
point (``Sensor.project`` then ``measured``), plus Gaussian phase noise. A pixel is kept
only if

* its ray hits the sphere before any other sphere (spheres occlude each other; the rods
  are treated as absent),
* the hit point is lit: the projector sees it (no other sphere in the way, facing the
  projector, inside the SLM),
* it is not on the rim: the surface normal is within ``max_incidence_deg`` of both the
  camera and the projector directions (the control-point selection's rim exclusion).

The phase noise is sized so that alpha1 (epsilon-1) computed with the true parameters
has the requested RMS (the thesis reached 45 um): its standard deviation in rad is
``noise_eps1_mm / sqrt(mean(|d eps1 / d tau|^2))`` over the control points.

Also here: the thesis rig and poses as data, a three-scanner variant, a ring of any
number of scanners for benchmarks, and the start values used by tests (DLT from noisy
sphere centres; or the truth perturbed).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact, load_artefact
from fringecal.calibration.initial import initial_rig_from_dlt
from fringecal.calibration.model import POSE_COLUMNS
from fringecal.config import thesis_dir
from fringecal.frames import Frame
from fringecal.rig import Rig, Scanner, load_rig
from fringecal.rotation import angles_from_matrix, rotation_matrix
from fringecal.sensor import Sensor
from fringecal.spheres.pose import estimate_poses
from fringecal.triangulation import closest_approach

__all__ = [
    "SimulatedControlPoints",
    "simulate_control_points",
    "thesis_truth",
    "three_scanner_truth",
    "ring_truth",
    "random_poses",
    "perturbed_start",
    "dlt_start",
    "sphere_centre_observations",
    "write_run_inputs",
]


@dataclass(frozen=True)
class SimulatedControlPoints:
    """Simulated control points and the truth they came from.

    control_points : ControlPointsTable frame (measurement, scanner, sphere_id, u_px,
        v_px, tau_x_rad, tau_y_rad), with noisy phases
    tau_exact : ndarray (n, 2), the noise-free phases
    points_world : ndarray (n, 3), the true surface points
    tau_sigma_rad : float, standard deviation of the phase noise
    """

    rig: Rig
    artefact: Artefact
    poses: pd.DataFrame
    control_points: pd.DataFrame
    tau_exact: np.ndarray
    points_world: np.ndarray
    tau_sigma_rad: float


def _first_hits(o, d, centres, radii):
    """Ray parameter of the first intersection of rays o + t d (unit d, (k, 3)) with
    each sphere, (k, n_spheres); inf where missed or behind."""
    oc = o[:, None, :] - centres[None, :, :]
    b = np.einsum("kj,knj->kn", d, oc)
    c = np.einsum("knj,knj->kn", oc, oc) - radii[None, :] ** 2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    return np.where((disc > 0) & (t > 1e-9), t, np.inf)


def _segment_blocked(x, target, centres, radii, skip):
    """True where the segment x -> target (x (k, 3)) passes through a sphere other than ``skip`` (k,)."""
    d = target[None, :] - x
    length = np.linalg.norm(d, axis=1)
    d = d / length[:, None]
    oc = x[:, None, :] - centres[None, :, :]
    b = np.einsum("kj,knj->kn", d, oc)
    c = np.einsum("knj,knj->kn", oc, oc) - radii[None, :] ** 2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t1 = -b - np.sqrt(disc)
        t2 = -b + np.sqrt(disc)
    hit = (disc > 0) & (t2 > 1e-6) & (t1 < length[:, None])
    hit[np.arange(len(x)), skip] = False
    return hit.any(axis=1)


def _grid_over_sphere(cam: Sensor, centre, radius, spacing):
    """Grid pixels (k, 2) covering the image of one sphere (bounding box of its outline)."""
    o = cam.pinhole
    v = centre - o
    L = np.linalg.norm(v)
    if L <= radius:
        return np.zeros((0, 2))
    v /= L
    e1 = np.cross(v, [0.0, 0.0, 1.0] if abs(v[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v, e1)
    phi = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    # the outline is the tangent cone: half-angle asin(r/L); sample it slightly wide
    beta = np.arcsin(min(radius / L, 0.999)) * 1.05
    dirs = np.cos(beta) * v + np.sin(beta) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    xy = cam.project(o + dirs * L)
    if not np.all(np.isfinite(xy)):
        return np.zeros((0, 2))
    uv = cam.measured(xy)
    fmt = cam.format
    lo = np.maximum(np.floor(uv.min(0) / spacing) * spacing, 0)
    hi = np.minimum(np.ceil(uv.max(0)), [fmt.width_px - 1, fmt.height_px - 1])
    if np.any(hi < lo):
        return np.zeros((0, 2))
    us = np.arange(lo[0], hi[0] + 1, spacing)
    vs = np.arange(lo[1], hi[1] + 1, spacing)
    U, V = np.meshgrid(us, vs)
    return np.stack([U.ravel(), V.ravel()], axis=1).astype(float)


def _view(scanner: Scanner, centres, radii, spacing, cos_max, allowed=None):
    """Control points of one scanner on spheres at world ``centres``: (sphere, uv, X, tau)."""
    cam, prj = scanner.camera, scanner.projector
    out_s, out_uv, out_x = [], [], []
    for j in range(len(centres)):
        if allowed is not None and j not in allowed:
            continue
        uv = _grid_over_sphere(cam, centres[j], radii[j], spacing)
        if not len(uv):
            continue
        o, d = cam.rays(cam.image_mm(uv))
        o = np.broadcast_to(o, d.shape)
        t = _first_hits(o, d, centres, radii)
        first = np.argmin(t, axis=1)
        mine = (first == j) & np.isfinite(t[np.arange(len(t)), j])
        if not mine.any():
            continue
        uv, d, tj = uv[mine], d[mine], t[mine, j]
        X = cam.pinhole + tj[:, None] * d
        n = (X - centres[j]) / radii[j]
        to_prj = prj.pinhole - X
        to_prj /= np.linalg.norm(to_prj, axis=1, keepdims=True)
        keep = (np.einsum("kj,kj->k", n, -d) >= cos_max) & (np.einsum("kj,kj->k", n, to_prj) >= cos_max)
        keep &= ~_segment_blocked(X, prj.pinhole, centres, radii, np.full(len(X), j))
        xy = prj.project(X)
        keep &= np.all(np.isfinite(xy), axis=1) & prj.format.contains_mm(xy)
        out_s.append(np.full(int(keep.sum()), j))
        out_uv.append(uv[keep])
        out_x.append(X[keep])
    if not out_s:
        return np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 3)), np.zeros((0, 2))
    s = np.concatenate(out_s)
    X = np.concatenate(out_x)
    return s, np.concatenate(out_uv), X, prj.measured(prj.project(X))


def _eps1_phase_sensitivity(scanner: Scanner, uv, tau, h=1e-6):
    """|d eps1 / d tau|^2 per control point, (k,), by central differences."""
    cam, prj = scanner.camera, scanner.projector
    o1, d1 = cam.rays(cam.image_mm(uv))
    g2 = np.zeros(len(uv))
    for axis in range(2):
        e = np.zeros(2)
        e[axis] = h
        o2, dp = prj.rays(prj.image_mm(tau + e))
        _, ep = closest_approach(o1, d1, o2, dp)
        o2, dm = prj.rays(prj.image_mm(tau - e))
        _, em = closest_approach(o1, d1, o2, dm)
        g2 += ((ep - em) / (2 * h)) ** 2
    return g2


def simulate_control_points(rig: Rig, artefact: Artefact, poses: pd.DataFrame, spacing_px: int = 10,
                            max_incidence_deg: float = 70.0, noise_eps1_mm: float = 0.045,
                            rng: np.random.Generator | int | None = 0,
                            require_all_views: bool = False,
                            spheres_of: dict | None = None) -> SimulatedControlPoints:
    """Control points of every scanner of ``rig`` for every pose of ``poses``.

    Parameters
    ----------
    rig : Rig, the truth
    artefact : Artefact
    poses : DataFrame with ``measurement`` and ``tx_mm .. kappa_rad`` (T_world_artefact)
    spacing_px : grid spacing of camera pixels (section 6.4: 10 px)
    max_incidence_deg : rim exclusion, angle between surface normal and the camera and
        projector directions
    noise_eps1_mm : target RMS of epsilon-1 with the true parameters (0: no noise)
    rng : generator or seed
    require_all_views : raise if some scanner sees no sphere in some measurement
    spheres_of : optional dict scanner name -> sphere ids it may use (others are masked,
        e.g. to keep scanners' volumes from sharing any sphere)
    """
    rng = np.random.default_rng(rng)
    poses = poses.reset_index(drop=True)
    radii = artefact.radii
    cos_max = np.cos(np.radians(max_incidence_deg))
    rows, taus, xs, sens = [], [], [], []
    for _, p in poses.iterrows():
        T = Frame.from_params(p[list(POSE_COLUMNS)].to_numpy(float))
        centres = T.to_world(artefact.centres)
        for sc in rig.scanners:
            allowed = None if spheres_of is None else set(artefact.index(spheres_of[sc.name]))
            s, uv, X, tau = _view(sc, centres, radii, spacing_px, cos_max, allowed)
            if require_all_views and not len(s):
                raise ValueError(f"scanner {sc.name} sees no sphere in measurement {p['measurement']}")
            if not len(s):
                continue
            rows.append(pd.DataFrame({"measurement": str(p["measurement"]), "scanner": sc.name,
                                      "sphere_id": [artefact.ids[k] for k in s],
                                      "u_px": uv[:, 0], "v_px": uv[:, 1]}))
            taus.append(tau)
            xs.append(X)
            sens.append(_eps1_phase_sensitivity(sc, uv, tau) if noise_eps1_mm > 0 else np.zeros(len(s)))
    if not rows:
        raise ValueError("no scanner sees any sphere in any pose")
    cp = pd.concat(rows, ignore_index=True)
    tau = np.concatenate(taus)
    sigma = float(noise_eps1_mm / np.sqrt(np.mean(np.concatenate(sens)))) if noise_eps1_mm > 0 else 0.0
    noisy = tau + rng.normal(0.0, sigma, tau.shape) if sigma > 0 else tau.copy()
    noisy = np.clip(noisy, -np.pi, np.pi)
    cp["tau_x_rad"] = noisy[:, 0]
    cp["tau_y_rad"] = noisy[:, 1]
    return SimulatedControlPoints(rig, artefact, poses, cp, tau, np.concatenate(xs), sigma)


# -- rigs and poses ------------------------------------------------------------

def thesis_truth() -> tuple[Rig, Artefact, pd.DataFrame]:
    """The thesis rig (table 6-8), artefact (CMM set 2) and the 12 poses of table 6-1."""
    d = thesis_dir()
    rig = load_rig(d / "sensors_refined_table6-8.csv")
    art = load_artefact(d / "artefact_cmm2.csv")
    poses = pd.read_csv(d / "poses_scanner1_table6-1.csv", dtype={"measurement": str})
    return rig, art, poses[["measurement", *POSE_COLUMNS]]


def _moved_sensor(sensor: Sensor, name: str, T: Frame) -> Sensor:
    """``sensor`` carried rigidly by T (world -> world), renamed."""
    X0 = T.to_world(sensor.pinhole[None])[0]
    R = sensor.R @ T.R  # x' = R_s (R_T (X_new - t)) ... sensor axes carried along

    angles = angles_from_matrix(R, near=sensor.angles)
    params = np.array(sensor.params, copy=True)
    params[:3] = X0
    params[3:6] = angles
    return replace(sensor, name=name, params=params)


def _moved_scanner(sc: Scanner, name: str, cam: str, prj: str, T: Frame) -> Scanner:
    return Scanner(name, _moved_sensor(sc.camera, cam, T), _moved_sensor(sc.projector, prj, T))


def three_scanner_truth() -> tuple[Rig, Artefact, pd.DataFrame, dict]:
    """Three scanners side by side with non-overlapping volumes, and 12 poses.

    scanner1 is table 6-8's (the reference), scanner3 a copy of it shifted 980 mm to the
    right (+x), scanner2 table 6-8's scanner two shifted 490 mm to the right, so the three
    cameras look at three neighbouring regions about 980 mm apart; the poses are table
    6-1's shifted by +736 mm in x, so that scanner3 sees the artefact's end with spheres
    4-9, scanner1 its middle row 1-3 and scanner2 the far end 10-15. The camera fields are
    ~950 mm wide at 3.3 m, so neighbouring fields touch; the returned ``spheres_of``
    (scanner -> sphere ids) masks each scanner to its own spheres, so no sphere is ever
    seen by two scanners and only the shared poses link them.
    """
    rig, art, poses = thesis_truth()
    s1, s2 = rig.scanners
    s2m = _moved_scanner(s2, "scanner2", "C2", "P2", Frame([490.0, 0, 0], [0, 0, 0]))
    s3 = _moved_scanner(s1, "scanner3", "C3", "P3", Frame([980.0, 0, 0], [0, 0, 0]))
    rig3 = Rig((s1, s2m, s3), "scanner1")
    poses = poses.copy()
    poses["tx_mm"] = poses["tx_mm"] + 736.0
    spheres_of = {"scanner3": [str(i) for i in range(4, 10)], "scanner1": ["1", "2", "3"],
                  "scanner2": [str(i) for i in range(10, 16)]}
    return rig3, art, poses, spheres_of


def ring_truth(n_scanners: int = 8, radius_mm: float = 2950.0) -> tuple[Rig, Artefact]:
    """``n_scanners`` copies of the thesis scanners on a horizontal ring, all looking at
    the centre of the thesis measurement volume (for benchmarks: overlapping volumes).

    The thesis scanners look along world -z with y up; copy k is rotated by 2 pi k / n about
    the vertical axis through the volume centre (alternating scanner one and two).
    """
    rig, art, poses = thesis_truth()
    centre = np.array([-50.0, 80.0, -650.0])
    scanners = []
    for k in range(n_scanners):
        src = rig.scanners[k % 2]
        cam_target = src.camera.pinhole + src.camera.R[2] * (src.camera.pinhole[2] - centre[2]) / -src.camera.R[2, 2]
        shift = Frame(centre - cam_target, [0, 0, 0])
        # rotation about world y through the centre: x_new = Ry (x - centre) + centre
        a = 2 * np.pi * k / n_scanners
        # Frame with x_world_new = R^T x + t: choose R = rotation by -a about y (eq. 2-6 phi)
        rot = Frame(centre - rotation_matrix(0.0, a, 0.0).T @ centre, [0.0, a, 0.0])
        moved = _moved_scanner(src, f"scanner{k + 1}", f"C{k + 1}", f"P{k + 1}", shift)
        moved = _moved_scanner(moved, moved.name, moved.camera.name, moved.projector.name, rot)
        scanners.append(moved)
    return Rig(tuple(scanners), "scanner1"), art


def random_poses(n: int, rng, centre=(-50.0, 80.0, -650.0), spread_mm=(150.0, 60.0, 200.0),
                 base=(-1.570, -0.001, 1.64), spin_rad=np.pi) -> pd.DataFrame:
    """``n`` artefact poses around ``centre``: the thesis orientation turned about the
    vertical by up to +-``spin_rad``, centred so that the artefact's middle sits near ``centre``."""
    rng = np.random.default_rng(rng)
    _, art, _ = thesis_truth()
    mid = art.centres.mean(axis=0)
    rows = []
    for i in range(n):
        spin = rng.uniform(-spin_rad, spin_rad)
        T0 = Frame([0, 0, 0], base)
        Ry = rotation_matrix(0.0, spin, 0.0)
        R = T0.R @ Ry.T  # world rotation about y applied after the base pose
        offset = np.asarray(centre) + rng.uniform(-1, 1, 3) * np.asarray(spread_mm)
        t = offset - R.T @ mid
        f = Frame.from_matrix(R, t, near=base)
        rows.append((f"m{i + 1:03d}", *f.params))
    return pd.DataFrame(rows, columns=["measurement", *POSE_COLUMNS])


# -- start values ----------------------------------------------------------------

def perturbed_start(rig: Rig, poses: np.ndarray, rng, length_mm: float = 5.0, angle_rad: float = 0.02,
                    internal_mm: float = 0.2, zero_distortion: bool = True) -> tuple[Rig, np.ndarray]:
    """The truth moved by +-``length_mm`` (pinholes, pose translations), +-``angle_rad``
    (sensor and pose angles) and +-``internal_mm`` (xi_h, eta_h, c), random signs; free
    parameters only; distortion set to zero (as a DLT start would have it).

    0.2 mm on the internal parameters is about what the DLT gives (section 6.3); it matters
    for the reference camera only when the adjustment re-initialises from the data."""
    rng = np.random.default_rng(rng)
    p = rig.params.copy()
    sign = lambda shape: rng.choice([-1.0, 1.0], size=shape)  # noqa: E731
    step = np.zeros_like(p)
    step[:, :3] = length_mm * sign((len(p), 3))
    step[:, 3:6] = angle_rad * sign((len(p), 3))
    step[:, 6:9] = internal_mm * sign((len(p), 3))
    p = np.where(rig.free, p + step, p)
    if zero_distortion:
        p[:, 9:] = np.where(rig.free[:, 9:], 0.0, p[:, 9:])
    poses = np.asarray(poses, float).copy()
    poses[:, :3] += length_mm * sign((len(poses), 3))
    poses[:, 3:] += angle_rad * sign((len(poses), 3))
    return rig.with_params(p), poses


def sphere_centre_observations(sim: SimulatedControlPoints) -> pd.DataFrame:
    """(measurement, scanner, sphere_id) groups that carry control points, with the true
    world centre of each sphere."""
    groups = sim.control_points[["measurement", "scanner", "sphere_id"]].drop_duplicates()
    rows = []
    for _, p in sim.poses.iterrows():
        T = Frame.from_params(p[list(POSE_COLUMNS)].to_numpy(float))
        g = groups[groups["measurement"] == str(p["measurement"])]
        w = T.to_world(sim.artefact.centres_of(g["sphere_id"]))
        rows.append(g.assign(x_mm=w[:, 0], y_mm=w[:, 1], z_mm=w[:, 2]))
    return pd.concat(rows, ignore_index=True)


def dlt_start(sim: SimulatedControlPoints, rng, centre_noise_mm: float = 0.05,
              image_noise_mm: float = 0.002) -> tuple[Rig, pd.DataFrame]:
    """Start values as the thesis obtained them (section 6.3), from simulated data.

    Sphere centres the scanner saw (true pose applied to the CMM centres, plus Gaussian
    noise of ``centre_noise_mm`` per coordinate, as a sphere fit would give them) and
    their image coordinates in each sensor (the true centre projected with the true
    sensor, plus ``image_noise_mm``) give each sensor's nine undistorted parameters by the
    DLT. The reference camera's external parameters are set to the truth: they define the
    world frame (the gauge), which a real calibration takes from that camera's prior
    calibration. The start poses are the SVD registrations of the noisy centres seen by
    all scanners against the artefact (fringecal.spheres.pose).

    Returns the start rig (free flags of the truth rig) and a PosePlanTable frame.
    """

    rng = np.random.default_rng(rng)
    obs = sphere_centre_observations(sim)
    noisy = obs[["x_mm", "y_mm", "z_mm"]].to_numpy(float) + rng.normal(0, centre_noise_mm, (len(obs), 3))
    obs = obs.assign(x_mm=noisy[:, 0], y_mm=noisy[:, 1], z_mm=noisy[:, 2])
    points, images = {}, {}
    truth_world = sphere_centre_observations(sim)[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    for sc in sim.rig.scanners:
        sel = (obs["scanner"] == sc.name).to_numpy()
        for sensor in sc.sensors:
            xy = sensor.project(truth_world[sel]) + rng.normal(0, image_noise_mm, (int(sel.sum()), 2))
            points[sensor.name] = noisy[sel]
            images[sensor.name] = xy
    rig, _ = initial_rig_from_dlt(sim.rig, points, images)
    centres = obs.groupby(["measurement", "sphere_id"], as_index=False, sort=False)[["x_mm", "y_mm", "z_mm"]].mean()
    res = estimate_poses(centres.assign(scanner="all"), sim.artefact)
    if len(res.skipped):
        raise ValueError(f"no start pose for {res.skipped.to_dict('records')}")
    return rig, res.poses[["measurement", *POSE_COLUMNS]].reset_index(drop=True)


def write_run_inputs(rd, sim: SimulatedControlPoints, start_rig: Rig, start_poses: pd.DataFrame) -> None:
    """Write the bundle adjustment's inputs into a run directory
    (:class:`fringecal.rundir.RunDir`) from a simulation: artefact, control points,
    start poses and start sensors."""
    rd.artefact.save(sim.artefact)
    rd.control_points.save(sim.control_points)
    rd.poses_initial.save(start_poses[["measurement", *POSE_COLUMNS]])
    rd.sensors_initial.save(start_rig)
