"""The report's plots, drawn with matplotlib (Agg, no display) and embedded as PNG.

The residual histograms are the run's own ``figures/*.png``
(:mod:`fringecal.report.plotting`); drawn here are the ball-bar errors per position and
the acceptance test's positions in the world frame.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass

import numpy as np

from fringecal.report.formatting import finite
from fringecal.report.plotting import figure as _figure
from fringecal.report.plotting import png as _png

__all__ = ["TEST_COLOURS", "Image", "acceptance_png", "ballbar_png"]

#: Colour of each acceptance object (and of the ball-bar) in the positions figure.
TEST_COLOURS = {"sphere": "tab:blue", "dumbbell": "tab:orange", "flat": "tab:green", "ballbar": "tab:purple"}

#: The two views of the positions figure: title, (horizontal, vertical) world axis.
VIEWS = (("top view", (0, 2)), ("side view", (2, 1)))


@dataclass(frozen=True)
class Image:
    """A PNG embedded in the page, with its alternative text."""

    png: bytes
    alt: str

    @property
    def src(self) -> str:
        """The ``data:`` URI of the PNG."""
        return "data:image/png;base64," + base64.b64encode(self.png).decode("ascii")


def ballbar_png(cal: dict, true: dict | None) -> bytes:
    """The length error per ball-bar position, calibrated and (if known) with the true
    parameters side by side, with the ±MPE lines.

    Parameters
    ----------
    cal : the verification with the calibrated parameters (``positions``, ``mpe_mm``)
    true : the same with the true parameters, or None

    Returns
    -------
    The PNG's bytes.
    """
    pos = [str(p["measurement"]) for p in cal["positions"]]
    err = np.array([p["error_mm"] for p in cal["positions"]], float) * 1000
    fig = _figure(8.5, 3.4)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(pos))
    w = 0.38 if true else 0.6
    ax.bar(x - (w / 2 if true else 0), err, w, label="calibrated parameters", color="tab:blue")
    if true:
        by = {str(p["measurement"]): p["error_mm"] * 1000 for p in true["positions"]}
        ax.bar(x + w / 2, [by.get(p, np.nan) for p in pos], w, label="true parameters", color="tab:gray")
    if finite(cal.get("mpe_mm")):
        for s in (1, -1):
            ax.axhline(s * cal["mpe_mm"] * 1000, color="tab:red", ls="--", lw=1, label="± MPE" if s == 1 else None)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(x, pos)
    ax.set_xlabel("ball-bar position")
    ax.set_ylabel("length error (µm)")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)
    fig.tight_layout()
    return _png(fig)


def acceptance_png(shapes: list[dict], pinholes: list[tuple], bars: list[np.ndarray]) -> bytes:
    """The acceptance test's positions in two views of the world frame.

    Parameters
    ----------
    shapes : the positions as :func:`fringecal.report.sections.placements.placement` gives them
    pinholes : (scanner, camera pinhole, reference scanner) per scanner
    bars : the ball-bar positions, each as its two sphere centres (2, 3)

    Returns
    -------
    The PNG's bytes: spheres as circles, dumbbells as segments with their spheres,
    flats as outlines, coloured per test; the camera pinholes as triangles.
    """
    from matplotlib.lines import Line2D

    fig = _figure(10, 5.2)
    names = "xyz"
    for j, (title, (h, v)) in enumerate(VIEWS):
        ax = fig.add_subplot(1, 2, j + 1)
        for s in shapes:
            _draw_shape(ax, s, h, v)
        for pts in bars:
            ax.plot(pts[:, h], pts[:, v], "-o", color=TEST_COLOURS["ballbar"], lw=1, ms=3, alpha=0.6)
        for i, (name, p, _) in enumerate(pinholes):  # labels staggered: pinholes may coincide in a view
            ax.plot(p[h], p[v], "^", color="k", ms=8)
            ax.annotate(name, (p[h], p[v]), textcoords="offset points", xytext=(6, 6 - 11 * i), fontsize=8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(f"{title} (world {names[h]}-{names[v]})", fontsize=10)
        ax.set_xlabel(f"world {names[h]} (mm)")
        ax.set_ylabel(f"world {names[v]} (mm)")
        ax.grid(True, lw=0.3)
    tests = [t for t in TEST_COLOURS if any(s["test"] == t for s in shapes) or (t == "ballbar" and bars)]
    handles = [Line2D([], [], color=TEST_COLOURS[t], marker="o", label=t) for t in tests]
    if pinholes:
        handles.append(Line2D([], [], color="k", marker="^", ls="", label="camera pinhole"))
    fig.legend(handles=handles, fontsize=8, loc="lower center", ncol=len(handles), frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return _png(fig)


def _draw_shape(ax, shape: dict, h: int, v: int) -> None:
    """One position in the view of world axes ``h`` (horizontal) and ``v`` (vertical)."""
    from matplotlib.patches import Circle

    colour = TEST_COLOURS.get(shape["test"], "tab:gray")
    pts = shape["points"]
    if shape["radius"]:
        ax.add_patch(Circle((pts[0, h], pts[0, v]), shape["radius"], fill=False, color=colour, lw=1.2))
        ax.plot(pts[0, h], pts[0, v], "+", color=colour, ms=4)
    elif shape["test"] == "dumbbell" and len(pts) == 2:
        ax.plot(pts[:, h], pts[:, v], "-o", color=colour, lw=1.5, ms=4)
    elif len(pts) > 1:
        ax.plot(pts[:, h], pts[:, v], "-", color=colour, lw=1.2)
    else:
        ax.plot(pts[0, h], pts[0, v], "o", color=colour, ms=4)
