"""The flow behind ``fringecal run``: the pipeline's steps, wired once.

The steps come from :func:`fringecal.steps.pipeline` (a simulated rig's or a
recorded data set's source steps, then the common ones); each instance runs as
:func:`fringecal.tasks.step.step_task`, keyed by what the step declares it reads, its
settings and its code. Instances of one step are submitted together (bounded
threads, or a Dask cluster with ``--runner dask``); a step starts when the one
before it has finished. A rerun with nothing changed is all cache hits; a changed
input, setting or module reruns exactly the steps that depend on it; a deleted or
changed output is recomputed; a run killed midway resumes from what had finished:
the flow first removes the hidden temporaries of the writes the interruption cut
short and reports, in ``summary.json``'s ``resumed``, how many step instances it
reused (:mod:`fringecal.run.resume`).

The run's verdict (``summary.json``'s ``verdict``,
:func:`fringecal.acceptance.verdict.run_verdict`) decides the flow run's final state:
Completed when the run is ACCEPTED or NOT VERIFIED, Failed with the message ``NOT
ACCEPTED: <failing components>`` when it is not accepted -- after every output and
``summary.json`` are written, so that a served or scheduled run shows its verdict in
the Prefect UI. Called directly, the flow then raises :class:`NotAccepted`, which
carries the summary.
"""

from __future__ import annotations

import datetime as _dt
import os
import threading
import time

# the steps log through the "fringecal" logger; Prefect attaches its handlers to it and
# files its records under the task run that emitted them (read when Prefect starts)
os.environ.setdefault("PREFECT_LOGGING_EXTRA_LOGGERS", "fringecal")
os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")

from prefect import flow  # noqa: E402
from prefect.states import Failed, State  # noqa: E402

from fringecal.flows import interrupt, progress  # noqa: E402
from fringecal.run import resume, warmup  # noqa: E402
from fringecal.run.config import RunConfig, load_run_config  # noqa: E402
from fringecal.run.summary import manifest, run_summary  # noqa: E402
from fringecal.rundir import RunDir  # noqa: E402
from fringecal.steps import Step, current_record, pipeline, step_key  # noqa: E402
from fringecal.tasks.step import step_task  # noqa: E402
from fringecal.threads import ThreadPolicy  # noqa: E402

__all__ = ["run_flow", "StepRunner", "NotAccepted"]


class NotAccepted(Exception):
    """A finished run whose verdict is NOT ACCEPTED: the data of the flow run's Failed
    state, raised by a direct call of :func:`run_flow`; ``summary`` is the run's summary
    (also in ``summary.json``)."""

    def __init__(self, message: str, summary: dict):
        super().__init__(message, summary)  # both in args: the exception pickles as Prefect stores it
        self.summary = summary

    def __str__(self) -> str:
        return self.args[0]


class StepRunner:
    """Submits every instance of a step, gathers the records, and notes what ran and
    what came from the cache (Prefect's, or a current record of an earlier run)."""

    def __init__(self, rd: RunDir, config: RunConfig, policy: ThreadPolicy | None = None):
        self.rd = rd
        self.config = config
        self.policy = policy or config.thread_policy()
        self.ran: list[str] = []
        self.cached: list[str] = []
        self.timings: dict[str, float] = {}
        self.compile_seconds: dict[str, float] = {}
        self.kernel_wait_seconds = 0.0  # waiting for the renderer's warm-up (first run only)
        self.records: dict[str, dict] = {}
        self.finished = 0  # instances finished so far, counted as they end (what an interruption keeps)
        self._lock = threading.Lock()

    def _count(self, future) -> None:  # in the thread that ends the task
        with self._lock:
            self.finished += 1

    def run(self, step: Step, context: dict | None = None) -> None:
        t0 = time.perf_counter()
        view = step.view(self.config)
        items = step.items(self.rd, view)
        progress.step(step.label, len(items))
        if step.name == "simulate-render":  # a first run: the renderer compiles in a helper (fringecal.run.warmup)
            self.kernel_wait_seconds += warmup.wait_for_renderer(
                lambda: progress.say(f"{progress.COMPILING}: the renderer's kernel, in a helper process"))
        threads = self.policy.instance_threads(len(items))
        futures = {}
        for item in items:
            key = step_key(step, self.rd, view, item)
            stale = current_record(step, self.rd, view, item, key) is None
            task = step_task.with_options(name=step.name, task_run_name=f"{step.name}:{item}" if item else step.name,
                                          result_storage=self.rd.prefect_storage, refresh_cache=stale or None)
            futures[item] = task.submit(step.name, str(self.rd.root), self.config, item, key, context, threads)
            futures[item].add_done_callback(self._count)
        for item, future in futures.items():
            name = f"{step.name}:{item}" if item else step.name
            try:
                record = future.result()
            except Exception as err:  # the command's one line says which step instance failed
                if getattr(err, "fringecal_step", None) is None:
                    try:
                        err.fringecal_step = name
                    except AttributeError:  # an exception type without a __dict__
                        pass
                raise
            (self.cached if future.state.name == "Cached" or record.get("reused") else self.ran).append(name)
            self.records[name] = {"key": record["key"], "outputs": record["outputs"]}
            if record.get("compile_seconds") and not record.get("reused"):
                self.compile_seconds[step.name] = self.compile_seconds.get(step.name, 0.0) + record["compile_seconds"]
            progress.advance(step.label)
        self.timings[step.name] = time.perf_counter() - t0


