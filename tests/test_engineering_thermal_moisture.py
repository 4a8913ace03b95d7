"""CTE from table 3-5, thermal compensation, Fickian moisture fits, CME, length consistency."""

import numpy as np
import pytest
from scipy import stats

from fringecal.artefact import load_artefact, load_rods
from fringecal.engineering import (
    CteFit,
    EarlyTimeDiffusion,
    EngineeringInputError,
    FickianFit,
    LengthChange,
    artefact_from_rod_lengths,
    compensate_temperature,
    fickian_fraction,
    moisture_content_pct,
    moisture_expansion_coefficient,
    rod_length_consistency,
)
from fringecal.schemas import HumidityLengthsTable, ThermalLogTable, read_table


def test_table_3_5_gives_the_thesis_cte(thesis_dir):
    log = read_table(thesis_dir / "thermal_log_table3-5.csv", ThermalLogTable)
    fit = CteFit.from_log(log)
    assert round(fit.cte_per_c, 7) == 1.9e-6            # printed "1.9 x 10^-6 per deg C"
    assert fit.cte_per_c == pytest.approx(1.897e-6, abs=0.0005e-6)
    ref = stats.linregress(log.temperature_c, log.length_mm)  # an independent regression
    assert fit.slope_mm_per_c == pytest.approx(ref.slope, rel=1e-12)
    assert fit.u_slope_mm_per_c == pytest.approx(ref.stderr, rel=1e-9)
    assert fit.u_cte_per_c == pytest.approx(1.01e-7, abs=0.01e-7)
    assert np.abs(fit.residuals()).max() < 0.002


def test_cte_exact_data_and_bad_logs():
    T = np.array([45.0, 38.0, 31.0, 26.0, 22.0])
    fit = CteFit.from_estimate(T, 1000 * (1 + 3.2e-6 * (T - 20)))
    assert fit.cte_per_c == pytest.approx(3.2e-6, rel=1e-9) and fit.length_ref_mm == pytest.approx(1000, abs=1e-9)
    with pytest.raises(EngineeringInputError, match="all temperatures are equal"):
        CteFit.from_estimate([20, 20, 20], [1, 2, 3])
    with pytest.raises(EngineeringInputError, match=">= 3"):
        CteFit.from_estimate([20, 21], [1, 2])


