"""Compile the pipeline's kernels in helper processes while the first run starts.

On a machine that has never run fringecal, numba compiles every kernel on first use
and caches it (``__pycache__`` or ``NUMBA_CACHE_DIR``). Compilation is single-threaded
and serialised within a process, and a run's first half minute is spent starting
Prefect (its temporary server, and on a first run its database), which needs no
kernel. :func:`start` uses that time: when the cache is cold it starts, at once,

* ``python -m fringecal.run.warmup renderer`` (a simulated run only): the renderer's
  kernel, the longest compilation (some 27 s on an idle core), on a tiny measurement of
  the pipeline's own types. The flow waits for it before the first render
  (:func:`wait_for_renderer`) and then loads it from the cache, instead of compiling it
  only once Prefect is up;
* ``python -m fringecal.run.warmup``: the decoder first (the run needs it right after
  the first render), then, at low priority (``nice 10``, so as not to slow the
  rendering), the triangulation, the sphere fits (and the passes over a black-box
  scanner's cloud) and the bundle adjustment's residual, normal-equation and bootstrap
  kernels, through their public functions on tiny inputs of the pipeline's types, so
  that numba writes them to the cache before the run needs them.

Nothing else depends on the warm-up: if a helper is slower than the run, or its types
miss a signature the run uses, the run compiles that kernel itself, as without it;
their output goes nowhere. They only ever write numba's cache files, which numba
writes atomically.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from fringecal import lifeline

__all__ = ["cache_is_cold", "renderer_is_cold", "start", "wait_for_renderer", "warm_up", "warm_up_renderer"]

#: the renderer's helper process of this command, while the flow may wait for it
_renderer: subprocess.Popen | None = None


def _index_missing(kernel) -> bool:
    try:  # numba's cache-index path is internal: if it moves, skip the warm-up rather than the run
        index = kernel._cache._cache_file._index_path
    except AttributeError:
        return False
    return not os.path.exists(index)


def cache_is_cold() -> bool:
    """True when numba's cache holds no compiled decoder (a first run on this machine
    or in this checkout)."""
    from fringecal.fringe.decode import _decode_rows  # lazy: numba loads only for this check

    return _index_missing(_decode_rows)


def renderer_is_cold() -> bool:
    """True when numba's cache holds no compiled renderer."""
    from fringecal.simulate.kernel import render_tiles  # lazy: numba loads only for this check

    return _index_missing(render_tiles)


