"""Where to put the ball-bar: verification positions planned for any rig.

The thesis verified its two scanners with nine hand-chosen positions, sphere A in
scanner one's volume and B in scanner two's (table 6-9). For any rig the question is
the same -- is every scanner, and is every link between neighbouring scanners, as
good as the calibration says? -- so the plan covers:

- every pair of **neighbouring scanners** with ``per_pair`` positions that put
  sphere A in one scanner's measurement volume and B in the other's (a length that
  crosses the link);
- every **scanner** with ``per_scanner`` positions that put both spheres in its own
  volume, where the bar fits into it (a thesis-sized scanner's field, ~0.95 m, is
  shorter than a 1 m bar, but its diagonal through depth may hold it).

Decisions
---------
- A scanner's **measurement volume** (:class:`MeasurementVolume`) is where its
  calibration has data: sphere centres whose sphere image lies wholly inside the
  camera image (with ``margin`` times its image radius) and inside the projector's
  field, at a depth along the camera axis within the range the artefact's spheres
  covered in that scanner during calibration, and with its whole image inside the
  region of each image the calibration observed (:mod:`fringecal.lens.observed_region`;
  beyond it the model extrapolates). It comes from the calibrated run
  (:func:`volumes_from_run`: calibrated sensors and poses, spheres with control
  points, the calibration's observed regions) or, in a simulation, from the true rig
  and the planned poses (the regions predicted from the artefact's sphere images,
  :func:`fringecal.simulate.source.predicted_regions`).
- **Neighbours** are the edges of the Gabriel graph of the scanners' positions (the
  midpoint of camera and projector): two scanners are neighbours when no third lies
  inside the sphere that has them as diameter. A row gives consecutive pairs, a ring
  adjacent pairs, two scanners one pair.
- **Candidates** are drawn at random inside the volumes (a pixel and a depth in
  range), sphere B at the bar's length from A in the direction of a point drawn in
  the other volume; a candidate counts when both spheres are inside their volumes.
  A candidate is refused when the bar runs within ``min_view_angle_deg`` (60 deg) of
  a measuring sensor's line of sight to a sphere: the rod or the other sphere would
  hide the cap. The positions kept are spread by farthest-point selection over (A, B), starting
  from the candidate nearest the middle of the feasible set: varied heights, depths
  and directions, as VDI/VDE 2634 part 2 asks of its length measurements.
- A pair or scanner for which no candidate is found inside the observed regions is
  planned in the fields alone and named in :attr:`VerificationPlan.beyond_region` with
  the numbers (how far apart sphere centres inside the regions can be, against the
  bar's length); one for which none is found at all in :attr:`VerificationPlan.uncovered`,
  never silently dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import combinations

import numpy as np
import pandas as pd

from fringecal.frames import Frame, frames_from_rows
from fringecal.rig import Rig
from fringecal.verification.ballbar import BallBarPosition, frame_along

__all__ = ["MeasurementVolume", "VerificationPlan", "neighbours", "volumes_from_observations", "volumes_from_run",
           "plan_positions", "positions_table"]


@dataclass(frozen=True)
class MeasurementVolume:
    """Where one scanner measures a sphere of ``radius_mm``: inside both fields and in
    ``depth_range_mm`` along the camera axis, and, where ``regions`` gives the camera's
    and the projector's observed region (:class:`~fringecal.lens.observed_region.ObservedRegion`,
    None: not known), with the sphere's whole image inside each."""

    scanner: str
    camera: object
    projector: object
    depth_range_mm: tuple[float, float]
    radius_mm: float
    margin: float = 1.5
    regions: tuple = (None, None)

    def contains(self, points) -> np.ndarray:
        """Whether each sphere centre (n, 3) lies in the volume, shape (n,)."""
        X = np.atleast_2d(np.asarray(points, float))
        depth = self.camera.to_sensor(X)[:, 2]
        ok = (depth >= self.depth_range_mm[0]) & (depth <= self.depth_range_mm[1])
        for sensor, region in zip((self.camera, self.projector), self.regions):
            z = np.maximum(sensor.to_sensor(X)[:, 2], self.radius_mm)
            ok &= sensor.in_view(X, self.margin * sensor.c * self.radius_mm / z)
            if region is not None:  # the image disc (radius c r / z) inside what the calibration observed
                ok &= region.contains_disc(sensor.project(X), sensor.c * self.radius_mm / z)
        return ok

    def sample(self, n: int, rng) -> np.ndarray:
        """``n`` random points (n, 3) of the camera's field within the depth range
        (not all inside the volume: filter with :meth:`contains`)."""
        f = self.camera.format
        uv = rng.uniform(-0.5, 0.5, (n, 2)) * [f.width_mm, f.height_mm]
        origin, direction = self.camera.rays(uv)
        direction = direction / np.linalg.norm(direction, axis=1, keepdims=True)
        axis = self.camera.R[2]
        depth = rng.uniform(*self.depth_range_mm, n)
        cos = direction @ axis
        return origin + direction * (depth / np.where(np.abs(cos) > 1e-9, cos, 1e-9))[:, None]


