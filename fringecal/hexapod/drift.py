"""Stability (drift) check after a move, thesis section 4.5.2.

Sphere centres measured repeatedly while the platform should stand still give, per
sphere and per pair of consecutive measurements, a displacement and a drift velocity.
Assuming a constant drift velocity (as the thesis does), the drift expected during one
scan is ``mean displacement x scan duration / interval``, to be compared with a
tolerance (section 4.1: about 1/10 of the target accuracy, ~5 um for a 3 x 1 x 1 m^3
volume at 1 part in 20 000 of its diagonal).

The thesis's own numbers (table 4-1, measurements ~2 min apart, a scan of ~15 s, or
~30 s including processing) are reproduced in docs/hexapod.md and the tests: see
:func:`thesis_reading`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

__all__ = ["DriftReport", "drift_check", "thesis_reading"]


@dataclass(frozen=True)
class DriftReport:
    """Displacements between consecutive measurements and the drift expected in one scan.

    ``pairs`` has one row per (sphere, consecutive pair of measurements):
    ``sphere_id, from_measurement, to_measurement, dt_s, dx_um, dy_um, dz_um,
    displacement_um, velocity_um_s``. ``per_sphere`` aggregates them per sphere
    (mean and max displacement, mean velocity).
    """

    pairs: pd.DataFrame
    per_sphere: pd.DataFrame
    mean_displacement_um: float
    mean_interval_s: float
    mean_velocity_um_s: float
    scan_duration_s: float
    expected_scan_drift_um: float
    tolerance_um: float

    @property
    def ok(self) -> bool:
        return self.expected_scan_drift_um <= self.tolerance_um

    def summary(self) -> dict:
        return {
            "mean_displacement_um": self.mean_displacement_um,
            "mean_interval_s": self.mean_interval_s,
            "mean_velocity_um_s": self.mean_velocity_um_s,
            "scan_duration_s": self.scan_duration_s,
            "expected_scan_drift_um": self.expected_scan_drift_um,
            "tolerance_um": self.tolerance_um,
            "ok": self.ok,
        }


def drift_check(centres: pd.DataFrame, scan_duration_s: float = 15.0, tolerance_um: float = 5.0,
                interval_s: float | None = None) -> DriftReport:
    """Drift statistics from a DriftCentresTable (measurement, sphere_id, x_mm, y_mm, z_mm
    and optionally time_s).

    Measurements are taken in order of ``time_s`` when given, else in file order with
    ``interval_s`` between consecutive ones. Only spheres present in both measurements
    of a pair count.

    Examples
    --------
    >>> c = pd.DataFrame({"measurement": ["1", "2"], "sphere_id": ["a", "a"],
    ...                   "x_mm": [0.0, 0.012], "y_mm": [0.0, 0.0], "z_mm": [0.0, 0.0]})
    >>> r = drift_check(c, scan_duration_s=15, interval_s=120)
    >>> round(r.mean_displacement_um, 6), round(r.expected_scan_drift_um, 6)
    (12.0, 1.5)
    """
    if scan_duration_s <= 0 or tolerance_um < 0:
        raise ValueError("scan duration must be positive and tolerance non-negative")
    df = centres.copy()
    df["measurement"] = df["measurement"].astype(str)
    df["sphere_id"] = df["sphere_id"].astype(str)
    order = list(dict.fromkeys(df["measurement"]))
    if "time_s" in df.columns:
        times = df.groupby("measurement", sort=False)["time_s"].first()
        if (df.groupby("measurement")["time_s"].nunique() > 1).any():
            raise ValueError("time_s differs within a measurement; give one time per measurement")
        order = sorted(order, key=lambda m: times[m])
    elif interval_s is None or interval_s <= 0:
        raise ValueError("the centres have no time_s column: give a positive interval between measurements")
    else:
        times = pd.Series({m: i * interval_s for i, m in enumerate(order)})
    if len(order) < 2:
        raise ValueError("a drift check needs at least two measurements")
    xyz = df.set_index(["measurement", "sphere_id"])[["x_mm", "y_mm", "z_mm"]]
    rows = []
    for a, b in zip(order[:-1], order[1:]):
        dt = float(times[b] - times[a])
        if dt <= 0:
            raise ValueError(f"measurements {a} and {b} are not separated in time")
        common = xyz.loc[a].index.intersection(xyz.loc[b].index)
        d = (xyz.loc[b].loc[common].to_numpy() - xyz.loc[a].loc[common].to_numpy()) * 1000.0
        for sid, v in zip(common, d):
            n = float(np.linalg.norm(v))
            rows.append([sid, a, b, dt, *v, n, n / dt])
    pairs = pd.DataFrame(rows, columns=["sphere_id", "from_measurement", "to_measurement", "dt_s",
                                        "dx_um", "dy_um", "dz_um", "displacement_um", "velocity_um_s"])
    if pairs.empty:
        raise ValueError("no sphere appears in two consecutive measurements")
    per_sphere = pairs.groupby("sphere_id", sort=False).agg(
        mean_displacement_um=("displacement_um", "mean"), max_displacement_um=("displacement_um", "max"),
        mean_velocity_um_s=("velocity_um_s", "mean")).reset_index()
    mean_d = float(pairs["displacement_um"].mean())
    mean_dt = float(pairs["dt_s"].mean())
    mean_v = float(pairs["velocity_um_s"].mean())
    return DriftReport(pairs, per_sphere, mean_d, mean_dt, mean_v, float(scan_duration_s),
                       mean_v * scan_duration_s, float(tolerance_um))


def thesis_reading(centres: pd.DataFrame) -> dict:
    """How the numbers of section 4.5.2 and 4.6 relate to table 4-1 (values in um).

    The thesis states an average displacement of 53 um between measurements two
    minutes apart, ~7 um expected over a ~15 s scan ("one quarter" of 53) and, in its
    summary (4.6), ~13 um per measurement. Returned:

    - ``mean_3d_consecutive``: mean 3-D displacement between consecutive measurements
    - ``mean_3d_all_pairs``: over all three pairs (1-2, 2-3, 1-3)
    - ``mean_abs_coordinate_all_pairs``: mean |dx|, |dy|, |dz| over all pairs
    - ``mean_abs_dy_consecutive``: mean |dy| between consecutive measurements
    - ``thesis_53_x_15_over_120`` and ``thesis_53_x_one_quarter``: 53 x 15/120 and 53/4
    """
    df = centres.copy()
    df["measurement"] = df["measurement"].astype(str)
    df["sphere_id"] = df["sphere_id"].astype(str)
    order = list(dict.fromkeys(df["measurement"]))
    P = np.stack([df[df.measurement == m].set_index("sphere_id").sort_index()[["x_mm", "y_mm", "z_mm"]]
                  .to_numpy() for m in order]) * 1000.0
    consecutive = [(i, i + 1) for i in range(len(order) - 1)]
    all_pairs = [(i, j) for i in range(len(order)) for j in range(i + 1, len(order))]
    d_cons = np.stack([P[j] - P[i] for i, j in consecutive])
    d_all = np.stack([P[j] - P[i] for i, j in all_pairs])
    return {
        "mean_3d_consecutive": float(np.linalg.norm(d_cons, axis=-1).mean()),
        "mean_3d_all_pairs": float(np.linalg.norm(d_all, axis=-1).mean()),
        "mean_abs_coordinate_all_pairs": float(np.abs(d_all).mean()),
        "mean_abs_dy_consecutive": float(np.abs(d_cons[..., 1]).mean()),
        "thesis_53_x_15_over_120": 53.0 * 15.0 / 120.0,
        "thesis_53_x_one_quarter": 53.0 / 4.0,
    }
