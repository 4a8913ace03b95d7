"""Artefact definitions: sphere centres in the CMM frame, diameters and rods.

The default artefact is the thesis's 15-sphere large-volume artefact with the
coordinates of CMM measurement 2 of table 3-13 (``configs/thesis/artefact_cmm2.csv``):
registering the thesis's measured centres (tables 6-3 and 6-6) against measurement 2
reproduces its pose tables 6-1 and 6-4 to the printed precision, measurement 1 does
not (scanner two's translations miss by up to 0.2 mm), so measurement 2 is what the
thesis used.

Also reads and writes the thesis's legacy artefact definition file (section 6.6):
four rows per sphere (``x``, ``y``, ``z``, ``r``), four whitespace-separated columns:
description, free flag (1 free, 0 fixed), value, accuracy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from fringecal.atomic import write_text
from fringecal.schemas import ArtefactTable, RodsTable, TableError, read_table, validate_table

__all__ = [
    "Artefact",
    "load_artefact",
    "load_rods",
    "check_rods",
    "read_legacy_definition",
    "write_legacy_definition",
]


@dataclass(frozen=True)
class Artefact:
    """Spheres of an artefact in its own (CMM) frame.

    Attributes
    ----------
    ids : tuple of str, length n
    centres : ndarray, shape (n, 3), mm
    diameters : ndarray, shape (n,), mm
    u : ndarray, shape (n,), standard uncertainty of each centre coordinate, mm
    name : str
    """

    ids: tuple[str, ...]
    centres: np.ndarray
    diameters: np.ndarray
    u: np.ndarray = field(default=None)
    name: str = "artefact"

    def __post_init__(self):
        ids = tuple(str(i) for i in self.ids)
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "centres", np.asarray(self.centres, float).reshape(len(ids), 3))
        object.__setattr__(self, "diameters", np.asarray(self.diameters, float).reshape(len(ids)))
        u = np.zeros(len(ids)) if self.u is None else np.asarray(self.u, float).reshape(len(ids))
        object.__setattr__(self, "u", u)
        if len(set(ids)) != len(ids):
            dup = sorted({i for i in ids if ids.count(i) > 1})
            raise ValueError(f"artefact {self.name!r}: duplicate sphere ids {dup}")

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def radii(self) -> np.ndarray:
        return self.diameters / 2

    def index(self, sphere_ids) -> np.ndarray:
        """Row indices of ``sphere_ids``; KeyError naming unknown ids."""
        lookup = {s: i for i, s in enumerate(self.ids)}
        unknown = [s for s in map(str, sphere_ids) if s not in lookup]
        if unknown:
            raise KeyError(f"unknown sphere id(s) {unknown} for artefact {self.name!r} "
                           f"(known: {list(self.ids)})")
        return np.array([lookup[str(s)] for s in sphere_ids], dtype=int)

    def centres_of(self, sphere_ids) -> np.ndarray:
        return self.centres[self.index(sphere_ids)]

    def distance_matrix(self) -> np.ndarray:
        """Inter-centre distances, shape (n, n)."""
        d = self.centres[:, None, :] - self.centres[None, :, :]
        return np.linalg.norm(d, axis=-1)

    @property
    def diagonal_mm(self) -> float:
        """Diagonal of the axis-aligned bounding box of the sphere centres."""
        return float(np.linalg.norm(self.centres.max(0) - self.centres.min(0)))

    def to_frame(self) -> pd.DataFrame:
        return pd.DataFrame({
            "sphere_id": list(self.ids),
            "x_mm": self.centres[:, 0], "y_mm": self.centres[:, 1], "z_mm": self.centres[:, 2],
            "diameter_mm": self.diameters, "u_mm": self.u,
        })

    @classmethod
    def from_frame(cls, df: pd.DataFrame, name: str = "artefact") -> "Artefact":
        df = validate_table(df, ArtefactTable, name)
        u = df["u_mm"].to_numpy(float) if "u_mm" in df.columns else None
        return cls(tuple(df["sphere_id"]), df[["x_mm", "y_mm", "z_mm"]].to_numpy(float),
                   df["diameter_mm"].to_numpy(float), u, name)


def load_artefact(path) -> Artefact:
    """Read an artefact definition CSV (``sphere_id, x_mm, y_mm, z_mm, diameter_mm[, u_mm]``)."""
    df = read_table(path, ArtefactTable)
    u = df["u_mm"].to_numpy(float) if "u_mm" in df.columns else None
    return Artefact(tuple(df["sphere_id"]), df[["x_mm", "y_mm", "z_mm"]].to_numpy(float),
                    df["diameter_mm"].to_numpy(float), u, name=Path(path).stem)


def check_rods(rods: pd.DataFrame, artefact: Artefact, source: str = "<rods>") -> pd.DataFrame:
    """Rods must join two different, known spheres, each pair at most once."""
    problems = []
    known = set(artefact.ids)
    seen: dict[frozenset, int] = {}
    for i, r in rods.reset_index(drop=True).iterrows():
        line = i + 2
        for col in ("sphere_a", "sphere_b"):
            if r[col] not in known:
                problems.append((line, col, f"sphere {r[col]!r} is not in artefact {artefact.name!r}"))
        if r["sphere_a"] == r["sphere_b"]:
            problems.append((line, "sphere_b", f"rod {r['rod_id']!r} joins sphere {r['sphere_a']!r} to itself"))
        key = frozenset((r["sphere_a"], r["sphere_b"]))
        if key in seen:
            problems.append((line, "sphere_a, sphere_b",
                             f"spheres {sorted(key)} are already joined (line {seen[key]})"))
        else:
            seen[key] = line
    if problems:
        raise TableError(source, problems)
    return rods


def load_rods(path, artefact: Artefact | None = None) -> pd.DataFrame:
    """Read a rods table; with ``artefact``, also check that every sphere exists."""
    df = read_table(path, RodsTable)
    if artefact is not None:
        check_rods(df, artefact, str(path))
    return df


def write_legacy_definition(artefact: Artefact, path, free: bool = False) -> Path:
    """Write the thesis's legacy artefact definition file (section 6.6)."""
    path = Path(path)
    flag = "1" if free else "0"
    lines = []
    for i in range(len(artefact)):
        x, y, z = map(float, artefact.centres[i])
        u = float(artefact.u[i])
        for label, value in (("x", x), ("y", y), ("z", z), ("r", float(artefact.radii[i]))):
            lines.append(f"{label}\t{flag}\t{value!r}\t{(u if label != 'r' else 0.0)!r}")
    return write_text(path, "\n".join(lines) + "\n")


