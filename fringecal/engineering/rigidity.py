"""Rigidity of a bar-and-joint framework (thesis section 3.4.1, Maxwell-Laman).

Counting: a framework of N joints in space needs E = 3N - 6 bars to be minimally
rigid (eq. 3-1). The count is necessary, not sufficient (in 3-D no counting rule is),
so rigidity is decided from the rigidity matrix R (one row per bar,
``(p_a - p_b)`` at a and ``(p_b - p_a)`` at b, shape (E, 3N)):

* infinitesimal flexes are the velocities ``v`` with ``R v = 0``; the trivial ones
  are the rigid motions (6 for joints spanning a plane or more, 5 on a line);
  the others are flexes, and the joints that move in them are the under-braced part;
* self-stresses are bar tensions ``w`` with ``R^T w = 0``; the bars carrying one are
  redundant (removing any one of them keeps the rank), the over-braced part.

The framework is infinitesimally rigid at its actual coordinates if
``rank R = 3N - trivial``; generic rigidity (a property of the graph alone) is the
same test at random coordinates, which hits the generic rank with probability 1.
Both are reported: a generically rigid graph built flat or otherwise special can
still be flexible at its actual coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import null_space

__all__ = ["rigidity_matrix", "trivial_motions", "rigid_components", "RigidityReport", "analyse_rigidity"]


def rigidity_matrix(coords, members) -> np.ndarray:
    """Rigidity matrix, shape (E, 3N).

    Parameters
    ----------
    coords : array_like, shape (N, 3)
    members : array_like of int, shape (E, 2)

    >>> rigidity_matrix([[0, 0, 0], [2, 0, 0]], [[0, 1]])
    array([[-2.,  0.,  0.,  2.,  0.,  0.]])
    """
    X = np.asarray(coords, float)
    M = np.asarray(members, int).reshape(-1, 2)
    diff = X[M[:, 0]] - X[M[:, 1]]
    R = np.zeros((len(M), X.size))
    rows = np.arange(len(M))[:, None]
    cols = np.arange(3)[None, :]
    R[rows, 3 * M[:, :1] + cols] = diff
    R[rows, 3 * M[:, 1:] + cols] = -diff
    return R + 0.0  # no negative zeros


def trivial_motions(coords) -> np.ndarray:
    """Orthonormal basis of the rigid-body velocities of the joints, shape (3N, t), t <= 6."""
    X = np.asarray(coords, float)
    n = len(X)
    c = X - X.mean(axis=0)
    T = np.zeros((3 * n, 6))
    for k in range(3):
        T[k::3, k] = 1.0
        w = np.zeros(3)
        w[k] = 1.0
        T[:, 3 + k] = np.cross(w, c).ravel()
    u, s, _ = np.linalg.svd(T, full_matrices=False)
    tol = max(T.shape) * np.finfo(float).eps * (s[0] if s.size else 1) * 1e3
    return u[:, s > tol]


def _maximal_cliques(adj: np.ndarray) -> list[tuple[int, ...]]:
    """Maximal cliques of a small undirected graph (Bron-Kerbosch with pivoting)."""
    nbrs = [set(np.flatnonzero(row)) - {i} for i, row in enumerate(adj)]
    out: list[tuple[int, ...]] = []

    def grow(r: set, p: set, x: set):
        if not p and not x:
            out.append(tuple(sorted(r)))
            return
        pivot = max(p | x, key=lambda u: len(nbrs[u] & p))
        for v in list(p - nbrs[pivot]):
            grow(r | {v}, p & nbrs[v], x & nbrs[v])
            p = p - {v}
            x = x | {v}

    grow(set(), set(range(len(adj))), set())
    return sorted(out, key=lambda c: (-len(c), c))


def rigid_components(coords, members, rtol: float = 1e-9, tol: float = 1e-7) -> list[tuple[int, ...]]:
    """Maximal sets of joints that keep their mutual distances in every flex.

    Joints i, j belong to one rigid body when a bar i-j would be implied by the
    others (its row lies in the row space of R, i.e. is orthogonal to every flex);
    rigid bodies are the maximal cliques of that relation, largest first. Bodies
    may share joints (hinges).

    Returns
    -------
    list of tuple of int
        Node indices of each rigid body.
    """
    X = np.asarray(coords, float)
    scale = float(np.linalg.norm(X.max(0) - X.min(0))) or 1.0
    X = X / scale
    N = null_space(rigidity_matrix(X, members), rcond=rtol).reshape(len(X), 3, -1)
    dp = X[:, None, :] - X[None, :, :]                       # (n, n, 3)
    dv = N[:, None] - N[None, :]                             # (n, n, 3, k)
    rate = np.abs(np.einsum("ijc,ijck->ijk", dp, dv)).max(axis=-1, initial=0.0)
    return _maximal_cliques(rate <= tol)


def _rank(A: np.ndarray, rtol: float) -> int:
    if A.size == 0:
        return 0
    s = np.linalg.svd(A, compute_uv=False)
    return int(np.sum(s > rtol * s[0])) if s[0] > 0 else 0


@dataclass(frozen=True)
class RigidityReport:
    """Counting and rank results for one framework.

    Attributes
    ----------
    n_nodes, n_members : int
    maxwell_excess : int
        E - (3N - 6): 0 meets the count of eq. 3-1, > 0 over-braced, < 0 under-braced.
    trivial : int
        Rigid-body freedoms of the joints (6, or 5 for collinear joints).
    rank, rank_generic : int
        Rank of R at the actual coordinates and at random (generic) coordinates.
    self_stresses : ndarray, shape (s, E)
        Orthonormal basis of self-stresses at the actual coordinates.
    flexes : ndarray, shape (f, N, 3)
        Basis of the non-trivial infinitesimal flexes at the actual coordinates, each
        relative to the largest rigid body (which stays still), unit norm.
    redundant_members : tuple of str
        Members carrying a self-stress (any one can be removed without loss of rank).
    flexible_nodes : tuple of str
        Nodes that move relative to the largest rigid body in some flex.
    rigid_bodies : tuple of tuple of str
        Maximal rigid sub-frameworks (:func:`rigid_components`), largest first.
    """

    n_nodes: int
    n_members: int
    maxwell_excess: int
    trivial: int
    rank: int
    rank_generic: int
    self_stresses: np.ndarray = field(repr=False)
    flexes: np.ndarray = field(repr=False)
    redundant_members: tuple[str, ...]
    flexible_nodes: tuple[str, ...]
    rigid_bodies: tuple[tuple[str, ...], ...] = ()

    @property
    def required_rank(self) -> int:
        return 3 * self.n_nodes - self.trivial

    @property
    def infinitesimally_rigid(self) -> bool:
        return self.rank == self.required_rank

    @property
    def generically_rigid(self) -> bool:
        return self.rank_generic == self.required_rank

    @property
    def minimally_rigid(self) -> bool:
        """Rigid with no redundant member (E = rank = 3N - 6)."""
        return self.infinitesimally_rigid and self.n_members == self.rank

    def summary(self) -> dict:
        return {
            "n_nodes": self.n_nodes, "n_members": self.n_members,
            "maxwell_required_members": 3 * self.n_nodes - 6,
            "maxwell_excess": self.maxwell_excess,
            "rank": self.rank, "rank_generic": self.rank_generic, "required_rank": self.required_rank,
            "infinitesimally_rigid": self.infinitesimally_rigid,
            "generically_rigid": self.generically_rigid,
            "minimally_rigid": self.minimally_rigid,
            "n_self_stresses": int(len(self.self_stresses)), "n_flexes": int(len(self.flexes)),
            "redundant_members": list(self.redundant_members),
            "flexible_nodes": list(self.flexible_nodes),
            "rigid_bodies": [list(b) for b in self.rigid_bodies],
        }


def analyse_rigidity(coords, members, node_ids=None, member_ids=None, seed: int = 0,
                     n_generic: int = 3, rtol: float = 1e-9, part_tol: float = 1e-6) -> RigidityReport:
    """Maxwell count, infinitesimal and generic rigidity, redundant members and flexes.

    Parameters
    ----------
    coords : array_like, shape (N, 3), mm
    members : array_like of int, shape (E, 2)
    node_ids, member_ids : sequences of str, optional
    seed : int
        Seed of the random (generic) configurations.
    n_generic : int
        Number of random configurations; the largest rank found is the generic rank.
    rtol : float
        Singular values below ``rtol * largest`` count as zero.
    part_tol : float
        A member is redundant (a node flexible) if its share of the self-stress
        (flex) space exceeds this.

    Examples
    --------
    An octahedron is minimally rigid; remove a bar and one flex appears.

    >>> X = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    >>> bars = [[i, j] for i in range(6) for j in range(i + 1, 6) if i // 2 != j // 2]
    >>> analyse_rigidity(X, bars).minimally_rigid
    True
    >>> r = analyse_rigidity(X, bars[1:])
    >>> r.maxwell_excess, len(r.flexes), r.infinitesimally_rigid
    (-1, 1, False)
    """
    X = np.asarray(coords, float)
    M = np.asarray(members, int).reshape(-1, 2)
    n, m = len(X), len(M)
    node_ids = tuple(str(i) for i in (node_ids if node_ids is not None else range(1, n + 1)))
    member_ids = tuple(str(i) for i in (member_ids if member_ids is not None else range(1, m + 1)))
    scale = float(np.linalg.norm(X.max(0) - X.min(0))) or 1.0
    R = rigidity_matrix(X / scale, M)
    rank = _rank(R, rtol)
    rng = np.random.default_rng(seed)
    rank_generic = max(_rank(rigidity_matrix(rng.uniform(-1, 1, size=X.shape), M), rtol)
                       for _ in range(max(n_generic, 1)))
    T = trivial_motions(X / scale)
    stresses = null_space(R.T, rcond=rtol).T if m else np.zeros((0, 0))
    N = null_space(R, rcond=rtol) if m else np.eye(3 * n)
    P = N - T @ (T.T @ N)  # the rigid motions lie in the null space; keep the rest
    u, s, _ = np.linalg.svd(P, full_matrices=False)
    flex = u[:, s > 0.5].T  # s is ~1 (flex) or ~0 (rigid motion)
    stress_share = np.sqrt((stresses ** 2).sum(axis=0)) if stresses.size else np.zeros(m)
    bodies = rigid_components(X, M, rtol) if len(flex) else [tuple(range(n))]
    if len(flex):
        flex = _relative_to(flex, X / scale, bodies[0])
    flex_nodes = flex.reshape(len(flex), n, 3)
    node_share = np.abs(flex_nodes).max(axis=(0, 2)) if len(flex) else np.zeros(n)
    return RigidityReport(
        n_nodes=n, n_members=m, maxwell_excess=m - (3 * n - 6), trivial=T.shape[1],
        rank=rank, rank_generic=rank_generic, self_stresses=stresses, flexes=flex_nodes,
        redundant_members=tuple(member_ids[i] for i in np.flatnonzero(stress_share > part_tol)),
        flexible_nodes=tuple(node_ids[i] for i in np.flatnonzero(node_share > part_tol)),
        rigid_bodies=tuple(tuple(node_ids[i] for i in b) for b in bodies),
    )


def _relative_to(flex: np.ndarray, X: np.ndarray, body) -> np.ndarray:
    """Flexes (f, 3N) minus the rigid motion of ``body``, so that body stays still."""
    idx = np.array(body)
    T = trivial_motions(X)                                   # (3N, t)
    rows = (3 * idx[:, None] + np.arange(3)).ravel()
    coef, *_ = np.linalg.lstsq(T[rows], flex[:, rows].T, rcond=None)
    rel = flex - (T @ coef).T
    norms = np.linalg.norm(rel, axis=1, keepdims=True)
    return rel / np.where(norms > 0, norms, 1.0)
