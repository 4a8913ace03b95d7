"""Scanners (one camera + one projector) and rigs of any number of scanners.

A :class:`Rig` holds the sensors with their parameters and, per parameter, whether
the bundle adjustment may change it (``free``, shape (n_sensors, 14)), and whether it
adjusts each sensor's thin-prism terms (``prism_free``, (n_sensors, 4), all False unless
the run's sensor model frees them), and whether it adjusts each sensor's correction field
(``field_free``, (n_sensors,), :mod:`fringecal.lens.field`). It converts to and from the
sensor-parameter table (docs/contracts.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from fringecal.lens.field import FIELD_DEGREE, CorrectionField, field_names, field_terms
from fringecal.names import check_name
from fringecal.schemas import FREE_COLUMNS, SensorParametersTable, TableError, read_csv_text, validate_table
from fringecal.sensor import PARAM_COLUMNS, PRISM_COLUMNS, Sensor, SensorFormat, scaled_format, sensor_in_frame

__all__ = ["Scanner", "Rig", "load_rig", "scaled_scanner", "scaled_rig", "rig_in_frame"]


@dataclass(frozen=True)
class Scanner:
    """A camera/projector pair."""

    name: str
    camera: Sensor
    projector: Sensor

    @property
    def sensors(self) -> tuple[Sensor, Sensor]:
        return (self.camera, self.projector)


@dataclass(frozen=True)
class Rig:
    """Scanners, the reference scanner and per-parameter free flags.

    ``free[i, j]`` says whether parameter ``PARAM_NAMES[j]`` of ``sensors[i]`` is
    adjusted; sensors are ordered scanner by scanner, camera first.
    """

    scanners: tuple[Scanner, ...]
    reference: str
    free: np.ndarray = field(default=None, repr=False)
    uncertainty: np.ndarray | None = field(default=None, repr=False)
    prism_free: np.ndarray | None = field(default=None, repr=False)
    prism_uncertainty: np.ndarray | None = field(default=None, repr=False)
    field_free: np.ndarray | None = field(default=None, repr=False)
    field_uncertainty: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        for s in self.scanners:  # names become file names (an export's <scanner>.yml, a run's stores)
            check_name(s.name, "scanner")
            for sensor in s.sensors:
                check_name(sensor.name, f"sensor of scanner {s.name!r}")
        names = [s.name for s in self.scanners]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate scanner names {names}")
        if self.reference not in names:
            raise ValueError(f"reference scanner {self.reference!r} is not one of {names}")
        sensor_names = [s.name for s in self.sensors]
        if len(set(sensor_names)) != len(sensor_names):
            raise ValueError(f"duplicate sensor names {sensor_names}")
        free = self.free
        if free is None:
            free = self.default_free(self.scanners, self.reference)
        free = np.asarray(free, bool).reshape(len(self.sensors), 14)
        object.__setattr__(self, "free", free)
        pf = np.zeros((len(self.sensors), 4), bool) if self.prism_free is None else self.prism_free
        object.__setattr__(self, "prism_free", np.asarray(pf, bool).reshape(len(self.sensors), 4))
        ff = np.zeros(len(self.sensors), bool) if self.field_free is None else self.field_free
        object.__setattr__(self, "field_free", np.asarray(ff, bool).reshape(len(self.sensors)))
        for free, sensor in zip(self.field_free, self.sensors):
            if free and (sensor.field is None or sensor.field.degree != FIELD_DEGREE):
                raise ValueError(f"sensor {sensor.name!r}: a free correction field needs a degree-{FIELD_DEGREE} "
                                 "field (Rig.with_field_free gives one)")

    @staticmethod
    def default_free(scanners, reference) -> np.ndarray:
        """All free but the reference camera's six external parameters (as the thesis)."""
        n = 2 * len(scanners)
        free = np.ones((n, 14), bool)
        for i, s in enumerate(scanners):
            if s.name == reference:
                free[2 * i, :6] = False
        return free

    @property
    def sensors(self) -> tuple[Sensor, ...]:
        return tuple(x for s in self.scanners for x in s.sensors)

    def scanner(self, name: str) -> Scanner:
        for s in self.scanners:
            if s.name == name:
                return s
        raise KeyError(f"no scanner {name!r} in rig (have {[s.name for s in self.scanners]})")

    @property
    def params(self) -> np.ndarray:
        """Parameters of every sensor, shape (n_sensors, 14)."""
        return np.stack([s.params for s in self.sensors])

    @property
    def prism(self) -> np.ndarray:
        """Thin-prism terms s1..s4 of every sensor, shape (n_sensors, 4)."""
        return np.stack([s.prism for s in self.sensors])

    @property
    def has_prism(self) -> bool:
        """Whether any sensor has thin-prism terms or may have them adjusted."""
        return bool(self.prism_free.any() or np.any(self.prism != 0.0))

    @property
    def has_field(self) -> bool:
        """Whether any sensor has a correction field or may have one adjusted."""
        return bool(self.field_free.any() or any(s.has_field for s in self.sensors))

    @property
    def fields(self) -> np.ndarray:
        """Coefficients (n_sensors, K) of every sensor's degree-``FIELD_DEGREE`` correction
        field (zero for a sensor without one)."""
        out = np.zeros((len(self.sensors), field_terms(FIELD_DEGREE)))
        for i, s in enumerate(self.sensors):
            if s.field is not None and s.field.degree == FIELD_DEGREE:
                out[i] = s.field.coefficients
        return out

    def with_params(self, params, uncertainty=None, prism=None, fields=None) -> "Rig":
        """The rig with other parameters (n_sensors, 14) and, if given, thin-prism terms
        (n_sensors, 4) and correction-field coefficients (n_sensors, K; rows of sensors
        without a field and all zero leave them without one)."""
        params = np.asarray(params, float).reshape(len(self.sensors), 14)
        pr = self.prism if prism is None else np.asarray(prism, float).reshape(len(self.sensors), 4)
        sensors = [s.with_params(params[i], pr[i]) for i, s in enumerate(self.sensors)]
        if fields is not None:
            fields = np.asarray(fields, float).reshape(len(self.sensors), -1)
            for i, s in enumerate(sensors):
                if s.field is not None or np.any(fields[i] != 0.0):
                    base = s.field if s.field is not None else _zero_field(s)
                    sensors[i] = s.with_field(base.with_coefficients(fields[i]))
        scanners = tuple(Scanner(s.name, sensors[2 * i], sensors[2 * i + 1]) for i, s in enumerate(self.scanners))
        return replace(self, scanners=scanners, uncertainty=uncertainty, prism_uncertainty=None,
                       field_uncertainty=None)

    def with_field_free(self, field_free) -> "Rig":
        """The rig with other correction-field free flags ((n_sensors,) or one bool for all);
        a sensor whose field becomes free and has none gets a zero one."""
        ff = np.broadcast_to(np.asarray(field_free, bool), (len(self.sensors),)).copy()
        sensors = [s.with_field(_zero_field(s)) if f and (s.field is None or s.field.degree != FIELD_DEGREE) else s
                   for f, s in zip(ff, self.sensors)]
        scanners = tuple(Scanner(s.name, sensors[2 * i], sensors[2 * i + 1]) for i, s in enumerate(self.scanners))
        return replace(self, scanners=scanners, field_free=ff)

    def with_prism_free(self, prism_free) -> "Rig":
        """The rig with other thin-prism free flags ((n_sensors, 4) or one bool for all)."""
        pf = np.broadcast_to(np.asarray(prism_free, bool), (len(self.sensors), 4)).copy()
        return replace(self, prism_free=pf)

    # -- table conversion ------------------------------------------------
    def to_frame(self) -> pd.DataFrame:
        rows = []
        for si, (scanner, sensor) in enumerate(
            (sc, se) for sc in self.scanners for se in sc.sensors
        ):
            row = {"sensor": sensor.name, "scanner": scanner.name, "role": sensor.role}
            row.update(dict(zip(PARAM_COLUMNS, map(float, sensor.params))))
            row.update(dict(zip(FREE_COLUMNS, map(bool, self.free[si]))))
            if self.has_prism:  # optional columns: a 14-parameter rig's table is unchanged
                row.update(dict(zip(PRISM_COLUMNS, map(float, sensor.prism))))
            if self.has_field:
                row.update(_field_columns(sensor))
            f = sensor.format
            row.update(width_px=f.width_px, height_px=f.height_px, width_mm=f.width_mm, height_mm=f.height_mm)
            if self.uncertainty is not None:
                row.update({f"u_{c}": float(u) for c, u in zip(PARAM_COLUMNS, self.uncertainty[si])})
            rows.append(row)
        return pd.DataFrame(rows)

    @classmethod
    def from_frame(cls, df: pd.DataFrame, reference: str | None = None, source: str = "<sensors>",
                   formats: dict[str, SensorFormat] | None = None) -> "Rig":
        """Build a rig from a sensor-parameter table (validated).

        Each scanner needs exactly one camera and one projector row. Sensor formats come
        from the table's ``width_px, height_px, width_mm, height_mm`` columns or ``formats``.
        ``reference`` defaults to the scanner whose camera has all six external
        parameters fixed, else the first scanner.
        """
        df = validate_table(df, SensorParametersTable, source)
        if df.empty:
            raise TableError(source, [(None, None, "no sensors (the table has a header and no rows); a rig needs "
                                                   "a camera and a projector row per scanner")])
        formats = formats or {}
        problems = []
        scanners = []
        free_rows = []
        unc_rows = []
        has_u = all(f"u_{c}" in df.columns for c in PARAM_COLUMNS)
        prism_cols = [c for c in PRISM_COLUMNS if c in df.columns]
        for name, g in df.groupby("scanner", sort=False):
            roles = list(g["role"])
            if sorted(roles) != ["camera", "projector"]:
                lines = [int(i) + 2 for i in g.index]
                problems.append((lines[0], "role", f"scanner {name!r} needs one camera and one projector, "
                                                   f"found {roles} (lines {lines})"))
                continue
            pair = {}
            for i, r in g.iterrows():
                fmt = formats.get(r["sensor"])
                if fmt is None:
                    if not all(c in df.columns and not pd.isna(r[c]) for c in ("width_px", "height_px", "width_mm", "height_mm")):
                        problems.append((int(i) + 2, "width_px", f"sensor {r['sensor']!r} has no format "
                                                                "(width_px, height_px, width_mm, height_mm)"))
                        continue
                    fmt = SensorFormat(int(r["width_px"]), int(r["height_px"]), float(r["width_mm"]), float(r["height_mm"]))
                prism = [0.0 if c not in prism_cols or pd.isna(r[c]) else float(r[c]) for c in PRISM_COLUMNS]
                sensor = Sensor(r["sensor"], r["role"], fmt, r[list(PARAM_COLUMNS)].to_numpy(float), prism)
                try:
                    sensor = sensor.with_field(_field_of_row(r, fmt))
                except ValueError as err:
                    problems.append((int(i) + 2, "field_degree", str(err)))
                    continue
                pair[r["role"]] = (sensor,
                                   r[list(FREE_COLUMNS)].to_numpy(bool),
                                   r[[f"u_{c}" for c in PARAM_COLUMNS]].to_numpy(float) if has_u else None)
            if len(pair) == 2:
                scanners.append(Scanner(str(name), pair["camera"][0], pair["projector"][0]))
                free_rows += [pair["camera"][1], pair["projector"][1]]
                unc_rows += [pair["camera"][2], pair["projector"][2]]
        if problems:
            raise TableError(source, problems)
        if reference is None:
            reference = next((s.name for s, f in zip(scanners, free_rows[::2]) if not f[:6].any()),
                             scanners[0].name)
        unc = np.stack(unc_rows) if has_u else None
        return cls(tuple(scanners), reference, np.stack(free_rows), unc)


