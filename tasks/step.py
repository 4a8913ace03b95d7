"""The one adapter from a pipeline step to a Prefect task.

``step_task`` runs one instance of a named step (:mod:`fringecal.steps`) over a run
directory. Its cache key is the step's declared key, computed by the flow from the
files on disk once the steps before it finished (:func:`fringecal.steps.step_key`);
the cached result is the step's record (key and output digests), kept in the run
directory's ``.prefect`` folder. The flow refreshes a cached result whose outputs
changed since (:func:`fringecal.steps.current_record`).
"""

from __future__ import annotations

from prefect import task

from fringecal.run.config import RunConfig
from fringecal.rundir import RunDir
from fringecal.steps import get_step, run_step

__all__ = ["step_task"]


@task(cache_key_fn=lambda context, parameters: parameters["key"], persist_result=True)
def step_task(step: str, run_dir: str, config: RunConfig, item: str, key: str, context: dict | None = None,
              threads: int | None = None) -> dict:
    """Run ``item`` of ``step`` over ``run_dir`` with the run's ``config``; return its record.
    ``threads``: the numba threads the instance may use (:mod:`fringecal.threads`).

    The steps log through the ``fringecal`` logger, which the flow registers with
    Prefect (``PREFECT_LOGGING_EXTRA_LOGGERS``), so their messages belong to the task run.
    """
    return run_step(get_step(step), RunDir(run_dir), config, item, context, key=key, threads=threads)