def _helper(*args: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "fringecal.run.warmup", *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    lifeline.adopt(proc)
    return proc


def start(renderer: bool = False, others: bool = True) -> list[subprocess.Popen]:
    """Start the warm-up processes the cache needs (see the module notes); return them.

    ``renderer``: the run renders (a simulated source); ``others``: it decodes or
    processes (the decoder and the later kernels). They never outlive the command that
    started them (:mod:`fringecal.lifeline`): stop them with
    :func:`fringecal.lifeline.stop` when the run ends; if the command is killed, the
    lifeline stops them.
    """
    global _renderer
    procs = []
    if renderer and renderer_is_cold():
        _renderer = _helper("renderer")
        procs.append(_renderer)
    if others and cache_is_cold():
        procs.append(_helper())
    return procs


def wait_for_renderer(announce=None, timeout: float = 600.0) -> float:
    """Wait until this command's renderer warm-up has ended (its kernel is then in the
    cache); return the seconds waited (0 when there is none). ``announce()`` is called
    first when there is something to wait for."""
    global _renderer
    proc, _renderer = _renderer, None
    if proc is None or proc.poll() is not None:
        return 0.0
    if announce is not None:
        announce()
    t0 = time.perf_counter()
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:  # the run compiles the kernel itself, as without a warm-up
        pass
    return time.perf_counter() - t0


def warm_up_renderer() -> None:
    """Render a tiny measurement of the default simulated rig, as the pipeline renders
    (:func:`fringecal.simulate.measurement.render_frames`, the acquisition settings'
    types), so that the renderer's kernel is compiled into the cache."""
    # lazy: only the warm-up process loads the renderer
    from fringecal.run.config import load_run_config
    from fringecal.simulate.measurement import render_frames
    from fringecal.simulate.scenes import artefact_scene
    from fringecal.simulate.source import load_simulated_rig

    sim = load_run_config().simulate
    sim = sim.model_copy(update={"acquisition": sim.acquisition.model_copy(update={"camera_width_px": 32})})
    sr = load_simulated_rig(sim)
    pose, T = next(iter(sr.planned.items()))
    scanner = sr.truth.scanners[0]
    render_frames(f"{pose}-{scanner.name}", scanner, artefact_scene(sr.artefact, sr.rods, T, sr.hardware),
                  sim.acquisition)


def warm_up() -> None:
    """Call each later kernel once on tiny inputs of the pipeline's types, decoder first
    (the run needs it right after rendering the first store)."""
    import numpy as np

    # lazy: only the warm-up process loads the kernels, not the run that starts it
    from fringecal.calibration.model import POSE_COLUMNS, BundleProblem, Evaluator
    from fringecal.fringe.decode import DecodeSettings, decode
    from fringecal.fringe.sequence import FringeSequence
    from fringecal.pointcloud import triangulate_image_points, triangulate_maps
    from fringecal.simulate.control_points import simulate_control_points, thesis_truth
    from fringecal.spheres import cloud_kernels
    from fringecal.spheres.fit import SphereModel, angular_coverage
    from fringecal.spheres.robust import RejectionConfig, fit_sphere_robust

    sequence = FringeSequence()
    decode(np.zeros((sequence.n_frames, 4, 4), np.uint16), sequence, DecodeSettings())
    os.nice(10)  # the rest is needed later: from here on the rendering has the cores

    rig, artefact, poses = thesis_truth()
    scanner = rig.scanners[0]
    shape = scanner.camera.format.shape
    tau = np.full(shape, 0.5, np.float32)
    triangulate_maps(scanner.camera, scanner.projector, tau, tau, np.ones(shape, bool))
    triangulate_image_points(scanner.camera, scanner.projector, np.zeros((2, 2)), np.zeros((2, 2)))

    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))
    points = 25.0 * d / np.linalg.norm(d, axis=1)[:, None] + rng.normal(0, 0.01, (200, 3))
    SphereModel.from_estimate(points)
    SphereModel.from_estimate(points, 25.0)
    angular_coverage(d / np.linalg.norm(d, axis=1)[:, None])
    fit_sphere_robust(points, 25.0, expected_radius=25.0, config=RejectionConfig(noise_mm=0.01, min_points=4))
    # a black-box scanner's cloud: its cubes and the spheres' neighbourhoods (fringecal.spheres.cloud_spheres)
    keys = cloud_kernels.cube_keys(points, 6.25, np.floor(points.min(axis=0) / 6.25) - 1)
    order = np.argsort(keys)
    start = np.flatnonzero(np.r_[True, np.diff(keys[order]) != 0])
    s1, s2 = cloud_kernels.cube_sums(points, order, start, points.mean(axis=0))
    cloud_kernels.neighbourhood_sums(keys[order][start], np.diff(np.r_[start, len(keys)]), s1, s2,
                                     np.array([1, -1], np.int64))
    cloud_kernels.within_reach(points, points[0], 31.25)
    cloud_kernels.within_reach_of_any(points, points[:2].copy(), 31.25)

    sim = simulate_control_points(rig, artefact, poses.iloc[:2], spacing_px=200, rng=0)
    problem = BundleProblem.from_tables(rig, artefact, sim.control_points, poses.iloc[:2])
    evaluator = Evaluator(problem)
    x = evaluator.layout.pack(rig.params, poses.iloc[:2][list(POSE_COLUMNS)].to_numpy(float))
    evaluator.evaluate(x, True)
    evaluator.jacobian_rows(x)
    flip = np.zeros((2, problem.n_points), bool)
    evaluator.replica_differences(x, problem.prj_mm, problem.prj_mm, flip)


if __name__ == "__main__":  # pragma: no cover - run as processes by start()
    if sys.argv[1:] == ["renderer"]:
        warm_up_renderer()
    else:
        warm_up()