def _field_columns(sensor: Sensor) -> dict:
    """Optional table columns of a sensor's correction field: its degree and coefficients
    (``field_f01_mm`` ...; empty for a sensor without one)."""
    if sensor.field is None:
        return {"field_degree": np.nan}
    names = field_names(sensor.field.degree)
    return {"field_degree": float(sensor.field.degree),
            **{f"field_{n}_mm": float(a) for n, a in zip(names, sensor.field.coefficients)}}


def _field_of_row(r, fmt: SensorFormat) -> CorrectionField | None:
    """The correction field of a table row (None without ``field_degree``)."""
    degree = r.get("field_degree", np.nan)
    if degree is None or pd.isna(degree):
        return None
    if float(degree) != int(degree) or not 2 <= int(degree) <= 8:
        raise ValueError(f"field_degree {degree!r} must be a whole number from 2 to 8")
    names = [f"field_{n}_mm" for n in field_names(int(degree))]
    missing = [c for c in names if c not in r.index or pd.isna(r[c])]
    if missing:
        raise ValueError(f"a degree-{int(degree)} correction field needs columns {names[0]}..{names[-1]}; "
                         f"{missing[0]} is missing or empty")
    return CorrectionField(fmt.width_mm, fmt.height_mm, int(degree), r[names].to_numpy(float))


