"""Acceptance and reverification per VDI/VDE 2634 parts 2 and 3 (thesis section 6.9.3).

Characteristics, each compared with a maximum permissible error (MPE):

* length measurement error E / sphere-spacing error SD: measured minus calibrated
  centre distance of a ball-bar, per position (part 2 uses the dumbbell's sphere
  spacing; part 3 the length across several views/scanners, as the thesis did);
* probing error form P_F: range of the radial residuals of a least-squares sphere fit;
* probing error size P_S: measured minus calibrated sphere diameter;
* flatness measurement error F: range of the signed residuals of a least-squares plane.

The guideline lets a small fraction of points (0.3 %) be discarded before taking the
ranges P_F and F; ``exclude_fraction`` does that symmetrically from the worst points.

An uncertainty statement per GUM accompanies the ball-bar result: type A from the
repeatability of the positions (standard deviation of the mean of the lengths), type B
from the artefact's certificate (expanded uncertainty divided by its coverage factor),
combined in quadrature and expanded with a stated coverage factor (1.96 for 95 %, as the
thesis uses).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import pandas as pd

from fringecal.schemas import BallbarCentresTable, SphereCentresTable, TableError, validate_table

__all__ = [
    "GumStatement",
    "BallBarResult",
    "ballbar_lengths",
    "evaluate_ballbar",
    "probing_form_error",
    "probing_size_error",
    "flatness_error",
    "seven_ballbar_positions",
    "one_part_in",
]


def one_part_in(error_mm: float, diagonal_mm: float) -> float:
    """Express an error as "one part in N" of a length (N = diagonal / |error|)."""
    e = abs(float(error_mm))
    return float("inf") if e == 0 else float(diagonal_mm) / e


@dataclass(frozen=True)
class GumStatement:
    """Combined and expanded uncertainty of a mean length (GUM)."""

    u_type_a_mm: float
    u_type_b_mm: float
    u_combined_mm: float
    coverage_factor: float
    expanded_mm: float
    n_repeats: int

    @classmethod
    def from_repeats(cls, values_mm, certificate_expanded_mm: float, certificate_k: float = 2.0,
                     coverage_factor: float = 1.96) -> "GumStatement":
        values = np.asarray(values_mm, float)
        n = len(values)
        u_a = float(np.std(values, ddof=1) / np.sqrt(n)) if n > 1 else 0.0
        u_b = float(certificate_expanded_mm) / float(certificate_k)
        u_c = float(np.hypot(u_a, u_b))
        return cls(u_a, u_b, u_c, float(coverage_factor), coverage_factor * u_c, n)

    def sentence(self) -> str:
        return (f"U = {self.expanded_mm * 1000:.1f} um (k = {self.coverage_factor:g}; type A "
                f"{self.u_type_a_mm * 1000:.1f} um from {self.n_repeats} positions, type B "
                f"{self.u_type_b_mm * 1000:.2f} um from the certificate)")


@dataclass(frozen=True)
class BallBarResult:
    """Per-position lengths and errors of a ball-bar test, with the summary figures."""

    positions: pd.DataFrame  # measurement, length_mm, error_mm, pass
    reference_length_mm: float
    mean_length_mm: float
    max_abs_error_mm: float
    mpe_mm: float | None
    volume_diagonal_mm: float | None
    uncertainty: GumStatement
    passed: bool = field(default=True)
    # position -> the sphere fits' pixels outside the calibration's observed region
    # (fringecal.verification.measure.positions_outside); None: not known
    observed_region: dict | None = None

    @property
    def one_part_in(self) -> float | None:
        if self.volume_diagonal_mm is None:
            return None
        return one_part_in(self.max_abs_error_mm, self.volume_diagonal_mm)

    def to_dict(self) -> dict:
        return {
            "reference_length_mm": self.reference_length_mm,
            "mean_length_mm": self.mean_length_mm,
            "mean_error_mm": self.mean_length_mm - self.reference_length_mm,
            "max_abs_error_mm": self.max_abs_error_mm,
            "volume_diagonal_mm": self.volume_diagonal_mm,
            "one_part_in": self.one_part_in,
            "mpe_mm": self.mpe_mm,
            "pass": self.passed,
            "uncertainty": asdict(self.uncertainty),
            "positions": self.positions.to_dict("records"),
            **({"observed_region": self.observed_region} if self.observed_region is not None else {}),
        }


def ballbar_lengths(centres: pd.DataFrame, source: str = "<centres>", ids=("A", "B")) -> pd.DataFrame:
    """Centre distance of spheres ``A`` and ``B`` per position.

    Rows are grouped by ``position`` (the table of
    :func:`fringecal.verification.measure.measure_position`) or, in tables without that
    column, by ``measurement`` (thesis table 6-9, the plan-driven centres). The two
    spheres of a position may come from different scanners (one sphere seen by each,
    as in thesis table 6-9). A sphere seen by several scanners has a row from each;
    the position then gives one length per (scanner of A, scanner of B) pair, each a
    test of the link between those two scanners.

    Returns
    -------
    DataFrame with columns ``measurement, length_mm, position, scanner_a, scanner_b``,
    positions in first-seen order, pairs in row order. ``measurement`` names the
    length: the position when it has one pair, ``"<position>:<scannerA>/<scannerB>"``
    otherwise.

    Raises
    ------
    TableError
        A position without a row for ``A`` or ``B``, or with other sphere ids (all
        problems at once, with line numbers).
    """
    key = "position" if "position" in centres.columns else "measurement"
    model = BallbarCentresTable if key == "position" else SphereCentresTable
    table = validate_table(centres, model, source)
    problems = []
    rows = []
    for meas, g in table.groupby(key, sort=False):
        found = {sid: g[g.sphere_id == sid] for sid in ids}
        for sid, rows_sid in found.items():
            if len(rows_sid) == 0:
                problems.append((int(g.index[0]) + 2, "sphere_id",
                                 f"{key} {meas!r} has no row(s) for sphere {sid!r}; need at least one"))
        others = sorted(set(g.sphere_id) - set(ids))
        if others:
            problems.append((int(g.index[0]) + 2, "sphere_id",
                             f"{key} {meas!r}: sphere id(s) {others} are not ball-bar spheres {list(ids)}"))
        if all(len(v) for v in found.values()):
            rows += _pair_lengths(meas, found[ids[0]], found[ids[1]])
    if problems:
        raise TableError(source, problems)
    return pd.DataFrame(rows, columns=["measurement", "length_mm", "position", "scanner_a", "scanner_b"])


def _pair_lengths(position, rows_a: pd.DataFrame, rows_b: pd.DataFrame) -> list[tuple]:
    """(name, length, position, scanner A, scanner B) for every pair of an A and a B row."""
    xyz = ["x_mm", "y_mm", "z_mm"]
    pairs = [(a, b) for a in rows_a.itertuples() for b in rows_b.itertuples()]
    out = []
    for a, b in pairs:
        name = position if len(pairs) == 1 else f"{position}:{a.scanner}/{b.scanner}"
        length = float(np.linalg.norm(np.array([getattr(b, c) - getattr(a, c) for c in xyz], float)))
        out.append((name, length, position, a.scanner, b.scanner))
    return out


def evaluate_ballbar(lengths_mm, reference_length_mm: float, measurements=None, mpe_mm: float | None = None,
                     volume_diagonal_mm: float | None = None, certificate_expanded_mm: float = 0.0,
                     certificate_k: float = 2.0, coverage_factor: float = 1.96) -> BallBarResult:
    """Length errors of a ball-bar over its positions against an MPE.

    A position passes when its error is finite and within the MPE; without an MPE
    ``passed`` only says that every error is finite (there is no verdict). A NaN
    length or reference never passes.

    Examples
    --------
    >>> r = evaluate_ballbar([1015.543, 1015.799], 1015.650, mpe_mm=0.2, volume_diagonal_mm=2872.3)
    >>> round(r.max_abs_error_mm, 3), r.passed, round(r.one_part_in)
    (0.149, True, 19277)
    """
    lengths = np.asarray(lengths_mm, float)
    if lengths.size == 0:
        raise ValueError("no ball-bar positions to evaluate")
    if measurements is None:
        measurements = [str(i + 1) for i in range(len(lengths))]
    errors = lengths - float(reference_length_mm)
    # a NaN length, reference or MPE never passes (NaN compares false, and is excluded explicitly)
    ok = np.isfinite(errors) if mpe_mm is None else np.isfinite(errors) & (np.abs(errors) <= float(mpe_mm))
    positions = pd.DataFrame({"measurement": list(measurements), "length_mm": lengths,
                              "error_mm": errors, "pass": ok})
    gum = GumStatement.from_repeats(lengths, certificate_expanded_mm, certificate_k, coverage_factor)
    return BallBarResult(positions, float(reference_length_mm), float(lengths.mean()),
                         float(np.abs(errors).max()), mpe_mm, volume_diagonal_mm, gum, bool(ok.all()))


def _trim(residuals, exclude_fraction: float) -> np.ndarray:
    r = np.sort(np.asarray(residuals, float))
    k = int(np.floor(exclude_fraction * len(r) / 2))
    return r[k:len(r) - k] if k else r


def probing_form_error(radial_residuals_mm, exclude_fraction: float = 0.003) -> float:
    """P_F: range of radial residuals of a least-squares sphere fit (mm)."""
    r = _trim(radial_residuals_mm, exclude_fraction)
    return float(r.max() - r.min())


def probing_size_error(measured_diameter_mm: float, calibrated_diameter_mm: float) -> float:
    """P_S: measured minus calibrated diameter (mm)."""
    return float(measured_diameter_mm) - float(calibrated_diameter_mm)


def flatness_error(signed_residuals_mm, exclude_fraction: float = 0.003) -> float:
    """F: range of signed residuals of a least-squares plane (mm)."""
    r = _trim(signed_residuals_mm, exclude_fraction)
    return float(r.max() - r.min())


def seven_ballbar_positions(volume_min, volume_max, length_mm: float, directions: str = "face") -> np.ndarray:
    """The guideline's seven ball-bar positions in a box-shaped measurement volume.

    Four along the space diagonals of the box, (+,+,+), (-,+,+), (+,-,+), (+,+,-)
    times its half sizes, and three more, each bar centred in the box. VDI/VDE
    2634 part 2 puts the three along face diagonals (``directions="face"``): one in
    each of the faces spanned by x-y, x-z and y-z, i.e. (+,+,0), (+,0,+), (0,+,+)
    times the half sizes. ``directions="axes"`` puts them parallel to the x, y and z
    axes instead.

    Returns
    -------
    ndarray, shape (7, 2, 3)
        Centres of spheres A and B per position (B - A along the direction).
    """
    if directions not in ("face", "axes"):
        raise ValueError(f"directions must be 'face' or 'axes', not {directions!r}")
    lo = np.asarray(volume_min, float)
    hi = np.asarray(volume_max, float)
    centre = (lo + hi) / 2
    half = (hi - lo) / 2
    dirs = [np.array(d, float) * half for d in ((1, 1, 1), (-1, 1, 1), (1, -1, 1), (1, 1, -1))]
    if directions == "face":
        dirs += [np.array(d, float) * half for d in ((1, 1, 0), (1, 0, 1), (0, 1, 1))]
    else:
        dirs += [np.eye(3)[i] for i in range(3)]
    out = []
    for d in dirs:
        u = d / np.linalg.norm(d)
        out.append([centre - u * length_mm / 2, centre + u * length_mm / 2])
    return np.array(out)
