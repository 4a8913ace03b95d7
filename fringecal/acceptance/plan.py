"""Where to put the acceptance test's objects: positions planned inside each scanner's
measurement volume (VDI/VDE 2634 part 2 tests one scanner's volume at a time).

:func:`plan_acceptance` returns one row per position (``measurement`` = position name
``<test>-<k>-<nn>``, k the 1-based scanner index in rig order, nn = 01, 02, ...), the
``test`` (sphere, dumbbell, flat), the ``scanner`` that records it and the object's
placement ``T_world_<object>`` (tx_mm .. kappa_rad), with the object frames of the
acceptance design: the sphere's frame has its centre as origin (rotation identity),
the dumbbell's has sphere A at the origin and B at (length_mm, 0, 0), the flat's has
the centre of its measured face as origin, +z the face's outward normal, x along its
length and y along its width.

Decisions
---------
- **Volumes** are :class:`~fringecal.verification.plan.MeasurementVolume` (both fields and
  the calibrated depth range): in a simulation from the true rig and the planned
  poses, for a calibrated run from :func:`~fringecal.verification.plan.volumes_from_run`.
  A volume is resized to the sphere being placed (``radius_mm``), so that its whole
  image lies inside both fields with the volume's margin.
- **Sphere** (P_F, P_S): ``samples`` random candidates of the volume (a pixel and a
  depth), the ones the volume contains spread by farthest-point selection starting
  from the candidate nearest their mean: the first position is in the middle, the
  next ones at the corners and faces of the volume, near and far.
- **Dumbbell** (SD): the guideline's seven directions, four along the space diagonals
  and three along face diagonals (x-y, x-z, y-z) of a box in the scanner's **camera
  frame** (x, y across the image, z the depth along the optical axis), by
  :func:`fringecal.verification.lengths.seven_ballbar_positions`. The box is the part of the
  volume around its centre: the centre is the mean of the contained candidates
  (uniform over image and depth), each half size the distance from the centre to the
  volume's boundary along that camera axis. The bar (its certified length) is
  centred at the box's centre. A direction whose bar runs within
  ``min_view_angle_deg`` (60 deg) of the camera's or projector's line of sight to
  either sphere is tilted toward the image plane (its depth component shrunk, its
  direction across the image kept) in 0.5 deg steps until it is not: the rod or the
  other sphere would otherwise hide that sphere's cap. With the thesis rig's volumes
  (about 0.9 x 0.9 x 1.2 m) every space diagonal and the two face diagonals through
  depth are tilted, to 13-26 deg out of the image plane (47 deg untilted); the x-y
  face diagonal then lies 14-26 deg from the two space diagonals over the same
  image diagonal. ``count`` < 7 takes the first ``count`` directions
  (the space diagonals first).
- **Flat** (F): six positions [U: the guideline asks for about six and leaves the
  arrangement to the user], the face's length along an image diagonal of the camera
  (the longest extent of the field), the face's normal along the bisector of the
  directions from its centre to the camera and the projector, then: (1) facing the
  scanner as near as it fits, (2) facing as far as it fits, (3, 4) tilted by
  +-``flat_tilt_deg`` (30 deg) about its length axis, (5, 6) turned along the other
  image diagonal and tilted +-30 deg about its width axis; (3)-(6) in the middle of
  the depths where they fit. The face's centre moves along the line from the camera
  through the volume's centre. A position fits when a 5 x 3 grid of points of the
  face (corners, edge midpoints, centre) lies inside the camera's and the
  projector's fields (``field_margin`` of the format's shorter side from the edges),
  within the volume's depth range and is seen by both at incidence below
  ``max_incidence_deg`` (60 deg). A seventh and further positions are not defined.
- **Reports, never silent drops**: a scanner without a volume, a test with fewer
  positions than asked (a dumbbell direction that does not fit the volume or cannot
  be tilted clear, a flat position that fits at no depth) are listed in
  :attr:`AcceptancePlan.uncovered`, one line each. Callers decide: the simulation
  refuses the config (:mod:`fringecal.simulate.source`).
- **Deterministic**: each scanner and test draws from its own generator
  (``seed``, scanner index, test), so adding a scanner or a test leaves the others'
  positions unchanged.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numpy as np
import pandas as pd

from fringecal.frames import POSE_COLUMNS, Frame
from fringecal.rig import Rig
from fringecal.verification.ballbar import frame_along
from fringecal.verification.lengths import seven_ballbar_positions
from fringecal.verification.plan import MeasurementVolume, _clear, _spread

__all__ = ["TESTS", "FLAT_POSITIONS", "AcceptancePlan", "plan_acceptance", "sphere_centres", "volume_box",
           "dumbbell_bars", "flat_frame", "flat_face_points", "flat_fits", "position_name", "PLAN_COLUMNS"]

#: The acceptance tests that need positions, in planning order.
TESTS = ("sphere", "dumbbell", "flat")

#: Columns of the plan: position, test, scanner and ``T_world_<object>``.
PLAN_COLUMNS = ("measurement", "test", "scanner", *POSE_COLUMNS)

#: The flat's positions: (label, image diagonal 0 or 1, tilt axis, tilt sign, depth).
FLAT_POSITIONS = (
    ("facing, near", 0, None, 0, "near"),
    ("facing, far", 0, None, 0, "far"),
    ("tilted + about its length", 0, "length", 1, "middle"),
    ("tilted - about its length", 0, "length", -1, "middle"),
    ("other diagonal, tilted + about its width", 1, "width", 1, "middle"),
    ("other diagonal, tilted - about its width", 1, "width", -1, "middle"),
)


class AcceptancePlan(NamedTuple):
    """``positions``: one row per position (:data:`PLAN_COLUMNS`); ``uncovered``: what
    could not be planned, one line each (empty when every position asked for fits)."""

    positions: pd.DataFrame
    uncovered: list


def position_name(test: str, scanner_index: int, n: int) -> str:
    """``<test>-<k>-<nn>`` (k 1-based scanner index, n 1-based position).

    >>> position_name("dumbbell", 2, 7)
    'dumbbell-2-07'
    """
    return f"{test}-{scanner_index}-{n:02d}"


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _candidates(volume: MeasurementVolume, rng, samples: int) -> np.ndarray:
    X = volume.sample(samples, rng)
    return X[volume.contains(X)]


def sphere_centres(volume: MeasurementVolume, radius_mm: float, n: int, rng, samples: int = 20000) -> np.ndarray:
    """Up to ``n`` centres (m, 3) of a sphere of ``radius_mm`` spread over ``volume``
    (farthest-point selection from the candidate nearest the middle); fewer when the
    volume holds fewer candidates."""
    X = _candidates(replace(volume, radius_mm=radius_mm), rng, samples)
    return X[_spread(X, n)] if len(X) and n > 0 else np.empty((0, 3))


def _reach(volume: MeasurementVolume, start: np.ndarray, direction: np.ndarray, max_mm: float,
           step_mm: float = 1.0) -> float:
    """How far (mm) from ``start`` along ``direction`` the volume goes on (the last
    contained point before the first that is not)."""
    t = np.arange(0.0, max_mm + step_mm, step_mm)
    inside = volume.contains(start + t[:, None] * direction)
    out = np.flatnonzero(~inside)
    return float(t[out[0] - 1]) if len(out) and out[0] > 0 else (0.0 if len(out) else float(t[-1]))


def volume_box(volume: MeasurementVolume, rng, samples: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """The box of the volume around its centre, in the camera frame.

    Returns
    -------
    centre_world : ndarray, shape (3,)
        The mean of the contained candidates (or the contained candidate nearest it,
        should the mean fall outside).
    half_size : ndarray, shape (3,)
        Per camera axis (x, y across the image, z along the optical axis), the
        distance from the centre to the volume's boundary, the smaller of the two
        ways; zeros when the volume holds no candidate.
    """
    X = _candidates(volume, rng, samples)
    if not len(X):
        return np.full(3, np.nan), np.zeros(3)
    centre = X.mean(0)
    if not volume.contains(centre[None])[0]:
        centre = X[np.argmin(np.sum((X - centre) ** 2, axis=1))]
    span = float(volume.depth_range_mm[1] - volume.depth_range_mm[0]) + 4 * volume.radius_mm
    axes = volume.camera.R  # rows: camera axes in the world
    half = np.array([min(_reach(volume, centre, a, span), _reach(volume, centre, -a, span)) for a in axes])
    return centre, half


def _tilted_clear(volume: MeasurementVolume, centre: np.ndarray, u: np.ndarray, length: float,
                  min_angle_deg: float, step_deg: float = 0.5) -> tuple[np.ndarray | None, float]:
    """The direction nearest ``u`` (tilted toward the camera's image plane, its
    direction across the image kept) along which the bar centred at ``centre`` keeps
    ``min_angle_deg`` off every line of sight to both spheres; (None, nan) if even
    the image plane does not. Also returns the tilt (deg) it took."""
    axis = volume.camera.R[2]
    along = u @ axis
    across = u - along * axis
    if np.linalg.norm(across) < 1e-9:  # along the optical axis: tilt toward the image x axis
        across = volume.camera.R[0]
    across = _unit(across)
    elevation = float(np.degrees(np.arcsin(np.clip(abs(along), 0.0, 1.0))))
    sign = 1.0 if along >= 0 else -1.0
    for el in np.arange(elevation, -step_deg / 2, -step_deg):
        el = max(float(el), 0.0)
        v = np.cos(np.radians(el)) * across + sign * np.sin(np.radians(el)) * axis
        A, B = centre - v * length / 2, centre + v * length / 2
        if _clear(volume, A[None], v[None], min_angle_deg)[0] and _clear(volume, B[None], -v[None], min_angle_deg)[0]:
            return v, elevation - el
    return None, float("nan")


def dumbbell_bars(volume: MeasurementVolume, length_mm: float, radius_mm: float, rng, samples: int = 20000,
                  min_view_angle_deg: float = 60.0) -> list:
    """The seven dumbbell positions of one volume.

    Returns
    -------
    list of 7 (A, B, tilt_deg, problem)
        Sphere centres A, B (3,) (None when the direction is not usable), the tilt
        toward the image plane it took (deg), and why it is not usable ("" if it is).
    """
    vol = replace(volume, radius_mm=radius_mm)
    centre, half = volume_box(vol, rng, samples)
    if not np.all(half > 0):
        return [(None, None, float("nan"), "the volume holds no sphere of the dumbbell")] * 7
    R = vol.camera.R
    c = R @ (centre - vol.camera.pinhole)
    bars = seven_ballbar_positions(c - half, c + half, 1.0, directions="face")
    out = []
    for a, b in bars:
        u = (b - a) @ R  # camera frame -> world (x_world = R^T x_camera)
        v, tilt = _tilted_clear(vol, centre, u, length_mm, min_view_angle_deg)
        if v is None:
            out.append((None, None, tilt, f"no tilt keeps it {min_view_angle_deg:g} deg off the lines of sight"))
            continue
        A, B = centre - v * length_mm / 2, centre + v * length_mm / 2
        inside = vol.contains(np.array([A, B]))
        if not inside.all():
            out.append((None, None, tilt, f"sphere {'A' if not inside[0] else 'B'} of the {length_mm:g} mm bar "
                                          "leaves the volume"))
            continue
        out.append((A, B, tilt, ""))
    return out


def _diagonal(camera, which: int) -> np.ndarray:
    """Unit world direction of the camera image's diagonal ``which`` (0: +x+y, 1: +x-y)."""
    f = camera.format
    d = np.array([f.width_mm, f.height_mm if which == 0 else -f.height_mm, 0.0])
    return _unit(d @ camera.R)


