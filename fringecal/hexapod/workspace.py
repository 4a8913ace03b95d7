"""Workspace of the platform: strokes within the actuator travel, joints within their limits.

A pose is inside the workspace when every leg's stroke ``L - retracted_length`` lies in
``[0, stroke_mm]`` and every joint angle (angle between the leg and the joint's neutral
axis, the leg direction at the home pose; fixed in BASE for base joints, in TOP for
top joints) is at most the configured limit. :func:`axis_range` walks out from the home
pose along one pose coordinate and names the constraint that stops it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fringecal.hexapod.config import HexapodConfig
from fringecal.hexapod.kinematics import POSE_NAMES, leg_vectors, rotation_base_top

__all__ = ["WorkspaceCheck", "check_poses", "AxisRange", "axis_range", "reach_report", "describe_violations",
           "CubeReach", "cube_reach"]


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _neutral_axes(config: HexapodConfig):
    home = config.home_pose.vector
    u = _unit(leg_vectors(config.platform, home))  # (6, 3) in BASE
    R = rotation_base_top(*home[3:])
    return u, u @ R  # base-fixed and top-fixed (R^T u) neutral axes


@dataclass(frozen=True)
class WorkspaceCheck:
    """Per-pose workspace quantities, arrays with leading shape (...).

    lengths_mm, strokes_mm, base_angles_rad, top_angles_rad : (..., 6)
    margins : (..., 24) normalised margins (>= 0 inside) in the order
        stroke low (legs 1..6), stroke high, base joint, top joint.
    """

    lengths_mm: np.ndarray
    strokes_mm: np.ndarray
    base_angles_rad: np.ndarray
    top_angles_rad: np.ndarray
    margins: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        return np.all(self.margins >= 0, axis=-1)


#: rounding slack on the stroke ends, so that a leg exactly at 0 or full stroke (the
#: HOME reference run, a target of MAX counts) passes after forward kinematics
STROKE_SLACK_MM = 1e-6

#: what each margin column means, for messages
CONSTRAINTS = ([f"leg {i} stroke below 0 mm (fully retracted)" for i in range(1, 7)]
               + [f"leg {i} stroke beyond full extension" for i in range(1, 7)]
               + [f"base joint {i} angle beyond limit" for i in range(1, 7)]
               + [f"top joint {i} angle beyond limit" for i in range(1, 7)])


def check_poses(config: HexapodConfig, poses) -> WorkspaceCheck:
    """Workspace quantities for platform poses (..., 6) (mm, rad)."""
    poses = np.asarray(poses, float)
    legs = leg_vectors(config.platform, poses)
    lengths = np.linalg.norm(legs, axis=-1)
    u = legs / lengths[..., None]
    nb, nt = _neutral_axes(config)
    R = rotation_base_top(poses[..., 3], poses[..., 4], poses[..., 5])
    u_top = np.einsum("...ji,...lj->...li", R, u)  # R^T u per leg
    base_ang = np.arccos(np.clip(np.sum(u * nb, axis=-1), -1.0, 1.0))
    top_ang = np.arccos(np.clip(np.sum(u_top * nt, axis=-1), -1.0, 1.0))
    act = config.actuator
    strokes = lengths - act.retracted_length_mm
    lim_b, lim_t = np.radians(config.joints.base_max_deg), np.radians(config.joints.top_max_deg)
    margins = np.concatenate([
        (strokes + STROKE_SLACK_MM) / act.stroke_mm,
        (act.stroke_mm + STROKE_SLACK_MM - strokes) / act.stroke_mm,
        (lim_b - base_ang) / lim_b,
        (lim_t - top_ang) / lim_t,
    ], axis=-1)
    return WorkspaceCheck(lengths, strokes, base_ang, top_ang, margins)


def describe_violations(config: HexapodConfig, check: WorkspaceCheck, index=()) -> list[str]:
    """Readable list of the constraints one pose (``index`` into the leading axes) breaks."""
    m = check.margins[index]
    s = check.strokes_mm[index]
    out = []
    for k in np.flatnonzero(m < 0):
        leg = k % 6
        if k < 12:
            out.append(f"leg {leg + 1} stroke {s[leg]:.2f} mm outside 0..{config.actuator.stroke_mm:g} mm")
        elif k < 18:
            out.append(f"base joint {leg + 1} at {np.degrees(check.base_angles_rad[index][leg]):.2f} deg "
                       f"> {config.joints.base_max_deg:g} deg")
        else:
            out.append(f"top joint {leg + 1} at {np.degrees(check.top_angles_rad[index][leg]):.2f} deg "
                       f"> {config.joints.top_max_deg:g} deg")
    return out


@dataclass(frozen=True)
class AxisRange:
    """Reach from the home pose along one pose coordinate.

    ``lower``/``upper`` are offsets from home (mm, or rad for angles), each the last
    feasible offset up to ``limit`` (in magnitude, found to the bisection tolerance);
    ``lower_by``/``upper_by`` name the constraint(s) broken just beyond it ("; "-joined
    when several break together), or ``None`` when ``limit`` itself is reached.
    """

    axis: str
    lower: float
    upper: float
    lower_by: str | None
    upper_by: str | None
    limit: float

    @property
    def reaches_limit(self) -> bool:
        return self.lower_by is None and self.upper_by is None


def _walk(config, axis_index, sign, limit, step, tol):
    home = config.home_pose.vector

    def margins(x):
        x = np.atleast_1d(x)
        p = np.repeat(home[None, :], len(x), axis=0)
        p[:, axis_index] += sign * x
        return check_poses(config, p).margins

    if np.min(margins(0.0)) < 0:
        raise ValueError("the home pose itself is outside the workspace")
    xs = np.append(np.arange(0.0, limit, step), limit)
    bad = np.flatnonzero(np.min(margins(xs), axis=-1) < 0)
    if bad.size == 0:
        return float(limit), None
    lo, hi = xs[bad[0] - 1], xs[bad[0]]
    while hi - lo > tol:
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if np.min(margins(mid)) >= 0 else (lo, mid)
    broken = np.flatnonzero(margins(hi)[0] < 0)
    return float(lo), "; ".join(CONSTRAINTS[k] for k in broken)


def axis_range(config: HexapodConfig, axis: str, limit: float, step: float | None = None,
               tol: float | None = None) -> AxisRange:
    """Reach from the home pose along ``axis`` (one of px, py, pz, alpha, beta, gamma).

    Walks out in ``step`` increments (default 1 mm or 0.1 deg) up to ``limit`` (mm or
    rad) and bisects the first violation to ``tol`` (default 1e-3 mm or 1e-6 rad).
    """
    k = POSE_NAMES.index(axis)
    angular = k >= 3
    step = step or (np.radians(0.1) if angular else 1.0)
    tol = tol or (1e-6 if angular else 1e-3)
    up, up_by = _walk(config, k, +1, limit, step, tol)
    lo, lo_by = _walk(config, k, -1, limit, step, tol)
    return AxisRange(axis, -lo, up, lo_by, up_by, limit)


def reach_report(config: HexapodConfig, translation_mm: float = 250.0,
                 rotation_deg: float = 10.0) -> list[AxisRange]:
    """Reach along each of the six pose coordinates from home: +-``translation_mm`` for
    px, py, pz (the thesis's +-0.25 m target, section 4.1), +-``rotation_deg`` for the angles."""
    return [axis_range(config, a, translation_mm if a in ("px", "py", "pz") else np.radians(rotation_deg))
            for a in POSE_NAMES]


@dataclass(frozen=True)
class CubeReach:
    """Translations combined: the cube of half-size ``half_mm`` about the home pose
    (orientation fixed), sampled on a ``n`` x ``n`` x ``n`` grid including its corners.

    ``inside`` says whether every sample is in the workspace; ``largest_half_mm`` is the
    largest half-size whose samples all are (bisection to 0.01 mm), ``worst_offset_mm``
    the sample just beyond it and ``limited_by`` what it breaks there.
    """

    half_mm: float
    inside: bool
    largest_half_mm: float
    worst_offset_mm: tuple[float, float, float]
    limited_by: str


def cube_reach(config: HexapodConfig, half_mm: float = 250.0, n: int = 9) -> CubeReach:
    """Reach of combined translations (section 4.1 asks for +-0.25 m along all three axes)."""
    home = config.home_pose.vector
    unit = np.stack(np.meshgrid(*[np.linspace(-1, 1, n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)

    def check(h):
        p = np.repeat(home[None, :], len(unit), axis=0)
        p[:, :3] += h * unit
        return check_poses(config, p)

    inside = bool(check(half_mm).ok.all())
    lo, hi = 0.0, half_mm
    if inside:
        lo = hi = half_mm
    while hi - lo > 0.01:
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if check(mid).ok.all() else (lo, mid)
    chk = check(hi)
    k = int(np.argmin(chk.margins.min(axis=-1)))
    broken = "; ".join(describe_violations(config, chk, k)) or "none"
    return CubeReach(float(half_mm), inside, float(lo), tuple(float(v) for v in hi * unit[k]), broken)