def neighbours(rig: Rig) -> list[tuple[str, str]]:
    """Pairs of neighbouring scanners: the Gabriel graph of the scanners' positions."""
    names = [s.name for s in rig.scanners]
    P = np.array([(s.camera.pinhole + s.projector.pinhole) / 2 for s in rig.scanners])
    out = []
    for i, j in combinations(range(len(names)), 2):
        mid, r2 = (P[i] + P[j]) / 2, np.sum((P[i] - P[j]) ** 2) / 4
        others = [k for k in range(len(names)) if k not in (i, j)]
        if all(np.sum((P[k] - mid) ** 2) > r2 for k in others):
            out.append((names[i], names[j]))
    return out


def volumes_from_observations(rig: Rig, observations: pd.DataFrame, poses: dict[str, Frame], artefact,
                              margin: float = 1.5, regions: dict | None = None) -> dict[str, MeasurementVolume]:
    """Each scanner's volume from the artefact spheres it measured.

    Parameters
    ----------
    rig : Rig
        Sensors in the frame of ``poses``.
    observations : DataFrame
        measurement, scanner, sphere_id: which sphere each scanner measured where.
    poses : dict measurement -> Frame
        ``T_world_artefact``.
    artefact : Artefact
        The CMM table (centres; its smallest radius sizes the margins).
    regions : dict sensor name -> ObservedRegion, optional
        Where each sensor's image was observed (the calibration's, or predicted from
        the poses): a sphere counts only with its whole image inside them.
    """
    radius = float(np.min(artefact.diameters)) / 2
    out = {}
    for s in rig.scanners:
        obs = observations[observations["scanner"] == s.name]
        if obs.empty:
            continue
        X = np.concatenate([poses[str(m)].to_world(artefact.centres_of(g["sphere_id"].astype(str)))
                            for m, g in obs.groupby("measurement") if str(m) in poses])
        depth = s.camera.to_sensor(X)[:, 2]
        out[s.name] = MeasurementVolume(s.name, s.camera, s.projector, (float(depth.min()), float(depth.max())),
                                        radius, margin, tuple((regions or {}).get(x.name) for x in s.sensors))
    return out


def volumes_from_run(rd, margin: float = 1.5) -> dict[str, MeasurementVolume]:
    """The measurement volumes of a calibrated run directory: calibrated sensors and
    poses, the spheres that gave control points, and the observed regions of the
    calibration (none known: the whole fields)."""
    from fringecal.calibration.file import read_calibration  # lazy: numba loads when a calibration is read

    cps = rd.control_points.load()
    observations = cps[["measurement", "scanner", "sphere_id"]].drop_duplicates()
    cal = read_calibration(rd.calibration.path)
    return volumes_from_observations(cal.rig, observations, frames_from_rows(rd.poses_calibrated.load()),
                                     rd.artefact.load(), margin, cal.observed_regions)


@dataclass(frozen=True)
class VerificationPlan:
    """Planned positions (``scanner_of``: the volume each sphere was planned in) and
    what could not be covered."""

    positions: list
    pairs: list
    uncovered: list = field(default_factory=list)
    # why a pair's or scanner's positions leave the observed regions, with the numbers
    # (the bar fits its volumes only beyond them); empty when every sphere image is inside
    beyond_region: list = field(default_factory=list)


def _spread(candidates: np.ndarray, k: int) -> list[int]:
    """Indices of ``k`` rows of ``candidates`` spread by farthest-point selection."""
    first = int(np.argmin(np.sum((candidates - candidates.mean(0)) ** 2, axis=1)))
    chosen = [first]
    d = np.sum((candidates - candidates[first]) ** 2, axis=1)
    while len(chosen) < min(k, len(candidates)):
        nxt = int(np.argmax(d))
        chosen.append(nxt)
        d = np.minimum(d, np.sum((candidates - candidates[nxt]) ** 2, axis=1))
    return chosen


def _clear(volume: MeasurementVolume, X: np.ndarray, along: np.ndarray, min_angle_deg: float) -> np.ndarray:
    """Whether the bar (unit directions ``along`` from the spheres X to the other
    sphere) stays at least ``min_angle_deg`` off both sensors' lines of sight, so that
    neither the rod nor the other sphere hides the sphere's cap."""
    ok = np.ones(len(X), bool)
    for sensor in (volume.camera, volume.projector):
        sight = sensor.pinhole - X
        cos = np.sum(sight * along, axis=1) / np.linalg.norm(sight, axis=1)
        ok &= cos <= np.cos(np.radians(min_angle_deg))
    return ok