def _flat_axes(volume: MeasurementVolume, centres: np.ndarray, diagonal: int, tilt_axis: str | None,
               tilt_rad: float) -> np.ndarray:
    """The flat's axes (m, 3, 3) (rows x, y, z in the world) at face centres (m, 3)."""
    to_cam, to_prj = _unit(volume.camera.pinhole - centres), _unit(volume.projector.pinhole - centres)
    z = _unit(to_cam + to_prj)  # the bisector
    d = _diagonal(volume.camera, diagonal)
    x = _unit(d - (z @ d)[:, None] * z)
    y = np.cross(z, x)
    c, s = np.cos(tilt_rad), np.sin(tilt_rad)
    if tilt_axis == "length":
        y, z = c * y - s * z, c * z + s * y
    elif tilt_axis == "width":
        x, z = c * x - s * z, c * z + s * x
    elif tilt_axis is not None:
        raise ValueError(f"tilt_axis must be 'length', 'width' or None, not {tilt_axis!r}")
    return np.stack([x, y, z], axis=1)


def flat_frame(volume: MeasurementVolume, centre_world, diagonal: int, tilt_axis: str | None,
                tilt_rad: float) -> Frame:
    """``T_world_flat`` with the face's centre at ``centre_world``: normal along the
    bisector of the directions from there to camera and projector, length along the
    camera's image diagonal ``diagonal`` (0: +x+y, 1: +x-y), then tilted by
    ``tilt_rad`` about its ``"length"`` or ``"width"`` axis (None: not tilted)."""
    c = np.asarray(centre_world, float).reshape(1, 3)
    return Frame.from_matrix(_flat_axes(volume, c, diagonal, tilt_axis, tilt_rad)[0], c[0])


