"""The report's plots, drawn with matplotlib (Agg, no display) and embedded as PNG.

The residual histograms are the run's own ``figures/*.png``
(:mod:`fringecal.report.plotting`); drawn here are the ball-bar errors per position, the
acceptance test's positions in the world frame, each scanner's residual and coverage
maps over its images, the regions of its image planes the calibration observed and its
measuring-uncertainty maps.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass

import numpy as np

from fringecal.report.formatting import finite
from fringecal.report.plotting import figure as _figure
from fringecal.report.plotting import png as _png

__all__ = ["TEST_COLOURS", "Image", "acceptance_png", "ballbar_png", "residual_maps_png", "uncertainty_maps_png",
           "binned_grid", "observed_regions_png"]

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


#: The panels of a residual map: column of the binned table, title, colour map, symmetric about 0.
RESIDUAL_PANELS = (("n_points", "control points per cell", "viridis", False),
                   ("mean_eps1_mm", "mean ε1 (µm)", "RdBu_r", True),
                   ("mean_eps2_mm", "mean ε2 (µm)", "RdBu_r", True),
                   ("rms_eps2_mm", "RMS ε2 (µm)", "magma", False))


def _locator(n: int):
    from matplotlib.ticker import MaxNLocator

    return MaxNLocator(n)


def _few_ticks(ax, fmt) -> None:
    """Ticks at the first, middle and last pixel of an image axis (drawing many ticks is
    most of a small panel's cost)."""
    ax.set_xticks([0, (fmt.width_px - 1) // 2, fmt.width_px - 1])
    ax.set_yticks([0, (fmt.height_px - 1) // 2, fmt.height_px - 1])
    ax.tick_params(labelsize=6)


def binned_grid(rows, column: str) -> np.ndarray:
    """The values of ``column`` of one sensor's binned residuals (rows with ``nx``,
    ``ny``, ``ix``, ``iy``) as an (ny, nx) grid, NaN where a cell holds no point.

    >>> import pandas as pd
    >>> g = binned_grid(pd.DataFrame({"nx": [2, 2], "ny": [1, 1], "ix": [1, 0], "iy": [0, 0], "v": [5.0, 3.0]}), "v")
    >>> g.tolist()
    [[3.0, 5.0]]
    """
    nx, ny = int(rows["nx"].iloc[0]), int(rows["ny"].iloc[0])
    grid = np.full((ny, nx), np.nan)
    grid[rows["iy"].to_numpy(int), rows["ix"].to_numpy(int)] = rows[column].to_numpy(float)
    return grid


def residual_maps_png(bins, formats: dict) -> bytes:
    """One scanner's residuals over its images: a row per sensor (camera, then
    projector) of :data:`RESIDUAL_PANELS` drawn over the sensor's pixels.

    Parameters
    ----------
    bins : the scanner's rows of the binned residuals (:class:`~fringecal.schemas.BinnedResidualsTable`)
    formats : sensor name -> its :class:`~fringecal.sensor.SensorFormat`

    Returns
    -------
    The PNG's bytes.
    """
    sensors = [(name, g) for role in ("camera", "projector")
               for name, g in bins[bins["role"] == role].groupby("sensor", sort=False)]
    fig = _figure(10, 2.55 * len(sensors) + 0.3)
    for i, (name, g) in enumerate(sensors):
        fmt = formats[name]
        for j, (column, title, cmap, symmetric) in enumerate(RESIDUAL_PANELS):
            ax = fig.add_subplot(len(sensors), len(RESIDUAL_PANELS), i * len(RESIDUAL_PANELS) + j + 1)
            grid = binned_grid(g, column) * (1.0 if column == "n_points" else 1000.0)
            vmax = float(np.nanmax(np.abs(grid))) if np.isfinite(grid).any() else 1.0
            image = ax.imshow(grid, cmap=cmap, origin="upper", interpolation="nearest",
                              extent=(-0.5, fmt.width_px - 0.5, fmt.height_px - 0.5, -0.5),
                              vmin=-vmax if symmetric else (0 if column == "n_points" else None),
                              vmax=vmax if symmetric else None)
            ax.set_title(f"{name} ({g['role'].iloc[0]}): {title}", fontsize=7)
            _few_ticks(ax, fmt)
            if j == 0:
                ax.set_ylabel("row (px)", fontsize=7)
            if i == len(sensors) - 1:
                ax.set_xlabel("column (px)", fontsize=7)
            bar = fig.colorbar(image, ax=ax, fraction=0.046, pad=0.03)
            bar.ax.tick_params(labelsize=6)
            bar.locator = _locator(4)
            bar.update_ticks()
    fig.subplots_adjust(left=0.06, right=0.97, bottom=0.1, top=0.93, wspace=0.45, hspace=0.35)
    return _png(fig)


def uncertainty_maps_png(maps: list, fmt) -> bytes:
    """The calibration's uncertainty of a measured point over the camera image at a
    few depths (:class:`~fringecal.calibration.propagation.DepthUncertainty` each), on
    one colour scale (µm).

    Returns
    -------
    The PNG's bytes.
    """
    fig = _figure(10, 3.2)
    values = [m.u_mm[np.isfinite(m.u_mm)] for m in maps]
    top = max((float(v.max()) for v in values if v.size), default=1.0) * 1000
    image = None
    for k, m in enumerate(maps):
        ax = fig.add_subplot(1, len(maps), k + 1)
        image = ax.imshow(m.u_mm * 1000, cmap="viridis", origin="upper", interpolation="nearest", vmin=0, vmax=top,
                          extent=(-0.5, fmt.width_px - 0.5, fmt.height_px - 0.5, -0.5))
        ax.set_title(f"depth {m.depth_mm:.0f} mm", fontsize=8)
        ax.set_xlabel("camera column (px)", fontsize=7)
        if k == 0:
            ax.set_ylabel("camera row (px)", fontsize=7)
        _few_ticks(ax, fmt)
    if image is not None:
        bar = fig.colorbar(image, ax=fig.axes, fraction=0.02, pad=0.02)
        bar.set_label("u of a measured point (µm, k = 1)", fontsize=7)
        bar.ax.tick_params(labelsize=6)
    return _png(fig)


def observed_regions_png(regions: list) -> bytes:
    """The observed region of each sensor of a scanner, side by side: over the image plane
    (mm from the format's centre, rows down as the camera's) the cells holding control
    points (grey) and the hull of them (the region, outlined), its share of the format in
    the title.

    Parameters
    ----------
    regions : (sensor name, role, :class:`~fringecal.lens.observed_region.ObservedRegion`) per sensor

    Returns
    -------
    The PNG's bytes.
    """
    fig = _figure(3.4 * len(regions) + 0.4, 2.9)
    for k, (name, role, region) in enumerate(regions):
        ax = fig.add_subplot(1, len(regions), k + 1)
        w, h = region.width_mm, region.height_mm
        ax.imshow(region.observed.astype(float), cmap="Greys", vmin=0, vmax=1.6, origin="upper",
                  interpolation="nearest", extent=(-w / 2, w / 2, h / 2, -h / 2))
        ny, nx = region.shape
        ax.set_xticks(np.linspace(-w / 2, w / 2, nx + 1), minor=True)
        ax.set_yticks(np.linspace(-h / 2, h / 2, ny + 1), minor=True)
        ax.grid(which="minor", color="0.75", lw=0.3)
        ax.tick_params(which="minor", length=0)
        ax.tick_params(labelsize=6)
        if len(region.hull):
            ring = np.vstack([region.hull, region.hull[:1]])
            ax.plot(ring[:, 0], ring[:, 1], color="C3", lw=1.2)
        ax.set_title(f"{name} ({role}): {100 * region.fraction:.0f} % observed", fontsize=8)
        ax.set_xlabel("image plane x (mm)", fontsize=7)
        if k == 0:
            ax.set_ylabel("image plane y (mm)", fontsize=7)
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.16, top=0.88, wspace=0.3)
    return _png(fig)
