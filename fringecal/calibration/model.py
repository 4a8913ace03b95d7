"""The bundle-adjustment problem: control points, parameters and their evaluation.

A :class:`BundleProblem` holds everything the adjustment needs as arrays: the rig (start
values, free flags, formats), the artefact, one pose ``T_world_artefact`` per measurement
(shared by every scanner that saw it: this is what links scanners whose volumes do not
overlap) and the control points, sorted by (scanner, measurement) so that each group's
points are contiguous. :class:`ParameterLayout` maps the free sensor and pose parameters
to one vector; :class:`Evaluator` evaluates residuals and normal equations through the
compiled kernels.
"""

from __future__ import annotations

import copy
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from fringecal.artefact import Artefact
from fringecal.calibration import kernels
from fringecal.lens.field import FIELD_DEGREE, field_names, field_terms
from fringecal.rig import Rig
from fringecal.rotation import rotation_derivatives, rotation_matrix
from fringecal.schemas import ControlPointsTable, PosePlanTable, TableError, validate_table
from fringecal.sensor import PARAM_NAMES, PRISM_NAMES
from fringecal.triangulation import closest_approach

__all__ = ["BundleProblem", "ParameterLayout", "Evaluator", "Evaluation", "POSE_NAMES", "POSE_COLUMNS", "triangulated_points",
           "too_few_spheres"]

POSE_NAMES = ("tx", "ty", "tz", "omega", "phi", "kappa")
POSE_COLUMNS = ("tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad")


#: below this many control points the kernels run on one thread: a parallel region then
#: saves a few milliseconds but, on a loaded machine, waits for a descheduled thread
PARALLEL_MIN_POINTS = 50_000


@contextmanager
def _threads_for(n_points: int):
    import numba

    if n_points >= PARALLEL_MIN_POINTS:
        yield
        return
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(before)


