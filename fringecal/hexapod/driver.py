"""Safe driver for the hexapod control box over pyserial (protocol in :mod:`.protocol`).

Safety rules, in order:

1. Every target is checked before anything is sent: each leg's counts within
   ``0..stroke x counts/mm``, the target pose (forward kinematics of the target leg
   lengths) inside the workspace, and ``serial.path_checks`` intermediate poses along
   the move inside it too. A refused target raises :class:`TargetRejected` and sends
   nothing.
2. Any failure while talking to the box -- no reply within ``reply_timeout_s``, a
   garbled reply (framing, checksum, wrong echo), an ``ERR`` reply, a port error, no
   encoder progress for ``stall_polls`` polls, a move that outlasts its travel time
   plus ``move_timeout_margin_s``, or encoders that end more than
   ``position_tolerance_counts`` from the target -- sends ``STOP`` (best effort, once)
   and raises one :class:`HexapodFault`. The driver is then latched: every later call
   raises without sending anything. Open a new driver once the cause is fixed.

Command files (section 4.5.1) hold one protocol command per line (no checksums
needed; ``#`` starts a comment). :meth:`HexapodDriver.run_command_file` checks the
whole file -- syntax, ranges and the workspace of every pose it passes through --
before it sends the first line, then runs it line by line, waiting for every move.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import serial

from fringecal.atomic import write_text
from fringecal.hexapod.config import HexapodConfig
from fringecal.hexapod.kinematics import ForwardKinematicsError, forward_kinematics, inverse_kinematics
from fringecal.hexapod.planning import counts_from_lengths, lengths_from_counts
from fringecal.hexapod.protocol import (
    Command,
    ProtocolError,
    Reply,
    format_command,
    frame,
    parse_command,
    parse_reply,
    unframe,
)
from fringecal.hexapod.workspace import check_poses, describe_violations

__all__ = ["HexapodDriver", "HexapodFault", "TargetRejected", "read_command_file", "write_command_file"]


class HexapodFault(RuntimeError):
    """Communication or motion fault; motion was stopped. ``kind`` names the fault:
    unplugged, io, timeout, garbled, error-reply, stall, move-timeout, mismatch, latched."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


class TargetRejected(ValueError):
    """A target refused before anything was sent (stroke or workspace)."""


