"""Acceptance-test positions (VDI/VDE 2634 parts 2 and 3) planned in the thesis rig's
measurement volumes, checked against the volumes, the seven directions of the
guideline, the fields and the incidence on the flat."""

from dataclasses import replace

import numpy as np
import pytest

from fringecal.acceptance.plan import (
    FLAT_POSITIONS,
    PLAN_COLUMNS,
    dumbbell_bars,
    flat_face_points,
    flat_fits,
    flat_frame,
    plan_acceptance,
    volume_box,
)
from fringecal.acceptance.standards import AcceptanceStandards, DumbbellStandard, FlatStandard, load_standards
from fringecal.config import ConfigError
from fringecal.frames import frames_from_rows
from fringecal.simulate.settings import SimulationConfig
from fringecal.simulate.source import acquisition_table, load_simulated_rig, true_volumes
from fringecal.verification.lengths import seven_ballbar_positions

COUNTS = {"sphere": 10, "dumbbell": 7, "flat": 6}


@pytest.fixture(scope="module")
def thesis():
    """The thesis rig as the default simulation builds it (true sensors, planned poses),
    its measurement volumes and the default acceptance certificates."""
    sim = SimulationConfig()
    sr = load_simulated_rig(sim)
    return sim, sr, true_volumes(sr.truth, sr.artefact, sr.planned), load_standards(sim.acceptance.standards_path())


@pytest.fixture(scope="module")
def plan(thesis):
    sim, sr, volumes, standards = thesis
    return plan_acceptance(sr.truth, volumes, standards, COUNTS, seed=sim.acceptance.seed)


def rows(plan, test, scanner):
    df = plan.positions
    return df[(df["test"] == test) & (df["scanner"] == scanner)]


def sight_angles_deg(volume, X, along):
    """Angles (n,) between the bar direction ``along`` (n, 3) at sphere X (n, 3) and the
    lines of sight from X to camera and projector (the smaller of the two)."""
    out = []
    for sensor in (volume.camera, volume.projector):
        sight = sensor.pinhole - X
        cos = np.sum(sight * along, axis=1) / np.linalg.norm(sight, axis=1) / np.linalg.norm(along, axis=1)
        out.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.minimum(*out)


def test_the_thesis_rig_plans_10_7_6_positions_per_scanner(thesis, plan):
    sim, sr, volumes, standards = thesis
    assert plan.uncovered == []
    df = plan.positions
    assert list(df.columns) == list(PLAN_COLUMNS)
    for k, scanner in enumerate(("scanner1", "scanner2"), start=1):
        for test, n in COUNTS.items():
            assert list(rows(plan, test, scanner)["measurement"]) == [f"{test}-{k}-{i:02d}" for i in range(1, n + 1)]
    assert len(df) == 46 and df["measurement"].is_unique
    # the simulated rig carries exactly this plan, and each position becomes one store of its scanner
    np.testing.assert_array_equal(sr.acceptance[list(PLAN_COLUMNS)].to_numpy(), df.to_numpy())
    assert sr.acceptance_standards == standards
    table = acquisition_table(sr)
    acc = table[table["kind"].isin(["sphere", "dumbbell", "flat"])]
    assert list(acc["measurement"]) == [f"{m}-{s}" for m, s in zip(df["measurement"], df["scanner"])]
    assert list(acc["kind"]) == list(df["test"]) and list(acc["pose"]) == list(df["measurement"])


def test_sphere_centres_are_inside_and_spread_over_the_volume(thesis, plan):
    _, sr, volumes, standards = thesis
    radius = standards.sphere.diameter_mm / 2
    for scanner, volume in volumes.items():
        df = rows(plan, "sphere", scanner)
        X = df[["tx_mm", "ty_mm", "tz_mm"]].to_numpy()
        assert np.all(df[["omega_rad", "phi_rad", "kappa_rad"]].to_numpy() == 0)
        vol = replace(volume, radius_mm=radius)
        assert vol.contains(X).all()
        d = np.linalg.norm(X[:, None] - X[None], axis=2)[np.triu_indices(len(X), 1)]
        assert d.min() > 250.0  # ten spheres spread over ~0.9 x 0.9 x 1.2 m, not clustered
        depth = volume.camera.to_sensor(X)[:, 2]
        lo, hi = volume.depth_range_mm
        assert depth.max() - depth.min() > 0.7 * (hi - lo)  # near and far
        xy = volume.camera.to_sensor(X)[:, :2] / depth[:, None]
        assert np.all(np.ptp(xy, axis=0) > 0.2)  # across the image (field ~0.29 wide per unit depth)


