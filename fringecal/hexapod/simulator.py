"""A simulated hexapod control box, reachable as the pyserial URL ``hexsim://``.

It speaks the protocol of :mod:`fringecal.hexapod.protocol` like the real box: legs
move at a finite speed (a ``MOVEALL`` brings all legs in together, the slowest at full
speed), encoders count in driving counts, bad commands and out-of-range targets get
``ERR`` replies, and faults can be injected. Every line received is kept in
``controller.log`` (time, text), so tests can assert on what was sent.

URL: ``hexsim://[name][?option=value&...]``. A named box persists for the life of the
process (reopening ``hexsim://bench`` finds the same box, with its leg positions and
log; options given on a reopen change it); without a name every open makes a new box,
reachable as ``port.controller``. Options:

``config``         hexapod YAML giving counts per mm, stroke, speed and home pose
                   (default: configs/hexapod/thesis_platform.yaml)
``speed_mm_s``, ``counts_per_mm``, ``max_counts``   override the config's values
``start``          ``home`` (default: legs at the home pose), ``zero``, or six counts ``c1,...,c6``
``clock``          ``virtual`` (default): time passes only when the driver waits
                   (``port.sleep``), so a simulated move costs no wall time; ``real``:
                   wall time multiplied by ``time_scale``
``fault``          ``unplugged`` (open fails), ``disconnect`` (the port dies),
                   ``timeout`` (no more replies), ``garbled`` (replies corrupted),
                   ``stall`` (leg ``leg`` stops moving, box stays BUSY),
                   ``mismatch`` (leg ``leg`` ends ``offset`` counts off target, box says IDLE)
``after``          commands handled normally before the fault strikes (default 0)
``leg``, ``offset``  for stall and mismatch (defaults 1 and 40)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from urllib.parse import parse_qs, urlsplit

import numpy as np

from fringecal.hexapod.config import load_hexapod_config
from fringecal.hexapod.kinematics import inverse_kinematics
from fringecal.hexapod.protocol import ERROR_CODES, ProtocolError, frame, parse_command, unframe

__all__ = ["SimulatedController", "get_controller", "controller_for_url", "forget_controllers", "FAULTS"]

FAULTS = ("unplugged", "disconnect", "timeout", "garbled", "stall", "mismatch")
_REGISTRY: dict[str, "SimulatedController"] = {}


@dataclass
class SimulatedController:
    """The box: six legs with encoders, a motion model, a command log and fault injection."""

    counts_per_mm: float
    max_counts: int
    speed_mm_s: float
    start_counts: np.ndarray
    name: str = "HEXSIM"
    clock: str = "virtual"
    time_scale: float = 1.0
    fault: str | None = None
    fault_after: int = 0
    fault_leg: int = 1
    fault_offset: int = 40
    log: list[tuple[float, str]] = field(default_factory=list)

    def __post_init__(self):
        self._start = np.asarray(self.start_counts, float).copy()
        self._target = self._start.copy()
        self._t0 = 0.0
        self._duration = 0.0
        self._stalled_leg: int | None = None
        self._virtual_now = 0.0
        self._real_t0 = time.monotonic()
        self.n_received = 0

    # -- time -----------------------------------------------------------------
    def now(self) -> float:
        if self.clock == "real":
            return (time.monotonic() - self._real_t0) * self.time_scale
        return self._virtual_now

    def sleep(self, seconds: float) -> None:
        if self.clock == "real":
            time.sleep(max(seconds, 0.0) / self.time_scale)
        else:
            self._virtual_now += max(seconds, 0.0)

    # -- motion ---------------------------------------------------------------
    def positions(self) -> np.ndarray:
        """Leg positions in counts (float) at the current time, shape (6,)."""
        if self._duration <= 0:
            frac = 1.0
        else:
            frac = min(1.0, (self.now() - self._t0) / self._duration)
        pos = self._start + (self._target - self._start) * frac
        if self._stalled_leg is not None:
            pos[self._stalled_leg] = self._start[self._stalled_leg]
        return pos

    @property
    def busy(self) -> bool:
        if self._stalled_leg is not None:
            return True
        return self.now() < self._t0 + self._duration

    def _begin(self, target):
        self._start = self.positions()
        self._target = np.asarray(target, float)
        self._t0 = self.now()
        travel_mm = np.max(np.abs(self._target - self._start)) / self.counts_per_mm
        self._duration = travel_mm / self.speed_mm_s
        self._stalled_leg = None
        if self._fault_active("stall"):
            self._stalled_leg = self.fault_leg - 1
        elif self._fault_active("mismatch"):
            self._target[self.fault_leg - 1] += self.fault_offset

    def _halt(self):
        pos = self.positions()
        self._start, self._target, self._duration, self._stalled_leg = pos, pos.copy(), 0.0, None

    def encoder_counts(self) -> np.ndarray:
        return np.rint(self.positions()).astype(np.int64)

    # -- commands -------------------------------------------------------------
    def _fault_active(self, kind: str) -> bool:
        return self.fault == kind and self.n_received > self.fault_after

    def motion_log(self) -> list[str]:
        """Lines received that make legs move (MOVE, MOVEALL, HOME), checksums removed."""
        out = []
        for _, text in self.log:
            body = text.rpartition("*")[0] if "*" in text else text
            if body.split()[:1] and body.split()[0].upper() in ("MOVE", "MOVEALL", "HOME"):
                out.append(body)
        return out

    def handle(self, line: bytes) -> bytes | None:
        """Process one received line; return the reply bytes (None when silent)."""
        self.n_received += 1
        self.log.append((self.now(), line.decode("ascii", "replace").rstrip("\r\n")))
        if self._fault_active("timeout"):
            return None
        body = self._respond(line)
        out = frame(body)
        if self._fault_active("garbled"):
            out = _garble(out)
        return out

    def _respond(self, line: bytes) -> str:
        try:
            cmd = parse_command(unframe(line, require_checksum=False))
        except ProtocolError as err:
            return f"ERR {err.code} {err}"
        kw, args = cmd.keyword, cmd.args
        if kw == "ID?":
            return f"OK ID {self.name} 1.0 {self.max_counts}"
        if kw == "POS?":
            counts = " ".join(str(c) for c in self.encoder_counts())
            return f"OK POS {counts} {'BUSY' if self.busy else 'IDLE'}"
        if kw == "STOP":
            self._halt()
            return "OK STOP"
        if self.busy:
            return f"ERR 4 {ERROR_CODES[4]}: a move is running, send STOP first"
        if kw == "HOME":
            self._begin(np.zeros(6))
            return "OK HOME"
        if kw == "MOVE":
            leg, target = args
            if not 0 <= target <= self.max_counts:
                return f"ERR 3 leg {leg} target {target} outside 0..{self.max_counts}"
            new = self.positions()
            new[leg - 1] = target
            self._begin(new)
            return f"OK MOVE {leg} {target}"
        # MOVEALL
        bad = [f"leg {i + 1} target {c}" for i, c in enumerate(args) if not 0 <= c <= self.max_counts]
        if bad:
            return f"ERR 3 {', '.join(bad)} outside 0..{self.max_counts}"
        self._begin(args)
        return "OK MOVEALL " + " ".join(str(a) for a in args)


def _garble(line: bytes) -> bytes:
    """Corrupt one character of the body (line noise); the checksum no longer matches."""
    b = bytearray(line)
    i = max(0, len(b) // 2 - 1)
    b[i] = ord("#") if b[i] != ord("#") else ord("?")
    return bytes(b)


def get_controller(name: str) -> SimulatedController:
    """The named simulated box (created by opening ``hexsim://<name>``)."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"no simulated hexapod box named {name!r} has been opened") from None


def forget_controllers() -> None:
    """Drop every named simulated box."""
    _REGISTRY.clear()


_OPTIONS = ("config", "speed_mm_s", "counts_per_mm", "max_counts", "start", "clock", "time_scale",
            "fault", "after", "leg", "offset")


def controller_for_url(url: str) -> SimulatedController:
    """Create (or find, for a named box) the controller a ``hexsim://`` URL refers to.

    Raises ValueError naming a bad option or value.
    """
    parts = urlsplit(url)
    if parts.scheme.lower() != "hexsim":
        raise ValueError(f"{url!r} is not a hexsim:// URL")
    name = parts.netloc or parts.path.strip("/")
    raw = parse_qs(parts.query, keep_blank_values=True)
    unknown = sorted(set(raw) - set(_OPTIONS))
    if unknown:
        raise ValueError(f"{url}: unknown option(s) {unknown}; known: {list(_OPTIONS)}")
    opts = {k: v[-1] for k, v in raw.items()}
    try:
        return _configure(name, opts)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{url}: {err}") from None


def _configure(name: str, opts: dict) -> SimulatedController:
    box = _REGISTRY.get(name) if name else None
    fault = opts.get("fault")
    if fault is not None and fault not in FAULTS + ("", "none"):
        raise ValueError(f"fault must be one of {list(FAULTS)}, got {fault!r}")
    if box is None:
        cfg = load_hexapod_config(opts.get("config"))
        act = cfg.actuator
        cpm = float(opts.get("counts_per_mm", act.counts_per_mm))
        max_counts = int(opts.get("max_counts", np.floor(act.stroke_mm * cpm + 1e-9)))
        start = opts.get("start", "home")
        if start == "home":
            stroke = inverse_kinematics(cfg.platform, cfg.home_pose.vector) - act.retracted_length_mm
            start_counts = np.rint(stroke * cpm)
        elif start == "zero":
            start_counts = np.zeros(6)
        else:
            start_counts = np.array([int(c) for c in start.split(",")], float)
            if start_counts.shape != (6,):
                raise ValueError("start needs six counts")
        box = SimulatedController(counts_per_mm=cpm, max_counts=max_counts,
                                  speed_mm_s=float(opts.get("speed_mm_s", act.speed_mm_s)),
                                  start_counts=start_counts, name=(name or "HEXSIM").upper())
        if name:
            _REGISTRY[name] = box
    elif "config" in opts or "start" in opts or "counts_per_mm" in opts or "max_counts" in opts:
        raise ValueError(f"box {name!r} exists already; config, start, counts_per_mm and max_counts "
                         "are fixed when it is first opened")
    if "speed_mm_s" in opts:
        box.speed_mm_s = float(opts["speed_mm_s"])
    if "clock" in opts:
        if opts["clock"] not in ("virtual", "real"):
            raise ValueError(f"clock must be virtual or real, got {opts['clock']!r}")
        box.clock = opts["clock"]
    if "time_scale" in opts:
        box.time_scale = float(opts["time_scale"])
        if box.time_scale <= 0:
            raise ValueError("time_scale must be positive")
    if fault is not None:
        box.fault = fault if fault not in ("", "none") else None
        box.fault_after = box.n_received + int(opts.get("after", 0))
    if "leg" in opts:
        box.fault_leg = int(opts["leg"])
        if not 1 <= box.fault_leg <= 6:
            raise ValueError("leg must be 1..6")
    if "offset" in opts:
        box.fault_offset = int(opts["offset"])
    return box