def test_thermal_compensation_scales_every_distance(thesis_artefact):
    a = compensate_temperature(thesis_artefact, 24.5)
    s = 1 + 1.9e-6 * 4.5
    np.testing.assert_allclose(a.distance_matrix(), s * thesis_artefact.distance_matrix(), rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(a.centres.mean(0), thesis_artefact.centres.mean(0), atol=1e-10)  # centroid fixed
    b = compensate_temperature(thesis_artefact, 24.5, centre=(0, 0, 0))
    shift = 1.9e-6 * 4.5 * thesis_artefact.centres.mean(0)   # alpha dT (c_a - c_b): a translation only
    np.testing.assert_allclose(b.centres - a.centres, np.broadcast_to(shift, a.centres.shape), atol=1e-10)
    c = compensate_temperature(thesis_artefact, 24.5, u_cte_per_c=1e-7)
    r = np.linalg.norm(thesis_artefact.centres - thesis_artefact.centres.mean(0), axis=1)
    np.testing.assert_allclose(c.u, np.hypot(0.010, 4.5e-7 * r))
    assert compensate_temperature(thesis_artefact, 20.0).centres.tolist() == thesis_artefact.centres.tolist()


def test_fickian_fraction_matches_the_brute_force_series():
    tau = np.r_[np.geomspace(1e-6, 0.049999, 20), 0.05, np.geomspace(0.050001, 2, 20)]
    k = 2 * np.arange(200_000) + 1.0
    brute = np.array([1 - 8 / np.pi ** 2 * np.sum(np.exp(-k ** 2 * np.pi ** 2 * x) / k ** 2) for x in tau])
    np.testing.assert_allclose(fickian_fraction(tau * 7.0, 1.0 / 7.0, 1.0), brute, rtol=0, atol=1e-11)
    small = np.geomspace(1e-8, 1e-3, 5)
    np.testing.assert_allclose(fickian_fraction(small, 1.0, 1.0), 4 / np.sqrt(np.pi) * np.sqrt(small), rtol=1e-12)


H, D_TRUE, MINF = 2.8, 1.8e-7, 0.62     # mm, mm^2/s (1.8e-13 m^2/s, the 75 % RH value), percent
T_S = np.linspace(0, 200, 41) ** 2 * 1e3   # 0 .. 4e7 s, evenly spaced in sqrt(t)


def test_noise_free_series_is_recovered_exactly():
    m = MINF * fickian_fraction(T_S, D_TRUE, H)
    full = FickianFit.from_estimate(T_S, m, H)
    assert full.D_mm2_s == pytest.approx(D_TRUE, rel=1e-8) and full.m_inf_pct == pytest.approx(MINF, rel=1e-8)
    early = EarlyTimeDiffusion.from_estimate(T_S, m, H, m_inf_pct=MINF)
    assert early.D_mm2_s == pytest.approx(D_TRUE, rel=1e-3)  # eq. 3-23 drops terms of ~1e-4 at G <= 0.5
    assert early.n_points >= 5


def test_noisy_series_within_stated_uncertainty():
    """1 % of M_inf Gaussian noise, five series: the fit's D within 3 u, u below 3 %."""
    rng = np.random.default_rng(7)
    m = MINF * fickian_fraction(T_S, D_TRUE, H)
    for _ in range(5):
        noisy = m + rng.normal(0, 0.01 * MINF, m.shape)
        full = FickianFit.from_estimate(T_S, noisy, H)
        assert abs(full.D_mm2_s - D_TRUE) < 3 * full.u_D_mm2_s and full.u_D_mm2_s < 0.03 * D_TRUE
        assert abs(full.m_inf_pct - MINF) < 3 * full.u_m_inf_pct
        early = EarlyTimeDiffusion.from_estimate(T_S, noisy, H, full.m_inf_pct, u_m_inf_pct=full.u_m_inf_pct)
        assert abs(early.D_mm2_s - D_TRUE) < max(3 * early.u_D_mm2_s, 0.01 * D_TRUE) and early.u_D_mm2_s < 0.05 * D_TRUE


def test_desorption_and_mass_input():
    m0, minf = 0.62, 0.21   # 75 % -> 25 % RH
    t = np.linspace(0, 6e7, 30)
    m = m0 + (minf - m0) * fickian_fraction(t, 9.2e-8, H)
    full = FickianFit.from_estimate(t, m, H, m0_pct=m0)
    assert full.D_mm2_s == pytest.approx(9.2e-8, rel=1e-7) and full.m_inf_pct == pytest.approx(minf, rel=1e-7)
    np.testing.assert_allclose(moisture_content_pct(12.0 * (1 + m / 100), 12.0), m, atol=1e-12)
    with pytest.raises(EngineeringInputError, match="early-time slope needs at least 2"):
        EarlyTimeDiffusion.from_estimate(t[[0, -1]], m[[0, -1]], H, m0_pct=m0)


def test_cme_order_of_magnitude_from_table_3_6(thesis_dir):
    """Table 3-6 lengths and an assumed 0.05 % mass change give the thesis's order, 1e-5 per %."""
    df = read_table(thesis_dir / "humidity_lengths_table3-6.csv", HumidityLengthsTable)
    ch = LengthChange.from_lengths(df.time_h, df.length_mm)
    assert ch.range_mm == pytest.approx(0.0004, abs=1e-9) and ch.change_mm == pytest.approx(0.0001, abs=1e-9)
    cme = moisture_expansion_coefficient(ch.range_mm, ch.length_start_mm, 0.05)
    assert round(np.log10(cme)) == -5 and cme == pytest.approx(1.34e-5, abs=0.01e-5)
    assert moisture_expansion_coefficient(0.0003, ch.length_start_mm, 0.05) == pytest.approx(1.0e-5, rel=0.01)


@pytest.fixture(scope="module")
def consistency(thesis_dir):
    a1 = load_artefact(thesis_dir / "artefact_cmm1.csv")
    a2 = load_artefact(thesis_dir / "artefact_cmm2.csv")
    single = load_rods(thesis_dir / "rods.csv", a2)
    assembled = load_rods(thesis_dir / "rods_assembled.csv", a2)
    return rod_length_consistency(single, assembled, {"cmm1": a1, "cmm2": a2}), a2, single


def test_rod_length_consistency_of_the_thesis_artefact(consistency):
    rep, _, _ = consistency
    c = rep.comparisons.set_index("comparison")
    # table 3-12's repeats are the distances of table 3-13's two coordinate sets (rounding only)
    assert c.loc["coords_cmm1 - assembled_1", "max_abs_um"] <= 0.6
    assert c.loc["coords_cmm2 - assembled_2", "max_abs_um"] <= 0.6
    row = c.loc["assembled - single"]
    assert (row.worst_rod, row.worst_spheres) == ("13", "2-6") and row.worst_um == pytest.approx(74.0, abs=0.01)
    assert row.rms_um == pytest.approx(21.6, abs=0.05)
    spread = c.loc["assembled repeats: max - min"]
    assert spread.worst_spheres == "2-6" and spread.max_abs_um == pytest.approx(212.0, abs=0.01)
    assert c.loc["coords_cmm1 - coords_cmm2", "rms_um"] == pytest.approx(36.7, abs=0.05)


def test_coordinates_from_rod_lengths(consistency, rng):
    _, a2, single = consistency
    true = a2.centres + rng.normal(0, 0.05, a2.centres.shape)   # a different shape, 50 um
    ia, ib = a2.index(single.sphere_a), a2.index(single.sphere_b)
    lengths = np.linalg.norm(true[ib] - true[ia], axis=1)
    rebuilt, dev = artefact_from_rod_lengths(a2, single, lengths)
    ib2, ia2 = rebuilt.index(single.sphere_b), rebuilt.index(single.sphere_a)
    np.testing.assert_allclose(np.linalg.norm(rebuilt.centres[ib2] - rebuilt.centres[ia2], axis=1), lengths, atol=1e-9)
    from fringecal.registration import kabsch
    M, T = kabsch(true, rebuilt.centres)
    np.testing.assert_allclose(true @ M.T + T, rebuilt.centres, atol=1e-8)   # same shape as the truth
    _, thesis_dev = artefact_from_rod_lengths(a2, single)
    assert 0.02 < thesis_dev.d_mm.max() < 0.08   # table 3-11 alone vs CMM set 2: tens of microns
