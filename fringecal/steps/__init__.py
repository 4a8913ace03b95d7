"""The pipeline's named steps, one module each, and their order.

A run is a data source's steps followed by the common ones; every step is an object
with one entry point over the run directory and its typed settings
(:class:`~fringecal.steps.base.Step`), so the Prefect flow, ``fringecal step``,
``fringecal calibrate`` and the benchmarks all call the same code:

=====================  ====================================================================
simulated source       ``simulate-prepare`` -> ``simulate-hexapod`` -> ``simulate-render``
                       -> ``simulate-ballbar`` -> ``simulate-sphere`` -> ``simulate-dumbbell``
                       -> ``simulate-flat``
recorded data set      ``ingest`` -> ``decode``
every run              ``spheres-first`` -> ``label`` -> ``spheres-second`` -> ``initialise``
                       -> ``bundle`` -> ``cross-validate`` -> ``verify`` -> ``acceptance``
                       -> (simulated: ``evaluate``)
                       -> ``report``
=====================  ====================================================================
"""

from __future__ import annotations

from fringecal.steps.acceptance import Acceptance
from fringecal.steps.base import Rows, Settings, Step, StepError, Value
from fringecal.steps.bundle import Bundle
from fringecal.steps.crossval import CrossValidate
from fringecal.steps.decode import Decode, DecodePositions
from fringecal.steps.evaluate import Evaluate
from fringecal.steps.ingest import Ingest
from fringecal.steps.initialise import Initialise
from fringecal.steps.keys import current_record, run_step, step_key
from fringecal.steps.label import Label
from fringecal.steps.report import Report
from fringecal.steps.simulate_acceptance import SimulateDumbbell, SimulateFlat, SimulateSphere
from fringecal.steps.simulate_ballbar import SimulateBallbar
from fringecal.steps.simulate_hexapod import SimulateHexapod
from fringecal.steps.simulate_prepare import SimulatePrepare
from fringecal.steps.simulate_render import SimulateRender
from fringecal.steps.spheres_first import SpheresFirst
from fringecal.steps.spheres_second import SpheresSecond
from fringecal.steps.verify import Verify

__all__ = ["STEPS", "SIMULATED_SOURCE", "DATASET_SOURCE", "COMMON", "pipeline", "get_step", "run_pipeline", "Step",
           "Settings", "Rows", "Value", "StepError", "run_step", "step_key", "current_record"]

SIMULATED_SOURCE = (SimulatePrepare(), SimulateHexapod(), SimulateRender(), SimulateBallbar(), SimulateSphere(),
                    SimulateDumbbell(), SimulateFlat())
DATASET_SOURCE = (Ingest(), Decode(), DecodePositions())
COMMON = (SpheresFirst(), Label(), SpheresSecond(), Initialise(), Bundle(), CrossValidate(), Verify(), Acceptance())
EVALUATION = (Evaluate(),)
REPORT = (Report(),)

STEPS = {s.name: s for s in SIMULATED_SOURCE + DATASET_SOURCE + COMMON + EVALUATION + REPORT}


def pipeline(config) -> list[Step]:
    """The steps of a run of ``config`` (a :class:`~fringecal.run.config.RunConfig`), in order."""
    source = SIMULATED_SOURCE if config.source == "simulated" else DATASET_SOURCE
    evaluation = EVALUATION if config.source == "simulated" else ()
    return list(source + COMMON + evaluation + REPORT)


def get_step(name: str) -> Step:
    try:
        return STEPS[name]
    except KeyError:
        raise KeyError(f"no step {name!r}; the steps are {', '.join(STEPS)}") from None


def run_pipeline(rd, config, workers: int = 1, until: str | None = None, force: bool = False,
                 context: dict | None = None) -> dict[str, dict[str, dict]]:
    """Run every step of ``config`` over ``rd`` without Prefect (tests, benchmarks,
    ``fringecal step``): the instances of a step in a pool of ``workers`` threads (at
    most the run's cores, :meth:`~fringecal.run.config.RunConfig.thread_policy`), one
    step after the other, each instance with its share of numba's threads. Returns step
    name -> item -> record (``reused`` says whether it had to run). ``context`` goes to
    the report step.
    """
    from concurrent.futures import ThreadPoolExecutor

    policy = config.thread_policy(workers)
    out: dict[str, dict[str, dict]] = {}
    with ThreadPoolExecutor(max_workers=policy.workers) as pool:
        for step in pipeline(config):
            items = step.items(rd, step.view(config))
            ctx = context if step.name == "report" else None
            threads = policy.instance_threads(len(items))
            records = pool.map(lambda item: run_step(step, rd, config, item, ctx, force, threads=threads), items)
            out[step.name] = dict(zip(items, records))
            if step.name == until:
                break
    return out
