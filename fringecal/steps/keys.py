"""Cache keys, records and the one validity check of pipeline steps.

A step instance's key is the SHA-256 of

* the step's name and item,
* the values of its declared settings,
* the source digest of its module and declared modules with everything they import,
* the content digest of every file it reads (absent optional files count as absent;
  :class:`~fringecal.steps.base.Rows` by the selected rows only).

After an instance runs, :func:`run_step` writes its *record* (``RunDir.step_record``):
the key and the digest of every output it declares (``None`` for an optional output
it did not write). An instance is *current* when its record has today's key and
every declared output is on disk with the recorded digest -- the one validity
check, used by the flow (to recompute stale cached results), by
``fringecal run``'s up-to-date shortcut (before Prefect starts) and by
:func:`run_step` itself (which then returns the record without running). Digests
come from the run directory's :class:`~fringecal.digests.DigestCache`, so checking
an unchanged run costs file-system stats, not hashing.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from fringecal import compile_clock
from fringecal.digests import DigestCache, digest_value, source_digest
from fringecal.rundir import RunDir, RunFile
from fringecal.steps.base import Rows, Settings, Step, StepError, Value
from fringecal.threads import step_threads

__all__ = ["step_key", "current_record", "run_step", "digests_of", "RunFileChanged", "recorded_outputs",
           "check_unchanged"]

log = logging.getLogger(__name__)

_caches: dict[Path, DigestCache] = {}


def digest_cache(rd: RunDir) -> DigestCache:
    """The (per-process) digest cache of a run directory."""
    root = rd.root.resolve()
    if root not in _caches:
        _caches[root] = DigestCache(rd.digest_cache_dir)
    return _caches[root]


def _digest(rd: RunDir, read) -> str | None:
    if isinstance(read, Value):
        return digest_value(read.value)
    if isinstance(read, Rows):
        if not read.table.exists():
            return None
        return digest_value(read.text())
    path = read.path if isinstance(read, RunFile) else Path(read)
    if isinstance(read, RunFile) and not read.exists():  # a store only counts once complete
        return None
    if not path.exists():
        return None
    return digest_cache(rd).digest(path)


def _label(read, index: int) -> str:
    if isinstance(read, Value):
        return f"value:{read.label}"
    if isinstance(read, Rows):
        return f"{read.table.rel}?{'&'.join(f'{k}={v}' for k, v in sorted(read.where.items()))}"
    if isinstance(read, RunFile):
        return read.rel
    # a file outside the run directory counts by its content, not by where it lies, so a
    # data set or rig moved to another folder or machine keeps its keys
    return f"input {index}: {Path(read).name}"


def digests_of(rd: RunDir, files) -> dict[str, str | None]:
    """Label (run-relative path, or position and name of an outside file) -> content digest."""
    return {_label(f, i): _digest(rd, f) for i, f in enumerate(files)}


class RunFileChanged(ValueError):
    """A run file differs from what the step that wrote it recorded; the message names it."""


_records: dict[str, tuple[int, int, str, dict]] = {}


def recorded_outputs(rd: RunDir) -> dict[str, tuple[str, str | None]]:
    """Run-relative path -> (the step instance that last wrote it, its recorded digest),
    from every step record of ``rd`` (an unreadable record counts as absent; when two
    records name one file, as after a run of another source into the same directory,
    the newer record counts). Records are parsed once per process while unchanged."""
    found = []
    for rec_file in rd.step_records():
        try:
            st = rec_file.path.stat()
        except OSError:
            continue
        key = str(rec_file.path)
        hit = _records.get(key)
        if hit is None or hit[:2] != (st.st_mtime_ns, st.st_size):
            try:
                rec = rec_file.load()
                label = f"{rec['step']}:{rec['item']}" if rec.get("item") else rec["step"]
                hit = (st.st_mtime_ns, st.st_size, label, dict(rec["outputs"]))
            except (ValueError, KeyError, TypeError, AttributeError):
                continue
            _records[key] = hit
        found.append(hit)
    out = {}
    for _, _, label, outputs in sorted(found, key=lambda h: h[0]):
        for rel, digest in outputs.items():
            out[rel] = (label, digest)
    return out


def check_unchanged(rd: RunDir, files, recorded: dict | None = None) -> None:
    """Refuse (:class:`RunFileChanged`) a run file whose content differs from the digest
    its step recorded when it wrote it: a file the run trusts was damaged or edited
    after it was written (its size and dates may be unchanged). Files without a record
    (written by no step) pass."""
    recorded = recorded_outputs(rd) if recorded is None else recorded
    for f in files:
        f = f.table if isinstance(f, Rows) else f
        if not isinstance(f, RunFile) or f.rel not in recorded or not f.exists():
            continue
        producer, digest = recorded[f.rel]
        if digest is not None and _digest(rd, f) != digest:
            raise RunFileChanged(f"{f.path}: changed since step {producer} wrote it (its content digest differs "
                                 "from the step's record: a damaged or edited file); rerun `fringecal run` on this "
                                 "run directory to recompute it")


def step_key(step: Step, rd: RunDir, cfg: Settings, item: str) -> str:
    """The cache key of one instance of ``step`` (see the module notes)."""
    doc = {"step": step.name, "item": item, "settings": cfg.keyed(),
           "code": source_digest(step.module_names()),
           "inputs": digests_of(rd, step.reads(rd, cfg, item))}
    return f"{step.name}-{digest_value(doc)[:40]}"


def current_record(step: Step, rd: RunDir, cfg: Settings, item: str, key: str) -> dict | None:
    """The instance's record if it was computed with ``key`` and every declared output
    is unchanged since; None otherwise."""
    rec_file = rd.step_record(step.name, item)
    if not rec_file.exists():
        return None
    try:
        rec = rec_file.load()
    except ValueError:
        return None
    if rec.get("key") != key:
        return None
    outputs = step.writes(rd, cfg, item)
    if sorted(rec.get("outputs", {})) != sorted(f.rel for f in outputs):
        return None
    for f in outputs:
        if _digest(rd, f) != rec["outputs"][f.rel]:
            if rec["outputs"][f.rel] is not None and f.exists():  # there, but not what the step wrote
                log.warning("%s: changed since step %s wrote it (content digest); it is computed again",
                            f.path, step.name)
            return None
    return rec


def run_step(step: Step, rd: RunDir, config, item: str = "", context: dict | None = None,
             force: bool = False, key: str | None = None, threads: int | None = None) -> dict:
    """Run one instance of ``step`` over ``rd`` unless it is current; return its record.

    ``config`` is the resolved :class:`~fringecal.run.config.RunConfig`; the step sees
    only its declared part. ``context`` holds values that do not change what a step
    computes (the report's step timings) and are not keyed. ``key`` is the
    instance's key when the caller has just computed it (the flow does, to submit the
    task). The record gains ``"reused": True`` when nothing had to run, and
    ``"seconds"`` (wall) and ``"compile_seconds"`` (numba compiling kernels on a first
    run, part of the wall time; :mod:`fringecal.compile_clock`) otherwise. ``threads``:
    the numba threads this instance may use (:func:`fringecal.threads.step_threads`;
    None: every core the run's policy allows, for an instance that runs alone).
    """
    cfg = step.view(config)
    key = key or step_key(step, rd, cfg, item)
    if not force and (rec := current_record(step, rd, cfg, item, key)) is not None:
        return {**rec, "reused": True}
    check_unchanged(rd, step.reads(rd, cfg, item))  # what it reads is what the steps before it wrote
    clock = compile_clock.install()
    t0, c0 = time.perf_counter(), clock.thread_seconds()
    if threads is None:
        threads = config.thread_policy(1).instance_threads(1)
    with step_threads(threads):
        step.run(rd, cfg, item, **(context or {}))
    seconds, compile_seconds = time.perf_counter() - t0, clock.thread_seconds() - c0
    outputs = step.writes(rd, cfg, item)
    missing = [f.rel for f in outputs if not f.optional and not f.exists()]
    if missing:
        raise StepError(f"step {step.name} ({item or 'run'}) did not write {', '.join(missing)}")
    rec = {"step": step.name, "item": item, "key": key, "outputs": {f.rel: _digest(rd, f) for f in outputs},
           "seconds": seconds, "compile_seconds": compile_seconds}
    rd.step_record(step.name, item).save(rec)
    return {**rec, "reused": False}
