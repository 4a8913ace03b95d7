"""Workspace and reach of the platform; the +-250 mm target of section 4.1."""

from __future__ import annotations

import numpy as np
import pytest

from fringecal.hexapod import load_hexapod_config
from fringecal.hexapod.config import HexapodConfig
from fringecal.hexapod.workspace import CONSTRAINTS, axis_range, check_poses, reach_report

CFG = load_hexapod_config()
R_H = 553.0220007700  # horizontal joint offset of every leg at a level, centred pose


def variant(**changes) -> HexapodConfig:
    data = CFG.model_dump()
    for path, value in changes.items():
        section, key = path.split("__")
        data[section][key] = value
    return HexapodConfig.model_validate(data)


def test_home_pose_is_level_mid_stroke_with_joints_neutral():
    chk = check_poses(CFG, CFG.home_pose.vector)
    assert chk.ok
    assert chk.strokes_mm == pytest.approx(np.full(6, 250.0), abs=1e-3)
    assert chk.base_angles_rad == pytest.approx(np.zeros(6), abs=1e-7)
    assert chk.top_angles_rad == pytest.approx(np.zeros(6), abs=1e-7)


def test_thesis_platform_reaches_250_mm_along_each_axis():
    """Must-show: the report says the +-250 mm target is met (with the stated assumptions)."""
    report = {r.axis: r for r in reach_report(CFG, translation_mm=250.0, rotation_deg=10.0)}
    for axis in ("px", "py", "pz"):
        r = report[axis]
        assert r.reaches_limit and (r.lower, r.upper) == (-250.0, 250.0), r
    for axis in ("px", "py", "pz"):
        p = CFG.home_pose.vector.copy()
        p[("px", "py", "pz").index(axis)] += 250.0
        assert check_poses(CFG, p).ok


@pytest.mark.parametrize("axis", ["px", "py", "pz", "gamma"])
def test_reported_bound_is_exact_and_names_the_broken_constraint(axis):
    limit = 600.0 if axis != "gamma" else np.radians(40.0)
    r = axis_range(CFG, axis, limit)
    k = ("px", "py", "pz", "alpha", "beta", "gamma").index(axis)
    tol = 1e-3 if k < 3 else 1e-6
    for offset, named in ((r.upper, r.upper_by), (r.lower, r.lower_by)):
        assert named is not None and abs(offset) < limit
        inside = CFG.home_pose.vector.copy()
        inside[k] += offset
        beyond = inside.copy()
        beyond[k] += np.sign(offset) * 2 * tol
        assert check_poses(CFG, inside).ok
        broken = {CONSTRAINTS[i] for i in np.flatnonzero(check_poses(CFG, beyond).margins < 0)}
        assert broken == set(named.split("; "))


def test_short_stroke_platform_misses_250_mm_in_z_exactly_where_expected():
    """A 300 mm stroke cannot give +-250 mm in z; the report says so, with the analytic bound."""
    L0, stroke = 750.0, 300.0
    z_home = np.sqrt((L0 + stroke / 2) ** 2 - R_H ** 2)
    cfg = variant(actuator__stroke_mm=stroke, home_pose__pz_mm=float(z_home))
    r = axis_range(cfg, "pz", 250.0)
    assert not r.reaches_limit
    assert r.upper == pytest.approx(np.sqrt((L0 + stroke) ** 2 - R_H ** 2) - z_home, abs=2e-3)
    assert r.lower == pytest.approx(np.sqrt(L0 ** 2 - R_H ** 2) - z_home, abs=2e-3)
    assert r.upper_by == "; ".join(f"leg {i} stroke beyond full extension" for i in range(1, 7))
    assert r.lower_by == "; ".join(f"leg {i} stroke below 0 mm (fully retracted)" for i in range(1, 7))


def test_tight_joints_limit_lateral_reach():
    cfg = variant(joints__base_max_deg=10.0, joints__top_max_deg=10.0)
    r = axis_range(cfg, "px", 250.0)
    assert not r.reaches_limit
    assert "joint" in (r.upper_by or "") and "joint" in (r.lower_by or "")
    assert 100 < r.upper < 250 and -250 < r.lower < -100


def test_home_outside_stroke_is_a_config_error(tmp_path):
    from fringecal.config import ConfigError
    from fringecal.hexapod.config import default_hexapod_config_path, load_hexapod_config

    text = default_hexapod_config_path().read_text().replace("pz_mm: 833.167", "pz_mm: 1500.0")
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match="home_pose needs strokes"):
        load_hexapod_config(bad)
    bad.write_text(default_hexapod_config_path().read_text().replace("speed_mm_s:", "sped_mm_s:"))
    with pytest.raises(ConfigError, match=r"bad.yaml: invalid configuration(.|\n)*actuator.sped_mm_s: unknown key"):
        load_hexapod_config(bad)


def test_combined_translations_report_the_largest_cube():
    """+-250 mm along each axis alone is not +-250 mm along all three at once."""
    import itertools

    from fringecal.hexapod.workspace import cube_reach, describe_violations

    cube = cube_reach(CFG, 250.0)
    assert not cube.inside and 100.0 < cube.largest_half_mm < 250.0
    home = CFG.home_pose.vector
    signs = np.array(list(itertools.product((-1, 1), repeat=3)), float)
    corners = np.repeat(home[None], 8, axis=0)
    corners[:, :3] += cube.largest_half_mm * signs
    assert check_poses(CFG, corners).ok.all()
    beyond = home.copy()
    beyond[:3] += np.array(cube.worst_offset_mm) * (cube.largest_half_mm + 0.02) / cube.largest_half_mm
    chk = check_poses(CFG, beyond)
    assert not chk.ok
    assert describe_violations(CFG, chk)[0].split(" stroke")[0] in cube.limited_by
    assert cube_reach(CFG, 100.0).inside
