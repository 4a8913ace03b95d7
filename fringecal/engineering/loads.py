"""Nodal loads of an artefact truss: gravity on its parts, or prescribed per node / rod end.

Mass loads (default): each sphere's weight at its node; each rod's tube, two end caps
and two magnets as point masses on the rod axis, shared between the rod's two nodes
by the lever rule (a mass at distance s from node a along a rod of length L puts
``1 - s/L`` of its weight on a and ``s/L`` on b: the statically equivalent nodal
loads of a pin-ended member). Along a rod from sphere a (radius r_a): end cap from
the sphere surface to ``r_a + cap length``, magnet centred at ``r_a + magnet
length / 2`` (it sits in the cap's bore against the sphere), tube between the caps.

Prescribed loads: ``node_load_n`` at every node and ``rod_end_load_n`` per rod end
(so a node with six rods gets six of them), both along gravity. The thesis's
table 3-3 is reproduced by 3.825 N per rod end and nothing else (see docs/engineering.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.engineering.errors import EngineeringInputError, TrussError
from fringecal.engineering.materials import Materials
from fringecal.engineering.truss import Truss

__all__ = ["STANDARD_GRAVITY", "GravityLoads", "unit_vector", "mass_loads", "uniform_loads"]

#: m/s^2
STANDARD_GRAVITY = 9.80665


def unit_vector(v, name: str = "gravity") -> np.ndarray:
    """``v`` normalised, shape (3,); EngineeringInputError if not three finite numbers or zero."""
    a = np.asarray(v, float).ravel()
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise EngineeringInputError(f"{name}: expected three numbers, got {v!r}")
    n = np.linalg.norm(a)
    if n < 1e-12:
        raise EngineeringInputError(f"{name}: the direction must not be zero")
    return a / n


@dataclass(frozen=True)
class GravityLoads:
    """Weights lumped at the nodes.

    Attributes
    ----------
    forces_n : ndarray, shape (n, 3), N
    masses : DataFrame
        Per node: ``sphere_id, sphere_kg, tube_kg, end_cap_kg, magnet_kg, total_kg``.
    gravity : ndarray, shape (3,), unit direction
    g : float, m/s^2
    """

    forces_n: np.ndarray
    masses: pd.DataFrame
    gravity: np.ndarray
    g: float

    @property
    def total_mass_kg(self) -> float:
        return float(self.masses["total_kg"].sum())


def _lever(truss: Truss, mass_kg: np.ndarray, s_mm: np.ndarray) -> np.ndarray:
    """Masses on the member axes at distance s from node a, lumped to nodes, shape (n,)."""
    frac_b = s_mm / truss.lengths
    out = np.bincount(truss.members[:, 0], mass_kg * (1 - frac_b), minlength=truss.n_nodes)
    return out + np.bincount(truss.members[:, 1], mass_kg * frac_b, minlength=truss.n_nodes)


def mass_loads(truss: Truss, diameters_mm, materials: Materials, gravity=(0.0, 0.0, -1.0),
               g: float = STANDARD_GRAVITY) -> GravityLoads:
    """Weights of spheres, tubes, end caps and magnets at the nodes.

    Parameters
    ----------
    truss : Truss
    diameters_mm : array_like, shape (n,)
        Sphere diameters in node order.
    materials : Materials
    gravity : array_like, shape (3,)
        Direction of gravity in the truss frame (normalised here).
    g : float
        Gravitational acceleration, m/s^2.
    """
    gdir = unit_vector(gravity)
    d = np.asarray(diameters_mm, float).reshape(truss.n_nodes)
    r = d / 2
    ra, rb = r[truss.members[:, 0]], r[truss.members[:, 1]]
    cap = materials.end_cap.length_mm
    L = truss.lengths
    tube_len = L - ra - rb - 2 * cap
    if np.any(tube_len < 0):
        bad = [truss.member_names[i] for i in np.flatnonzero(tube_len < 0)]
        raise TrussError(f"rods {bad} are shorter than their spheres' radii plus two end caps "
                         f"({cap} mm each): no room for a tube")
    sphere = materials.sphere_mass_kg(d)
    tube = _lever(truss, materials.tube_mass_kg(tube_len), ra + cap + tube_len / 2)
    mc = np.full(truss.n_members, materials.end_cap_mass_kg)
    caps = _lever(truss, mc, ra + cap / 2) + _lever(truss, mc, L - rb - cap / 2)
    mm = np.full(truss.n_members, materials.magnet_mass_kg)
    half = materials.magnet.length_mm / 2
    magnets = _lever(truss, mm, ra + half) + _lever(truss, mm, L - rb - half)
    total = sphere + tube + caps + magnets
    table = pd.DataFrame({"sphere_id": list(truss.node_ids), "sphere_kg": sphere, "tube_kg": tube,
                          "end_cap_kg": caps, "magnet_kg": magnets, "total_kg": total})
    return GravityLoads(total[:, None] * g * gdir, table, gdir, g)


def uniform_loads(truss: Truss, gravity=(0.0, 0.0, -1.0), node_load_n: float = 0.0,
                  rod_end_load_n: float = 0.0) -> np.ndarray:
    """``node_load_n`` at each node plus ``rod_end_load_n`` per rod end, along gravity, shape (n, 3).

    >>> t = Truss(("a", "b", "c"), [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1], [0, 2]], ea_n=1.0)
    >>> uniform_loads(t, (0, 0, -2), node_load_n=1.0, rod_end_load_n=0.5)[:, 2]
    array([-2. , -1.5, -1.5])
    """
    gdir = unit_vector(gravity)
    degree = np.bincount(truss.members.ravel(), minlength=truss.n_nodes)
    return (node_load_n + rod_end_load_n * degree)[:, None] * gdir
