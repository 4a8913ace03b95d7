"""Live acquisition: a real hexapod carries the artefact, real scanners record it.

``fringecal acquire --dataset DIR --hexapod URL --capture CMD`` fills the
``measurements/`` of a data set the user prepared, measurement by measurement:

1. **Check everything before the hexapod moves** (:func:`prepare`, :func:`check_reachable`):
   ``dataset.yaml``, ``artefact.csv`` (and ``rods.csv``), ``sensors_prior.csv`` (the
   scanners and their camera formats), ``poses_planned.csv`` (the measurements, in
   acquisition order, and their planned ``T_world_artefact``; required here), the hexapod
   config (``T_world_base`` and ``T_top_artefact`` from :meth:`HexapodRig.from_config`),
   the capture template (:class:`~.live_capture.CaptureCommand`: placeholders, program
   found), what is already in ``measurements/`` (:func:`~.live_state.survey`), and that
   every pose still to measure is inside the workspace. Then the box must identify, be
   idle, and every move of the sequence (from the encoders' position, through the
   remaining poses in order) must pass the driver's path check. Nothing is sent but
   queries until all of this passed.
2. **Per measurement** (plan order, complete measurements skipped): move the artefact
   (:meth:`PlatformMover.move_artefact_to`: the driver waits for IDLE and checks the
   encoders), record the move in the journal, check the reached pose (forward
   kinematics of the encoder counts) against the planned one within :func:`reach_tolerance`,
   wait ``settle_s`` and check the encoders did not change, then run the capture command
   once per scanner still missing, one after the other (the projectors would see each
   other), in ``sensors_prior.csv`` order (:func:`~.live_capture.capture_stack`: staging
   folder, completeness wait, atomic rename). When every scanner's stack is in place,
   ``hexapod_moves.csv`` is rewritten (atomically) with the measurement's row.
3. **Finally** the data set must open (:meth:`DataSet.open`), as ``fringecal run
   --dataset`` will open it.

Resuming: run the same command again. A measurement is complete when every scanner's
stack is in place; complete measurements are neither moved to nor captured again.
Staging folders a killed run left behind are removed. A partial measurement (some
scanners in place) is moved to again and captures only the missing scanners; its row
in ``hexapod_moves.csv`` is the last move, with ``moves`` > 1 (both moves go to the same
target counts).

Failures stop the acquisition with one message naming the measurement (and scanner),
and an exit status per cause (:data:`EXIT_HEXAPOD`, :data:`EXIT_INPUT`,
:data:`EXIT_CAPTURE`, :data:`EXIT_INTERRUPTED`). After a hexapod fault the driver is
latched (it sent STOP once and sends nothing more); after any failure the hexapod is
not commanded again. A failed capture is retried ``retries`` times at the same pose
(default 0: a failing vendor tool usually needs a person; resuming costs one move); a
wrong stack (size, sequence, names) is never retried. SIGINT and SIGTERM
(:func:`stop_on_signals`) stop between steps: a running move is finished and
verified, a running capture is stopped and its staging folder removed; completed
measurements stay, nothing is half-renamed.
"""

from __future__ import annotations

import signal
import time
from contextlib import contextmanager
from typing import Callable, Iterator, Optional

import numpy as np

from fringecal.acquisition.live_capture import (
    CaptureFailed,
    CaptureTemplateError,
    StackExpectation,
    capture_stack,
    remove_staging,
)
from fringecal.acquisition.live_plan import TOLERANCE_MARGIN, LivePlan, check_reachable, prepare, reach_tolerance
from fringecal.acquisition.live_state import MovesLog, Survey, acquisition_lock, move_row, survey
from fringecal.dataset import MEASUREMENTS_DIR, DataSet
from fringecal.hexapod import ForwardKinematicsError, HexapodFault, HexapodRig, PlatformMover, TargetRejected
from fringecal.names import check_name, confined

__all__ = ["EXIT_HEXAPOD", "EXIT_INPUT", "EXIT_CAPTURE", "EXIT_INTERRUPTED", "TOLERANCE_MARGIN", "AcquisitionError",
           "StopRequest", "stop_on_signals", "LivePlan", "prepare", "check_reachable", "reach_tolerance",
           "open_mover", "check_path", "acquire"]

#: exit status: hexapod fault, pose not reached within tolerance, box busy or not answering
EXIT_HEXAPOD = 1
#: exit status: bad input, refused before anything moved
EXIT_INPUT = 2
#: exit status: capture failed, timed out, or gave an incomplete or wrong stack
EXIT_CAPTURE = 4  # not 3: 3 is "verification failed" in every command
#: exit status: stopped by SIGINT or SIGTERM (resumable)
EXIT_INTERRUPTED = 130


