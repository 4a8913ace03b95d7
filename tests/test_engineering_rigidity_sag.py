"""Rigidity (Maxwell-Laman count, rank, self-stresses, flexes) and the gravity-sag correction."""

import numpy as np
import pytest

from fringecal.artefact import load_artefact, load_rods
from fringecal.engineering import (
    SupportCondition,
    Truss,
    analyse_rigidity,
    gravity_in_artefact_frame,
    gravity_sag_correction,
    load_materials,
    mass_loads,
    parse_supports,
    solve_truss,
)
from fringecal.engineering.rigidity import rigid_components
from fringecal.frames import Frame

OCTA = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float) * 300
OCTA_BARS = [[i, j] for i in range(6) for j in range(i + 1, 6) if i // 2 != j // 2]


def members(art, rods):
    return np.column_stack([art.index(rods.sphere_a), art.index(rods.sphere_b)])


def test_thesis_artefact_is_minimally_rigid(thesis_dir, thesis_artefact):
    rods = load_rods(thesis_dir / "rods.csv", thesis_artefact)
    rep = analyse_rigidity(thesis_artefact.centres, members(thesis_artefact, rods), thesis_artefact.ids, rods.rod_id)
    s = rep.summary()
    assert (s["maxwell_excess"], s["rank"], s["rank_generic"], s["required_rank"]) == (0, 39, 39, 39)
    assert rep.minimally_rigid and not rep.redundant_members and not rep.flexible_nodes


def test_octahedron_minus_and_plus_a_bar():
    assert analyse_rigidity(OCTA, OCTA_BARS).minimally_rigid
    less = analyse_rigidity(OCTA, OCTA_BARS[1:])
    assert (less.maxwell_excess, len(less.flexes), less.generically_rigid) == (-1, 1, False)
    more = analyse_rigidity(OCTA, OCTA_BARS + [[0, 1]])  # a diagonal through the centre
    assert more.infinitesimally_rigid and not more.minimally_rigid
    assert len(more.self_stresses) == 1 and len(more.redundant_members) == 13  # every bar shares it


def test_flat_realisation_of_a_generically_rigid_graph():
    flat = OCTA.copy()
    flat[:, 2] = 0.0
    flat[4] = [120, 80, 0]
    flat[5] = [-90, 60, 0]
    rep = analyse_rigidity(flat, OCTA_BARS)
    assert rep.generically_rigid and not rep.infinitesimally_rigid
    assert rep.rank < rep.rank_generic and len(rep.flexes) == rep.required_rank - rep.rank


def test_double_banana_meets_the_count_but_is_not_rigid(rng):
    """Two triangular bipyramids sharing their poles: E = 3N - 6 = 18, one hinge flex, one self-stress."""
    poles = np.array([[0, 0, 500.0], [0, 0, -500.0]])
    eq1 = np.array([[200 + 100 * np.cos(a), 100 * np.sin(a), 0] for a in (0, 2.1, 4.2)])
    eq2 = np.array([[-200 + 100 * np.cos(a), 100 * np.sin(a), 30] for a in (0.3, 2.4, 4.5)])
    X = np.vstack([poles, eq1, eq2])
    bars = []
    for ring in ([2, 3, 4], [5, 6, 7]):
        bars += [[ring[0], ring[1]], [ring[1], ring[2]], [ring[0], ring[2]]]
        bars += [[p, q] for p in (0, 1) for q in ring]
    rep = analyse_rigidity(X, bars, list("NSabcdef"))
    assert rep.maxwell_excess == 0 and not rep.generically_rigid
    assert len(rep.flexes) == 1 and len(rep.self_stresses) == 1
    bodies = [set(b) for b in rep.rigid_bodies]
    assert {"N", "S", "a", "b", "c"} in bodies and {"N", "S", "d", "e", "f"} in bodies
    assert set(rep.flexible_nodes) == {"d", "e", "f"} or set(rep.flexible_nodes) == {"a", "b", "c"}
    assert rigid_components(X, bars)[0] in ((0, 1, 2, 3, 4), (0, 1, 5, 6, 7))


@pytest.fixture(scope="module")
def thesis(thesis_dir):
    art = load_artefact(thesis_dir / "artefact_cmm2.csv")
    return art, load_rods(thesis_dir / "rods.csv", art), load_materials(thesis_dir / "materials.yaml")


def test_sag_same_condition_is_no_correction(thesis):
    art, rods, mat = thesis
    c = SupportCondition("5:xyz,1:yz,14:z", (0, 0, -1))
    res = gravity_sag_correction(art, rods, mat, c, c)
    assert res.max_correction_mm == 0.0
    np.testing.assert_array_equal(res.artefact.centres, art.centres)


def test_sag_reversed_gravity_is_minus_twice_the_cmm_sag(thesis):
    art, rods, mat = thesis
    cmm = SupportCondition("5:xyz,1:yz,14:z", (0, 0, -1))
    flipped = SupportCondition("5:xyz,1:yz,14:z", (0, 0, 1))
    res = gravity_sag_correction(art, rods, mat, cmm, flipped, remove_rigid=False)
    truss = Truss.from_artefact(art, rods, mat)
    d = solve_truss(truss, cmm.supports, mass_loads(truss, art.diameters, mat, (0, 0, -1)).forces_n).displacements_mm
    np.testing.assert_allclose(res.artefact.centres - art.centres, -2 * d, rtol=0, atol=1e-12)  # round-off of 2 m coordinates
    # removing the rigid part of the correction changes no distance
    rigid_free = gravity_sag_correction(art, rods, mat, cmm, flipped).artefact
    np.testing.assert_allclose(rigid_free.distance_matrix(), res.artefact.distance_matrix(), rtol=0, atol=1e-11)
    assert np.abs(rigid_free.centres - res.artefact.centres).max() > 1e-3  # the rigid part was microns
    assert np.abs(res.artefact.distance_matrix() - art.distance_matrix()).max() > 1e-3 * 1e-3  # > 1 nm: real change


def test_sag_correction_for_a_tilted_pose_is_microns(thesis):
    art, rods, mat = thesis
    pose = Frame.from_params([0, 0, 0, 0, np.radians(10), 0])  # tilted 10 deg about the long axis
    g = gravity_in_artefact_frame(pose)
    np.testing.assert_allclose(g, pose.R @ [0, 0, -1], atol=1e-15)
    res = gravity_sag_correction(art, rods, mat, SupportCondition("5:xyz,1:yz,14:z", (0, 0, -1)),
                                 SupportCondition("5:xyz,1:yz,14:z", g))
    assert 1e-3 < res.max_correction_mm < 3e-3
    assert list(res.table.columns[:4]) == ["sphere_id", "cmm_dx_mm", "cmm_dy_mm", "cmm_dz_mm"]


def test_supports_rotate_with_the_structure():
    s = parse_supports("a:xyz,b:yz,c:z")
    R = Frame.from_params([0, 0, 0, 0.3, 0.2, 0.1]).R
    np.testing.assert_allclose(s.rotated(R).directions, s.directions @ R.T)