@dataclass(frozen=True)
class BundleProblem:
    """Control points and start values of an object-space bundle adjustment.

    Attributes
    ----------
    rig : Rig
        Start parameters, free flags (``rig.free``, shape (n_sensors, 14)), formats and
        the reference scanner.
    artefact : Artefact
    measurements : tuple of str, length n_meas
    poses : ndarray, shape (n_meas, 6)
        Start values of T_world_artefact per measurement (tx, ty, tz, omega, phi, kappa).
    scanner_idx, meas_idx, sphere_idx : ndarray of int, shape (n,)
        Per control point: index into ``rig.scanners``, ``measurements``, ``artefact.ids``.
    cam_mm, prj_mm : ndarray, shape (n, 2)
        Camera pixel and projector phases of each control point as image-plane mm.
    row : ndarray of int, shape (n,)
        Row of each control point in the table it came from (the arrays are sorted by
        scanner, then measurement).
    pose_free : ndarray of bool, shape (n_meas, 6)
    gamma1, gamma2 : float
        Weights of the alpha1 and alpha2 terms of F (thesis eq. 2-24).
    dropped : tuple of (measurement, reason)
        Measurements of the pose table that were left out (no control points).
    field_prior_weight : float
        lambda of the correction fields' prior: F gains ``lambda sum a_j^2`` over the free
        coefficients (0: none; :mod:`fringecal.calibration.models` sets it).
    """

    rig: Rig
    artefact: Artefact
    measurements: tuple
    poses: np.ndarray
    scanner_idx: np.ndarray
    meas_idx: np.ndarray
    sphere_idx: np.ndarray
    cam_mm: np.ndarray
    prj_mm: np.ndarray
    row: np.ndarray
    pose_free: np.ndarray = None
    gamma1: float = 1.0
    gamma2: float = 1.0
    dropped: tuple = ()
    field_prior_weight: float = 0.0

    def __post_init__(self):
        n_m = len(self.measurements)
        object.__setattr__(self, "measurements", tuple(str(m) for m in self.measurements))
        object.__setattr__(self, "poses", np.asarray(self.poses, float).reshape(n_m, 6))
        for name in ("scanner_idx", "meas_idx", "sphere_idx", "row"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), np.int64))
        for name in ("cam_mm", "prj_mm"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), float).reshape(-1, 2))
        pf = np.ones((n_m, 6), bool) if self.pose_free is None else np.asarray(self.pose_free, bool)
        object.__setattr__(self, "pose_free", pf.reshape(n_m, 6))
        key = self.scanner_idx * max(n_m, 1) + self.meas_idx
        if np.any(np.diff(key) < 0):
            order = np.argsort(key, kind="stable")
            for name in ("scanner_idx", "meas_idx", "sphere_idx", "row", "cam_mm", "prj_mm"):
                object.__setattr__(self, name, getattr(self, name)[order])
        if not (self.gamma1 > 0 and self.gamma2 > 0):
            raise ValueError(f"gamma1 and gamma2 must be > 0, got {self.gamma1}, {self.gamma2}")

    # -- construction ----------------------------------------------------
    @classmethod
    def from_tables(cls, rig: Rig, artefact: Artefact, control_points: pd.DataFrame,
                    poses: pd.DataFrame, gamma1: float = 1.0, gamma2: float = 1.0,
                    source: str = "control_points.csv", poses_source: str = "poses_initial.csv"
                    ) -> "BundleProblem":
        """Build a problem from a ControlPointsTable and a PosePlanTable (one pose per measurement).

        Every control point must name a scanner of the rig, a sphere of the artefact and a
        measurement of the pose table, and lie on the camera's pixel grid; violations raise
        one :class:`TableError` naming the lines. Measurements of the pose table without
        control points, and those whose control points lie on fewer than three spheres
        (their pose's rotation is not determined, :func:`too_few_spheres`), are left out
        with their points and recorded in ``dropped``: one occluded or badly labelled
        placement should not refuse a calibration the others determine. ``row`` keeps
        each remaining point's row in ``control_points``.
        """
        cp = validate_table(control_points, ControlPointsTable, source)
        poses = validate_table(poses, PosePlanTable, poses_source)
        scanners = {s.name: i for i, s in enumerate(rig.scanners)}
        spheres = {s: i for i, s in enumerate(artefact.ids)}
        pose_ids = list(poses["measurement"])
        problems = []

        def check(column, known, what):
            bad = ~cp[column].isin(list(known))
            for i in np.flatnonzero(bad.to_numpy())[:20]:
                problems.append((int(i) + 2, column, f"{what} {cp[column].iloc[i]!r} is not one of "
                                 f"{sorted(known) if len(known) < 20 else str(len(known)) + ' known'}"))
            if bad.sum() > 20:
                problems.append((None, column, f"... {int(bad.sum()) - 20} more unknown {what}s"))

        check("scanner", scanners, "scanner")
        check("sphere_id", spheres, "sphere")
        check("measurement", set(pose_ids), f"measurement (not in {poses_source})")
        if problems:
            raise TableError(source, problems)
        s_idx = cp["scanner"].map(scanners).to_numpy(np.int64)
        # C-ordered, writable arrays whatever the frame's memory layout, so that the compiled
        # kernels see one signature (one compilation) for every problem
        uv = np.ascontiguousarray(cp[["u_px", "v_px"]].to_numpy(float))
        tau = np.ascontiguousarray(cp[["tau_x_rad", "tau_y_rad"]].to_numpy(float))
        cam_mm = np.empty_like(uv)
        prj_mm = np.empty_like(tau)
        for i, sc in enumerate(rig.scanners):
            sel = s_idx == i
            fmt = sc.camera.format
            outside = sel & ((uv[:, 0] > fmt.width_px - 1) | (uv[:, 1] > fmt.height_px - 1))
            for k in np.flatnonzero(outside)[:10]:
                problems.append((int(k) + 2, "u_px, v_px", f"pixel ({uv[k, 0]:g}, {uv[k, 1]:g}) lies outside "
                                 f"camera {sc.camera.name} ({fmt.width_px} x {fmt.height_px})"))
            cam_mm[sel] = sc.camera.image_mm(uv[sel])
            prj_mm[sel] = sc.projector.image_mm(tau[sel])
        if problems:
            raise TableError(source, problems)
        dropped = dict.fromkeys(pose_ids, "no control points")
        for m, ids in cp.groupby("measurement", sort=False)["sphere_id"].unique().items():
            dropped.pop(m)
            if len(ids) < 3:
                dropped[m] = too_few_spheres(sorted(map(str, ids), key=artefact.ids.index))
        keep = [m for m in pose_ids if m not in dropped]
        used = cp["measurement"].isin(keep).to_numpy()
        meas = {m: i for i, m in enumerate(keep)}
        pose_rows = poses.set_index("measurement").loc[keep, list(POSE_COLUMNS)].to_numpy(float)
        return cls(rig, artefact, tuple(keep), pose_rows, s_idx[used],
                   cp["measurement"][used].map(meas).to_numpy(np.int64),
                   np.array(cp["sphere_id"][used].map(spheres).to_numpy(np.int64)), cam_mm[used], prj_mm[used],
                   np.flatnonzero(used), None, float(gamma1), float(gamma2),
                   tuple((m, dropped[m]) for m in pose_ids if m in dropped))

    # -- views -----------------------------------------------------------
    @property
    def n_points(self) -> int:
        return int(self.scanner_idx.shape[0])

    def poses_frame(self, poses: np.ndarray | None = None) -> pd.DataFrame:
        """Poses (n_meas, 6) as a PosePlanTable frame."""
        poses = self.poses if poses is None else poses
        df = pd.DataFrame(poses, columns=list(POSE_COLUMNS))
        df.insert(0, "measurement", list(self.measurements))
        return df

    def with_start(self, rig: Rig | None = None, poses: np.ndarray | None = None) -> "BundleProblem":
        """The same control points from other start values."""
        from dataclasses import replace

        return replace(self, rig=self.rig if rig is None else rig,
                       poses=self.poses if poses is None else np.asarray(poses, float))

    def thinned(self, every: int) -> "BundleProblem":
        """Every ``every``-th control point of each (scanner, measurement) group (at least
        one per group): a uniform subsample with the same measurements and spheres."""
        from dataclasses import replace

        start, stop, _, _ = self.groups()
        keep = np.concatenate([np.arange(a, b, max(int(every), 1)) for a, b in zip(start, stop)])
        return replace(self, scanner_idx=self.scanner_idx[keep], meas_idx=self.meas_idx[keep],
                       sphere_idx=self.sphere_idx[keep], cam_mm=self.cam_mm[keep], prj_mm=self.prj_mm[keep],
                       row=self.row[keep])

    def groups(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Contiguous (scanner, measurement) groups: (start, stop, scanner, measurement)."""
        n = self.n_points
        if n == 0:
            e = np.zeros(0, np.int64)
            return e, e, e, e
        key = self.scanner_idx * len(self.measurements) + self.meas_idx
        brk = np.flatnonzero(np.diff(key)) + 1
        start = np.concatenate([[0], brk]).astype(np.int64)
        stop = np.concatenate([brk, [n]]).astype(np.int64)
        return start, stop, self.scanner_idx[start], self.meas_idx[start]


@dataclass(frozen=True)
class ParameterLayout:
    """Where each free sensor and pose parameter sits in the unknown vector x.

    ``sensor_index[i, j]`` is the position of parameter ``PARAM_NAMES[j]`` of sensor i in
    x, or -1 if fixed; ``prism_index[i, j]`` likewise for thin-prism term
    ``PRISM_NAMES[j]``; ``field_index[i, j]`` for coefficient j of sensor i's correction
    field (:mod:`fringecal.lens.field`); ``pose_index[m, k]`` for pose parameter
    ``POSE_NAMES[k]``. The 14 sensor parameters come first (in rig order), then the free
    thin-prism terms, then the free field coefficients (neither for the thesis's model),
    then poses.
    """

    sensor_index: np.ndarray
    pose_index: np.ndarray
    names: tuple
    sensor_names: tuple
    measurements: tuple
    prism_index: np.ndarray = None
    field_index: np.ndarray = None

    def __post_init__(self):
        if self.prism_index is None:
            object.__setattr__(self, "prism_index", np.full((self.sensor_index.shape[0], 4), -1, np.int64))
        if self.field_index is None:
            object.__setattr__(self, "field_index", np.full((self.sensor_index.shape[0], 0), -1, np.int64))

    @classmethod
    def of(cls, problem: BundleProblem) -> "ParameterLayout":
        free = problem.rig.free
        si = np.full(free.shape, -1, np.int64)
        si[free] = np.arange(int(free.sum()))
        prf = problem.rig.prism_free
        spi = np.full(prf.shape, -1, np.int64)
        spi[prf] = int(free.sum()) + np.arange(int(prf.sum()))
        ff = problem.rig.field_free
        n_terms = field_terms(FIELD_DEGREE) if ff.any() else 0
        ffk = np.repeat(ff[:, None], n_terms, axis=1)
        sfi = np.full(ffk.shape, -1, np.int64)
        n_before = int(free.sum()) + int(prf.sum())
        sfi[ffk] = n_before + np.arange(int(ffk.sum()))
        pf = problem.pose_free
        pi = np.full(pf.shape, -1, np.int64)
        pi[pf] = n_before + int(ffk.sum()) + np.arange(int(pf.sum()))
        sensors = tuple(s.name for s in problem.rig.sensors)
        names = [f"{sensors[i]}.{PARAM_NAMES[j]}" for i, j in zip(*np.nonzero(free))]
        names += [f"{sensors[i]}.{PRISM_NAMES[j]}" for i, j in zip(*np.nonzero(prf))]
        fnames = field_names(FIELD_DEGREE)
        names += [f"{sensors[i]}.field.{fnames[j]}" for i, j in zip(*np.nonzero(ffk))]
        names += [f"pose[{problem.measurements[m]}].{POSE_NAMES[k]}" for m, k in zip(*np.nonzero(pf))]
        return cls(si, pi, tuple(names), sensors, problem.measurements, spi, sfi)

    @property
    def field_free(self) -> bool:
        """Whether any correction-field coefficient is adjusted (the kernels then have
        ``2 K`` more local slots, K = ``field_index.shape[1]``)."""
        return bool(np.any(self.field_index >= 0))

    @property
    def n_field_terms(self) -> int:
        return int(self.field_index.shape[1]) if self.field_free else 0

    def field_slots(self, prior_weight: float) -> np.ndarray | None:
        """(n,) bool: the free correction-field coefficients, where a prior of
        ``prior_weight`` > 0 holds them (:attr:`BundleProblem.field_prior_weight`); None
        without one (nothing regularised)."""
        if not (self.field_free and prior_weight > 0):
            return None
        out = np.zeros(self.n, bool)
        out[self.field_index[self.field_index >= 0]] = True
        return out

    def unpack_fields(self, x: np.ndarray, fields: np.ndarray) -> np.ndarray:
        """Correction-field coefficients (n_sensors, K) with the free entries taken from x."""
        out = np.array(fields, float, copy=True)
        if self.field_free:
            m = self.field_index >= 0
            out[m] = np.asarray(x, float)[self.field_index[m]]
        return out

    def sensor_rows(self, x: np.ndarray, rig: Rig, poses: np.ndarray) -> np.ndarray:
        """Each sensor's parameters at x as a replica stores them: (n_sensors, 14), or
        (n_sensors, 14 + K) with its correction-field coefficients after its 14 where the
        fields are free (:func:`fringecal.calibration.propagation.scanner_with` reads both)."""
        sp = self.unpack(x, rig.params, poses)[0]
        return np.concatenate([sp, self.unpack_fields(x, rig.fields)], axis=1) if self.field_free else sp

    def pack_rig(self, rig: Rig, poses: np.ndarray) -> np.ndarray:
        """x of ``rig``'s parameters (14, thin-prism, correction field) and ``poses``."""
        x = self.pack(rig.params, poses, rig.prism)
        if self.field_free:
            m = self.field_index >= 0
            x[self.field_index[m]] = rig.fields[m]
        return x

    @property
    def prism_free(self) -> bool:
        """Whether any thin-prism term is adjusted (the kernels then have 8 more local slots)."""
        return bool(np.any(self.prism_index >= 0))

    def unpack_prism(self, x: np.ndarray, prism: np.ndarray) -> np.ndarray:
        """Thin-prism terms (n_sensors, 4) with the free entries taken from x."""
        out = np.array(prism, float, copy=True)
        m = self.prism_index >= 0
        out[m] = np.asarray(x, float)[self.prism_index[m]]
        return out

    def pack_prism(self, x: np.ndarray, prism: np.ndarray) -> np.ndarray:
        """x with the free thin-prism entries set from ``prism`` (n_sensors, 4)."""
        x = np.array(x, float, copy=True)
        m = self.prism_index >= 0
        x[self.prism_index[m]] = np.asarray(prism, float)[m]
        return x

    @property
    def n(self) -> int:
        return len(self.names)

    def pack(self, sensor_params: np.ndarray, poses: np.ndarray, prism: np.ndarray | None = None) -> np.ndarray:
        """x of the given sensor parameters (n_sensors, 14), poses (n_meas, 6) and
        thin-prism terms (n_sensors, 4; None: zero, the start of a model that frees them)."""
        x = np.zeros(self.n)
        m = self.sensor_index >= 0
        x[self.sensor_index[m]] = sensor_params[m]
        m = self.pose_index >= 0
        x[self.pose_index[m]] = poses[m]
        if prism is not None and self.prism_free:
            m = self.prism_index >= 0
            x[self.prism_index[m]] = np.asarray(prism, float)[m]
        return x

    def unpack(self, x: np.ndarray, sensor_params: np.ndarray, poses: np.ndarray):
        """Full (n_sensors, 14) and (n_meas, 6) arrays with the free entries taken from x."""
        sp = np.array(sensor_params, float, copy=True)
        po = np.array(poses, float, copy=True)
        m = self.sensor_index >= 0
        sp[m] = x[self.sensor_index[m]]
        m = self.pose_index >= 0
        po[m] = x[self.pose_index[m]]
        return sp, po


@dataclass
class Evaluation:
    """Residuals and (optionally) normal equations at one parameter vector.

    cost : F = gamma1 sum rho(alpha1) + gamma2 sum rho(alpha2) (rho(a) = a^2 without robust loss)
    res : (n, 2) alpha1, alpha2 per control point (problem order)
    ok : (n,) False where a ray could not be formed
    N1, N2 : (p, p) sum w j1 j1^T and sum w j2 j2^T (no gamma), or None
    b : (p,) sum gamma w alpha j over both terms (half the gradient of F), or None
    """

    cost: float
    res: np.ndarray
    ok: np.ndarray
    N1: np.ndarray | None = None
    N2: np.ndarray | None = None
    b: np.ndarray | None = None

    def normal(self, gamma1: float, gamma2: float) -> np.ndarray:
        """gamma1 N1 + gamma2 N2 (half the Gauss-Newton Hessian of F)."""
        return gamma1 * self.N1 + gamma2 * self.N2


@dataclass
class Evaluator:
    """Evaluates a :class:`BundleProblem` at parameter vectors through the compiled kernels."""

    problem: BundleProblem
    layout: ParameterLayout = None
    chunk_size: int = 2048
    loss: str = "none"
    scales: tuple = (1.0, 1.0)
    _arrays: dict = field(default=None, repr=False)

    def __post_init__(self):
        pr = self.problem
        if self.layout is None:
            self.layout = ParameterLayout.of(pr)
        if self.loss not in kernels.LOSS_CODES:
            raise ValueError(f"unknown robust loss {self.loss!r}; choose one of none, huber, cauchy")
        start, stop, g_scan, g_meas = pr.groups()
        c_start, c_stop, c_group = [], [], []
        for g, (a, b) in enumerate(zip(start, stop)):
            edges = np.arange(a, b, self.chunk_size)
            c_start += list(edges)
            c_stop += list(np.minimum(edges + self.chunk_size, b))
            c_group += [g] * len(edges)
        lay = self.layout
        nf = lay.n_field_terms
        npr = kernels.N_PRISM if lay.prism_free else 0
        nl = kernels.local_slots(lay.prism_free, nf)
        gmap = np.full((len(start), nl), -1, np.int64)
        f0 = kernels.N_LOCAL + 2 * npr
        for g, (s, m) in enumerate(zip(g_scan, g_meas)):
            gmap[g, :14] = lay.sensor_index[2 * s]
            gmap[g, 14:28] = lay.sensor_index[2 * s + 1]
            gmap[g, 28:34] = lay.pose_index[m]
            if lay.prism_free:
                gmap[g, 34:38] = lay.prism_index[2 * s]
                gmap[g, 38:42] = lay.prism_index[2 * s + 1]
            if nf:
                gmap[g, f0:f0 + nf] = lay.field_index[2 * s]
                gmap[g, f0 + nf:f0 + 2 * nf] = lay.field_index[2 * s + 1]
        self._arrays = dict(
            chunk_start=np.asarray(c_start, np.int64), chunk_stop=np.asarray(c_stop, np.int64),
            chunk_group=np.asarray(c_group, np.int64), group_cam=(2 * g_scan).astype(np.int64),
            group_prj=(2 * g_scan + 1).astype(np.int64), group_meas=g_meas.astype(np.int64), gmap=gmap,
            centres=np.ascontiguousarray(pr.artefact.centres), radii=np.ascontiguousarray(pr.artefact.radii),
        )
        phi_cam, phi_prj = self._field_bases()
        self._arrays.update(phi_cam=phi_cam, phi_prj=phi_prj,
                            kernel_phi_cam=np.ascontiguousarray(phi_cam[:, :nf]),
                            kernel_phi_prj=np.ascontiguousarray(phi_prj[:, :nf]))

    def _field_bases(self) -> tuple[np.ndarray, np.ndarray]:
        """Correction-field basis at every observation, (n, K, 2) for camera and projector
        (K = 0 without a field). The basis is evaluated at the observations once: they do
        not change with the parameters (a bootstrap replica's move them by micrometres,
        which changes the basis by the field's slope, below 1e-5 of its value)."""
        pr = self.problem
        if not pr.rig.has_field:
            empty = np.zeros((pr.n_points, 0, 2))
            return empty, empty
        K = field_terms(FIELD_DEGREE)
        phi = [np.zeros((pr.n_points, K, 2)), np.zeros((pr.n_points, K, 2))]
        for si, sc in enumerate(pr.rig.scanners):
            sel = pr.scanner_idx == si
            for k, (sensor, obs) in enumerate(((sc.camera, pr.cam_mm), (sc.projector, pr.prj_mm))):
                if sensor.field is not None and sensor.field.degree == FIELD_DEGREE:
                    phi[k][sel] = np.swapaxes(sensor.field.basis(obs[sel]), 1, 2)
        return np.ascontiguousarray(phi[0]), np.ascontiguousarray(phi[1])

    def fields(self, x) -> np.ndarray:
        """Correction-field coefficients (n_sensors, K) at x."""
        return self.layout.unpack_fields(np.asarray(x, float), self.problem.rig.fields)

    def observations(self, x, prj_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Camera and projector observations (n, 2) as the 14-parameter model sees them at x:
        ``m - f(m)`` with each sensor's correction field (the problem's own without one)."""
        pr, a = self.problem, self._arrays
        cam, prj = pr.cam_mm, pr.prj_mm if prj_mm is None else prj_mm
        rig = pr.rig
        if not rig.has_field:
            return cam, np.ascontiguousarray(prj, float)
        coef = self.fields(x)
        cam = cam - np.einsum("nkd,nk->nd", a["phi_cam"], coef[2 * pr.scanner_idx])
        prj = prj - np.einsum("nkd,nk->nd", a["phi_prj"], coef[2 * pr.scanner_idx + 1])
        for si, sc in enumerate(rig.scanners):  # fields of another degree, held fixed
            sel = pr.scanner_idx == si
            if sc.camera.has_field and sc.camera.field.degree != FIELD_DEGREE:
                cam[sel] = sc.camera.field.corrected(pr.cam_mm[sel])
            if sc.projector.has_field and sc.projector.field.degree != FIELD_DEGREE:
                prj[sel] = sc.projector.field.corrected(np.asarray(prj_mm if prj_mm is not None else pr.prj_mm)[sel])
        return np.ascontiguousarray(cam), np.ascontiguousarray(prj)

    @property
    def n_chunks(self) -> int:
        return len(self._arrays["chunk_start"])

    @property
    def n_local(self) -> int:
        """Local parameter slots per control point (34, more with free thin-prism terms or fields)."""
        return self._arrays["gmap"].shape[1]

    def prism(self, x) -> np.ndarray:
        """Thin-prism terms (n_sensors, 4) at x."""
        return self.layout.unpack_prism(np.asarray(x, float), self.problem.rig.prism)

    def full_params(self, x) -> tuple[np.ndarray, np.ndarray]:
        return self.layout.unpack(np.asarray(x, float), self.problem.rig.params, self.problem.poses)

    def _geometry(self, x):
        sp, po = self.full_params(x)
        sR = rotation_matrix(sp[:, 3], sp[:, 4], sp[:, 5])
        sdR = np.ascontiguousarray(np.moveaxis(rotation_derivatives(sp[:, 3], sp[:, 4], sp[:, 5]), 0, 1))
        pR = rotation_matrix(po[:, 3], po[:, 4], po[:, 5])
        pdR = np.ascontiguousarray(np.moveaxis(rotation_derivatives(po[:, 3], po[:, 4], po[:, 5]), 0, 1))
        return (np.ascontiguousarray(sp), np.ascontiguousarray(self.prism(x)), sR, sdR,
                np.ascontiguousarray(po[:, :3]), pR, pdR)

    def evaluate(self, x, want_jac: bool = True) -> Evaluation:
        """Residuals, cost and (with ``want_jac``) the normal equations at x."""
        with _threads_for(self.problem.n_points):
            return self._evaluate(x, want_jac)

    def _evaluate(self, x, want_jac: bool) -> Evaluation:
        pr, a = self.problem, self._arrays
        n, nc, p = pr.n_points, self.n_chunks, self.layout.n
        res = np.empty((n, 2))
        ok = np.empty(n, np.bool_)
        cost = np.empty(nc)
        nl = self.n_local
        nb = nc if want_jac else 1
        n1 = 28 if nl == kernels.N_LOCAL else nl  # alpha1's slots (with more: zero pose slots)
        A1 = np.empty((nb, n1, n1))
        A2 = np.empty((nb, nl, nl))
        bv = np.empty((nb, nl))
        sp, ss, sR, sdR, pt, pR, pdR = self._geometry(x)
        cam, prj = self.observations(x)
        kernels.assemble(a["chunk_start"], a["chunk_stop"], a["chunk_group"], a["group_cam"], a["group_prj"],
                         a["group_meas"], sp, ss, sR, sdR, pt, pR, pdR, pr.sphere_idx, a["centres"], a["radii"],
                         cam, prj, a["kernel_phi_cam"], a["kernel_phi_prj"], pr.gamma1, pr.gamma2, kernels.LOSS_CODES[self.loss],
                         float(self.scales[0]), float(self.scales[1]), want_jac, res, ok, cost, A1, A2, bv)
        ev = Evaluation(float(cost.sum()), res, ok)
        if want_jac:
            N1 = np.zeros((p, p))
            N2 = np.zeros((p, p))
            b = np.zeros(p)
            kernels.scatter(a["chunk_group"], a["gmap"], A1, A2, bv, N1, N2, b)
            ev.N1, ev.N2, ev.b = N1, N2, b
        lam = pr.field_prior_weight
        if lam > 0 and self.layout.field_free:
            # the fields' prior: lambda |a|^2 in F, lambda I in its half Hessian (held in N2,
            # which Evaluation.normal multiplies by gamma2), lambda a in its half gradient
            idx = self.layout.field_index[self.layout.field_index >= 0]
            coef = np.asarray(x, float)[idx]
            ev.cost += lam * float(coef @ coef)
            if want_jac:
                ev.N2[idx, idx] += lam / pr.gamma2
                ev.b[idx] += lam * coef
        return ev

    def replica_differences(self, x, prj_a: np.ndarray, prj_b: np.ndarray, flip: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cost and gradient of R data replicas at x, as differences from observing ``prj_a``
        everywhere: replica r observes ``prj_b[k]`` where ``flip[r, k]`` (a bootstrap
        replica's flipped residuals), else ``prj_a[k]``; no robust loss.

        Returns dcost (R,), dgrad (R, p) (half the gradient of F, as ``Evaluation.b``) and
        ok (n,) (False where a ray cannot be formed with either observation). One pass
        over the control points serves every replica.
        """
        pr, a = self.problem, self._arrays
        flip = np.ascontiguousarray(flip, np.bool_)
        R, nc = flip.shape[0], self.n_chunks
        ok = np.empty(pr.n_points, np.bool_)
        dcost = np.empty((nc, R))
        dgrad = np.empty((nc, R, self.n_local))
        cam, prj_a = self.observations(x, prj_a)
        _, prj_b = self.observations(x, prj_b)
        with _threads_for(pr.n_points):
            kernels.replica_gradients(a["chunk_start"], a["chunk_stop"], a["chunk_group"], a["group_cam"],
                                      a["group_prj"], a["group_meas"], *self._geometry(x), pr.sphere_idx,
                                      a["centres"], a["radii"], cam, prj_a, prj_b, a["kernel_phi_cam"],
                                      a["kernel_phi_prj"], flip, pr.gamma1, pr.gamma2, ok, dcost, dgrad)
        grad = np.zeros((R, self.layout.n))
        for ch, g in enumerate(a["chunk_group"]):
            cols = a["gmap"][g]
            used = cols >= 0
            grad[:, cols[used]] += dgrad[ch][:, used]
        return dcost.sum(axis=0), grad, ok

    def jacobian_rows(self, x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals (n, 2), local Jacobian rows (n, 2, n_local) and ok (n,) at x (memory n*544 bytes
        with 34 slots)."""
        pr, a = self.problem, self._arrays
        n = pr.n_points
        res = np.empty((n, 2))
        ok = np.empty(n, np.bool_)
        J = np.empty((n, 2, self.n_local))
        sp, ss, sR, sdR, pt, pR, pdR = self._geometry(x)
        cam, prj = self.observations(x)
        kernels.residual_rows(a["chunk_start"], a["chunk_stop"], a["chunk_group"], a["group_cam"], a["group_prj"],
                              a["group_meas"], sp, ss, sR, sdR, pt, pR, pdR, pr.sphere_idx, a["centres"], a["radii"],
                              cam, prj, a["kernel_phi_cam"], a["kernel_phi_prj"], res, ok, J)
        return res, J, ok

    def robust(self, loss: str, scales: tuple) -> "Evaluator":
        """The same evaluator with a robust ``loss`` (``none``, ``huber``, ``cauchy``) of
        ``scales`` (alpha1, alpha2), sharing its structure."""
        if loss not in kernels.LOSS_CODES:
            raise ValueError(f"unknown robust loss {loss!r}; choose one of none, huber, cauchy")
        other = copy.copy(self)
        other.loss, other.scales = loss, tuple(scales)
        return other

    def with_projector(self, prj_mm: np.ndarray) -> "Evaluator":
        """The same evaluator with other projector observations (n, 2), in problem order
        (a bootstrap replica): the structure (layout, groups, chunks) is shared."""
        from dataclasses import replace

        other = copy.copy(self)
        other.problem = replace(self.problem, prj_mm=np.asarray(prj_mm, float))
        return other

    def with_artefact(self, centres: np.ndarray, radii: np.ndarray) -> "Evaluator":
        """The same evaluator against other sphere centres (n_spheres, 3) and radii
        (n_spheres,): what the residuals would be if the artefact were as given."""
        other = copy.copy(self)
        other._arrays = {**self._arrays, "centres": np.ascontiguousarray(centres, float),
                         "radii": np.ascontiguousarray(radii, float)}
        return other

    def global_columns(self) -> np.ndarray:
        """Global parameter index of each local slot of each control point, (n, n_local) (-1: fixed)."""
        a = self._arrays
        start, stop, _, _ = self.problem.groups()
        counts = stop - start
        return np.repeat(a["gmap"], counts, axis=0)


def too_few_spheres(ids: list) -> str:
    """The reason a measurement seen on ``ids`` (fewer than three spheres) is left out."""
    what = ("its three rotation angles" if len(ids) == 1 else
            "its rotation about the line through the two sphere centres")
    return (f"control points on {len(ids)} sphere(s) only ({', '.join(ids)}): {what} cannot be determined "
            "(a sphere looks the same after any rotation about its centre)")


def triangulated_points(problem: BundleProblem, rig=None) -> np.ndarray:
    """Midpoints of closest approach (n, 3) of every control point with ``rig``'s sensors."""
    rig = problem.rig if rig is None else rig
    S = np.full((problem.n_points, 3), np.nan)
    for si, sc in enumerate(rig.scanners):
        sel = problem.scanner_idx == si
        if sel.any():
            o1, d1 = sc.camera.rays(problem.cam_mm[sel])
            o2, d2 = sc.projector.rays(problem.prj_mm[sel])
            S[sel], _ = closest_approach(o1, d1, o2, d2)
    return S
