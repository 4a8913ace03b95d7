"""Kinematics of the 6-3 Stewart platform (thesis section 4.3) against the printed equations."""

from __future__ import annotations

import numpy as np
import pytest

from fringecal.hexapod import load_hexapod_config
from fringecal.hexapod.kinematics import (
    ForwardKinematicsError,
    PlatformGeometry,
    forward_kinematics,
    inverse_kinematics,
    leg_jacobian,
    pose_from_frame,
    pose_to_frame,
    rotation_base_top,
    top_joints_in_base,
)
from fringecal.hexapod.workspace import check_poses

A, B, D = 1100.0, 1100.0, 450.0
GEOM = PlatformGeometry(A, B, D)
S3 = np.sqrt(3.0)


def eq43(al, be, ga):
    """Eq. 4-3 written out entry by entry."""
    sa, ca, sb, cb, sg, cg = np.sin(al), np.cos(al), np.sin(be), np.cos(be), np.sin(ga), np.cos(ga)
    return np.array([
        [cb * cg + sa * sb * sg, -cb * sg + sa * sb * cg, ca * sb],
        [ca * sg, ca * cg, -sa],
        [-sb * cg + sa * cb * sg, sb * sg + sa * cb * cg, ca * cb],
    ])


def eqs_4_5_to_4_20(pose, a=A, b=B, d=D, printed=False):
    """Leg lengths by the expanded eqs. 4-5..4-13 and 4-15..4-20, with the typos corrected
    (``printed=True`` uses the printed 4-10 and 4-15 instead)."""
    px, py, pz, al, be, ga = pose
    sa, ca, sb, cb = np.sin(al), np.cos(al), np.sin(be), np.cos(be)
    k = a / S3
    g60p, g60m = ga + np.pi / 3, ga - np.pi / 3
    XT1 = px + k * (sa * sb * np.sin(g60p) + cb * np.cos(g60p))
    YT1 = py + k * ca * np.sin(g60p)
    ZT1 = pz + k * (sa * cb * np.sin(g60p) - sb * np.cos(g60p))
    XT2 = px - k * (sa * sb * np.sin(ga) + cb * np.cos(ga))
    YT2 = py - k * ca * np.sin(ga)
    ZT2 = pz - k * ((sa * sb if printed else sa * cb) * np.sin(ga) - sb * np.cos(ga))  # eq. 4-10
    XT3 = px + k * (sa * sb * np.sin(g60m) + cb * np.cos(g60m))
    YT3 = py + k * ca * np.sin(g60m)
    ZT3 = pz + k * (sa * cb * np.sin(g60m) - sb * np.cos(g60m))
    b_term_1 = d * b / S3 if printed else b / S3  # eq. 4-15 prints "d b / sqrt(3)"
    return np.array([
        np.sqrt((XT1 - d / (2 * S3) - b_term_1) ** 2 + (YT1 - d / 2) ** 2 + ZT1 ** 2),
        np.sqrt((XT1 - d / (2 * S3) + b / (2 * S3)) ** 2 + (YT1 - d / 2 - b / 2) ** 2 + ZT1 ** 2),
        np.sqrt((XT2 + d / S3 + b / (2 * S3)) ** 2 + (YT2 - b / 2) ** 2 + ZT2 ** 2),
        np.sqrt((XT2 + d / S3 + b / (2 * S3)) ** 2 + (YT2 + b / 2) ** 2 + ZT2 ** 2),
        np.sqrt((XT3 - d / (2 * S3) + b / (2 * S3)) ** 2 + (YT3 + b / 2 + d / 2) ** 2 + ZT3 ** 2),
        np.sqrt((XT3 - d / (2 * S3) - b / S3) ** 2 + (YT3 + d / 2) ** 2 + ZT3 ** 2),
    ])


def random_poses(rng, n, trans=250.0, rot_deg=8.0, z0=833.167):
    p = np.empty((n, 6))
    p[:, :3] = rng.uniform(-trans, trans, (n, 3))
    p[:, 2] += z0
    p[:, 3:] = np.radians(rng.uniform(-rot_deg, rot_deg, (n, 3)))
    return p