def test_dumbbell_positions_are_the_seven_directions_inside_the_volume(thesis, plan):
    _, sr, volumes, standards = thesis
    bell = standards.dumbbell
    for scanner, volume in volumes.items():
        vol = replace(volume, radius_mm=bell.diameter_mm / 2)
        frames = frames_from_rows(rows(plan, "dumbbell", scanner))
        A = np.array([T.to_world([[0.0, 0, 0]])[0] for T in frames.values()])
        B = np.array([T.to_world([[bell.length_mm, 0, 0]])[0] for T in frames.values()])
        assert vol.contains(A).all() and vol.contains(B).all()
        np.testing.assert_allclose(np.linalg.norm(B - A, axis=1), bell.length_mm, atol=1e-9)
        mid = (A + B) / 2
        np.testing.assert_allclose(mid, mid[[0] * 7], atol=1e-9)  # every bar centred at the box's centre
        # bar directions in the camera frame against the seven of the guideline in the volume's box
        centre, half = volume_box(vol, np.random.default_rng(0))  # another draw of the box: about the same
        c = vol.camera.R @ (centre - vol.camera.pinhole)
        ideal = seven_ballbar_positions(c - half, c + half, 1.0)
        u = (ideal[:, 1] - ideal[:, 0])
        v = (B - A) @ vol.camera.R.T / bell.length_mm
        azimuth = lambda w: np.degrees(np.arctan2(w[:, 1], w[:, 0]))  # noqa: E731
        elevation = lambda w: np.degrees(np.arcsin(w[:, 2] / np.linalg.norm(w, axis=1)))  # noqa: E731
        np.testing.assert_allclose(azimuth(v), azimuth(u), atol=1.0)  # across the image: the seven directions
        assert np.all(np.sign(np.round(v[:, 2], 9)) == np.sign(np.round(u[:, 2], 9)))
        assert np.all(np.abs(elevation(v)) <= np.abs(elevation(u)) + 1.0)  # only ever tilted toward the image
        # the space diagonals and the two face diagonals through depth run within 60 deg of a line of
        # sight as the box gives them; tilted, every bar keeps 60 deg off at both spheres
        assert np.all(np.minimum(sight_angles_deg(vol, A, B - A), sight_angles_deg(vol, B, A - B))
                      >= 60.0 - 1e-9)
        assert np.all(np.abs(elevation(v)[[0, 1, 2, 3, 5, 6]]) > 10.0)  # still out of the image plane
        np.testing.assert_allclose(v[4], u[4] / np.linalg.norm(u[4]), atol=2e-3)  # the x-y face diagonal: as is
        angles = np.degrees(np.arccos(np.clip(np.abs(v @ v.T), 0, 1)))[np.triu_indices(7, 1)]
        # seven different lines (a bar has no sense); the closest are the x-y face diagonal and the two
        # space diagonals over the same image diagonal, tilted to 13..26 deg on either side of it
        assert angles.min() > 10.0 and np.sort(angles)[3] > 25.0


def test_dumbbell_tilt_is_the_least_that_clears_the_lines_of_sight(thesis):
    _, sr, volumes, standards = thesis
    bell = standards.dumbbell
    volume = volumes["scanner1"]
    vol = replace(volume, radius_mm=bell.diameter_mm / 2)
    bars = dumbbell_bars(volume, bell.length_mm, bell.diameter_mm / 2, np.random.default_rng(5))
    tilts = [t for _, _, t, _ in bars]
    assert all(p == "" for *_, p in bars)
    assert tilts[4] == 0.0 and all(t > 0 for i, t in enumerate(tilts) if i != 4)
    axis = vol.camera.R[2]
    for A, B, tilt, _ in bars:
        if tilt == 0:
            continue
        u, mid = (B - A) / bell.length_mm, (A + B) / 2
        across = u - (u @ axis) * axis
        el = np.arcsin(abs(u @ axis)) + np.radians(0.5)  # half a step less tilt
        w = np.cos(el) * across / np.linalg.norm(across) + np.sign(u @ axis) * np.sin(el) * axis
        a, b = mid - w * bell.length_mm / 2, mid + w * bell.length_mm / 2
        assert min(sight_angles_deg(vol, a[None], w[None])[0], sight_angles_deg(vol, b[None], -w[None])[0]) < 60.0


