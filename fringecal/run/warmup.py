"""Compile the pipeline's later kernels in a second process while the first run renders.

On a machine that has never run fringecal, numba compiles every kernel on first use
and caches it (``__pycache__`` or ``NUMBA_CACHE_DIR``). Compilation is single-threaded
and serialised within a process, so on a first ``fringecal run`` one core compiles
the renderer's kernel while the other waits. :func:`start` uses that core: when the
cache holds no compiled decoder yet (a cold cache), it starts ``python -m
fringecal.run.warmup``, a low-priority process that drives the decoder, the
triangulation, the sphere fits and the bundle adjustment's residual and
normal-equation kernels through their public functions on tiny inputs of the
pipeline's own types, so that numba writes them to the cache before the run needs
them. The run then loads them (a cache hit) instead of compiling them.

Nothing depends on the warm-up: if it is slower than the run, or its types miss a
signature the run uses, the run compiles that kernel itself, as without it; its
output goes nowhere. It only ever writes numba's cache files, which numba writes
atomically.
"""

from __future__ import annotations

import os
import subprocess
import sys

from fringecal import lifeline

__all__ = ["cache_is_cold", "start", "warm_up"]


def cache_is_cold() -> bool:
    """True when numba's cache holds no compiled decoder (a first run on this machine
    or in this checkout)."""
    from fringecal.fringe.decode import _decode_rows  # lazy: numba loads only for this check

    try:  # numba's cache-index path is internal: if it moves, skip the warm-up rather than the run
        index = _decode_rows._cache._cache_file._index_path
    except AttributeError:
        return False
    return not os.path.exists(index)


def start() -> subprocess.Popen | None:
    """Start the warm-up process when the cache is cold; return it (or None).

    It never outlives the command that started it (:mod:`fringecal.lifeline`): stop
    it with :func:`fringecal.lifeline.stop` when the run ends; if the command is killed,
    the lifeline stops it.
    """
    if not cache_is_cold():
        return None
    proc = subprocess.Popen([sys.executable, "-m", "fringecal.run.warmup"], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    lifeline.adopt(proc)
    return proc


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
    from fringecal.spheres.fit import SphereModel, angular_coverage
    from fringecal.spheres.robust import RejectionConfig, fit_sphere_robust

    sequence = FringeSequence()
    decode(np.zeros((sequence.n_frames, 4, 4), np.uint16), sequence, DecodeSettings())

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

    sim = simulate_control_points(rig, artefact, poses.iloc[:2], spacing_px=200, rng=0)
    problem = BundleProblem.from_tables(rig, artefact, sim.control_points, poses.iloc[:2])
    evaluator = Evaluator(problem)
    x = evaluator.layout.pack(rig.params, poses.iloc[:2][list(POSE_COLUMNS)].to_numpy(float))
    evaluator.evaluate(x, True)
    evaluator.jacobian_rows(x)


if __name__ == "__main__":  # pragma: no cover - run as a process by start()
    os.nice(10)  # here rather than in a preexec_fn, which is unsafe when the caller has threads
    warm_up()
