"""The acceptance test's quality parameters on exact synthetic data: P_F, P_S, SD and F
known by construction, the 0.3 % outlier exclusion at its threshold, and the ISO
14253-1 verdicts of the certificate."""

import numpy as np
import pandas as pd
import pytest

from fringecal.acceptance.evaluate import VALUE_COLUMNS, certificate, parameters, verdict
from fringecal.acceptance.measure import probe_flat, probe_sphere, trim_by_residual
from fringecal.acceptance.standards import AcceptanceLimits, SphereStandard
from fringecal.verification.lengths import ballbar_lengths


def symmetric_directions(n_base: int, seed: int = 0) -> np.ndarray:
    """Unit vectors closed under x<->y swap and antipodes, holding the x and y axes: a
    deviation a (u_x^2 - u_y^2) then has zero mean and zero first moment, so the
    least-squares sphere through the deviated points is exactly the nominal one."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n_base, 3))
    u = np.vstack([u, [[1.0, 0, 0], [0, 1.0, 0]]])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = np.vstack([u, u[:, [1, 0, 2]]])
    return np.vstack([u, -u])


CENTRE = np.array([120.0, -80.0, 2400.0])


def sphere_points(radius: float, a: float, n_base: int = 1500):
    u = symmetric_directions(n_base)
    d = a * (u[:, 0] ** 2 - u[:, 1] ** 2)
    return CENTRE + (radius + d)[:, None] * u


def with_outliers(points: np.ndarray, centre, n_high: int, n_low: int, size_mm: float) -> np.ndarray:
    """The points plus copies of the first ones moved radially out (``n_high``) and in
    (``n_low``) by ``size_mm``."""
    u = (points - centre) / np.linalg.norm(points - centre, axis=1, keepdims=True)
    high = points[:n_high] + size_mm * u[:n_high]
    low = points[n_high:n_high + n_low] - size_mm * u[n_high:n_high + n_low]
    return np.vstack([points, high, low])


def threshold_count(n_clean: int, fraction: float = 0.003) -> int:
    """k such that k outliers on each side of ``n_clean`` points are exactly what the
    exclusion removes: k = floor(fraction (n_clean + 2 k) / 2)."""
    k = 0
    while int(np.floor(fraction * (n_clean + 2 * (k + 1)) / 2)) >= k + 1:
        k += 1
    return k


def test_probing_errors_of_a_sphere_with_known_form_and_size():
    # radius 63.52 mm against a calibrated 127.0 mm diameter: P_S = +0.04 mm;
    # the form a (u_x^2 - u_y^2) with a = 12 um spans exactly 2a = 24 um over the points
    pts = sphere_points(63.52, 0.012)
    m = probe_sphere(pts, SphereStandard(diameter_mm=127.0), exclude_fraction=0.0)
    assert m.form_mm == pytest.approx(0.024, abs=1e-9)
    assert m.size_mm == pytest.approx(0.040, abs=1e-9)
    np.testing.assert_allclose(m.centre, CENTRE, atol=1e-9)
    assert m.n_excluded == 0


def test_sphere_outliers_at_the_exclusion_threshold():
    pts = sphere_points(63.5, 0.012)
    k = threshold_count(len(pts))             # points the 0.3 % rule removes from each end
    assert k >= 4
    standard = SphereStandard(diameter_mm=127.0)
    # exactly k outliers on each side: all removed, the values are those of the clean sphere
    at = with_outliers(pts, CENTRE, k, k, 0.5)
    m = probe_sphere(at, standard, 0.003)
    assert m.n_excluded == 2 * k
    assert m.form_mm == pytest.approx(0.024, abs=1e-6)
    assert m.size_mm == pytest.approx(0.0, abs=1e-6)
    # one more outside on the high side: one stays and P_F holds its 0.5 mm
    over = with_outliers(pts, CENTRE, k + 1, k, 0.5)
    m_over = probe_sphere(over, standard, 0.003)
    assert m_over.n_excluded == 2 * k     # floor(0.003 (n + 2k + 1) / 2) is still k
    assert 0.45 < m_over.form_mm < 0.55


def flat_points(length: float, width: float, bow_mm: float, n: int = 201):
    """A grid symmetric in x and y with the deviation bow (x/L)^2 (even), minus its mean:
    the total-least-squares plane is exactly z = 0 and F = the deviation's range."""
    x, y = np.meshgrid(np.linspace(-length / 2, length / 2, n), np.linspace(-width / 2, width / 2, 11))
    x, y = x.ravel(), y.ravel()
    z = bow_mm * (2 * x / length) ** 2
    z -= z.mean()
    R = np.array([[np.cos(0.3), 0, np.sin(0.3)], [0, 1, 0], [-np.sin(0.3), 0, np.cos(0.3)]])
    return np.c_[x, y, z] @ R.T + [0.0, 50.0, 2500.0], R[:, 2]