class AcquisitionError(RuntimeError):
    """An acquisition that stopped; ``status`` is the exit status for the command line."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status


class StopRequest:
    """A request to stop between steps (set by a signal handler or by another thread).

    Setting it only stores the reason (no lock: a signal handler may run while the main
    thread holds any lock); :meth:`wait` polls it.
    """

    def __init__(self):
        self.reason = ""

    def set(self, reason: str = "a stop request") -> None:
        self.reason = reason or "a stop request"

    def is_set(self) -> bool:
        return bool(self.reason)

    def wait(self, seconds: float) -> bool:
        """Sleep up to ``seconds``; True as soon as a stop is requested."""
        end = time.monotonic() + seconds
        while not self.is_set():
            left = end - time.monotonic()
            if left <= 0:
                return False
            time.sleep(min(left, 0.05))
        return True


@contextmanager
def stop_on_signals(stop: Optional[StopRequest] = None) -> Iterator[StopRequest]:
    """SIGINT and SIGTERM set the returned :class:`StopRequest` instead of raising
    (main thread only); the previous handlers come back on exit."""
    stop = stop or StopRequest()

    def handler(signum, _frame):
        stop.set(signal.Signals(signum).name)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def open_mover(url: str, rig: HexapodRig) -> PlatformMover:
    """Open the box at ``url`` (``ID?``); a failure raises AcquisitionError (EXIT_HEXAPOD)."""
    try:
        return PlatformMover.open(url, rig)
    except HexapodFault as err:
        where = "" if url in str(err) else f"hexapod at {url}: "
        raise AcquisitionError(f"{where}{err}; nothing was moved", EXIT_HEXAPOD) from None


def check_path(mover: PlatformMover, plan: LivePlan, todo: list[str], counts) -> dict[str, str]:
    """The driver's path check for every move of the sequence (sends nothing): from
    ``counts`` through the poses of ``todo`` in order. Returns measurement -> problem."""
    problems, start, previous = {}, np.asarray(counts), "the current position"
    for m in todo:
        target, _ = plan.rig.counts_for(plan.planned[m])
        try:
            mover.driver.check_target(target, start)
        except TargetRejected as err:
            problems[m] = f"the move from {previous} is refused: {err}"
        start, previous = target, f"measurement {m}"
    return problems


def acquire(plan: LivePlan, url: str, timeout_s: float, retries: int = 0, settle_s: float = 1.0,
            stop: Optional[StopRequest] = None, report: Callable[[str], None] = lambda _: None) -> DataSet:
    """Acquire every measurement of ``plan`` that is not complete (see the module notes).

    Parameters
    ----------
    plan : LivePlan
        From :func:`prepare`, with a capture command.
    url : str
        The box's serial port (``/dev/ttyUSB0``) or a pyserial URL (``hexsim://...``).
    timeout_s : float
        Per capture: from starting the command until the stack is complete.
    retries : int
        Further attempts of a failed capture at the same pose.
    settle_s : float
        Wait after each move before the encoders are read again and the captures start.
    stop : StopRequest, optional
        Checked between steps (see :func:`stop_on_signals`).
    report : callable
        Called with one line per event (moves, stacks, skipped measurements).

    Returns
    -------
    DataSet
        The complete data set, opened and validated.

    Raises
    ------
    AcquisitionError
        With its exit status; TargetRejected or CaptureTemplateError for bad input.
    """
    if plan.capture is None:
        raise CaptureTemplateError("a capture command (--capture) is needed to acquire")
    stop = stop or StopRequest()
    check_reachable(plan)
    with acquisition_lock(plan.root):
        state = survey(plan.root, list(plan.planned), plan.cameras)  # again, now that the data set is ours
        for p in state.stale:
            remove_staging(p)
            report(f"removed the stale staging folder {p}")
        log = MovesLog(plan.root)
        complete = [m for m, s in state.states.items() if s.complete]
        log.publish(complete)
        for m in complete:
            report(f"measurement {m}: complete, skipped")
        todo = state.todo()
        if todo:
            _Run(plan, state, log, timeout_s, retries, settle_s, stop, report).run(url, todo)
    try:
        return DataSet.open(plan.root)
    except ValueError as err:
        raise AcquisitionError(f"every measurement is acquired, but the data set does not open: {err}",
                               EXIT_INPUT) from None


class _Run:
    """One acquisition pass over the measurements still to do (hardware open)."""

    def __init__(self, plan, state: Survey, log: MovesLog, timeout_s, retries, settle_s, stop, report):
        self.plan, self.state, self.log = plan, state, log
        self.timeout_s, self.retries, self.settle_s, self.stop, self.report = timeout_s, retries, settle_s, stop, report
        self.sequence, self.sequence_source = state.sequence, state.sequence_source
        self.complete = [m for m, s in state.states.items() if s.complete]

    def run(self, url: str, todo: list[str]) -> None:
        with open_mover(url, self.plan.rig) as mover:
            counts, busy = self._hexapod("before the first move", mover.driver.positions)
            if busy:
                raise AcquisitionError(f"hexapod at {url}: the box reports a move running; nothing was commanded "
                                       "(wait until it is idle)", EXIT_HEXAPOD)
            problems = check_path(mover, self.plan, todo, counts)
            if problems:
                raise TargetRejected("; ".join(f"measurement {m}: {p}" for m, p in problems.items())
                                     + "; nothing was moved")
            for m in todo:
                self._interrupted_check()
                self._move(mover, m)
                for s in self.state.states[m].missing:
                    self._interrupted_check()
                    self._capture(m, s)
                self.complete = [n for n in self.plan.planned if n in self.complete or n == m]
                self.log.publish(self.complete)
                self.report(f"measurement {m}: complete ({len(self.complete)} of {len(self.plan.planned)})")

    def _hexapod(self, where: str, call, *args):
        try:
            return call(*args)
        except HexapodFault as err:
            raise AcquisitionError(f"{where}: {err}", EXIT_HEXAPOD) from None
        except (TargetRejected, ForwardKinematicsError) as err:
            raise AcquisitionError(f"{where}: hexapod refused or lost the pose: {err}", EXIT_HEXAPOD) from None

    def _move(self, mover: PlatformMover, m: str) -> None:
        where = f"measurement {m}"
        move = self._hexapod(where, mover.move_artefact_to, self.plan.planned[m])
        tol = reach_tolerance(self.plan.rig, move.platform_pose_planned)
        self.log.record(move_row(m, move, tol))
        dt, dr = move.translation_error_mm, move.rotation_error_rad
        if dt > tol[0] or dr > tol[1]:
            raise AcquisitionError(f"{where}: the artefact reached {dt:.4f} mm / {dr * 1e6:.1f} urad from its planned "
                                   f"pose, beyond the tolerance {tol[0]:.4f} mm / {tol[1] * 1e6:.1f} urad; the hexapod "
                                   "is not commanded further", EXIT_HEXAPOD)
        self.report(f"{where}: moved, {dt:.4f} mm / {dr * 1e6:.1f} urad from plan "
                    f"(tolerance {tol[0]:.4f} mm / {tol[1] * 1e6:.1f} urad)")
        if self.stop.wait(self.settle_s):
            self._interrupted_check()
        counts, busy = self._hexapod(f"{where}, settling", mover.driver.positions)
        drift = np.abs(counts - move.counts_read).max()
        if busy or drift > self.plan.rig.config.actuator.position_tolerance_counts:
            raise AcquisitionError(f"{where}: the platform did not stay put while settling ({self.settle_s:g} s): "
                                   f"encoders {move.counts_read.tolist()} after the move, {counts.tolist()} "
                                   f"{'and BUSY ' if busy else ''}after settling; the hexapod is not commanded "
                                   "further", EXIT_HEXAPOD)

    def _capture(self, m: str, s: str) -> None:
        w, h = self.plan.cameras[s]
        expect = StackExpectation(m, s, w, h, self.sequence, self.sequence_source)
        final = confined(self.plan.root, MEASUREMENTS_DIR, check_name(m, "measurement"), check_name(s, "scanner"))
        for attempt in range(self.retries + 1):
            try:
                spec = capture_stack(self.plan.capture, expect, final, self.plan.root, self.timeout_s, self.stop)
                break
            except CaptureFailed as err:
                if err.kind == "interrupted":
                    self._interrupted_check()
                if err.kind == "wrong-stack" or attempt == self.retries:
                    tried = f" (attempt {attempt + 1} of {self.retries + 1})" if self.retries else ""
                    raise AcquisitionError(f"{err}{tried}; the hexapod is not commanded further", EXIT_CAPTURE) \
                        from None
                self.report(f"{err}; retrying ({attempt + 1} of {self.retries})")
        if self.sequence is None:
            self.sequence, self.sequence_source = spec.sequence, final
        self.report(f"measurement {m}, scanner {s}: stack complete ({spec.sequence.n_frames} frames)")

    def _interrupted_check(self) -> None:
        if self.stop.is_set():
            n, total = len(self.complete), len(self.plan.planned)
            raise AcquisitionError(f"interrupted by {self.stop.reason}: {n} of {total} measurements complete, "
                                   "nothing half-written; rerun the same command to resume", EXIT_INTERRUPTED)