def read_command_file(path) -> list[tuple[int, Command]]:
    """Parse a command file into (line number, Command); raises ValueError naming file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: command file not found") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not an ASCII command file") from None
    out = []
    for n, raw in enumerate(text.splitlines(), start=1):
        body = raw.split("#", 1)[0].strip()
        if not body:
            continue
        if "*" in body:
            try:
                body = unframe((body + "\n").encode("ascii"))
            except ProtocolError as err:
                raise ValueError(f"{path}, line {n}: {err}") from None
        try:
            out.append((n, parse_command(body)))
        except ProtocolError as err:
            raise ValueError(f"{path}, line {n}: {err}") from None
    return out


def write_command_file(path, counts_rows, comments=None) -> Path:
    """Write one ``MOVEALL`` line per row of counts (N, 6), atomically; optional comment per row."""
    path = Path(path)
    lines = ["# fringecal hexapod command file: one protocol command per line (section 4.5.1)"]
    for i, row in enumerate(np.asarray(counts_rows, np.int64).reshape(-1, 6)):
        if comments is not None:
            lines.append(f"# {comments[i]}")
        lines.append(format_command("MOVEALL", *row))
    return write_text(path, "\n".join(lines) + "\n")


class HexapodDriver:
    """Talks to one control box. Use :meth:`open` with a port name or URL
    (``/dev/ttyACM0``, ``hexsim://bench``) or wrap an open pyserial port.

    ``sent`` lists every line sent (without checksums), in order.
    """

    def __init__(self, port, config: HexapodConfig):
        self.port = port
        self.config = config
        self.sent: list[str] = []
        self._fault: HexapodFault | None = None
        self._pose = config.home_pose.vector.copy()
        # A simulated port brings its own time source, so simulated waits cost no wall time.
        self._clock = getattr(port, "clock", time.monotonic)
        self._sleep = getattr(port, "sleep", time.sleep)

    @classmethod
    def open(cls, url: str, config: HexapodConfig) -> "HexapodDriver":
        """Open ``url`` and check the box identifies with the configured count range."""
        try:
            port = serial.serial_for_url(url, baudrate=config.serial.baudrate,
                                         timeout=config.serial.reply_timeout_s,
                                         write_timeout=config.serial.reply_timeout_s)
        except (serial.SerialException, ValueError, OSError) as err:
            raise HexapodFault("unplugged", f"cannot open the hexapod controller at {url}: {err}") from None
        drv = cls(port, config)
        try:
            drv.identify()
        except BaseException:
            port.close()
            raise
        return drv

    def close(self):
        self.port.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- low level ------------------------------------------------------------
    @property
    def pose(self) -> np.ndarray:
        """Platform pose (6,) from the last encoder reading (forward kinematics)."""
        return self._pose.copy()

    @property
    def faulted(self) -> HexapodFault | None:
        return self._fault

    def _fail(self, kind: str, message: str):
        """Stop all motion (once, best effort), latch the fault and raise it."""
        try:
            self.port.reset_input_buffer()
            self.sent.append("STOP")
            self.port.write(frame("STOP"))
            self.port.flush()
            self.port.read_until(b"\n")
        except Exception:  # noqa: BLE001 - the port may be the very thing that failed
            pass
        self._fault = HexapodFault(kind, f"hexapod stopped: {message}")
        raise self._fault from None

    def _transact(self, body: str) -> Reply:
        if self._fault is not None:
            raise HexapodFault("latched", f"refusing {body!r}: the driver faulted earlier ({self._fault})")
        keyword = body.split()[0]
        try:
            self.port.reset_input_buffer()
            self.sent.append(body)
            self.port.write(frame(body))
            self.port.flush()
            line = self.port.read_until(b"\n")
        except serial.SerialException as err:
            self._fail("io", f"serial port error during {body!r}: {err}")
        if not line:
            self._fail("timeout", f"no reply to {body!r} within {self.config.serial.reply_timeout_s:g} s")
        try:
            reply = parse_reply(unframe(line))
        except ProtocolError as err:
            kind = "timeout" if not line.endswith(b"\n") else "garbled"
            self._fail(kind, f"bad reply to {body!r}: {err}")
        if not reply.ok:
            self._fail("error-reply", f"the box refused {body!r}: ERR {reply.code} {reply.text}")
        if reply.keyword != keyword.rstrip("?") and reply.keyword != keyword:
            self._fail("garbled", f"reply {str(reply)!r} does not answer {body!r}")
        return reply

    # -- queries --------------------------------------------------------------
    def identify(self) -> str:
        """``ID?``; checks the box's count range matches the config."""
        reply = self._transact("ID?")
        expected = self.config.actuator.max_counts
        try:
            box_max = int(reply.fields[-1])
        except (IndexError, ValueError):
            self._fail("garbled", f"malformed ID reply {str(reply)!r}")
        if box_max != expected:
            self._fail("error-reply", f"the box's count range 0..{box_max} differs from the config's "
                       f"0..{expected} (stroke x counts per mm); check counts_per_mm")
        return " ".join(reply.fields)

    def positions(self) -> tuple[np.ndarray, bool]:
        """(encoder counts (6,) int, busy) from ``POS?``."""
        reply = self._transact("POS?")
        f = reply.fields
        if len(f) != 7 or f[6] not in ("IDLE", "BUSY"):
            self._fail("garbled", f"malformed POS reply {str(reply)!r}")
        try:
            counts = np.array([int(x) for x in f[:6]], np.int64)
        except ValueError:
            self._fail("garbled", f"malformed POS reply {str(reply)!r}")
        return counts, f[6] == "BUSY"

    def current_pose(self) -> np.ndarray:
        """Platform pose (6,) from the encoders by forward kinematics."""
        counts, _ = self.positions()
        return self._pose_of(counts)

    def _pose_of(self, counts) -> np.ndarray:
        fk = forward_kinematics(self.config.platform, lengths_from_counts(self.config, counts), self._pose)
        self._pose = fk.poses
        return fk.poses

    def _idle_positions(self) -> np.ndarray:
        """Encoder counts of a box at rest, with the pose they give (the start of every check)."""
        counts, busy = self.positions()
        if busy:
            self._fail("error-reply", "the box reports a move already running")
        try:
            self._pose_of(counts)
        except ForwardKinematicsError as err:
            self._fail("mismatch", f"encoder readings {counts.tolist()} give no platform pose: {err}")
        return counts

    # -- checks ---------------------------------------------------------------
    def check_target(self, target_counts, from_counts) -> np.ndarray:
        """Refuse (TargetRejected) a target outside the stroke or a move leaving the workspace.

        Returns the target pose (6,). Nothing is sent.
        """
        target = np.asarray(target_counts, np.int64).reshape(6)
        max_c = self.config.actuator.max_counts
        bad = [f"leg {i + 1}: {c} counts" for i, c in enumerate(target) if not 0 <= c <= max_c]
        if bad:
            raise TargetRejected(f"target outside the stroke 0..{max_c} counts "
                                 f"(0..{self.config.actuator.stroke_mm:g} mm): {', '.join(bad)}")
        start_len = lengths_from_counts(self.config, from_counts)
        end_len = lengths_from_counts(self.config, target)
        n = self.config.serial.path_checks
        pose = self._pose
        for k, f in enumerate(np.linspace(0.0, 1.0, n + 1)[1:], start=1):
            try:
                pose = forward_kinematics(self.config.platform, start_len + f * (end_len - start_len), pose).poses
            except ForwardKinematicsError as err:
                raise TargetRejected(f"no platform pose for the leg lengths {k}/{n} of the way: {err}") from None
            check = check_poses(self.config, pose)
            if not check.ok:
                where = "the target pose" if k == n else f"the pose {k}/{n} of the way to the target"
                raise TargetRejected(f"{where} leaves the workspace: "
                                     + "; ".join(describe_violations(self.config, check)))
        return pose

    # -- motion ---------------------------------------------------------------
    def move_counts(self, target_counts) -> np.ndarray:
        """Move all legs together to ``target_counts`` (6,) and verify the encoders.

        Returns the encoder counts read after the move.
        """
        if self._fault is not None:
            raise HexapodFault("latched", f"refusing to move: the driver faulted earlier ({self._fault})")
        target = np.asarray(target_counts, np.int64).reshape(6)
        start = self._idle_positions()
        self.check_target(target, start)
        self._transact(format_command("MOVEALL", *target))
        return self._wait_and_verify(target, start)

    def move_leg(self, leg: int, counts: int) -> np.ndarray:
        """Move one leg (1..6); the whole resulting pose is checked first."""
        if not 1 <= leg <= 6:
            raise TargetRejected(f"leg must be 1..6, got {leg}")
        start = self._idle_positions()
        target = start.copy()
        target[leg - 1] = counts
        self.check_target(target, start)
        self._transact(format_command("MOVE", leg, counts))
        return self._wait_and_verify(target, start)

    def move_pose(self, pose) -> np.ndarray:
        """Move the platform to ``pose`` (6,) (mm, rad); returns the encoder counts read."""
        pose = np.asarray(pose, float).reshape(6)
        check = check_poses(self.config, pose)
        if not check.ok:
            raise TargetRejected("pose outside the workspace: " + "; ".join(describe_violations(self.config, check)))
        return self.move_counts(counts_from_lengths(self.config, inverse_kinematics(self.config.platform, pose)))

    def stop(self) -> None:
        self._transact("STOP")

    def home(self) -> np.ndarray:
        """Reference run (``HOME``): all legs to stroke zero, encoders zeroed; path checked first."""
        start = self._idle_positions()
        target = np.zeros(6, np.int64)
        self.check_target(target, start)
        self._transact("HOME")
        return self._wait_and_verify(target, start)

    def _wait_and_verify(self, target, start) -> np.ndarray:
        s = self.config.serial
        travel_mm = float(np.max(np.abs(target - start))) / self.config.actuator.counts_per_mm
        deadline = self._clock() + travel_mm / self.config.actuator.speed_mm_s + s.move_timeout_margin_s
        last, still = None, 0
        while True:
            counts, busy = self.positions()
            if not busy:
                break
            still = still + 1 if last is not None and np.array_equal(counts, last) else 0
            if still >= s.stall_polls:
                self._fail("stall", f"no encoder progress for {still} polls while moving to {target.tolist()}; "
                           f"encoders at {counts.tolist()}")
            if self._clock() > deadline:
                self._fail("move-timeout", f"move to {target.tolist()} not finished after "
                           f"{travel_mm / self.config.actuator.speed_mm_s + s.move_timeout_margin_s:.1f} s; "
                           f"encoders at {counts.tolist()}")
            last = counts
            self._sleep(s.poll_interval_s)
        off = counts - target
        tol = self.config.actuator.position_tolerance_counts
        if np.any(np.abs(off) > tol):
            legs = ", ".join(f"leg {i + 1} {int(off[i]):+d}" for i in np.flatnonzero(np.abs(off) > tol))
            self._fail("mismatch", f"encoders disagree with the target beyond {tol} counts ({legs}); "
                       f"target {target.tolist()}, read {counts.tolist()}")
        try:
            self._pose_of(counts)
        except ForwardKinematicsError as err:
            self._fail("mismatch", f"encoder readings give no platform pose: {err}")
        return counts

    # -- command files ----------------------------------------------------------
    def run_command_file(self, path) -> list[np.ndarray]:
        """Check a whole command file, then run it; returns the encoder counts after each move."""
        commands = read_command_file(path)
        start = self._idle_positions()
        state, saved_pose = start.copy(), self._pose.copy()
        try:
            for n, cmd in commands:
                if not cmd.is_motion:
                    continue
                target = (np.zeros(6, np.int64) if cmd.keyword == "HOME" else
                          np.array(cmd.args, np.int64) if cmd.keyword == "MOVEALL" else
                          np.where(np.arange(6) == cmd.args[0] - 1, cmd.args[1], state))
                try:
                    self._pose = self.check_target(target, state)
                except TargetRejected as err:
                    raise TargetRejected(f"{path}, line {n} ({cmd}): {err}") from None
                state = target
        finally:
            self._pose = saved_pose
        results = []
        for _, cmd in commands:
            if cmd.keyword == "MOVEALL":
                results.append(self.move_counts(cmd.args))
            elif cmd.keyword == "MOVE":
                results.append(self.move_leg(*cmd.args))
            elif cmd.keyword == "HOME":
                results.append(self.home())
            elif cmd.keyword == "STOP":
                self.stop()
            elif cmd.keyword == "POS?":
                self.positions()
            else:
                self.identify()
        return results
