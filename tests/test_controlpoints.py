"""Control-point selection (section 6.4) on label maps with known geometry."""

import numpy as np
import pandas as pd
import pytest

from fringecal.calibration.controlpoints import incidence_map, select_control_points
from fringecal.schemas import ControlPointsTable, validate_table

H, W = 120, 160


def _maps():
    yy, xx = np.mgrid[:H, :W]
    labels = -np.ones((H, W), int)
    d0 = np.hypot(xx - 45, yy - 60)
    d1 = np.hypot(xx - 115, yy - 60)
    labels[d0 <= 30] = 0
    labels[d1 <= 30] = 1
    tau_x = (xx / W - 0.5) * 2 * np.pi * 0.9
    tau_y = (yy / H - 0.5) * 2 * np.pi * 0.9
    return xx, yy, labels, tau_x, tau_y, d0, d1


def test_grid_rim_and_phases():
    xx, yy, labels, tx, ty, d0, d1 = _maps()
    cp = select_control_points(labels, ["7", "12"], tx, ty, measurement="3", scanner="scanner1",
                               spacing_px=10, erode_px=4)
    validate_table(cp, ControlPointsTable)
    assert set(cp["sphere_id"]) == {"7", "12"} and (cp["measurement"] == "3").all()
    u = cp["u_px"].to_numpy(int)
    v = cp["v_px"].to_numpy(int)
    assert np.all(u % 10 == 0) and np.all(v % 10 == 0)
    # a kept pixel has its whole 4 px disc inside its sphere: at most 30 - 4 from the centre
    d = np.where(cp["sphere_id"] == "7", d0[v, u], d1[v, u])
    assert d.max() <= 26.0 + 1e-9
    # and every grid pixel that far inside is kept
    inside = ((d0 <= 26) | (d1 <= 26)) & (xx % 10 == 0) & (yy % 10 == 0)
    assert len(cp) == int(inside.sum())
    np.testing.assert_array_equal(cp["tau_x_rad"], tx[v, u])
    np.testing.assert_array_equal(cp["tau_y_rad"], ty[v, u])


def test_rejected_invalid_and_offset():
    xx, yy, labels, tx, ty, d0, d1 = _maps()
    rejected = (np.abs(xx - 45) <= 3) & (yy < 60)  # an end cap across sphere 0
    valid = ~((xx > 100) & (yy > 70))  # low modulation in part of sphere 1
    tx = tx.copy()
    tx[55, 45] = np.nan
    cp = select_control_points(labels, {0: "7", 1: "12"}, tx, ty, valid, rejected, measurement="1",
                               scanner="s", spacing_px=5, offset_px=0, erode_px=2)
    u = cp["u_px"].to_numpy(int)
    v = cp["v_px"].to_numpy(int)
    assert not rejected[v, u].any() and valid[v, u].all()
    # erosion keeps a margin of more than 2 px from rejected, invalid and NaN pixels too
    bad = np.argwhere(rejected | ~valid | np.isnan(tx))  # (row, col)
    dist = np.min(np.hypot(v[:, None] - bad[None, :, 0], u[:, None] - bad[None, :, 1]), axis=1)
    assert dist.min() > 2
    assert ((np.abs(u - 45) <= 5) & (v < 60)).sum() < 4  # only the strip's corners survive
    shifted = select_control_points(labels, ["7", "12"], ty, ty, measurement="1", scanner="s",
                                    spacing_px=10, offset_px=5, erode_px=0)
    assert np.all(shifted["u_px"] % 10 == 5) and np.all(shifted["v_px"] % 10 == 5)


def test_incidence_limit_with_exact_normals():
    """A sphere of radius 1 seen orthographically along -z: incidence = asin(rho)."""
    n = 101
    yy, xx = np.mgrid[:n, :n]
    x = (xx - 50) / 50.0
    y = (yy - 50) / 50.0
    rho2 = x * x + y * y
    labels = np.where(rho2 <= 1, 0, -1)
    z = np.sqrt(np.clip(1 - rho2, 0, None))
    pts = np.stack([x, y, z], axis=-1)
    inc = incidence_map(pts, labels, np.zeros((1, 3)), [0, 0, 1e9])
    np.testing.assert_allclose(inc[labels == 0], np.arcsin(np.sqrt(rho2[labels == 0])), atol=1e-6)
    cp = select_control_points(labels, ["1"], x, y, measurement="m", scanner="s", spacing_px=2,
                               erode_px=0, incidence=inc, max_incidence_deg=60)
    rho = np.hypot(cp["tau_x_rad"], cp["tau_y_rad"])
    assert rho.max() <= np.sin(np.radians(60)) + 1e-9
    assert rho.max() > np.sin(np.radians(60)) - 0.05


def test_bad_input_is_refused():
    xx, yy, labels, tx, ty, *_ = _maps()
    with pytest.raises(ValueError, match="label values \\[1\\] have no sphere id"):
        select_control_points(labels, ["7"], tx, ty, measurement="1", scanner="s")
    with pytest.raises(ValueError, match="tau_y has shape"):
        select_control_points(labels, ["7", "8"], tx, ty[:10], measurement="1", scanner="s")
    with pytest.raises(ValueError, match="needs an incidence map"):
        select_control_points(labels, ["7", "8"], tx, ty, measurement="1", scanner="s", max_incidence_deg=70)
    empty = select_control_points(-np.ones((H, W), int), [], tx, ty, measurement="1", scanner="s")
    assert list(empty.columns) == ["measurement", "scanner", "sphere_id", "u_px", "v_px", "tau_x_rad", "tau_y_rad"]
    assert len(empty) == 0 and isinstance(empty, pd.DataFrame)
