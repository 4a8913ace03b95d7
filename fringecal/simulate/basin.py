"""Rough start values of stated error sizes, and the rigs on which the convergence basin
of the bundle adjustment is mapped (``benchmarks/convergence_basin.py``,
``tests/test_bundle_convergence.py``, docs/calibration.md).

:func:`rough_start` moves the truth as a user's own start values would be off: at
``scale`` 1 (the sizes of ``ERRORS_1X``, those of the rig in issue 12) every free pinhole
coordinate by 2 mm, every free sensor angle by 2 mrad, every free principal distance by
0.4 % of c, every free distortion coefficient to zero, and every pose coordinate by
1 mm / 1 mrad; each with a random sign, so every start sits at exactly that distance in
each coordinate. Principal points stay at the truth (a user's prior calibration knows
them to a few um). Fixed parameters are not touched: by default the reference camera's
six external parameters are fixed (:meth:`fringecal.rig.Rig.default_free`, the thesis's
choice) because they *define* the world frame; moving them would move the frame, not
make the start worse. Its internal parameters and distortion are free and are perturbed.

:func:`load_rig_config` reads a rig YAML (:class:`fringecal.config.RigConfig`: sensors,
artefact, artefact poses). :func:`flat_poses` and :func:`independent_spheres` build the
hard case of the issue: poses with little depth spread and each scanner limited to 3-4
spheres of its own.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact, load_artefact
from fringecal.calibration.model import POSE_COLUMNS
from fringecal.config import RigConfig, load_yaml_model
from fringecal.rig import Rig, load_rig
from fringecal.simulate.control_points import simulate_control_points

__all__ = ["ERRORS_1X", "flat_poses", "independent_spheres", "load_rig_config", "rough_start"]

#: error sizes at scale 1: pinhole mm, sensor angle rad, principal distance (fraction of
#: c), pose translation mm, pose angle rad
ERRORS_1X = {"pinhole_mm": 2.0, "angle_rad": 0.002, "c_fraction": 0.004, "pose_mm": 1.0, "pose_rad": 0.001}


def rough_start(rig: Rig, poses: np.ndarray, rng, scale: float = 1.0, errors: dict | None = None
                ) -> tuple[Rig, np.ndarray]:
    """The truth ``rig`` and ``poses`` (n_meas, 6) moved by ``scale`` times ``errors``
    (default ``ERRORS_1X``) with random signs, distortion zero (free parameters only);
    returns the start rig (same free flags) and start poses."""
    e = {**ERRORS_1X, **(errors or {})}
    rng = np.random.default_rng(rng)
    p = rig.params.copy()
    n = len(p)

    def sign(*shape):
        return rng.choice([-1.0, 1.0], size=shape)

    step = np.zeros_like(p)
    step[:, 0:3] = scale * e["pinhole_mm"] * sign(n, 3)
    step[:, 3:6] = scale * e["angle_rad"] * sign(n, 3)
    step[:, 8] = scale * e["c_fraction"] * p[:, 8] * sign(n)
    p = np.where(rig.free, p + step, p)
    p[:, 9:] = np.where(rig.free[:, 9:], 0.0, p[:, 9:])
    po = np.asarray(poses, float).copy()
    po[:, :3] += scale * e["pose_mm"] * sign(len(po), 3)
    po[:, 3:] += scale * e["pose_rad"] * sign(len(po), 3)
    return rig.with_params(p), po


def load_rig_config(path) -> tuple[Rig, Artefact, pd.DataFrame]:
    """Truth rig, artefact and poses (``measurement`` + pose columns) of a rig YAML."""

    cfg = load_yaml_model(Path(path), RigConfig)
    if cfg.artefact_poses is None:
        raise ValueError(f"{path}: the rig has no artefact_poses")
    rig = load_rig(cfg.sensors, reference=cfg.reference_scanner)
    poses = pd.read_csv(cfg.artefact_poses, dtype={"measurement": str})
    return rig, load_artefact(cfg.artefact), poses[["measurement", *POSE_COLUMNS]].reset_index(drop=True)


def flat_poses(poses: pd.DataFrame, n: int = 10, depth_spread_mm: float = 30.0, lateral_mm: float = 60.0,
               spin_rad: float = 0.03, rng=0) -> pd.DataFrame:
    """``n`` poses with little depth spread: the first pose of ``poses`` moved by up to
    +-``lateral_mm`` in world x and y, +-``depth_spread_mm``/2 in world z (the thesis
    cameras look along -z) and turned by up to +-``spin_rad`` about each axis."""
    rng = np.random.default_rng(rng)
    base = poses[list(POSE_COLUMNS)].to_numpy(float)[0]
    rows = []
    for i in range(n):
        p = base.copy()
        p[0:2] += rng.uniform(-lateral_mm, lateral_mm, 2)
        p[2] += rng.uniform(-depth_spread_mm / 2, depth_spread_mm / 2)
        p[3:] += rng.uniform(-spin_rad, spin_rad, 3)
        rows.append((f"f{i + 1:02d}", *p))
    return pd.DataFrame(rows, columns=["measurement", *POSE_COLUMNS])


def independent_spheres(rig: Rig, artefact: Artefact, poses: pd.DataFrame, per_scanner: int = 4,
                        spacing_px: int = 30) -> dict:
    """scanner -> the ``per_scanner`` spheres it images best (most control points over
    ``poses``), no sphere given to two scanners (scanners in rig order; at least three
    each, else ValueError): a rig whose volumes share no sphere."""

    cp = simulate_control_points(rig, artefact, poses, spacing_px=spacing_px, noise_eps1_mm=0.0).control_points
    counts = cp.groupby(["scanner", "sphere_id"]).size()
    taken: set = set()
    out = {}
    for sc in rig.scanners:
        seen = sc.name in set(counts.index.get_level_values("scanner"))
        own = counts.xs(sc.name, level="scanner") if seen else pd.Series(dtype=int)
        ranked = [s for s in own.sort_values(ascending=False, kind="stable").index if s not in taken]
        if len(ranked) < 3:
            raise ValueError(f"scanner {sc.name} images only {len(ranked)} spheres no other scanner took")
        out[sc.name] = [str(s) for s in ranked[:per_scanner]]
        taken.update(out[sc.name])
    return out