def test_flat_positions_fit_the_fields_at_incidence_below_60_deg(thesis, plan):
    _, sr, volumes, standards = thesis
    flat = standards.flat
    for scanner, volume in volumes.items():
        frames = list(frames_from_rows(rows(plan, "flat", scanner)).values())
        assert len(frames) == len(FLAT_POSITIONS) == 6
        depth_of_centre = []
        for T in frames:
            P = flat_face_points(flat, T)
            corners = T.to_world([[sx * flat.length_mm / 2, sy * flat.width_mm / 2, 0]
                                  for sx in (-1, 1) for sy in (-1, 1)])
            np.testing.assert_allclose(P[[0, 4, 10, 14]][[0, 2, 1, 3]], corners, atol=1e-9)
            for sensor in (volume.camera, volume.projector):
                assert sensor.in_view(P).all()
                sight = sensor.pinhole - P
                incidence = np.degrees(np.arccos(sight @ T.R[2] / np.linalg.norm(sight, axis=1)))
                assert incidence.max() < 60.0
            d = volume.camera.to_sensor(P)[:, 2]
            assert volume.depth_range_mm[0] <= d.min() and d.max() <= volume.depth_range_mm[1]
            depth_of_centre.append(volume.camera.to_sensor(T.t[None])[0, 2])
        # the normal: along the bisector for 1 and 2, tilted by 30 deg about the length (3, 4) and
        # the width (5, 6); the length along one image diagonal (1-4), the other one for 5 and 6
        def bisector(p):
            w = sum((s.pinhole - p) / np.linalg.norm(s.pinhole - p) for s in (volume.camera, volume.projector))
            return w / np.linalg.norm(w)
        tilt = [np.degrees(np.arccos(np.clip(T.R[2] @ bisector(T.t), -1, 1))) for T in frames]
        np.testing.assert_allclose(tilt, [0, 0, 30, 30, 30, 30], atol=1e-6)
        for i in (2, 3):
            assert abs(frames[i].R[0] @ bisector(frames[i].t)) < 1e-9  # turned about its length axis
        for i in (4, 5):
            assert abs(frames[i].R[1] @ bisector(frames[i].t)) < 1e-9  # turned about its width axis
        x_img = np.array([volume.camera.R[:2] @ T.R[0] for T in frames])
        assert np.all(x_img[:4, 0] * x_img[:4, 1] > 0) and np.all(x_img[4:, 0] * x_img[4:, 1] < 0)
        assert depth_of_centre[1] - depth_of_centre[0] > 500.0  # near and far
        # the planner's own check agrees; the near position is the nearest that fits (5 mm steps)
        assert all(flat_fits(volume, flat, T) for T in frames)
        for i, (_, diagonal, axis, sign, _) in enumerate(FLAT_POSITIONS):
            again = flat_frame(volume, frames[i].t, diagonal, axis, sign * np.radians(30.0))
            np.testing.assert_allclose(again.R, frames[i].R, atol=1e-12)
        ray = frames[0].t - volume.camera.pinhole
        nearer = frames[0].t - 5.0 * ray / (ray @ volume.camera.R[2])
        assert not flat_fits(volume, flat, flat_frame(volume, nearer, 0, None, 0.0))
        assert depth_of_centre[0] < min(depth_of_centre[2:]) and depth_of_centre[1] > max(depth_of_centre[2:])


def test_a_seed_gives_the_same_plan_and_scanners_plan_independently(thesis, plan):
    sim, sr, volumes, standards = thesis
    again = plan_acceptance(sr.truth, volumes, standards, COUNTS, seed=sim.acceptance.seed)
    np.testing.assert_array_equal(again.positions.to_numpy(), plan.positions.to_numpy())
    other = plan_acceptance(sr.truth, volumes, standards, COUNTS, seed=sim.acceptance.seed + 1).positions
    assert not np.allclose(other[other.test == "sphere"][["tx_mm", "ty_mm", "tz_mm"]].to_numpy(),
                           plan.positions[plan.positions.test == "sphere"][["tx_mm", "ty_mm", "tz_mm"]].to_numpy())
    # without scanner two's volume, scanner one's positions stay and scanner two is reported
    alone = plan_acceptance(sr.truth, {"scanner1": volumes["scanner1"]}, standards, COUNTS, seed=sim.acceptance.seed)
    np.testing.assert_array_equal(alone.positions.to_numpy(), rows_of(plan.positions, "scanner1").to_numpy())
    assert alone.uncovered == ["scanner2: no measurement volume (no sphere, dumbbell, flat position)"]


def rows_of(df, scanner):
    return df[df["scanner"] == scanner].reset_index(drop=True)


