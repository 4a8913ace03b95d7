"""Figures drawn with matplotlib (Agg, no display) as PNG bytes, and the residual
histograms that the bundle step writes into the run's ``figures/`` (thesis figures
6-10, 6-11). Imports nothing of fringecal, so the steps that draw depend on this alone."""

from __future__ import annotations

import io

import numpy as np

__all__ = ["figure", "png", "residual_histograms_png"]


def figure(width_in: float, height_in: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def residual_histograms_png(start: np.ndarray, after: np.ndarray, bins: int = 100) -> tuple[bytes, bytes]:
    """Histograms of epsilon-1 and epsilon-2 (thesis figures 6-10, 6-11): the residuals
    (n, 2) at the start values and after the adjustment side by side; the PNG of each term."""
    out = []
    for k, label in enumerate(("epsilon-1", "epsilon-2")):
        fig = figure(9, 3.6)
        fig.set_dpi(110)
        for j, (res, title) in enumerate(((start[:, k], "(a) start values"), (after[:, k], "(b) refined parameters"))):
            ax = fig.add_subplot(1, 2, j + 1)
            kept = res[np.isfinite(res)]
            ax.hist(kept, bins=bins, color="tab:blue" if j else "tab:gray")
            ax.set_title(f"{title}: RMS {1000 * float(np.sqrt(np.mean(np.square(kept)))):.1f} um", fontsize=9)
            ax.set_xlabel(f"{label} (mm)")
            ax.set_ylabel("control points")
        fig.suptitle(f"{label} over {len(res)} control points, {bins} bins", fontsize=10)
        fig.tight_layout()
        out.append(png(fig))
    return out[0], out[1]