def _face_grid(standard) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, 5) * standard.length_mm, np.linspace(-0.5, 0.5, 3) * standard.width_mm)
    return np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])


def flat_face_points(standard, T_world_flat: Frame) -> np.ndarray:
    """A 5 x 3 grid (15, 3) of the measured face in the world: corners, edge
    midpoints and centre."""
    return T_world_flat.to_world(_face_grid(standard))


def _fits(volume: MeasurementVolume, standard, centres: np.ndarray, axes: np.ndarray, field_margin: float,
          max_incidence_deg: float) -> np.ndarray:
    """Whether the flat fits (m,) at face centres (m, 3) with axes (m, 3, 3)."""
    P = centres[:, None, :] + np.einsum("pk,mkj->mpj", _face_grid(standard), axes)  # x_world = R^T x_local + t
    normal = axes[:, 2, :]
    depth = volume.camera.to_sensor(P)[..., 2]
    ok = np.all((depth >= volume.depth_range_mm[0]) & (depth <= volume.depth_range_mm[1]), axis=1)
    for sensor in (volume.camera, volume.projector):
        margin = field_margin * min(sensor.format.width_mm, sensor.format.height_mm)
        cos_incidence = np.einsum("mpj,mj->mp", _unit(sensor.pinhole - P), normal)
        ok &= np.all(sensor.in_view(P, margin), axis=1)
        ok &= np.all(cos_incidence > np.cos(np.radians(max_incidence_deg)), axis=1)
    return ok