@flow(name="fringecal-run")
def run_flow(config: RunConfig | str | None = None, run_dir: str = "runs/latest", overrides: dict | None = None,
             command: str = "fringecal run", until: str | None = None, workers: int | None = None) -> dict | State:
    """Run the pipeline into ``run_dir``; returns the summary (also ``summary.json``).

    ``config`` is the run's :class:`~fringecal.run.config.RunConfig` (a deployment's
    JSON parameter, a manifest's ``config``, is validated into one by Prefect) or a
    run-config YAML path (default ``configs/run_thesis.yaml``). The same object goes to
    every step's task. ``until`` stops after the named step (the summary then lists only
    what ran). ``workers``: the step instances the task runner runs at once, if not
    ``runner.max_workers`` (``--workers``); with ``runner.cores`` it sets the run's
    thread policy (:mod:`fringecal.threads`, recorded in ``summary.json``'s ``threads``).
    """
    interrupt.reassert()  # the command's Ctrl-C / SIGTERM handling instead of Prefect's (when armed)
    t_start = time.perf_counter()
    cfg = config if isinstance(config, RunConfig) else load_run_config(config, overrides)
    rd = RunDir(run_dir).create()
    interrupted = resume.begin(rd, command)  # before any step is submitted: no writer of this run is disturbed
    try:
        summary = _run(cfg, rd, command, until, t_start, interrupted, cfg.thread_policy(workers))
    except Exception:
        resume.finish(rd)  # an error, not an interruption
        raise
    resume.finish(rd)
    verdict = summary.get("verdict") or {}
    if verdict.get("accepted") is False:
        message = f"{verdict['word']}: {verdict['failing']} (outputs and summary.json written to {rd.root})"
        return Failed(message=message, data=NotAccepted(message, summary))
    return summary


def _run(cfg: RunConfig, rd: RunDir, command: str, until: str | None, t_start: float,
         interrupted: dict | None, policy: ThreadPolicy) -> dict:
    doc = manifest(cfg)
    if not rd.manifest.exists() or rd.manifest.load() != doc:
        rd.manifest.save(doc)
    execution = {"created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), "command": command,
                 "threads": policy.to_dict()}
    runner = StepRunner(rd, cfg, policy)
    interrupt.track(runner)
    steps = pipeline(cfg)
    if until is not None and until not in [s.name for s in steps]:
        raise ValueError(f"--until {until}: not a step of this run ({', '.join(s.name for s in steps)})")
    for step in steps:
        context = {"timings": {**runner.timings, "total": time.perf_counter() - t_start},
                   "compile_seconds": dict(runner.compile_seconds),
                   "execution": execution} if step.name == "report" else None
        runner.run(step, context)
        if step.name == until:
            break
    summary = run_summary(rd, cfg) if until is None else {"name": cfg.name, "source": cfg.source}
    summary.update(execution)
    # compile_seconds: numba compiling kernels (first run on a machine only), per step, summed
    # over the step's instances (which may overlap in time), part of the step's timing;
    # kernel_wait_seconds: waiting for the renderer compiled by a warm-up helper (first run)
    summary.update(timings=runner.timings, compile_seconds=runner.compile_seconds,
                   kernel_wait_seconds=runner.kernel_wait_seconds,
                   total_seconds=time.perf_counter() - t_start,
                   tasks={"ran": runner.ran, "cached": runner.cached}, steps=runner.records)
    if interrupted is not None:  # the last run of this directory was interrupted: what it left was reused
        summary["resumed"] = {"reused": len(runner.cached),
                              "interrupted_run_started_utc": interrupted.get("started_utc")}
    rd.summary.save(summary)
    return summary
