"""Black-box scanners in the adjustment (fringecal.calibration.blackbox): on sphere
centres simulated from known transforms and poses, the joint adjustment finds the
transforms within their stated uncertainty, a scale factor by the setting, beats
registering each scanner on its own, and the export's 4x4 maps like the transform."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fringecal.artefact import load_artefact
from fringecal.calibration.blackbox import (ModelPrior, adjust_black_boxes, export_table, pairwise_svd,
                                            registration_noise, scatter_between_spheres, transform_points)
from fringecal.frames import Frame

ARTEFACT = load_artefact(Path(__file__).resolve().parents[1] / "configs" / "thesis" / "artefact_cmm1.csv")
TRUE = {"a": Frame.from_params([0, 0, 0, 0, 0, 0]), "b": Frame.from_params([750, 20, -30, 0.02, -0.15, 0.01]),
        "c": Frame.from_params([1500, -10, 40, -0.01, -0.3, 0.02])}
U = np.array([0.004, 0.004, 0.010])  # the sphere fits' uncertainty (x, y along the view's normal plane, z)


def row_centres(seed: int, scales: dict | None = None, n_poses: int = 10, half_width: float = 700.0
                ) -> tuple[pd.DataFrame, dict]:
    """Labelled centres of three scanners in a row seeing the artefact's parts within
    ``half_width`` mm of their axis, with Gaussian noise of U; and the true poses."""
    rng = np.random.default_rng(seed)
    rows, poses = [], {}
    for m in range(n_poses):
        pose = Frame.from_params([750 + rng.normal(0, 100), rng.normal(0, 100), 3600 + rng.normal(0, 100),
                                  *rng.normal(0, 0.2, 3)])
        poses[str(m)] = pose
        world = pose.to_world(ARTEFACT.centres)
        for s, frame in TRUE.items():
            local = frame.to_local(world) / (scales or {}).get(s, 1.0)
            for j in np.flatnonzero(np.abs(local[:, 0]) < half_width):
                c = local[j] + rng.normal(0, U)
                rows.append({"measurement": str(m), "scanner": s, "sphere_id": ARTEFACT.ids[j], "x_mm": c[0],
                             "y_mm": c[1], "z_mm": c[2], "u_x_mm": U[0], "u_y_mm": U[1], "u_z_mm": U[2]})
    return pd.DataFrame(rows), poses


def start(seed: int = 5) -> dict:
    rng = np.random.default_rng(seed)
    out = {s: (Frame.from_params(f.params + rng.normal(0, [2, 2, 2, 0.002, 0.002, 0.002])), 1.0)
           for s, f in TRUE.items()}
    out["a"] = (TRUE["a"], 1.0)
    return out


def test_the_joint_adjustment_finds_the_transforms_within_their_uncertainty():
    centres, _ = row_centres(1)
    res = adjust_black_boxes(centres, ARTEFACT, "a", start())
    # the CMM's 10 um in the weights but not in the simulated centres: s0 below 1
    assert 0.3 < res.s0 < 1.0
    for s in ("b", "c"):
        b = res.scanners[s]
        err = b.params[:6] - TRUE[s].params
        std = np.sqrt(np.diag(b.covariance))[:6]
        assert np.all(std > 0) and np.all(np.abs(err) < 4 * std), (s, err / std)
        assert np.linalg.norm(err[:3]) < 0.05  # mm, against 2 mm of start error
    assert np.all(res.scanners["a"].covariance[:6, :6] == 0)  # the reference's frame is the world


def test_a_scale_factor_is_adjusted_by_the_setting():
    centres, _ = row_centres(2, scales={"c": 1.004})
    fixed = adjust_black_boxes(centres, ARTEFACT, "a", start())
    scaled = adjust_black_boxes(centres, ARTEFACT, "a", start(), scale=True)
    k, u = scaled.scanners["c"].scale, np.sqrt(scaled.scanners["c"].covariance[6, 6])
    assert abs(k - 1.004) < 4 * u and u < 2e-5
    assert scaled.scanners["c"].rms_mm < fixed.scanners["c"].rms_mm / 10  # 0.4 % of 0.5 m unexplained without


def test_the_joint_adjustment_beats_registering_each_scanner_on_its_own():
    """Where the outer scanner measures (its centres' mean), over three noise draws."""
    joint_err, svd_err = [], []
    for seed in range(3):
        centres, _ = row_centres(10 + seed)
        joint = adjust_black_boxes(centres, ARTEFACT, "a", start()).scanners["c"]
        svd = pairwise_svd(centres, ARTEFACT, "a")["c"]
        here = centres.loc[centres["scanner"] == "c", ["x_mm", "y_mm", "z_mm"]].to_numpy().mean(axis=0)[None]
        truth = TRUE["c"].to_world(here)
        joint_err.append(np.linalg.norm(transform_points(joint, here) - truth))
        svd_err.append(np.linalg.norm(transform_points(svd, here) - truth))
    assert np.mean(joint_err) < np.mean(svd_err), (joint_err, svd_err)


def test_the_registration_noise_is_the_centres_scatter():
    centres, _ = row_centres(3)
    from fringecal.calibration.blackbox import _centres

    noise = registration_noise(_centres(centres, ARTEFACT), ARTEFACT)
    assert noise.keys() == {"a", "b", "c"}
    assert all(0.5 * U.min() < v < 1.5 * np.sqrt(np.mean(U**2)) for v in noise.values()), noise
    # the scatter beyond what the fits and the CMM (u 10 um) state: none here; where each
    # centre moves by 15 um per coordinate more than its fit's u, sqrt(15^2 - 10^2) um
    assert all(v < 0.003 for v in scatter_between_spheres(_centres(centres, ARTEFACT), ARTEFACT).values())
    xyz = ["x_mm", "y_mm", "z_mm"]
    centres[xyz] += np.random.default_rng(7).normal(0, 0.015, (len(centres), 3))
    extra = scatter_between_spheres(_centres(centres, ARTEFACT), ARTEFACT)
    assert all(abs(v - np.sqrt(0.015**2 - 0.010**2)) < 0.002 for v in extra.values()), extra


def test_a_tight_pose_prior_holds_the_poses():
    centres, poses = row_centres(4)
    meas = sorted(poses, key=int)
    x = np.concatenate([poses[m].params for m in meas])
    prior = ModelPrior(x, 1e-10 * np.eye(len(x)), np.arange(len(x)).reshape(-1, 6), x.reshape(-1, 6),
                       tuple(meas), tuple(f"p{i}" for i in range(len(x))))
    boxes = {s: v for s, v in start().items()}
    res = adjust_black_boxes(centres, ARTEFACT, "modelled", boxes, prior=prior)
    assert np.abs(res.poses.iloc[:, 1:].to_numpy() - x.reshape(-1, 6)).max() < 1e-4
    assert res.joint["max_shift_sigma"] < 5
    assert np.linalg.norm(res.scanners["b"].params[:3] - TRUE["b"].params[:3]) < 0.05


def test_the_export_maps_points_like_the_transform():
    centres, _ = row_centres(6, scales={"b": 0.997})
    res = adjust_black_boxes(centres, ARTEFACT, "a", start(), scale=True)
    table = export_table(res.scanners.values())
    assert list(table["scanner"]) == ["a", "b", "c"]
    p = np.array([[10.0, -20.0, 3500.0]])
    for row, b in zip(table.itertuples(), res.scanners.values()):
        M = np.array([[getattr(row, f"m{i}{j}") for j in range(4)] for i in range(4)])
        assert np.allclose((M @ np.r_[p[0], 1.0])[:3], transform_points(b, p)[0], atol=1e-9)
        assert np.allclose(M[3], [0, 0, 0, 1]) and row.scale == pytest.approx(b.scale)


def test_a_swapped_cloud_is_refused_by_the_labelling_consistency():
    """Scanner b's and c's centres of measurement 3 exchanged (their files swapped):
    both views are found inconsistent, never linked; the others are labelled."""
    from fringecal.calibration.blackbox import inconsistent_views
    from fringecal.spheres.poses_and_links import label_pose_link

    centres, poses = row_centres(7, n_poses=8, half_width=450.0)  # 2-9 spheres a view: labelling in ~1 s
    fits = centres.assign(sphere_id="", radius_mm=25.0, rms_mm=0.05, n_points=500, cap_angle_deg=60.0, coverage=0.25,
                          n_rejected=0, candidate=[f"c{i}" for i in range(len(centres))])
    swap = fits["measurement"] == "3"
    fits.loc[swap, "scanner"] = fits.loc[swap, "scanner"].map({"a": "a", "b": "c", "c": "b"})
    res = label_pose_link(fits, ARTEFACT, "a", planned=poses)
    bad = inconsistent_views(res.labels, ["b", "c"])
    assert sorted(zip(bad["measurement"], bad["scanner"])) == [("3", "b"), ("3", "c")]
    refused = res.labels[res.labels["status"] == "refused"]
    assert set(refused["reason"]) <= {"inconsistent", "too_few_candidates"}  # scanner a sees 2 spheres in view 5


def test_a_point_s_uncertainty_is_its_transform_s_covariance_carried():
    """u of a point against the covariance carried by a numerical Jacobian of the
    transform (7 parameters, central differences)."""
    from fringecal.calibration.blackbox import BlackBoxScanner, point_uncertainty

    rng = np.random.default_rng(8)
    A = rng.normal(size=(7, 7)) * [0.05, 0.05, 0.1, 1e-4, 1e-4, 1e-4, 1e-5]
    box = BlackBoxScanner("b", np.r_[TRUE["b"].params, 1.002], A @ A.T, 0.0, 0)
    points = np.array([[10.0, -300.0, 3500.0], [400.0, 250.0, 3900.0]])
    J = np.empty((2, 3, 7))
    for i in range(7):
        h = 1e-6 * max(1.0, abs(box.params[i]))
        up, dn = box.params.copy(), box.params.copy()
        up[i] += h
        dn[i] -= h
        J[:, :, i] = (transform_points(BlackBoxScanner("b", up, box.covariance, 0, 0), points)
                      - transform_points(BlackBoxScanner("b", dn, box.covariance, 0, 0), points)) / (2 * h)
    expected = np.sqrt(np.einsum("nij,jk,nik->n", J, box.covariance, J))
    assert np.allclose(point_uncertainty(box, points), expected, rtol=1e-6)