def flat_fits(volume: MeasurementVolume, standard, T_world_flat: Frame, field_margin: float = 0.02,
              max_incidence_deg: float = 60.0) -> bool:
    """Whether the flat's face (:func:`flat_face_points`) lies inside both fields
    (``field_margin`` times the format's shorter side from the edges), within the
    depth range, and faces camera and projector at incidence below
    ``max_incidence_deg``."""
    return bool(_fits(volume, standard, T_world_flat.t[None], T_world_flat.R[None], field_margin,
                      max_incidence_deg)[0])


def _flat_positions(volume: MeasurementVolume, standard, n: int, rng, samples: int, tilt_deg: float,
                    field_margin: float, max_incidence_deg: float, depth_step_mm: float = 5.0) -> list:
    """Up to ``n`` of :data:`FLAT_POSITIONS` as (label, T_world_flat or None)."""
    centre, half = volume_box(volume, rng, samples)
    if not np.all(half > 0):
        return [(label, None) for label, *_ in FLAT_POSITIONS[:n]]
    cam = volume.camera
    ray = _unit(centre - cam.pinhole)
    lo, hi = volume.depth_range_mm
    depths = np.linspace(lo, hi, max(2, int(np.ceil((hi - lo) / depth_step_mm)) + 1))
    at = cam.pinhole + (depths / (ray @ cam.R[2]))[:, None] * ray  # face centres along the ray, by camera depth
    out = []
    for label, diagonal, axis, sign, where in FLAT_POSITIONS[:n]:
        axes = _flat_axes(volume, at, diagonal, axis, sign * np.radians(tilt_deg))
        fits = np.flatnonzero(_fits(volume, standard, at, axes, field_margin, max_incidence_deg))
        if not len(fits):
            out.append((label, None))
            continue
        if where == "near":
            i = fits[0]
        elif where == "far":
            i = fits[-1]
        else:
            i = fits[np.argmin(np.abs(depths[fits] - (depths[fits[0]] + depths[fits[-1]]) / 2))]
        out.append((label, Frame.from_matrix(axes[i], at[i])))
    return out