def test_flatness_error_known_by_construction_with_outliers_at_the_threshold():
    pts, normal = flat_points(700.0, 120.0, 0.017)
    m = probe_flat(pts, 0.0)
    assert m.flatness_mm == pytest.approx(0.017, abs=1e-9)
    assert abs(abs(m.normal @ normal) - 1) < 1e-12
    k = threshold_count(len(pts))
    assert k >= 1
    at = np.vstack([pts, pts[:k] + 0.3 * normal, pts[k:2 * k] - 0.3 * normal])
    m_at = probe_flat(at, 0.003)
    assert m_at.n_excluded == 2 * k
    assert m_at.flatness_mm == pytest.approx(0.017, abs=1e-9)
    over = np.vstack([at, pts[2 * k] + 0.3 * normal])          # k + 1 high: one stays
    assert probe_flat(over, 0.003).flatness_mm > 0.25


def test_trim_removes_floor_half_of_the_fraction_from_each_end():
    r = np.arange(1000.0)
    keep = trim_by_residual(r, 0.003)        # floor(1.5) = 1 from each end
    assert keep.sum() == 998 and not keep[0] and not keep[-1]
    assert trim_by_residual(r[:600], 0.003).all()    # floor(0.9) = 0


def test_sphere_spacing_error_from_centres():
    L = 500.0123
    d = np.array([0.6, -0.48, 0.64])
    rows = []
    for pos, c in (("d1", [0.0, 0.0, 2400.0]), ("d2", [300.0, -100.0, 2600.0])):
        a = np.array(c)
        rows += [(pos, "s1", "A", *a), (pos, "s1", "B", *(a + L * d))]
    centres = pd.DataFrame(rows, columns=["position", "scanner", "sphere_id", "x_mm", "y_mm", "z_mm"])
    lengths = ballbar_lengths(centres)
    np.testing.assert_allclose(lengths.length_mm - 500.0, [0.0123, 0.0123], atol=1e-9)


def values(rows):
    return pd.DataFrame([(*r, 100, 0) for r in rows], columns=VALUE_COLUMNS)


def test_parameters_take_the_worst_position_and_iso14253_verdicts():
    v = values([("sphere", "P_F", "s1", "scanner1", 0.300, 0.002),
                ("sphere", "P_F", "s2", "scanner1", 0.420, 0.002),
                ("sphere", "P_S", "s1", "scanner1", -0.030, 0.004),
                ("dumbbell", "SD", "d1", "scanner1", 0.080, 0.030),
                ("dumbbell", "SD", "d2", "scanner1", 0.140, 0.030),
                ("ballbar", "E", "bb01", "cell", 0.031, 0.037),
                ("flat", "F", "f1", "scanner1", 0.2, 0.004)])
    limits = AcceptanceLimits(P_F=0.5, P_S=0.1, SD=0.1, E=0.1, F=0.5)
    p = {x["name"]: x for x in parameters(v, limits, ["scanner1"])}
    assert [x["name"] for x in parameters(v, limits, ["scanner1"])] == ["P_F", "P_S", "SD", "E", "F"]
    assert p["P_F"]["measured_mm"] == 0.420 and p["P_F"]["worst_position"] == "s2"
    assert p["P_F"]["verdict"] == "conformance"                  # 0.420 + 0.002 <= 0.5
    assert p["P_S"]["measured_mm"] == -0.030                     # the sign is kept
    assert p["SD"]["verdict"] == "non-conformance"               # 0.140 - 0.030 > 0.1
    assert p["SD"]["within_mpe"] is False
    assert p["E"]["verdict"] == "conformance" and p["E"]["part"] == 3
    doc = certificate(v, limits, 2.0, 0.003, ["scanner1"])
    assert doc["accepted"] is False and doc["within_mpe"] is False
    ok = certificate(v[v.parameter != "SD"], limits, 2.0, 0.003, ["scanner1"])
    assert ok["accepted"] is True