def test_left_out_objects_zero_counts_and_misfits(thesis):
    sim, sr, volumes, standards = thesis
    only_sphere = AcceptanceStandards(sphere=standards.sphere)
    p = plan_acceptance(sr.truth, volumes, only_sphere, COUNTS)
    assert set(p.positions["test"]) == {"sphere"} and p.uncovered == []
    p = plan_acceptance(sr.truth, volumes, standards, {"sphere": 0, "dumbbell": 2, "flat": 0})
    assert list(p.positions["measurement"]) == ["dumbbell-1-01", "dumbbell-1-02", "dumbbell-2-01", "dumbbell-2-02"]
    assert plan_acceptance(sr.truth, volumes, standards, {}).positions.empty
    # a 1.5 m dumbbell and a 1.5 m flat do not fit a ~0.9 m field; eight flat positions are not defined
    big = AcceptanceStandards(sphere=standards.sphere, dumbbell=DumbbellStandard(length_mm=1500.0, diameter_mm=50.8),
                              flat=FlatStandard(length_mm=1500.0, width_mm=100.0))
    p = plan_acceptance(sr.truth, {"scanner1": volumes["scanner1"]}, big, {"sphere": 2, "dumbbell": 7, "flat": 8})
    assert list(p.positions["test"]) == ["sphere", "sphere"]
    assert len(p.uncovered) == 7 + 6 + 1 + 1  # seven directions, six flat positions, the 7th and 8th, scanner2
    assert "scanner1: dumbbell direction 1 (space diagonal): sphere A of the 1500 mm bar leaves the volume" \
        in p.uncovered or "scanner1: dumbbell direction 1 (space diagonal): sphere B of the 1500 mm bar leaves " \
        "the volume" in p.uncovered
    assert "scanner1: flat position 'facing, near': the 1500 x 100 mm face fits at no depth" in p.uncovered
    assert "scanner1: flat: 8 positions asked, 6 are defined" in p.uncovered


def test_the_simulation_refuses_positions_that_do_not_fit_and_can_be_switched_off(tmp_path):
    path = tmp_path / "acceptance.yaml"
    path.write_text("dumbbell:\n  length_mm: 1500\n  diameter_mm: 50.8\n")
    with pytest.raises(ConfigError, match=r"acceptance.yaml: the acceptance positions asked for do not fit .*"
                                          r"scanner1: dumbbell direction 1 \(space diagonal\)"):
        load_simulated_rig(SimulationConfig(acceptance={"standards": path}))
    sr = load_simulated_rig(SimulationConfig(acceptance={"standards": path, "enabled": False}))
    assert sr.acceptance is None and sr.acceptance_standards is None
    assert set(acquisition_table(sr)["kind"]) == {"artefact", "ballbar"}


def test_positions_lie_in_the_specified_measuring_volume(thesis):
    """A specification's depths (along each camera's axis) cut the volumes the positions
    are planned in: every sphere centre, dumbbell sphere and flat face point lies inside;
    a specified volume that misses a scanner's is refused, naming both."""
    sim, sr, volumes, standards = thesis
    inside = load_simulated_rig(sim, (2400.0, 3000.0))
    frames = frames_from_rows(inside.acceptance)
    assert len(inside.acceptance) == 2 * sum(COUNTS.values())
    for r in inside.acceptance.itertuples(index=False):
        T = frames[r.measurement]
        X = {"sphere": T.t[None], "dumbbell": T.to_world(np.array([[0.0, 0, 0], [standards.dumbbell.length_mm, 0, 0]])),
             "flat": flat_face_points(standards.flat, T)}[r.test]
        depth = sr.truth.scanner(r.scanner).camera.to_sensor(X)[:, 2]
        assert depth.min() >= 2400.0 - 1e-6 and depth.max() <= 3000.0 + 1e-6, r.measurement
    spheres = sr.acceptance[sr.acceptance["test"] == "sphere"]
    centres = frames_from_rows(spheres)
    far = max(sr.truth.scanner(r.scanner).camera.to_sensor(centres[r.measurement].t[None])[0, 2]
              for r in spheres.itertuples(index=False))
    assert far > 3500.0  # without a specification the spheres reach the far end (3.6 m)
    with pytest.raises(ConfigError, match=r"scanner1: the specified measuring volume \(depths 4000-4500 mm\) misses "
                                          r"the volume the artefact calibrates \(2429-3657 mm\)"):
        load_simulated_rig(sim, (4000.0, 4500.0))
