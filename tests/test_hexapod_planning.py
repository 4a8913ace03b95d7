"""Planning: artefact poses <-> platform poses <-> counts, the thesis rig placement."""

from __future__ import annotations

import numpy as np
import pytest

from fringecal.frames import Frame
from fringecal.hexapod import HexapodRig, load_hexapod_config
from fringecal.hexapod.kinematics import inverse_kinematics
from fringecal.hexapod.planning import (
    COUNT_COLUMNS,
    centre_base_on_poses,
    counts_from_lengths,
    frames_from_table,
    lengths_from_counts,
    plan_with_stations,
    thesis_grid,
)
from fringecal.schemas import HexapodPlanTable, PosePlanTable, TableError, read_table, write_table

CFG = load_hexapod_config()


@pytest.fixture(scope="module")
def table61(thesis_dir):
    return read_table(thesis_dir / "poses_scanner1_table6-1.csv", PosePlanTable)


def test_counts_are_zero_at_stroke_zero():
    L0, cpm = CFG.actuator.retracted_length_mm, CFG.actuator.counts_per_mm
    assert counts_from_lengths(CFG, [L0, L0 + 0.026, L0 + 500, L0 + 250, L0 - 1, L0 + 0.024]).tolist() == \
        [0, 1, 10000, 5000, -20, 0]
    assert lengths_from_counts(CFG, [0, 5000]) == pytest.approx([L0, L0 + 5000 / cpm])
    assert CFG.actuator.max_counts == 10000


def test_mounting_puts_the_supported_spheres_on_the_top_platform(thesis_artefact):
    """Spheres 5 and 14 at 150 mm above TOP over the T1-T3 member, sphere 1 on the longer support."""
    top = CFG.T_top_artefact.frame.to_world(thesis_artefact.centres_of(["5", "1", "14"]))
    assert top[:, 2] == pytest.approx([150.0, 321.5, 149.2], abs=0.05)
    assert top[[0, 2], 0] == pytest.approx(CFG.platform.top_vertices[0, 0], abs=1.0)
    # the artefact's CMM z axis is the TOP z axis (level mounting)
    assert CFG.T_top_artefact.frame.R[2] == pytest.approx([0, 0, 1], abs=1e-12)


def test_default_placement_is_derived_from_table_6_1(table61):
    T = centre_base_on_poses(CFG, frames_from_table(table61), CFG.T_top_artefact.frame)
    assert T.t == pytest.approx(CFG.T_world_base.frame.t, abs=1e-3)
    assert T.angles == pytest.approx(CFG.T_world_base.frame.angles, abs=1e-8)
    # BASE Z (up) is world +y
    assert CFG.T_world_base.frame.R[2] == pytest.approx([0, 1, 0], abs=1e-9)


def test_all_twelve_thesis_poses_are_reachable_and_round_trip(table61):
    rig = HexapodRig.from_config(CFG)
    plan = rig.plan(table61)
    assert plan.reachable.all(), plan.limits.tolist()
    assert (plan.limits == "ok").all()
    for T, row in zip(frames_from_table(table61), plan.itertuples(index=False)):
        pose = np.array([row.px_mm, row.py_mm, row.pz_mm, row.alpha_rad, row.beta_rad, row.gamma_rad])
        back = rig.artefact_pose_for(pose)
        assert back.t == pytest.approx(T.t, abs=1e-9)
        assert back.R == pytest.approx(T.R, abs=1e-12)
        counts = counts_from_lengths(CFG, inverse_kinematics(CFG.platform, pose))
        assert [getattr(row, c) for c in COUNT_COLUMNS] == counts.tolist()
    # excursions from home inside +-250 mm; tilts of a few mrad (table 6-1 prints angles to 1 mrad)
    assert plan.px_mm.abs().max() < 250 and plan.py_mm.abs().max() < 250
    assert np.abs(plan[["alpha_rad", "beta_rad"]].to_numpy()).max() < 5e-3
    assert plan.gamma_rad.abs().max() < np.radians(1.5)


def test_plan_table_contract(tmp_path, table61):
    plan = HexapodRig.from_config(CFG).plan(table61)
    path = write_table(plan, tmp_path / "plan.csv", HexapodPlanTable)
    back = read_table(path, HexapodPlanTable)
    assert back.counts_3.tolist() == plan.counts_3.tolist()
    bad = plan.drop(columns=["counts_4"])
    with pytest.raises(TableError, match="counts_4"):
        write_table(bad, tmp_path / "bad.csv", HexapodPlanTable)


def test_thesis_grid_one_station_versus_one_station_per_standoff(table61):
    first = frames_from_table(table61)[0]
    grid = thesis_grid(first)
    assert len(grid) == 12 and grid.measurement.tolist() == [str(i) for i in range(1, 13)]
    t = grid[["tx_mm", "ty_mm", "tz_mm"]].to_numpy()
    assert t[2] - t[0] == pytest.approx([200, 0, 0])
    assert t[11] - t[0] == pytest.approx([200, 0, -1000])
    # one station cannot cover a 1000 mm stand-off range with a +-250 mm platform
    single = HexapodRig.from_config(CFG).plan(grid)
    assert not single.reachable.all()
    assert (~single.reachable[6:]).all()  # stand-offs 2670 and 3000: out of reach
    assert single.limits[~single.reachable].str.contains("stroke|joint").all()
    # one station per stand-off row (the platform rolled on its castors) reaches all twelve
    plan, stations = plan_with_stations(CFG, grid, "standoff_mm")
    assert plan.reachable.all() and len(stations) == 4
    assert plan.station.tolist() == [s for s in "1234" for _ in range(3)]
    gap = stations["2"].t - stations["1"].t
    assert gap == pytest.approx([0, 0, -330], abs=1e-6)


def test_artefact_pose_from_counts_inverts_counts_for(table61):
    rig = HexapodRig.from_config(CFG)
    T = frames_from_table(table61)[4]
    counts, pose = rig.counts_for(T)
    reached, reached_pose = rig.artefact_pose_from_counts(counts, near=pose)
    # only the rounding to whole counts separates them (0.025 mm of leg length at most)
    assert np.abs(reached_pose - pose)[:3].max() < 0.1
    assert np.linalg.norm(reached.t - T.t) < 0.2
    assert isinstance(reached, Frame)