def test_verdict_zone_and_unknown_uncertainty():
    assert verdict(0.09, 0.02, 0.1) == "uncertainty zone"
    assert verdict(0.11, 0.02, 0.1) == "uncertainty zone"
    assert verdict(0.05, float("nan"), 0.1) == "uncertainty zone"   # no U: conformance not proven
    assert verdict(0.05, 0.01, None) == "not limited"


def test_positions_outside_the_specified_volume_are_listed_not_judged():
    from fringecal.acceptance.document import outside_volume
    from fringecal.acceptance.evaluate import DEPTH_COLUMNS
    from fringecal.acceptance.standards import ScannerSpecification

    v = pd.DataFrame([("sphere", "P_F", "s1", "scanner1", 0.30, 0.002, 100, 0, np.nan, 2500.0),
                      ("sphere", "P_S", "s1", "scanner1", 0.01, 0.004, 100, 0, np.nan, 2500.0),
                      ("sphere", "P_F", "s2", "scanner1", 2.90, 0.002, 100, 0, np.nan, 3600.0),
                      ("sphere", "P_S", "s2", "scanner1", -0.30, 0.004, 100, 0, np.nan, 3600.0),
                      ("dumbbell", "SD", "d1", "scanner1", 0.02, 0.030, 0, 0, 2380.0, 2700.0),
                      ("ballbar", "E", "bb01", "cell", 0.03, 0.040, 0, 0, np.nan, np.nan)],
                     columns=VALUE_COLUMNS + DEPTH_COLUMNS)
    kept, failures = outside_volume(v, ScannerSpecification(depth_range_mm=(2400, 3000)))
    assert list(kept["position"]) == ["s1", "s1", "bb01"]  # E has no depth: across scanners, always judged
    assert [(f["position"], f["reason"]) for f in failures] == [
        ("s2", "outside the specified measuring volume (camera depth 3600 mm, the specification's 2400-3000 mm): "
               "not judged"),
        ("d1", "outside the specified measuring volume (camera depth 2380-2700 mm, the specification's "
               "2400-3000 mm): not judged")]
    same, none = outside_volume(v, ScannerSpecification())
    assert same is v and none == []
    doc = certificate(kept, AcceptanceLimits(P_F=1.5, P_S=0.2), 2.0, 0.003, ["scanner1"], failures,
                      specification=ScannerSpecification(name="data sheet X", depth_range_mm=(2400, 3000)))
    assert doc["specification"] == {"name": "data sheet X", "depth_range_mm": [2400.0, 3000.0],
                                    "mpe_mm": {"P_F": 1.5, "P_S": 0.2, "SD": 0.1, "E": 0.1, "F": 0.5}}
    assert doc["values"][0]["depth_mm"] == 2500.0 and "depth_near_mm" not in doc["values"][0]
    assert "depth_mm" not in doc["values"][2] and doc["accepted"] is True


def test_p_s_of_a_cap_noisy_along_the_rays_is_unbiased_with_the_ray_fit():
    """A 127 mm sphere's cap seen from 3.6 m with 0.6 mm RMS noise along each camera ray:
    over 30 draws the orthogonal fit's P_S is biased by about -0.1 mm; P_S from
    probe_sphere (fit along the rays from the camera) is not, and its stated U covers
    the draws' scatter."""
    rng = np.random.default_rng(7)
    camera = np.zeros(3)
    u = symmetric_directions(2500, seed=3)
    u = u[u[:, 2] < -np.cos(np.radians(64))]
    centre = np.array([40.0, -30.0, 3600.0])
    sizes, orthogonal, U = [], [], []
    for _ in range(30):
        p = centre + 63.5 * u
        d = (p - camera) / np.linalg.norm(p - camera, axis=1, keepdims=True)
        p = p + rng.normal(0, 0.6, (len(p), 1)) * d
        m = probe_sphere(p, SphereStandard(diameter_mm=127.0), 0.0, origin=camera)
        sizes.append(m.size_mm)
        orthogonal.append(m.diameter_orthogonal_mm - 127.0)
        U.append(2 * m.diameter_u_fit_mm)
        assert m.fit == "along camera rays"
    sizes, orthogonal = np.array(sizes), np.array(orthogonal)
    sem = sizes.std(ddof=1) / np.sqrt(len(sizes))
    assert orthogonal.mean() < -0.06                       # the bias the fit along the rays removes
    assert abs(sizes.mean()) < 3 * sem                     # unbiased within its standard error (~0.02 mm)
    assert 0.7 < np.mean(U) / 2 / sizes.std(ddof=1) < 1.4  # the stated u is the scatter