def test_vertices_follow_eqs_4_1_and_4_2():
    Bv, Tv = GEOM.base_vertices, GEOM.top_vertices
    assert Bv[0] == pytest.approx([S3 / 6 * (2 * B + D), D / 2, 0])
    assert Bv[2] == pytest.approx([-S3 / 6 * (B + 2 * D), B / 2, 0])
    assert Bv[4] == pytest.approx([-S3 / 6 * (B - D), -(B + D) / 2, 0])
    # semi-regular hexagon: sides alternate b (B1B2, B3B4, B5B6) and d (B2B3, B4B5, B6B1)
    sides = np.linalg.norm(Bv - np.roll(Bv, -1, axis=0), axis=1)
    assert sides == pytest.approx([B, D, B, D, B, D])
    assert np.linalg.norm(Bv, axis=1) == pytest.approx(np.full(6, np.linalg.norm(Bv[0])))
    # equilateral top triangle of side a, centred on the TOP origin
    assert np.linalg.norm(Tv - np.roll(Tv, -1, axis=0), axis=1) == pytest.approx([A, A, A])
    assert Tv.mean(axis=0) == pytest.approx([0, 0, 0], abs=1e-12)
    # legs 1,2 -> T1, 3,4 -> T2, 5,6 -> T3
    assert GEOM.top_joints[[0, 1, 2, 3, 4, 5]] == pytest.approx(Tv[[0, 0, 1, 1, 2, 2]])


def test_rotation_is_eq_4_3(rng):
    for al, be, ga in rng.uniform(-1.2, 1.2, (20, 3)):
        assert rotation_base_top(al, be, ga) == pytest.approx(eq43(al, be, ga), abs=1e-15)
    # the approach vector (TOP z axis) depends on alpha, beta only; gamma rolls about it
    R1, R2 = rotation_base_top(0.2, -0.3, 0.0), rotation_base_top(0.2, -0.3, 1.0)
    assert R1[:, 2] == pytest.approx(R2[:, 2])


def test_inverse_kinematics_matches_corrected_expansions(rng):
    poses = random_poses(rng, 50, rot_deg=20.0)
    lengths = inverse_kinematics(GEOM, poses)
    expanded = np.array([eqs_4_5_to_4_20(p) for p in poses])
    assert lengths == pytest.approx(expanded, abs=1e-9)
    # the vertex positions of eqs. 4-5..4-13 are eq. 4-4 applied to eq. 4-2
    T = top_joints_in_base(GEOM, poses[0])
    assert T[0] == pytest.approx(eq43(*poses[0][3:]) @ GEOM.top_vertices[0] + poses[0][:3])


def test_printed_typos_really_differ():
    """Eq. 4-15 (d b / sqrt 3) and eq. 4-10 (sin a sin b sin g) as printed give other lengths."""
    pose = np.array([20.0, -30.0, 850.0, 0.1, 0.15, 0.2])
    correct, printed = eqs_4_5_to_4_20(pose), eqs_4_5_to_4_20(pose, printed=True)
    assert abs(printed[0] - correct[0]) > 100.0      # d b / sqrt(3) is ~2.9e5 mm
    assert abs(printed[2] - correct[2]) > 0.1        # eq. 4-10 typo
    assert printed[[1, 4, 5]] == pytest.approx(correct[[1, 4, 5]])


def test_jacobian_matches_finite_differences(rng):
    for pose in random_poses(rng, 5, rot_deg=15.0):
        J = leg_jacobian(GEOM, pose)
        num = np.empty((6, 6))
        for k in range(6):
            h = 1e-5 if k < 3 else 1e-8
            e = np.zeros(6)
            e[k] = h
            num[:, k] = (inverse_kinematics(GEOM, pose + e) - inverse_kinematics(GEOM, pose - e)) / (2 * h)
        assert J == pytest.approx(num, rel=1e-6, abs=1e-5)


def test_ik_then_fk_round_trip_over_the_workspace(rng):
    """Must-show: IK then FK returns the pose within 1e-6 mm and 1e-9 rad."""
    cfg = load_hexapod_config()
    poses = random_poses(rng, 2000, trans=300.0, rot_deg=12.0)
    poses = poses[check_poses(cfg, poses).ok]
    assert len(poses) > 200
    lengths = inverse_kinematics(cfg.platform, poses)
    fk = forward_kinematics(cfg.platform, lengths, start=cfg.home_pose.vector)
    err = np.abs(fk.poses - poses)
    assert err[:, :3].max() < 1e-6
    assert err[:, 3:].max() < 1e-9
    assert fk.iterations <= 10


def test_fk_reports_non_convergence():
    with pytest.raises(ForwardKinematicsError, match="did not converge.*residual"):
        forward_kinematics(GEOM, [100.0, 3000.0, 100.0, 3000.0, 100.0, 3000.0], start=[0, 0, 833, 0, 0, 0])
    with pytest.raises(ForwardKinematicsError, match="finite and positive"):
        forward_kinematics(GEOM, [1000.0, -1, 1000, 1000, 1000, 1000], start=[0, 0, 833, 0, 0, 0])


def test_pose_frame_conversion_agrees_with_eq_4_4(rng):
    for pose in random_poses(rng, 10, rot_deg=30.0):
        T_base_top = pose_to_frame(pose)
        assert T_base_top.to_world(GEOM.top_joints) == pytest.approx(top_joints_in_base(GEOM, pose), abs=1e-9)
        assert pose_from_frame(T_base_top) == pytest.approx(pose, abs=1e-12)
