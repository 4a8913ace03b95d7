"""Space-truss analysis by the stiffness-matrix method (thesis section 3.4.1).

Nodes are sphere centres, members are rods with pin (ball-and-socket) ends, loads
act at the nodes. Per member (eqs. 3-4..3-14) the global stiffness is
``EA/L [[e e^T, -e e^T], [-e e^T, e e^T]]`` with ``e`` the direction cosines; the
structure stiffness ``S = C^T diag(EA/L) C`` is assembled at once from the
compatibility matrix ``C`` (member elongation = ``C d``). Supports remove
displacement components (:mod:`.supports`); ``S d = F`` (eq. 3-15) is solved on the
remaining ones. Member forces are ``EA/L e.(d_b - d_a)``, tension positive, and
stresses force / area (eq. 3-16).

A supported structure whose reduced stiffness is singular is a mechanism: it is
reported with its free motions (the null space, per node) and not solved.

Units: mm, N, N/mm^2 (= MPa).

Examples
--------
Two bars from (+-400, 0, 0) meeting at (0, 0, 300) under 1 kN downwards: each
carries P/(2 sin theta) = 1000 / (2 * 0.6) in compression.

>>> t = Truss(("A", "B", "C"), [[-400, 0, 0], [400, 0, 0], [0, 0, 300]], [[0, 2], [1, 2]],
...           ea_n=[1e7, 1e7])
>>> sol = solve_truss(t, parse_supports("A:xyz,B:xyz,C:y"), [[0, 0, 0], [0, 0, 0], [0, 0, -1000]])
>>> sol.forces_n.round(6)
array([-833.333333, -833.333333])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.linalg import null_space

from fringecal.artefact import Artefact, check_rods
from fringecal.engineering.errors import MechanismError, TrussError
from fringecal.engineering.supports import Supports, parse_supports

__all__ = ["Truss", "TrussSolution", "solve_truss", "free_motions", "describe_motion", "parse_supports"]

#: Members shorter than this (mm) are refused as zero-length.
MIN_LENGTH_MM = 1e-6


@dataclass(frozen=True)
class Truss:
    """A pin-jointed space truss.

    Attributes
    ----------
    node_ids : tuple of str, length n
    coords : ndarray, shape (n, 3), mm
    members : ndarray of int, shape (m, 2)
        Node indices (a, b) of each member.
    ea_n : ndarray, shape (m,)
        Axial stiffness E*A of each member, N.
    area_mm2 : ndarray, shape (m,)
        Cross-section for stresses, mm^2 (NaN if unknown).
    member_ids : tuple of str, length m
    """

    node_ids: tuple[str, ...]
    coords: np.ndarray
    members: np.ndarray
    ea_n: np.ndarray
    area_mm2: np.ndarray = None
    member_ids: tuple[str, ...] = None

    def __post_init__(self):
        ids = tuple(str(i) for i in self.node_ids)
        X = np.asarray(self.coords, float).reshape(len(ids), 3)
        M = np.asarray(self.members, dtype=int).reshape(-1, 2)
        m = len(M)
        ea = np.broadcast_to(np.asarray(self.ea_n, float), (m,)).copy()
        area = np.full(m, np.nan) if self.area_mm2 is None else \
            np.broadcast_to(np.asarray(self.area_mm2, float), (m,)).copy()
        mids = tuple(str(i + 1) for i in range(m)) if self.member_ids is None else tuple(map(str, self.member_ids))
        for name, v in (("node_ids", ids), ("member_ids", mids)):
            if len(set(v)) != len(v):
                raise TrussError(f"truss: duplicate {name} {sorted({i for i in v if v.count(i) > 1})}")
        if len(mids) != m:
            raise TrussError(f"truss: {len(mids)} member ids for {m} members")
        if not np.all(np.isfinite(X)):
            raise TrussError("truss: node coordinates must be finite")
        if m and (M.min() < 0 or M.max() >= len(ids)):
            raise TrussError(f"truss: member node index out of range 0..{len(ids) - 1}")
        if np.any(~(ea > 0)):
            raise TrussError(f"truss: members {[mids[i] for i in np.flatnonzero(~(ea > 0))]} need EA > 0")
        same = M[:, 0] == M[:, 1]
        if same.any():
            raise TrussError(f"truss: member(s) {[mids[i] for i in np.flatnonzero(same)]} join a node to itself")
        pairs = np.sort(M, axis=1)
        _, first, counts = np.unique(pairs, axis=0, return_index=True, return_counts=True)
        if np.any(counts > 1):
            dup = [mids[i] for i in first[counts > 1]]
            raise TrussError(f"truss: member(s) {dup} are repeated (same two nodes)")
        L = np.linalg.norm(X[M[:, 1]] - X[M[:, 0]], axis=1)
        short = L < MIN_LENGTH_MM
        if short.any():
            bad = [f"{mids[i]} ({ids[M[i, 0]]}-{ids[M[i, 1]]})" for i in np.flatnonzero(short)]
            raise TrussError(f"truss: zero-length member(s) {bad}: their two nodes coincide")
        for name, v in (("node_ids", ids), ("coords", X), ("members", M), ("ea_n", ea),
                        ("area_mm2", area), ("member_ids", mids)):
            object.__setattr__(self, name, v)

    @classmethod
    def from_artefact(cls, artefact: Artefact, rods: pd.DataFrame, materials=None,
                      ea_n=None, area_mm2=None, source: str = "<rods>") -> "Truss":
        """Nodes at the sphere centres, one member per rod (``rod_id, sphere_a, sphere_b``).

        Section and stiffness come from ``materials`` (:class:`~.materials.Materials`,
        the tube of table 3-1) unless ``ea_n`` / ``area_mm2`` are given. Rods naming
        unknown spheres raise TableError naming the line of ``source``.
        """
        check_rods(rods, artefact, source)
        if ea_n is None:
            if materials is None:
                raise TrussError("truss: give materials or ea_n")
            ea_n = materials.tube_ea_n
        if area_mm2 is None and materials is not None:
            area_mm2 = materials.tube.area_mm2
        members = np.column_stack([artefact.index(rods["sphere_a"]), artefact.index(rods["sphere_b"])])
        return cls(artefact.ids, artefact.centres, members, ea_n, area_mm2, tuple(rods["rod_id"]))

    @property
    def n_nodes(self) -> int:
        return len(self.node_ids)

    @property
    def n_members(self) -> int:
        return len(self.members)

    @property
    def vectors(self) -> np.ndarray:
        """Member vectors b - a, shape (m, 3), mm."""
        return self.coords[self.members[:, 1]] - self.coords[self.members[:, 0]]

    @property
    def lengths(self) -> np.ndarray:
        """Member lengths, shape (m,), mm (eq. 3-5)."""
        return np.linalg.norm(self.vectors, axis=1)

    @property
    def directions(self) -> np.ndarray:
        """Direction cosines a -> b, shape (m, 3) (eqs. 3-6..3-8)."""
        return self.vectors / self.lengths[:, None]

    @property
    def member_names(self) -> list[str]:
        return [f"{self.node_ids[a]}-{self.node_ids[b]}" for a, b in self.members]

    def index(self, node_ids) -> np.ndarray:
        lookup = {s: i for i, s in enumerate(self.node_ids)}
        missing = [str(s) for s in node_ids if str(s) not in lookup]
        if missing:
            raise TrussError(f"truss: unknown node(s) {missing}")
        return np.array([lookup[str(s)] for s in node_ids], dtype=int)

    def compatibility_matrix(self) -> np.ndarray:
        """``C`` with member elongations ``C d``, shape (m, 3n); rows ``[-e at a, +e at b]``."""
        m, e = self.n_members, self.directions
        C = np.zeros((m, 3 * self.n_nodes))
        rows = np.arange(m)[:, None]
        cols = np.arange(3)[None, :]
        C[rows, 3 * self.members[:, :1] + cols] = -e
        C[rows, 3 * self.members[:, 1:] + cols] = e
        return C

    def stiffness_matrix(self) -> np.ndarray:
        """Structure stiffness ``S = C^T diag(EA/L) C`` (sum of eq. 3-14), shape (3n, 3n), N/mm."""
        C = self.compatibility_matrix()
        return C.T @ (C * (self.ea_n / self.lengths)[:, None])

    def transformed(self, R, t=(0.0, 0.0, 0.0)) -> "Truss":
        """The truss with node coordinates ``R x + t`` (a rigid motion of the whole structure)."""
        X = self.coords @ np.asarray(R, float).T + np.asarray(t, float)
        return Truss(self.node_ids, X, self.members, self.ea_n, self.area_mm2, self.member_ids)


@dataclass(frozen=True)
class TrussSolution:
    """Displacements, member forces and reactions of a supported, loaded truss.

    Attributes
    ----------
    truss : Truss
    supports : Supports
    loads_n : ndarray, shape (n, 3), N
    displacements_mm : ndarray, shape (n, 3)
    forces_n : ndarray, shape (m,), tension positive
    reactions_n : ndarray, shape (k,)
        Force of each support constraint along its direction, N.
    """

    truss: Truss
    supports: Supports
    loads_n: np.ndarray
    displacements_mm: np.ndarray
    forces_n: np.ndarray
    reactions_n: np.ndarray

    @property
    def stresses_mpa(self) -> np.ndarray:
        """Axial stresses, N/mm^2 (eq. 3-16), shape (m,)."""
        return self.forces_n / self.truss.area_mm2

    @property
    def equilibrium_residual_n(self) -> float:
        """Largest nodal force imbalance ``|C^T N - F - G^T R|``, N (a self-check)."""
        t = self.truss
        G = self.supports.constraint_matrix(t.node_ids)
        r = t.compatibility_matrix().T @ self.forces_n - self.loads_n.ravel() - G.T @ self.reactions_n
        return float(np.abs(r).max())

    def max_tension(self) -> tuple[float, str]:
        """Largest tensile force (N) and the member name, e.g. ``(35.3, '1-3')``."""
        i = int(np.argmax(self.forces_n))
        return float(self.forces_n[i]), self.truss.member_names[i]

    def magnet_safety_factor(self, pull_off_n: float) -> float:
        """Pull-off rating over the largest tension (section 3.5.1); inf if no member is in tension."""
        f, _ = self.max_tension()
        return float(pull_off_n / f) if f > 0 else float("inf")

    def forces_table(self) -> pd.DataFrame:
        t = self.truss
        return pd.DataFrame({
            "rod_id": list(t.member_ids),
            "sphere_a": [t.node_ids[a] for a in t.members[:, 0]],
            "sphere_b": [t.node_ids[b] for b in t.members[:, 1]],
            "length_mm": t.lengths,
            "force_n": self.forces_n,
            "stress_mpa": self.stresses_mpa,
        })

    def displacements_table(self) -> pd.DataFrame:
        d = self.displacements_mm
        return pd.DataFrame({"sphere_id": list(self.truss.node_ids), "dx_mm": d[:, 0], "dy_mm": d[:, 1],
                             "dz_mm": d[:, 2], "d_mm": np.linalg.norm(d, axis=1)})

    def reactions_table(self) -> pd.DataFrame:
        df = self.supports.to_frame()
        df["reaction_n"] = self.reactions_n
        return df


def _reduced_basis(truss: Truss, supports: Supports) -> np.ndarray:
    """Orthonormal basis Z of the displacements the supports allow, shape (3n, 3n - k)."""
    G = supports.constraint_matrix(truss.node_ids)
    if np.linalg.matrix_rank(G) < len(supports):
        raise TrussError("supports: constraints are linearly dependent")
    return null_space(G)


def free_motions(truss: Truss, supports: Supports, rcond: float = 1e-10) -> np.ndarray:
    """Free motions of the supported truss (null space of its reduced stiffness).

    Returns
    -------
    ndarray, shape (k, n, 3)
        Orthonormal displacement modes; k = 0 for a stable structure.
    """
    Z = _reduced_basis(truss, supports)
    lam, V = np.linalg.eigh(Z.T @ truss.stiffness_matrix() @ Z)
    scale = lam.max() if lam.size and lam.max() > 0 else 1.0
    null = V[:, lam <= rcond * scale]
    return (Z @ null).T.reshape(-1, truss.n_nodes, 3)


def _rigid_fit(mode: np.ndarray, coords: np.ndarray):
    """Least-squares ``v + w x (x - c)`` to a mode (n, 3): (v, w, c, relative residual)."""
    c = coords.mean(axis=0)
    r = coords - c
    A = np.zeros((len(coords), 3, 6))
    A[:, :, :3] = np.eye(3)
    # w x r = -r x w = [r]_x^T w
    A[:, 0, 4], A[:, 0, 5] = r[:, 2], -r[:, 1]
    A[:, 1, 3], A[:, 1, 5] = -r[:, 2], r[:, 0]
    A[:, 2, 3], A[:, 2, 4] = r[:, 1], -r[:, 0]
    p, *_ = np.linalg.lstsq(A.reshape(-1, 6), mode.ravel(), rcond=None)
    res = np.linalg.norm(A.reshape(-1, 6) @ p - mode.ravel()) / max(np.linalg.norm(mode), 1e-300)
    return p[:3], p[3:], c, res


def describe_motion(mode: np.ndarray, node_ids, coords=None, n_nodes: int = 6, tol: float = 1e-6) -> str:
    """One line describing a free motion ``mode`` (shape (n, 3)).

    With ``coords`` a rigid-body motion is named as such (a translation, or a
    rotation about an axis); otherwise the moving nodes are listed, largest first.
    """
    if coords is not None:
        v, w, c, res = _rigid_fit(mode, np.asarray(coords, float))
        if res < 1e-6:
            wn = np.linalg.norm(w)
            fmt = lambda a: "(" + ", ".join(f"{x:+.3f}" for x in a) + ")"  # noqa: E731
            if wn < 1e-9 * np.linalg.norm(v) / max(np.ptp(coords, axis=0).max(), 1e-300):
                return f"the whole structure translates along {fmt(v / np.linalg.norm(v))}"
            axis = w / wn
            point = c + np.cross(w, v) / wn ** 2
            return (f"the whole structure rotates about the axis through {fmt(point)} mm "
                    f"along {fmt(axis)}")
    amp = np.linalg.norm(mode, axis=1)
    order = np.argsort(-amp, kind="stable")
    moving = [i for i in order if amp[i] > tol * max(amp.max(), 1e-300)]
    parts = [f"{node_ids[i]} ({', '.join(f'{c:+.2f}' for c in mode[i] / amp.max())})" for i in moving[:n_nodes]]
    more = f" and {len(moving) - n_nodes} more" if len(moving) > n_nodes else ""
    return "nodes " + "; ".join(parts) + more


def solve_truss(truss: Truss, supports: Supports, loads_n, rcond: float = 1e-10) -> TrussSolution:
    """Solve ``S d = F`` with the supports' displacement components held at zero.

    Parameters
    ----------
    truss : Truss
    supports : Supports
        At least six independent constraints (3-2-1 or more).
    loads_n : array_like, shape (n, 3)
        External force at each node, N.
    rcond : float
        Eigenvalues of the reduced stiffness below ``rcond * max`` count as zero.

    Raises
    ------
    SupportError
        Unknown nodes, fewer than six constraints.
    MechanismError
        The reduced stiffness is singular; ``err.modes`` holds the free motions.
    """
    F = np.asarray(loads_n, float)
    if F.shape != (truss.n_nodes, 3):
        raise TrussError(f"loads: expected shape ({truss.n_nodes}, 3), got {F.shape}")
    Z = _reduced_basis(truss, supports)
    S = truss.stiffness_matrix()
    lam, V = np.linalg.eigh(Z.T @ S @ Z)
    scale = lam.max() if lam.size and lam.max() > 0 else 1.0
    zero = lam <= rcond * scale
    if zero.any():
        modes = (Z @ V[:, zero]).T.reshape(-1, truss.n_nodes, 3)
        lines = [f"  free motion {k + 1}: {describe_motion(m, truss.node_ids, truss.coords)}"
                 for k, m in enumerate(modes)]
        raise MechanismError(
            f"the truss with supports {supports.describe()} is a mechanism: its stiffness is singular "
            f"({len(modes)} free motion(s)); add rods or supports.\n" + "\n".join(lines),
            modes, truss.node_ids)
    q = V @ ((V.T @ (Z.T @ F.ravel())) / lam)
    d = Z @ q
    forces = (truss.ea_n / truss.lengths) * (truss.compatibility_matrix() @ d)
    G = supports.constraint_matrix(truss.node_ids)
    reactions, *_ = np.linalg.lstsq(G.T, S @ d - F.ravel(), rcond=None)
    return TrussSolution(truss, supports, F, d.reshape(-1, 3), forces, reactions)
