"""Matplotlib figures written as PNG: PSNR curves of one run or of a whole sweep."""

from __future__ import annotations

import io as _io
from collections.abc import Mapping, Sequence
from pathlib import Path

# a bare Figure, not pyplot: drawing a PNG chooses no backend, so importing this leaves a notebook's inline figures be
from matplotlib.figure import Figure

from nerf_lightning.io import write_atomic


def plot_psnr_curves(
    curves: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    path: str | Path,
    title: str = "PSNR",
    xlabel: str = "step",
    legend_below: bool = False,
) -> Path:
    """One line per curve: ``{label: (steps, psnr_db)}``; curves of a single point are drawn as markers. The legend
    goes inside the axes where it fits best, or below them (``legend_below``), off the points."""
    figure = Figure(figsize=(7, 4.2 + (0.25 * len(curves) if legend_below else 0.0)), dpi=110)
    axes = figure.subplots()
    for label, (steps, psnr) in curves.items():
        style = {"marker": "o"} if len(steps) < 30 else {}
        axes.plot(list(steps), list(psnr), label=label, linewidth=1.4, **style)
    axes.set_xlabel(xlabel)
    axes.set_ylabel("PSNR (dB)")
    axes.set_title(title)
    axes.grid(True, alpha=0.3)
    if curves:
        if legend_below:
            axes.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.15))
        else:
            axes.legend(fontsize=8, loc="best")
    figure.tight_layout()
    buffer = _io.BytesIO()
    figure.savefig(buffer, format="png")
    return write_atomic(path, buffer.getvalue())
