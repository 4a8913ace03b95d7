"""The acceptance objects measured in a black-box scanner's clouds
(:mod:`fringecal.acceptance.cloud`) against their truth: a black box with a known
transform and scale looks at a sphere, a flat (in front of a backdrop) and a dumbbell of
known sizes; P_F, P_S, F and SD come out as built, carried by the scale."""

from __future__ import annotations

import numpy as np
import pytest

from fringecal.acceptance.cloud import cloud_acceptance_values, measure_cloud_flat, measure_cloud_sphere, scale_u
from fringecal.acceptance.standards import (
    AcceptanceConfig,
    AcceptanceStandards,
    DumbbellStandard,
    FlatStandard,
    SphereStandard,
)
from fringecal.calibration.blackbox import BlackBoxScanner
from fringecal.rotation import rotation_matrix
from fringecal.scancloud import write_scanner_cloud

SCALE = 1.0003
U_SCALE = 2e-5
NOISE_MM = 0.04


def black_box() -> BlackBoxScanner:
    """A black box 2.6 m from the world origin, turned, its scale 3e-4 long (u 2e-5)."""
    cov = np.diag([0.01, 0.01, 0.01, 1e-8, 1e-8, 1e-8, U_SCALE**2])
    return BlackBoxScanner("box", np.array([150.0, -40.0, -2600.0, 0.05, -0.1, 0.2, SCALE]), cov, 0.01, 40)


def cap(centre, radius: float, rng, n: int = 3000, noise: float = NOISE_MM) -> np.ndarray:
    """Points of the cap of a sphere the scanner at the origin sees (within 65 degrees
    of the line of sight), noisy along the lines of sight."""
    sight = -np.asarray(centre, float) / np.linalg.norm(centre)
    u = rng.normal(size=(4 * n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u @ sight > np.cos(np.radians(65))][:n]
    p = centre + radius * u
    return p + rng.normal(0, noise, (len(p), 1)) * p / np.linalg.norm(p, axis=1, keepdims=True)


def test_a_sphere_in_a_cloud_gives_its_size_carried_by_the_scale():
    rng = np.random.default_rng(1)
    standard = SphereStandard(diameter_mm=127.0)
    true_diameter = 127.06  # the sphere as built: P_S in the scanner's frame +60 um
    exact, _ = measure_cloud_sphere(cap([80.0, -50.0, 2700.0], true_diameter / 2, rng, noise=0.0), black_box(),
                                    standard, 0.0)
    assert exact.size_mm == pytest.approx(SCALE * true_diameter - 127.0, abs=1e-6)  # +98 um in the world
    assert exact.form_mm < 1e-6
    noisy, depth = measure_cloud_sphere(cap([80.0, -50.0, 2700.0], true_diameter / 2, rng), black_box(), standard)
    u = np.sqrt(noisy.diameter_u_fit_mm**2 + (noisy.diameter_mm * scale_u(black_box()))**2)
    assert abs(noisy.size_mm - (SCALE * true_diameter - 127.0)) <= 2 * u
    assert 0.15 < noisy.form_mm < 0.45 and depth == pytest.approx(2700.0, abs=0.5)  # ~6-7 sigma of 0.04 mm


def test_a_flat_in_a_cloud_gives_its_bow_and_its_backdrop_is_set_aside():
    rng = np.random.default_rng(2)
    R = rotation_matrix(0.3, 0.2, 0.0)
    s, t = np.meshgrid(np.arange(-350, 350, 2.0), np.arange(-60, 60, 2.0))
    s, t = s.ravel(), t.ravel()
    bow = 0.010 * (s / 350) ** 2  # a 10 um bow along the flat's length
    flat = np.c_[s, t, bow] @ R + [0.0, 30.0, 2500.0]
    bs, bt = np.meshgrid(np.arange(-1000, 1000, 10.0), np.arange(-800, 800, 10.0))
    backdrop = np.c_[bs.ravel(), bt.ravel(), np.full(bs.size, 3400.0)]
    cloud = np.vstack([flat, backdrop + rng.normal(0, 0.05, backdrop.shape)])
    m, depth = measure_cloud_flat(cloud, black_box(), FlatStandard(length_mm=700.0, width_mm=120.0), 0.0)
    assert 0.0090 < m.flatness_mm <= SCALE * 0.010 + 1e-9  # the bow, its border cells left out
    assert m.n_points > 0.8 * len(flat) and depth == pytest.approx(2500.0, abs=20.0)


def test_a_dumbbell_in_a_cloud_gives_its_spacing_error_with_the_scale_s_uncertainty(tmp_path):
    rng = np.random.default_rng(3)
    box = black_box()
    a = np.array([-240.0, 20.0, 2650.0])
    b = a + 500.05 * np.array([0.96, 0.0, 0.28])  # built 50 um long
    path = write_scanner_cloud(tmp_path / "box.ply", np.vstack([cap(a, 25.4, rng, 3000), cap(b, 25.4, rng, 3000)]))
    doc = {"scanners": [box.to_dict()], "joint_covariance": {"n_sensor_parameters": 0, "black_boxes": ["box"],
                                                             "matrix": box.covariance.tolist()}}
    standards = AcceptanceStandards(dumbbell=DumbbellStandard(length_mm=500.0, diameter_mm=50.8))
    rows, failures = cloud_acceptance_values({"dumbbell": {"d1": {"box": str(path)}}}, doc, standards,
                                             AcceptanceConfig(), {})
    assert failures == [] and [r["parameter"] for r in rows] == ["SD"]
    (sd,) = rows
    truth = SCALE * 500.05 - 500.0  # +200 um: the build and the scale
    assert abs(sd["value_mm"] - truth) <= sd["U_mm"] and sd["U_mm"] > 2 * 500 * U_SCALE
    assert sd["depth_near_mm"] == pytest.approx(2650.0, abs=1.0) and sd["scanner"] == "box"


def test_a_rig_of_black_boxes_only_is_judged_on_its_clouds(tmp_path):
    """No sensors at all (``rig`` None): the sphere in the black box's cloud gives its
    P_F and P_S rows under the box's name, judged with the other parameters."""
    from fringecal.acceptance.document import acceptance_document
    from fringecal.verification.settings import LengthUncertaintyConfig

    box = black_box()
    path = write_scanner_cloud(tmp_path / "box.ply", cap([80.0, -50.0, 2700.0], 63.5, np.random.default_rng(4)))
    doc = {"scanners": [box.to_dict()], "joint_covariance": {"n_sensor_parameters": 0, "black_boxes": ["box"],
                                                             "matrix": box.covariance.tolist()}}
    cert, values = acceptance_document(None, AcceptanceStandards(sphere=SphereStandard(diameter_mm=127.0)),
                                       AcceptanceConfig(), {}, LengthUncertaintyConfig(), None,
                                       {"sphere": {"s1": {"box": str(path)}}}, black_boxes=doc)
    got = {(p["name"], p["scanner"]): p for p in cert["parameters"]}
    assert set(got) == {("P_F", "box"), ("P_S", "box")} and cert["black_boxes"] == ["box"]
    assert abs(got[("P_S", "box")]["measured_mm"] - (SCALE - 1) * 127.0) <= got[("P_S", "box")]["U_mm"]
    assert got[("P_S", "box")]["verdict"] == "conformance" and list(values["scanner"]) == ["box", "box"]
