"""Reproducibility of the artefact's lengths (thesis section 3.7).

Three sources give each rod's centre-to-centre length: the rod measured singly
(table 3-11), the assembled structure (table 3-12) and the distances between the
CMM sphere coordinates (table 3-13, one set per assembly). :func:`rod_length_consistency`
lines them up per rod and summarises each comparison (mean, RMS, worst rod).

:func:`artefact_from_rod_lengths` goes the other way: a minimally rigid structure
(E = 3N - 6) has its shape fixed by its rod lengths, so the single-rod lengths
define sphere coordinates of their own; comparing them with the CMM coordinates
(after a best-fit rigid registration) shows, per sphere, what building the artefact
from single-rod measurements alone would cost.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact, check_rods
from fringecal.engineering.errors import EngineeringInputError
from fringecal.engineering.truss import Truss
from fringecal.registration import kabsch

__all__ = ["ConsistencyReport", "rod_length_consistency", "artefact_from_rod_lengths"]


def _pair_key(a, b) -> tuple[str, str]:
    return tuple(sorted((str(a), str(b))))


def _keyed(df: pd.DataFrame) -> pd.DataFrame:
    out = df.copy()
    out.index = pd.MultiIndex.from_tuples([_pair_key(a, b) for a, b in zip(df["sphere_a"], df["sphere_b"])])
    return out


def _repeat_columns(df: pd.DataFrame) -> list[str]:
    return [c for c in df.columns if c.startswith("length_") and c.endswith("_mm") and c[7:-3].isdigit()]


@dataclass(frozen=True)
class ConsistencyReport:
    """Per-rod lengths and differences, and one summary row per comparison.

    Attributes
    ----------
    rods : DataFrame
        ``rod_id, sphere_a, sphere_b, single_mm[, assembled_mm, assembled_<k>_mm,
        assembled_spread_mm][, coords_<set>_mm...]`` and difference columns
        ``<x>_minus_<y>_um``.
    comparisons : DataFrame
        ``comparison, n, mean_um, rms_um, max_abs_um, worst_rod, worst_spheres, worst_um``.
    """

    rods: pd.DataFrame
    comparisons: pd.DataFrame


def _summarise(rods: pd.DataFrame, col: str, name: str) -> dict:
    d = rods[col].to_numpy(float)
    i = int(np.nanargmax(np.abs(d)))
    return {"comparison": name, "n": int(np.isfinite(d).sum()), "mean_um": float(np.nanmean(d)),
            "rms_um": float(np.sqrt(np.nanmean(d ** 2))), "max_abs_um": float(np.nanmax(np.abs(d))),
            "worst_rod": str(rods["rod_id"].iloc[i]),
            "worst_spheres": f"{rods['sphere_a'].iloc[i]}-{rods['sphere_b'].iloc[i]}", "worst_um": float(d[i])}


def rod_length_consistency(single: pd.DataFrame, assembled: pd.DataFrame | None = None,
                           artefacts: dict[str, Artefact] | None = None) -> ConsistencyReport:
    """Line up rod lengths from single rods, the assembled structure and coordinate sets.

    Parameters
    ----------
    single : DataFrame
        RodsTable of rods measured singly (``length_mm``; optional ``sd_mm``).
    assembled : DataFrame, optional
        RodsTable of the assembled structure (``length_mm``, optional repeats
        ``length_1_mm, length_2_mm, ...``). Rods are matched by their sphere pair.
    artefacts : dict of name -> Artefact, optional
        Coordinate sets; each gives a length per rod as the distance of its spheres.
    """
    artefacts = artefacts or {}
    s = _keyed(single)
    if s.index.duplicated().any():
        raise EngineeringInputError(f"single rods: sphere pairs {list(s.index[s.index.duplicated()])} repeat")
    rods = pd.DataFrame({"rod_id": s["rod_id"].astype(str), "sphere_a": s["sphere_a"].astype(str),
                         "sphere_b": s["sphere_b"].astype(str), "single_mm": s["length_mm"].astype(float)})
    if "sd_mm" in s:
        rods["single_sd_mm"] = s["sd_mm"].astype(float)
    sources = ["single"]
    if assembled is not None:
        a = _keyed(assembled)
        missing = [f"{p[0]}-{p[1]}" for p in rods.index if p not in a.index]
        extra = [f"{p[0]}-{p[1]}" for p in a.index if p not in rods.index]
        if missing or extra:
            raise EngineeringInputError(f"assembled rods do not match the single rods: missing {missing}, "
                                        f"not in the single rods {extra}")
        a = a.loc[rods.index]
        rods["assembled_mm"] = a["length_mm"].astype(float)
        reps = _repeat_columns(a)
        for c in reps:
            rods[f"assembled_{c[7:-3]}_mm"] = a[c].astype(float)
        if len(reps) >= 2:
            r = a[reps].astype(float)
            rods["assembled_spread_mm"] = r.max(axis=1) - r.min(axis=1)
        sources.append("assembled")
    for name, art in artefacts.items():
        check_rods(single, art, f"<rods against {name}>")
        ia, ib = art.index(rods["sphere_a"]), art.index(rods["sphere_b"])
        rods[f"coords_{name}_mm"] = np.linalg.norm(art.centres[ib] - art.centres[ia], axis=1)
        sources.append(f"coords_{name}")
    rows = []
    for x, y in [(x, "single") for x in sources[1:]] + [
            (x, y) for x, y in combinations(sources[1:], 2) if x.startswith("coords") and y.startswith("coords")]:
        col = f"{x}_minus_{y}_um"
        rods[col] = (rods[f"{x}_mm"] - rods[f"{y}_mm"]) * 1e3
        rows.append(_summarise(rods, col, f"{x} - {y}"))
    if "assembled_spread_mm" in rods:
        rods["assembled_spread_um"] = rods["assembled_spread_mm"] * 1e3
        rows.append(_summarise(rods, "assembled_spread_um", "assembled repeats: max - min"))
    reps = [c for c in rods.columns if c.startswith("assembled_") and c[10:-3].isdigit()]
    for name in artefacts:
        for c in reps:
            col = f"coords_{name}_minus_{c[:-3]}_um"
            rods[col] = (rods[f"coords_{name}_mm"] - rods[c]) * 1e3
            rows.append(_summarise(rods, col, f"coords_{name} - {c[:-3]}"))
    return ConsistencyReport(rods.reset_index(drop=True), pd.DataFrame(rows))


def artefact_from_rod_lengths(artefact: Artefact, rods: pd.DataFrame, lengths_mm=None,
                              max_iter: int = 50, tol_mm: float = 1e-10) -> tuple[Artefact, pd.DataFrame]:
    """Sphere coordinates that give the rods their lengths, registered onto ``artefact``.

    Gauss-Newton from the artefact's coordinates with minimum-norm steps (the
    rigid motions are left out), then a best-fit rigid registration onto the
    artefact's coordinates.

    Parameters
    ----------
    artefact : Artefact
        Starting (and reference) coordinates.
    rods : DataFrame
        RodsTable; ``length_mm`` are the lengths to honour unless ``lengths_mm`` is given.
    lengths_mm : array_like, shape (m,), optional

    Returns
    -------
    Artefact
        The coordinates defined by the lengths, in the artefact's frame.
    DataFrame
        Per sphere: ``sphere_id, dx_mm, dy_mm, dz_mm, d_mm`` (from-lengths minus artefact).
    """
    truss = Truss.from_artefact(artefact, rods, ea_n=1.0)
    L = rods["length_mm"].to_numpy(float) if lengths_mm is None else np.asarray(lengths_mm, float)
    X = artefact.centres.copy()
    for _ in range(max_iter):
        t = Truss(truss.node_ids, X, truss.members, 1.0)
        r = t.lengths - L
        step, *_ = np.linalg.lstsq(t.compatibility_matrix(), -r, rcond=1e-12)
        X = X + step.reshape(-1, 3)
        if np.abs(step).max() < tol_mm:
            break
    else:
        raise EngineeringInputError(f"rod lengths: no consistent coordinates after {max_iter} iterations")
    M, T = kabsch(X, artefact.centres)
    X = X @ M.T + T
    d = X - artefact.centres
    table = pd.DataFrame({"sphere_id": list(artefact.ids), "dx_mm": d[:, 0], "dy_mm": d[:, 1],
                          "dz_mm": d[:, 2], "d_mm": np.linalg.norm(d, axis=1)})
    return Artefact(artefact.ids, X, artefact.diameters, artefact.u, artefact.name + "+rods"), table
