"""The projected fringe sequence: the contract between acquisition and decoding.

For orientation ``x`` (vertical fringes), fringe count ``t`` and phase step
``k = 0..N-1`` the projector shows

    I = A + B cos(t * w_x + 2 pi k / N),   w_x = 2 pi xi_p / N_x,p

where ``xi_p`` is the projector image-plane coordinate of eq. 2-22 (zero at the
projector centre, +-pi at its edges), so the temporal phase gradient d(phase)/dt is
``w_x = tau_x``. Orientation ``y`` (horizontal fringes) uses ``eta_p`` and ``tau_y``.

Frames are acquired orientation by orientation, then fringe count by fringe count
(in the order given), then step by step; on disk each is
``{orientation}_{fringes:03d}_{step:02d}.png`` (or ``.tif``).

The fringe counts must follow a reverse-exponential schedule (thesis section 6.8):
``s, s-1, s-2, s-4, ..., s-2^(m-2)`` for some ``s`` and ``m >= 2`` counts, all positive;
the thesis uses s = 64, m = 7: (64, 63, 62, 60, 56, 48, 32).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from fringecal.config import StrictModel

__all__ = ["FringeSequence", "SequenceConfig", "reverse_exponential_counts", "SequenceError"]


class SequenceError(ValueError):
    """A fringe sequence that breaks the contract."""


def reverse_exponential_counts(s: int, m: int) -> tuple[int, ...]:
    """``(s, s-1, s-2, s-4, ..., s-2^(m-2))``.

    >>> reverse_exponential_counts(64, 7)
    (64, 63, 62, 60, 56, 48, 32)
    """
    if m < 2:
        raise SequenceError("a reverse-exponential schedule needs at least two fringe counts")
    counts = (s,) + tuple(s - 2**i for i in range(m - 1))
    if counts[-1] < 1:
        raise SequenceError(f"s = {s} is too small for {m} fringe counts (last would be {counts[-1]})")
    return counts


@dataclass(frozen=True)
class FringeSequence:
    """Orientations, fringe counts and phase steps of one measurement.

    Examples
    --------
    >>> seq = FringeSequence()
    >>> seq.n_frames, seq.frame_name("y", 48, 3)
    (98, 'y_048_03.png')
    >>> seq.frames()[7]
    ('x', 63, 0)
    """

    fringe_counts: tuple[int, ...] = (64, 63, 62, 60, 56, 48, 32)
    n_steps: int = 7
    orientations: tuple[str, ...] = ("x", "y")

    def __post_init__(self):
        counts = tuple(int(t) for t in self.fringe_counts)
        object.__setattr__(self, "fringe_counts", counts)
        object.__setattr__(self, "orientations", tuple(self.orientations))
        if self.n_steps < 3:
            raise SequenceError(f"phase stepping needs at least 3 steps, got {self.n_steps}")
        if not self.orientations or any(o not in ("x", "y") for o in self.orientations) \
                or len(set(self.orientations)) != len(self.orientations):
            raise SequenceError(f"orientations must be distinct values of 'x', 'y'; got {self.orientations}")
        expected = reverse_exponential_counts(counts[0], len(counts)) if len(counts) >= 2 else None
        if expected != counts:
            raise SequenceError(
                f"fringe counts {counts} are not a reverse-exponential schedule "
                f"(for s = {counts[0]} and {len(counts)} counts expect {expected})"
            )

    @property
    def s(self) -> int:
        """The highest fringe count."""
        return self.fringe_counts[0]

    @property
    def n_frames(self) -> int:
        return len(self.orientations) * len(self.fringe_counts) * self.n_steps

    def frames(self) -> list[tuple[str, int, int]]:
        """(orientation, fringe count, step) of every frame in acquisition order."""
        return [(o, t, k) for o in self.orientations for t in self.fringe_counts for k in range(self.n_steps)]

    @staticmethod
    def frame_name(orientation: str, fringes: int, step: int, ext: str = "png") -> str:
        return f"{orientation}_{fringes:03d}_{step:02d}.{ext}"

    def step_phases(self) -> np.ndarray:
        """Phase shifts 2 pi k / N, shape (N,)."""
        return 2 * np.pi * np.arange(self.n_steps) / self.n_steps

    def pattern(self, w, fringes: int, step: int, A: float = 0.5, B: float = 0.5) -> np.ndarray:
        """Projected intensity at projector phase coordinate(s) ``w`` (rad, in [-pi, pi])."""
        return A + B * np.cos(fringes * np.asarray(w, float) + 2 * np.pi * step / self.n_steps)

    def to_dict(self) -> dict:
        return {"fringe_counts": list(self.fringe_counts), "n_steps": self.n_steps,
                "orientations": list(self.orientations)}

    @classmethod
    def from_dict(cls, d: dict) -> "FringeSequence":
        """Inverse of :meth:`to_dict`.

        >>> FringeSequence.from_dict(FringeSequence().to_dict()) == FringeSequence()
        True
        """
        return cls(fringe_counts=tuple(d["fringe_counts"]), n_steps=int(d["n_steps"]),
                   orientations=tuple(d["orientations"]))

    def frame_index(self, orientation: str, fringes: int, step: int) -> int:
        """Position of a frame in :meth:`frames` order.

        >>> FringeSequence().frame_index("y", 63, 2)
        58
        """
        o = self.orientations.index(orientation)
        t = self.fringe_counts.index(fringes)
        if not 0 <= step < self.n_steps:
            raise SequenceError(f"step {step} outside 0..{self.n_steps - 1}")
        return (o * len(self.fringe_counts) + t) * self.n_steps + step


class SequenceConfig(StrictModel):
    """The projected fringe sequence (thesis: 7 counts x 7 steps x 2 orientations)."""

    fringe_counts: list[int] = Field(default_factory=lambda: [64, 63, 62, 60, 56, 48, 32])
    n_steps: int = 7
    orientations: list[str] = Field(default_factory=lambda: ["x", "y"])

    def build(self) -> FringeSequence:
        return FringeSequence(tuple(self.fringe_counts), self.n_steps, tuple(self.orientations))