def read_legacy_definition(path, ids=None) -> tuple[Artefact, np.ndarray]:
    """Read a legacy definition; returns the artefact and free flags, shape (n, 4).

    Spheres are numbered 1..n in file order unless ``ids`` is given.
    """
    path = Path(path)
    rows = []
    for lineno, raw in enumerate(path.read_text().splitlines(), 1):
        if not raw.strip():
            continue
        parts = raw.split()
        if len(parts) != 4:
            raise TableError(str(path), [(lineno, None, f"expected 4 columns (description, free, value, "
                                                        f"accuracy), found {len(parts)}: {raw!r}")])
        rows.append((lineno, parts))
    if len(rows) % 4:
        raise TableError(str(path), [(None, None, f"{len(rows)} rows is not a multiple of 4 "
                                                  "(x, y, z, r per sphere)")])
    n = len(rows) // 4
    values = np.empty((n, 4))
    acc = np.empty((n, 4))
    flags = np.empty((n, 4), dtype=bool)
    for k, (lineno, (label, flag, value, accuracy)) in enumerate(rows):
        s, j = divmod(k, 4)
        expected = "xyzr"[j]
        if label.lower() != expected:
            raise TableError(str(path), [(lineno, "description", f"expected {expected!r}, found {label!r}")])
        if flag not in ("0", "1"):
            raise TableError(str(path), [(lineno, "free", f"flag must be 0 or 1, found {flag!r}")])
        try:
            values[s, j] = float(value)
            acc[s, j] = float(accuracy)
        except ValueError:
            raise TableError(str(path), [(lineno, "value", f"not a number: {value!r} / {accuracy!r}")]) from None
        flags[s, j] = flag == "1"
    if np.any(values[:, 3] <= 0):
        bad = int(np.flatnonzero(values[:, 3] <= 0)[0])
        raise TableError(str(path), [(rows[4 * bad + 3][0], "value", "sphere radius must be > 0")])
    ids = tuple(str(i + 1) for i in range(n)) if ids is None else tuple(map(str, ids))
    art = Artefact(ids, values[:, :3], 2 * values[:, 3], acc[:, :3].max(axis=1), name=path.stem)
    return art, flags
