"""Support conditions of a truss: single-direction constraints at nodes.

A support spec lists ``node:axes`` items, e.g. ``5:xyz,1:yz,14:z`` (the thesis's
3-2-1 supports of section 3.4.2: node 5 fixed in x, y and z, node 1 in y and z,
node 14 in z). Axes are those of the artefact frame. Any direction can be given
through :class:`Supports` itself or a supports table (``sphere_id, nx, ny, nz``,
one row per constrained direction), so a support condition can be rotated with
the structure.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import pandas as pd

from fringecal.engineering.errors import SupportError

__all__ = ["Supports", "parse_supports", "supports_from_table", "MIN_CONSTRAINTS"]

#: Rigid-body freedoms of a body in space: the fewest constraints a 3-D truss needs.
MIN_CONSTRAINTS = 6

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
_ITEM = re.compile(r"^\s*([^:\s,]+)\s*:\s*([A-Za-z]+)\s*$")


@dataclass(frozen=True)
class Supports:
    """Constraints ``n . d_node = 0`` on node displacements.

    Attributes
    ----------
    nodes : tuple of str, length k
        The constrained node of each constraint (a node may appear up to 3 times).
    directions : ndarray, shape (k, 3)
        Unit direction of each constraint, artefact frame.
    """

    nodes: tuple[str, ...]
    directions: np.ndarray

    def __post_init__(self):
        nodes = tuple(str(n) for n in self.nodes)
        d = np.asarray(self.directions, float).reshape(len(nodes), 3)
        norm = np.linalg.norm(d, axis=1)
        if np.any(~np.isfinite(norm)) or np.any(norm < 1e-12):
            bad = [nodes[i] for i in np.flatnonzero(~(norm >= 1e-12))]
            raise SupportError(f"support direction(s) at node(s) {bad} are zero or not finite")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "directions", d / norm[:, None])

    def __len__(self) -> int:
        return len(self.nodes)

    def rotated(self, R) -> "Supports":
        """The same supports after rotating the structure by ``R`` (directions ``R n``)."""
        return Supports(self.nodes, self.directions @ np.asarray(R, float).T)

    def check(self, node_ids) -> None:
        """Raise SupportError for unknown nodes, too few or dependent constraints."""
        known = set(map(str, node_ids))
        unknown = sorted({n for n in self.nodes if n not in known}, key=str)
        if unknown:
            raise SupportError(f"support(s) at unknown node(s) {unknown} (known: {sorted(known, key=_natural)})")
        if len(self) < MIN_CONSTRAINTS:
            raise SupportError(
                f"{len(self)} support constraint(s) given; a space truss needs at least "
                f"{MIN_CONSTRAINTS} (3-2-1: e.g. '5:xyz,1:yz,14:z')")
        for node in dict.fromkeys(self.nodes):
            d = self.directions[[i for i, n in enumerate(self.nodes) if n == node]]
            if len(d) > 3 or np.linalg.matrix_rank(d, tol=1e-9) < len(d):
                raise SupportError(f"node {node}: its {len(d)} support directions are not independent")

    def constraint_matrix(self, node_ids) -> np.ndarray:
        """Rows ``G`` with ``G d = 0`` for the stacked displacements d, shape (k, 3n)."""
        self.check(node_ids)
        index = {str(s): i for i, s in enumerate(node_ids)}
        G = np.zeros((len(self), 3 * len(index)))
        rows = np.arange(len(self))
        cols = 3 * np.array([index[n] for n in self.nodes])
        for k in range(3):
            G[rows, cols + k] = self.directions[:, k]
        return G

    def to_frame(self) -> pd.DataFrame:
        return pd.DataFrame({"sphere_id": list(self.nodes), "nx": self.directions[:, 0],
                             "ny": self.directions[:, 1], "nz": self.directions[:, 2]})

    def describe(self) -> str:
        parts = []
        for node in dict.fromkeys(self.nodes):
            d = self.directions[[i for i, n in enumerate(self.nodes) if n == node]]
            names = []
            for v in d:
                axis = [a for a, e in _AXES.items() if np.allclose(v, e)]
                names.append(axis[0] if axis else "[" + ",".join(f"{c:.3g}" for c in v) + "]")
            parts.append(f"{node}:" + ("".join(names) if all(len(n) == 1 for n in names) else "+".join(names)))
        return ",".join(parts)


def _natural(s: str):
    return (0, int(s), "") if s.isdigit() else (1, 0, s)


def parse_supports(spec: str, node_ids=None) -> Supports:
    """Parse ``node:axes[,node:axes...]``; with ``node_ids`` also check it against a structure.

    >>> s = parse_supports("5:xyz,1:yz,14:z")
    >>> s.nodes, s.describe()
    (('5', '5', '5', '1', '1', '14'), '5:xyz,1:yz,14:z')
    >>> parse_supports("5:xq")
    Traceback (most recent call last):
    ...
    fringecal.engineering.errors.SupportError: support '5:xq': unknown axis 'q' (use x, y, z)
    """
    if not isinstance(spec, str) or not spec.strip():
        raise SupportError("empty support specification; expected e.g. '5:xyz,1:yz,14:z'")
    nodes, dirs, seen = [], [], {}
    for item in spec.split(","):
        m = _ITEM.match(item)
        if not m:
            raise SupportError(f"support item {item.strip()!r} is not of the form node:axes "
                               "(e.g. '5:xyz,1:yz,14:z')")
        node, axes = m.group(1), m.group(2).lower()
        if node in seen:
            raise SupportError(f"node {node} appears twice in {spec!r}; give all its axes at once "
                               f"(e.g. '{node}:{seen[node]}{axes}')")
        seen[node] = axes
        for a in axes:
            if a not in _AXES:
                raise SupportError(f"support {item.strip()!r}: unknown axis {a!r} (use x, y, z)")
        if len(set(axes)) != len(axes):
            raise SupportError(f"support {item.strip()!r}: an axis is repeated")
        for a in axes:
            nodes.append(node)
            dirs.append(_AXES[a])
    s = Supports(tuple(nodes), np.array(dirs))
    if node_ids is not None:
        s.check(node_ids)
    return s


def supports_from_table(df: pd.DataFrame, node_ids=None) -> Supports:
    """Supports from a validated ``SupportsTable`` frame (one row per constraint)."""
    s = Supports(tuple(df["sphere_id"]), df[["nx", "ny", "nz"]].to_numpy(float))
    if node_ids is not None:
        s.check(node_ids)
    return s