def _generator(seed: int, scanner_index: int, test: str) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(scanner_index), TESTS.index(test)]))


def plan_acceptance(rig: Rig, volumes: dict, standards, counts: dict, seed: int = 0, samples: int = 20000,
                    min_view_angle_deg: float = 60.0, flat_tilt_deg: float = 30.0, field_margin: float = 0.02,
                    max_incidence_deg: float = 60.0) -> AcceptancePlan:
    """The acceptance test's positions in every scanner's measurement volume.

    Parameters
    ----------
    rig : Rig
        The scanners, in the order that numbers the positions.
    volumes : dict scanner -> MeasurementVolume
        Each scanner's measurement volume (sensors in the world frame).
    standards : AcceptanceStandards
        The objects' certificates; an object left out (None) is not planned.
    counts : dict test -> int
        Positions per scanner (``sphere``, ``dumbbell`` <= 7, ``flat`` <= 6); a test
        left out or 0 is not planned.
    seed : int
        Seeds the random candidates (sphere positions, volume centres).
    samples : int
        Random candidates drawn per scanner and test.
    min_view_angle_deg : float
        Least angle between the dumbbell and the sensors' lines of sight to its spheres.
    flat_tilt_deg, field_margin, max_incidence_deg : float
        The flat's tilts, its margin to the fields' edges (fraction of the format's
        shorter side) and the largest incidence of camera and projector on its face.

    Returns
    -------
    AcceptancePlan
        ``positions`` (:data:`PLAN_COLUMNS`, scanners in rig order, then tests in
        :data:`TESTS` order) and ``uncovered``.
    """
    asked = {t: int(counts.get(t, 0) or 0) for t in TESTS if getattr(standards, t, None) is not None}
    asked = {t: n for t, n in asked.items() if n > 0}
    rows, uncovered = [], []
    for k, scanner in enumerate(rig.scanners, start=1):
        if not asked:
            break
        volume = volumes.get(scanner.name)
        if volume is None:
            uncovered.append(f"{scanner.name}: no measurement volume (no {', '.join(asked)} position)")
            continue
        placed: dict[str, list[Frame]] = {}
        for test, n in asked.items():
            rng = _generator(seed, k, test)
            standard = getattr(standards, test)
            frames = []
            if test == "sphere":
                X = sphere_centres(volume, standard.diameter_mm / 2, n, rng, samples)
                frames = [Frame(x, np.zeros(3)) for x in X]
                if len(frames) < n:
                    uncovered.append(f"{scanner.name}: sphere: {len(frames)} of {n} positions fit the volume")
            elif test == "dumbbell":
                for i, (A, B, _, problem) in enumerate(dumbbell_bars(volume, standard.length_mm,
                                                                     standard.diameter_mm / 2, rng, samples,
                                                                     min_view_angle_deg)[:n]):
                    if problem:
                        uncovered.append(f"{scanner.name}: dumbbell direction {i + 1} "
                                         f"({'space' if i < 4 else 'face'} diagonal): {problem}")
                    else:
                        frames.append(frame_along(A, B))
                if n > 7:
                    uncovered.append(f"{scanner.name}: dumbbell: {n} positions asked, the guideline's scheme has 7")
            else:
                for label, T in _flat_positions(volume, standard, n, rng, samples, flat_tilt_deg, field_margin,
                                                max_incidence_deg):
                    if T is None:
                        uncovered.append(f"{scanner.name}: flat position '{label}': the "
                                         f"{standard.length_mm:g} x {standard.width_mm:g} mm face fits at no depth")
                    else:
                        frames.append(T)
                if n > len(FLAT_POSITIONS):
                    uncovered.append(f"{scanner.name}: flat: {n} positions asked, {len(FLAT_POSITIONS)} are defined")
            placed[test] = frames
        for test, frames in placed.items():
            for i, T in enumerate(frames, start=1):
                rows.append({"measurement": position_name(test, k, i), "test": test, "scanner": scanner.name,
                             **dict(zip(POSE_COLUMNS, map(float, T.params)))})
    return AcceptancePlan(pd.DataFrame(rows, columns=list(PLAN_COLUMNS)), uncovered)