def _candidates(va: MeasurementVolume, vb: MeasurementVolume, length: float, n: int, rng,
                min_angle_deg: float) -> np.ndarray:
    A = va.sample(n, rng)
    A = A[va.contains(A)]
    if not len(A):
        return np.empty((0, 6))
    toward = vb.sample(len(A), rng)
    d = toward - A
    u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    B = A + length * u
    keep = vb.contains(B) & _clear(va, A, u, min_angle_deg) & _clear(vb, B, -u, min_angle_deg)
    return np.hstack([A[keep], B[keep]])


def plan_positions(rig: Rig, volumes: dict[str, MeasurementVolume], length_mm: float, per_pair: int = 3,
                   per_scanner: int = 2, samples: int = 20000, seed: int = 0,
                   min_view_angle_deg: float = 60.0) -> VerificationPlan:
    """Ball-bar positions covering every scanner and every pair of neighbouring scanners.

    Parameters
    ----------
    rig : Rig
        The rig (for the neighbours).
    volumes : dict scanner -> MeasurementVolume
    length_mm : float
        The bar's centre distance (A to B).
    per_pair, per_scanner : int
        Positions per neighbouring pair (A in one volume, B in the other) and per
        scanner (both spheres in its volume, where the bar fits).
    samples : int
        Random candidates drawn per pair and scanner.
    min_view_angle_deg : float
        Least angle between the bar and the lines of sight of the sensors that measure
        a sphere (the rod and the other sphere would hide its cap).

    Returns
    -------
    VerificationPlan
        Positions named ``v01, v02, ...``: pairs first (in rig order), then scanners.
    """
    rng = np.random.default_rng(seed)
    pairs = [(a, b) for a, b in neighbours(rig) if a in volumes and b in volumes]
    planned, uncovered = [], []
    jobs = [((a, b), per_pair) for a, b in pairs] + [((s, s), per_scanner) for s in volumes]
    beyond = []
    for (a, b), k in jobs:
        if k <= 0:
            continue
        cand = _candidates(volumes[a], volumes[b], length_mm, samples, rng, min_view_angle_deg)
        if not len(cand) and any(r is not None for v in (volumes[a], volumes[b]) for r in v.regions):
            # the bar fits no place inside the observed regions: place it in the fields, and say why
            beyond.append(_why_beyond(volumes[a], volumes[b], length_mm, rng))
            fields = [replace(v, regions=(None, None)) for v in (volumes[a], volumes[b])]
            cand = _candidates(*fields, length_mm, samples, rng, min_view_angle_deg)
        if not len(cand):
            uncovered.append(f"{a}-{b}" if a != b else a)
            continue
        for i in _spread(cand / length_mm, k):
            planned.append((cand[i, :3], cand[i, 3:], {"A": a, "B": b}))
    covered = {s for _, _, who in planned for s in who.values()}
    uncovered += [f"{s} (no position at all)" for s in volumes if s not in covered and s not in uncovered]
    positions = [BallBarPosition(f"v{i + 1:02d}", frame_along(A, B), who) for i, (A, B, who) in enumerate(planned)]
    return VerificationPlan(positions, pairs, uncovered, beyond)


def _why_beyond(va: MeasurementVolume, vb: MeasurementVolume, length_mm: float, rng, n: int = 20000) -> str:
    """Why no ball-bar position fits inside the observed regions, in numbers: the
    distances between sphere centres inside them (A in ``va``, B in ``vb``) against the
    bar's length."""
    A, B = (v.sample(n, rng) for v in (va, vb))
    A, B = A[va.contains(A)][:1500], B[vb.contains(B)][:1500]
    who = va.scanner if va is vb else f"{va.scanner}-{vb.scanner}"
    if not len(A) or not len(B):
        return f"{who}: no sphere image fits inside the observed regions at all"
    d = np.linalg.norm(A[:, None] - B[None], axis=-1)
    return (f"{who}: inside the observed regions sphere centres lie {d.min():.0f}-{d.max():.0f} mm apart and the "
            f"bar is {length_mm:.0f} mm (or would hide a cap): placed in the fields, partly beyond the regions")


def positions_table(positions: list, ballbar) -> pd.DataFrame:
    """The positions as a centres table (measurement, scanner, sphere_id, x_mm, y_mm,
    z_mm: thesis table 6-9's layout), ``scanner`` the volume each sphere is planned in."""
    rows = []
    for p in positions:
        X = p.T_world_ballbar.to_world(ballbar.centres[:2])
        for sid, x in zip(ballbar.ids[:2], X):
            rows.append({"measurement": p.name, "scanner": p.scanner_of.get(sid, ""), "sphere_id": sid,
                         "x_mm": x[0], "y_mm": x[1], "z_mm": x[2]})
    return pd.DataFrame(rows, columns=["measurement", "scanner", "sphere_id", "x_mm", "y_mm", "z_mm"])