def _zero_field(sensor: Sensor) -> CorrectionField:
    f = sensor.format
    return CorrectionField.zero(f.width_mm, f.height_mm, FIELD_DEGREE)


def load_rig(path, reference: str | None = None) -> Rig:
    """Read a sensor-parameter CSV into a :class:`Rig`."""
    return Rig.from_frame(read_csv_text(path), reference=reference, source=str(Path(path)))


def scaled_scanner(scanner: Scanner, width_px: int, height_px: int | None = None) -> Scanner:
    """``scanner`` with its camera resampled to ``width_px`` x ``height_px``."""
    cam = replace(scanner.camera, format=scaled_format(scanner.camera.format, width_px, height_px))
    return replace(scanner, camera=cam)


def scaled_rig(rig: Rig, width_px: int, height_px: int | None = None) -> Rig:
    """Every camera of ``rig`` resampled (projectors, parameters and flags unchanged)."""
    return replace(rig, scanners=tuple(scaled_scanner(s, width_px, height_px) for s in rig.scanners))


def rig_in_frame(rig: Rig, links: dict) -> Rig:
    """A :class:`fringecal.rig.Rig` with every linked scanner's sensors in the reference
    frame (``links``: scanner -> Frame, or a link with a ``frame``). Scanners without a link raise KeyError."""
    scanners = []
    for s in rig.scanners:
        if s.name not in links:
            raise KeyError(f"scanner {s.name!r} has no link to the reference frame")
        T = getattr(links[s.name], "frame", links[s.name])  # a FrameLink or a Frame
        scanners.append(Scanner(s.name, sensor_in_frame(s.camera, T), sensor_in_frame(s.projector, T)))
    return replace(rig, scanners=tuple(scanners))
